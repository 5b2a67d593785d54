//! Hand-offs across the realtime boundary (docs/DESIGN.md §4.7, "Across the realtime
//! boundary"): a thread at SCHED_FIFO (the servo, an arm's host) and threads of the normal
//! scheduler (zenoh's callbacks, a publishing thread) pass values through these queues without
//! either one ever waiting for the other.
//!
//! A bounded channel does not give that. Its receiver, finding a slot that a sender has claimed
//! but not yet filled, spins until the sender fills it: a sender on the normal scheduler
//! preempted in between (a CPU hog beside it) kept an arm's host spinning for 60–70 ms, and the
//! local haptic client's force went stale. And a sender whose receiver sleeps in `recv` takes
//! the lock the receiver registers under. Here the ring (`rtrb`, one producer and one consumer)
//! is wait-free at both ends; a consumer that sleeps does so on an eventfd ([`Bell`]) that the
//! producer rings; where several threads produce ([`SharedInlet`]), they take turns on a lock
//! that only they take, never the realtime side.

use std::os::fd::{AsRawFd, OwnedFd};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// An eventfd a producer rings and a consumer polls or sleeps on: one non-blocking `write`
/// (no lock, no allocation) to ring it.
#[derive(Debug)]
pub struct Bell {
    fd: OwnedFd,
}

impl Bell {
    /// A fresh eventfd; fails only when the process or system is out of descriptors.
    pub fn new() -> std::io::Result<Bell> {
        // SAFETY: eventfd has no pointer arguments; the result is checked before use.
        let fd = unsafe { libc::eventfd(0, libc::EFD_NONBLOCK | libc::EFD_CLOEXEC) };
        if fd < 0 {
            return Err(std::io::Error::last_os_error());
        }
        // SAFETY: `fd` is a fresh descriptor that nothing else owns.
        let fd = unsafe { <OwnedFd as std::os::fd::FromRawFd>::from_raw_fd(fd) };
        Ok(Bell { fd })
    }

    /// Ring (never blocks: the counter saturates only after 2⁶⁴ − 2 rings).
    pub fn ring(&self) {
        let one = 1u64.to_ne_bytes();
        // SAFETY: writes 8 bytes from a live local buffer to an owned descriptor.
        let _ = unsafe { libc::write(self.fd.as_raw_fd(), one.as_ptr().cast(), 8) };
    }

    /// Reset the counter (the consumer's side, after waking).
    pub fn clear(&self) {
        let mut buf = [0u8; 8];
        // SAFETY: reads at most 8 bytes into a live local buffer; EAGAIN when not rung.
        let _ = unsafe { libc::read(self.fd.as_raw_fd(), buf.as_mut_ptr().cast(), 8) };
    }

    /// Sleep until rung or `timeout` has passed, then reset the counter: true when rung.
    pub fn wait(&self, timeout: Duration) -> bool {
        let mut fd = libc::pollfd {
            fd: self.fd.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        let ms = timeout.as_millis().min(i32::MAX as u128) as i32;
        // SAFETY: one live pollfd.
        let rc = unsafe { libc::poll(&mut fd, 1, ms) };
        let rung = rc > 0 && fd.revents != 0;
        if rung {
            self.clear();
        }
        rung
    }

    /// The end to poll for readability.
    pub fn fd(&self) -> std::os::fd::BorrowedFd<'_> {
        use std::os::fd::AsFd;
        self.fd.as_fd()
    }
}

/// Why a value was not queued (it is dropped: the caller counts it).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refused {
    /// The queue is full (the consumer is behind).
    Full,
    /// The consumer has gone.
    Closed,
}

/// A queue of at most `capacity` values, wait-free at both ends.
pub fn queue<T>(capacity: usize) -> (Inlet<T>, Outlet<T>) {
    let (ring, out) = rtrb::RingBuffer::new(capacity);
    (Inlet { ring, bell: None }, Outlet { ring: out })
}

/// The producing end: one thread's.
pub struct Inlet<T> {
    ring: rtrb::Producer<T>,
    bell: Option<Arc<Bell>>,
}

impl<T> Inlet<T> {
    /// Ring `bell` after every value queued (for a consumer that sleeps on it).
    pub fn ringing(mut self, bell: Arc<Bell>) -> Inlet<T> {
        self.bell = Some(bell);
        self
    }

    /// Queue `v` without waiting.
    pub fn push(&mut self, v: T) -> Result<(), Refused> {
        self.push_or_return(v).map_err(|_| {
            if self.ring.is_abandoned() {
                Refused::Closed
            } else {
                Refused::Full
            }
        })
    }

    /// Queue `v` without waiting, or hand it back when it cannot be queued (full, or the
    /// consumer gone): for a value the caller keeps to use again.
    pub fn push_or_return(&mut self, v: T) -> Result<(), T> {
        if self.ring.is_abandoned() {
            return Err(v);
        }
        self.ring.push(v).map_err(|rtrb::PushError::Full(v)| v)?;
        if let Some(b) = &self.bell {
            b.ring();
        }
        Ok(())
    }

    /// The consumer has gone.
    pub fn is_closed(&self) -> bool {
        self.ring.is_abandoned()
    }

    /// This end for several producers of the normal scheduler.
    pub fn shared(self) -> SharedInlet<T> {
        SharedInlet {
            inlet: Mutex::new(self),
        }
    }
}

/// The producing end for several threads, none of them realtime: they take turns on a lock
/// the consumer never takes.
pub struct SharedInlet<T> {
    inlet: Mutex<Inlet<T>>,
}

impl<T> SharedInlet<T> {
    /// Queue `v` without waiting for the consumer (only for another producer's push).
    pub fn push(&self, v: T) -> Result<(), Refused> {
        self.inlet.lock().unwrap_or_else(|e| e.into_inner()).push(v)
    }
}

/// The consuming end: one thread's.
pub struct Outlet<T> {
    ring: rtrb::Consumer<T>,
}

impl<T> Outlet<T> {
    /// The oldest value queued, without waiting.
    pub fn pop(&mut self) -> Option<T> {
        self.ring.pop().ok()
    }

    /// Nothing is queued.
    pub fn is_empty(&self) -> bool {
        self.ring.is_empty()
    }

    /// The producer has gone and nothing is left.
    pub fn is_closed(&self) -> bool {
        self.ring.is_abandoned() && self.ring.is_empty()
    }

    /// Drop everything queued.
    pub fn clear(&mut self) {
        while self.pop().is_some() {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn values_come_out_in_order_and_a_full_queue_refuses() {
        let (mut i, mut o) = queue(2);
        assert_eq!(i.push(1), Ok(()));
        assert_eq!(i.push(2), Ok(()));
        assert_eq!(i.push(3), Err(Refused::Full));
        assert_eq!(o.pop(), Some(1));
        assert_eq!(i.push(4), Ok(()));
        assert_eq!(o.pop(), Some(2));
        assert_eq!(o.pop(), Some(4));
        assert_eq!(o.pop(), None);
        assert!(o.is_empty() && !o.is_closed());
        drop(o);
        assert_eq!(i.push(5), Err(Refused::Closed));
    }

    #[test]
    fn the_consumer_sees_the_producer_gone_only_once_drained() {
        let (mut i, mut o) = queue(4);
        i.push(7).unwrap();
        drop(i);
        assert!(!o.is_closed(), "a value is still queued");
        assert_eq!(o.pop(), Some(7));
        assert!(o.is_closed());
    }

    #[test]
    fn a_ringing_inlet_wakes_a_sleeping_consumer() {
        let bell = Arc::new(Bell::new().unwrap());
        let (i, mut o) = queue(100);
        let mut i = i.ringing(bell.clone());
        assert!(!bell.wait(Duration::ZERO), "not rung yet");
        let t = std::thread::spawn(move || {
            for v in 0..100 {
                i.push(v).unwrap();
                std::thread::yield_now();
            }
        });
        let mut got = Vec::new();
        while got.len() < 100 {
            // A long timeout: only the bell ends the wait early enough for the test to end.
            bell.wait(Duration::from_secs(10));
            while let Some(v) = o.pop() {
                got.push(v);
            }
        }
        t.join().unwrap();
        assert_eq!(got, (0..100).collect::<Vec<_>>());
    }

    #[test]
    fn several_producers_share_an_inlet() {
        let (i, mut o) = queue(4000);
        let i = Arc::new(i.shared());
        let ts: Vec<_> = (0..4)
            .map(|k| {
                let i = i.clone();
                std::thread::spawn(move || {
                    for v in 0..1000 {
                        i.push(k * 1000 + v).unwrap();
                    }
                })
            })
            .collect();
        for t in ts {
            t.join().unwrap();
        }
        let mut got = Vec::new();
        while let Some(v) = o.pop() {
            got.push(v);
        }
        // Each producer's values in its own order, all of them.
        for k in 0..4 {
            let mine: Vec<_> = got.iter().filter(|v| **v / 1000 == k).copied().collect();
            assert_eq!(mine, (k * 1000..k * 1000 + 1000).collect::<Vec<_>>());
        }
    }
}
