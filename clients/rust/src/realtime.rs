//! What a client's own realtime thread needs (libHD's scheduler runs at 1 kHz like the
//! daemon's servo): SCHED_FIFO for the calling thread, and what to do when it is not
//! permitted.

/// How to allow realtime priority and memory locking to an unprivileged user.
pub const LIMITS_HINT: &str =
    "install udev/omnid-limits.conf into /etc/security/limits.d/ and log in again (see udev/README.md)";

/// Put the calling thread on SCHED_FIFO at `priority` (1..=99), or 0: back on the normal
/// scheduler. Not permitted: the warning to print, naming the fix.
pub fn set_fifo_priority(priority: i32) -> Result<(), String> {
    let (policy, param) = if priority > 0 {
        (
            libc::SCHED_FIFO,
            libc::sched_param {
                sched_priority: priority,
            },
        )
    } else {
        (libc::SCHED_OTHER, libc::sched_param { sched_priority: 0 })
    };
    // SAFETY: param is a valid sched_param; 0 means the calling thread.
    if unsafe { libc::sched_setscheduler(0, policy, &param) } == 0 {
        Ok(())
    } else {
        Err(format!(
            "SCHED_FIFO priority {priority} not permitted ({}): {LIMITS_HINT}",
            std::io::Error::last_os_error()
        ))
    }
}
