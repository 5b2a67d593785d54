//! Monotonic clock and absolute-deadline sleep (clock_nanosleep with TIMER_ABSTIME), so pacing
//! errors never accumulate from tick to tick; [`sleep_until_ns_or_stop`] is the one way to wait
//! longer than a tick, ending early when the operator stops.

use std::sync::atomic::{AtomicBool, Ordering};

/// Longest single sleep of [`sleep_until_ns_or_stop`] between two looks at the stop flag.
pub const STOP_SLICE_NS: u64 = 20_000_000;

/// Monotonic time in nanoseconds.
pub fn now_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: ts is a valid, writable timespec; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Sleep until the monotonic clock reads `deadline_ns` (returns at once if it already has).
pub fn sleep_until_ns(deadline_ns: u64) {
    let ts = libc::timespec {
        tv_sec: (deadline_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (deadline_ns % 1_000_000_000) as libc::c_long,
    };
    loop {
        // SAFETY: ts is a valid timespec; a null remainder is allowed with TIMER_ABSTIME.
        let rc = unsafe {
            libc::clock_nanosleep(
                libc::CLOCK_MONOTONIC,
                libc::TIMER_ABSTIME,
                &ts,
                std::ptr::null_mut(),
            )
        };
        // EINTR: a signal arrived; the deadline is absolute, so just sleep again.
        if rc != libc::EINTR {
            break;
        }
    }
}

/// Sleep until `deadline_ns` or until `stop` is set, whichever comes first: in slices of at
/// most [`STOP_SLICE_NS`], so a wait of any length (a gap in a replay, an injected slowdown)
/// ends within one slice of Ctrl-C. A wait shorter than a slice is one `clock_nanosleep`, as
/// [`sleep_until_ns`]; nothing allocates or locks. Returns false when the flag cut it short.
pub fn sleep_until_ns_or_stop(deadline_ns: u64, stop: &AtomicBool) -> bool {
    loop {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        let now = now_ns();
        if now >= deadline_ns {
            return true;
        }
        sleep_until_ns(deadline_ns.min(now + STOP_SLICE_NS));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_sleep_ends_soon_after_the_stop_flag() {
        let stop = std::sync::Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let setter = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(100));
            flag.store(true, Ordering::Relaxed);
        });
        let t0 = now_ns();
        // An hour, cut short.
        assert!(!sleep_until_ns_or_stop(t0 + 3_600_000_000_000, &stop));
        setter.join().unwrap();
        let waited_s = (now_ns() - t0) as f64 * 1e-9;
        assert!((0.05..2.0).contains(&waited_s), "{waited_s} s");
        // Unset, it sleeps the whole way.
        stop.store(false, Ordering::Relaxed);
        let deadline = now_ns() + 30_000_000;
        assert!(sleep_until_ns_or_stop(deadline, &stop));
        assert!(now_ns() >= deadline);
    }

    #[test]
    fn sleep_until_does_not_return_early() {
        let t0 = now_ns();
        let deadline = t0 + 2_000_000;
        sleep_until_ns(deadline);
        assert!(now_ns() >= deadline);
        // A deadline in the past returns at once (nothing to assert about time; it must not hang).
        sleep_until_ns(t0);
    }
}
