//! The library's global state: the open devices, the current device (one for the whole
//! process, visible from every thread including the scheduler's), the capabilities, the
//! scheduler (docs/HDAPI.md, Devices).

use crate::consts::*;
use crate::device::Device;
use crate::scheduler::{Scheduler, Ticker};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, LazyLock, Mutex, MutexGuard};
use std::time::Duration;

pub struct Registry {
    devices: Mutex<Vec<Option<Arc<Device>>>>,
    current: AtomicU32,
    pub scheduler: Scheduler,
    /// Enabled capabilities, bit (cap − 0x4000) (`hdEnable`).
    pub caps: AtomicU32,
}

pub static REGISTRY: LazyLock<Registry> = LazyLock::new(|| Registry {
    devices: Mutex::new(Vec::new()),
    current: AtomicU32::new(HD_INVALID_HANDLE),
    scheduler: Scheduler::default(),
    // Everything on, as the vendor's library starts (docs/HDAPI.md, Capabilities).
    caps: AtomicU32::new(0b11111),
});

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Registry {
    /// The handle the next device will get.
    pub fn next_handle(&self) -> u32 {
        lock(&self.devices).len() as u32
    }

    pub fn add(&self, d: Device) -> u32 {
        let mut v = lock(&self.devices);
        let hhd = v.len() as u32;
        debug_assert_eq!(hhd, d.hhd);
        v.push(Some(Arc::new(d)));
        hhd
    }

    pub fn get(&self, hhd: u32) -> Option<Arc<Device>> {
        lock(&self.devices).get(hhd as usize).cloned().flatten()
    }

    pub fn remove(&self, hhd: u32) -> Option<Arc<Device>> {
        let d = lock(&self.devices).get_mut(hhd as usize)?.take();
        let _ = self.current.compare_exchange(
            hhd,
            HD_INVALID_HANDLE,
            Ordering::SeqCst,
            Ordering::SeqCst,
        );
        d
    }

    pub fn all(&self) -> Vec<Arc<Device>> {
        lock(&self.devices).iter().flatten().cloned().collect()
    }

    pub fn current_handle(&self) -> u32 {
        self.current.load(Ordering::SeqCst)
    }

    pub fn set_current(&self, hhd: u32) {
        self.current.store(hhd, Ordering::SeqCst);
    }

    pub fn current(&self) -> Option<Arc<Device>> {
        self.get(self.current_handle())
    }
}

/// The scheduler's ticks are the samples of the first open device.
impl Ticker for Registry {
    fn wait_tick(&self, seen: u64) -> Option<u64> {
        let first = lock(&self.devices).iter().flatten().next().cloned();
        match first {
            Some(d) if d.is_closed() => {
                // The daemon is gone: keep ticking slowly so callbacks see HD_COMM_ERROR in
                // their frames and synchronous calls return (docs/HDAPI.md, Scheduler).
                std::thread::sleep(Duration::from_millis(10));
                Some(seen + 1)
            }
            Some(d) => {
                // The scheduler reads this device's socket itself: the sample wakes it, and
                // the frame's force leaves on the same wake-up (docs/HDAPI.md, Scheduler).
                d.take_reading();
                let seen = seen.min(d.samples());
                d.wait_sample(seen, Duration::from_millis(100))
            }
            None => {
                std::thread::sleep(Duration::from_millis(10));
                None
            }
        }
    }

    fn tick_sample(&self, ticking: bool) {
        for d in self.all() {
            d.set_tick(ticking);
            if !ticking {
                d.give_back_reading();
            }
        }
    }

    fn after_tick(&self) {
        let me = std::thread::current().id();
        for d in self.all() {
            d.frame
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .close_left_open(me);
        }
    }
}
