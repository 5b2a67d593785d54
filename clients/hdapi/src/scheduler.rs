//! The servo scheduler: a thread in the client's process that runs the scheduled callbacks
//! once per sample of the daemon's state stream (one frame per device tick), highest
//! priority first (docs/HDAPI.md, Scheduler).

use crate::consts::*;
use std::ffi::c_void;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::thread::{JoinHandle, ThreadId};
use std::time::Instant;

pub type Callback = unsafe extern "C" fn(*mut c_void) -> u32;

#[derive(Clone, Copy)]
struct Entry {
    handle: u64,
    callback: Callback,
    /// The client's pointer, only ever handed back to its callback.
    data: usize,
    priority: u16,
}

#[derive(Default)]
struct Inner {
    /// Highest priority first; equal priorities in the order they were scheduled.
    entries: Vec<Entry>,
    /// Handles that completed (returned DONE) and nobody has waited for yet.
    done: Vec<u64>,
    next_handle: u64,
    running: bool,
    stop: bool,
    thread: Option<JoinHandle<()>>,
    thread_id: Option<ThreadId>,
    /// The callback running now, if any.
    active: Option<u64>,
    tick_start: Option<Instant>,
}

/// Where the ticks come from: the library's devices.
pub trait Ticker: Sync {
    /// Wait for a sample newer than `seen` (a count); None after a short time-out, so the
    /// scheduler can look at its stop flag.
    fn wait_tick(&self, seen: u64) -> Option<u64>;
    /// A tick begins (`true`) or the scheduler stopped (`false`).
    fn tick_sample(&self, ticking: bool);
    /// After every callback of a tick ran: close frames left open.
    fn after_tick(&self);
}

#[derive(Default)]
pub struct Scheduler {
    inner: Mutex<Inner>,
    cv: Condvar,
}

/// The scheduler thread's SCHED_FIFO priority unless `$OMNID_HD_FIFO_PRIORITY` says otherwise
/// (0: the normal scheduler): below the daemon's servo (80) and client hub (70), above
/// everything else, as the vendor's servo thread runs (docs/HDAPI.md, Scheduler).
const DEFAULT_FIFO_PRIORITY: i32 = 60;

/// Raise the calling thread (the scheduler's) to its realtime priority where permitted: a
/// frame answers its sample within the same device tick only if a busy machine cannot
/// preempt it. Not permitted (no `rtprio` limit), it runs on the normal scheduler, silently.
fn raise_priority() {
    let priority = std::env::var("OMNID_HD_FIFO_PRIORITY")
        .ok()
        .and_then(|v| v.trim().parse::<i32>().ok())
        .unwrap_or(DEFAULT_FIFO_PRIORITY)
        .clamp(0, 99);
    if priority > 0 {
        let _ = omnid_client::realtime::set_fifo_priority(priority);
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Scheduler {
    fn on_thread(inner: &Inner) -> bool {
        inner.thread_id == Some(std::thread::current().id())
    }

    pub fn is_running(&self) -> bool {
        lock(&self.inner).running
    }

    /// Add a callback; its handle.
    pub fn schedule(&self, callback: Callback, data: *mut c_void, priority: u16) -> u64 {
        let mut s = lock(&self.inner);
        s.next_handle += 1;
        let handle = s.next_handle;
        let at = s
            .entries
            .iter()
            .position(|e| e.priority < priority)
            .unwrap_or(s.entries.len());
        s.entries.insert(
            at,
            Entry {
                handle,
                callback,
                data: data as usize,
                priority,
            },
        );
        handle
    }

    /// Remove a callback (also after the scheduler stopped). From another thread, waits for
    /// it to finish if it is running, so its data may be freed after this returns.
    pub fn unschedule(&self, handle: u64) -> bool {
        let mut s = lock(&self.inner);
        let known = s.entries.iter().any(|e| e.handle == handle) || s.done.contains(&handle);
        s.entries.retain(|e| e.handle != handle);
        s.done.retain(|&h| h != handle);
        while s.active == Some(handle) && !Self::on_thread(&s) {
            s = self.cv.wait(s).unwrap_or_else(|e| e.into_inner());
        }
        known
    }

    pub fn is_scheduled(&self, handle: u64) -> bool {
        lock(&self.inner).entries.iter().any(|e| e.handle == handle)
    }

    /// Block until `handle` completed or was unscheduled, or the scheduler stopped.
    pub fn wait(&self, handle: u64) {
        let mut s = lock(&self.inner);
        loop {
            if let Some(k) = s.done.iter().position(|&h| h == handle) {
                s.done.remove(k);
                return;
            }
            if !s.entries.iter().any(|e| e.handle == handle) || !s.running {
                return;
            }
            s = self.cv.wait(s).unwrap_or_else(|e| e.into_inner());
        }
    }

    /// `hdScheduleSynchronous`: run `callback` in the scheduler's next tick and wait for it.
    /// On the scheduler's own thread, or with the scheduler stopped, it runs at once on the
    /// caller's thread (once), so no caller ever waits for a tick that will not come.
    pub fn run_sync(&self, callback: Callback, data: *mut c_void, priority: u16) {
        let now = {
            let s = lock(&self.inner);
            !s.running || Self::on_thread(&s)
        };
        if now {
            // SAFETY: the client gave us this callback and its data to call together.
            unsafe { callback(data) };
            return;
        }
        let handle = self.schedule(callback, data, priority);
        self.wait(handle);
        self.unschedule(handle);
    }

    /// Seconds since the current tick began (0 outside the scheduler).
    pub fn timestamp(&self) -> f64 {
        lock(&self.inner)
            .tick_start
            .map_or(0.0, |t| t.elapsed().as_secs_f64())
    }

    /// Start the thread (no effect when it runs).
    pub fn start(&'static self, ticker: &'static dyn Ticker) -> std::io::Result<()> {
        let mut s = lock(&self.inner);
        if s.running {
            return Ok(());
        }
        s.stop = false;
        let thread = std::thread::Builder::new()
            .name("omnid-hd-servo".into())
            .spawn(move || self.run(ticker))?;
        s.thread_id = Some(thread.thread().id());
        s.thread = Some(thread);
        s.running = true;
        Ok(())
    }

    /// Stop the thread after its current tick; callbacks stay scheduled (a later start runs
    /// them again). Called from a callback, it only asks.
    pub fn stop(&self) {
        let thread = {
            let mut s = lock(&self.inner);
            s.stop = true;
            if Self::on_thread(&s) {
                return;
            }
            s.thread.take()
        };
        if let Some(t) = thread {
            let _ = t.join();
        }
        let mut s = lock(&self.inner);
        s.running = false;
        s.thread_id = None;
        s.tick_start = None;
        self.cv.notify_all();
    }

    fn run(&self, ticker: &dyn Ticker) {
        raise_priority();
        let mut seen = 0;
        loop {
            if lock(&self.inner).stop {
                break;
            }
            match ticker.wait_tick(seen) {
                Some(n) => seen = n,
                None => continue,
            }
            ticker.tick_sample(true);
            self.tick();
            ticker.after_tick();
        }
        ticker.tick_sample(false);
        let mut s = lock(&self.inner);
        s.running = false;
        s.tick_start = None;
        self.cv.notify_all();
    }

    fn tick(&self) {
        let list = {
            let mut s = lock(&self.inner);
            s.tick_start = Some(Instant::now());
            s.entries.clone()
        };
        for e in list {
            {
                let mut s = lock(&self.inner);
                if !s.entries.iter().any(|x| x.handle == e.handle) {
                    continue;
                }
                s.active = Some(e.handle);
            }
            // SAFETY: the client gave us this callback and its data to call together.
            let code = unsafe { (e.callback)(e.data as *mut c_void) };
            let mut s = lock(&self.inner);
            s.active = None;
            if code == HD_CALLBACK_DONE && s.entries.iter().any(|x| x.handle == e.handle) {
                s.entries.retain(|x| x.handle != e.handle);
                s.done.push(e.handle);
                // Completions nobody waits for are forgotten (bounded).
                if s.done.len() > 4096 {
                    s.done.remove(0);
                }
            }
            self.cv.notify_all();
        }
    }
}
