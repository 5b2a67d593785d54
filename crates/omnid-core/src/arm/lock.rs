//! One process per arm: a name in the abstract Unix socket namespace, bound and listening while
//! the process drives the arm: `@omnid-arm-<name>` for real hardware (one device, one process,
//! whoever runs it), `@omnid-arm-u<uid>-<name>` for a simulated or replayed arm (each user's
//! `sim` is their own, as their runtime and state directories are). Binding it is exclusive
//! machine-wide and ends with the process, with no file to go stale, be followed through a symlink or be
//! truncated; a second `run`, `serve` or `probe` of the same arm connects to it to learn the
//! holder's process id (SO_PEERCRED) and names it. `hold` holds any such name (the daemon's
//! socket paths are held the same way).

use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};

/// Held while this process drives the arm.
#[derive(Debug)]
pub struct ArmLock {
    _fd: OwnedFd,
}

fn seqpacket() -> io::Result<OwnedFd> {
    // SAFETY: socket has no pointer arguments; the result is checked before use.
    let fd = unsafe { libc::socket(libc::AF_UNIX, libc::SOCK_SEQPACKET | libc::SOCK_CLOEXEC, 0) };
    if fd < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: a fresh descriptor nothing else owns.
    Ok(unsafe { OwnedFd::from_raw_fd(fd) })
}

/// The abstract address `id` (a leading NUL byte, no file).
fn address(id: &str) -> (libc::sockaddr_un, libc::socklen_t) {
    // SAFETY: sockaddr_un is plain data; all zeros is a valid value.
    let mut addr: libc::sockaddr_un = unsafe { std::mem::zeroed() };
    addr.sun_family = libc::AF_UNIX as libc::sa_family_t;
    // Ids are short (an arm name is at most 32 safe bytes); cut anyway.
    let bytes = &id.as_bytes()[..id.len().min(addr.sun_path.len() - 1)];
    for (dst, src) in addr.sun_path[1..].iter_mut().zip(bytes) {
        *dst = *src as libc::c_char;
    }
    let len = std::mem::size_of::<libc::sa_family_t>() + 1 + bytes.len();
    (addr, len as libc::socklen_t)
}

/// The abstract name that locks arm `name`: host-wide for real hardware, per user (the
/// effective uid in the name) for a simulated or replayed arm.
pub fn lock_id(name: &str, simulated: bool) -> String {
    if simulated {
        // SAFETY: geteuid has no arguments and cannot fail.
        let uid = unsafe { libc::geteuid() };
        format!("omnid-arm-u{uid}-{name}")
    } else {
        format!("omnid-arm-{name}")
    }
}

impl ArmLock {
    /// Take the real arm `name` (host-wide); refused, naming the holder, while another
    /// process has it.
    pub fn acquire(name: &str) -> Result<ArmLock, String> {
        Self::take(name, false)
    }

    /// Take the simulated (or replayed) arm `name`: this user's only, so another user's arm
    /// of the same name is not in the way.
    pub fn acquire_simulated(name: &str) -> Result<ArmLock, String> {
        Self::take(name, true)
    }

    fn take(name: &str, simulated: bool) -> Result<ArmLock, String> {
        let fd = hold(&lock_id(name, simulated))
            .map_err(|holder| format!("the arm `{name}` is in use by {holder}; stop it first"))?;
        Ok(ArmLock { _fd: fd })
    }
}

/// Hold the abstract name `id` for as long as the returned descriptor lives. Refused while
/// another process holds it: the error is that process (`omnid (pid N: COMMAND)`), or why
/// the name could not be taken.
pub fn hold(id: &str) -> Result<OwnedFd, String> {
    let fd = seqpacket().map_err(|e| format!("(lock {id}: {e})"))?;
    let (addr, len) = address(id);
    // SAFETY: `addr` is a valid sockaddr_un of `len` bytes.
    let rc = unsafe {
        libc::bind(
            fd.as_raw_fd(),
            (&addr as *const libc::sockaddr_un).cast(),
            len,
        )
    };
    if rc != 0 {
        let e = io::Error::last_os_error();
        return Err(if e.kind() == io::ErrorKind::AddrInUse {
            holder(id).unwrap_or_else(|| "another omnid (run, serve or probe)".into())
        } else {
            format!("(lock {id}: {e})")
        });
    }
    // Listening lets a contender connect and read our process id.
    // SAFETY: plain call on an owned descriptor.
    if unsafe { libc::listen(fd.as_raw_fd(), 8) } != 0 {
        return Err(format!("(lock {id}: {})", io::Error::last_os_error()));
    }
    Ok(fd)
}

/// `omnid (pid N: COMMAND LINE)` for the process holding `id`.
fn holder(id: &str) -> Option<String> {
    let fd = seqpacket().ok()?;
    let (addr, len) = address(id);
    // SAFETY: `addr` is a valid sockaddr_un of `len` bytes.
    let rc = unsafe {
        libc::connect(
            fd.as_raw_fd(),
            (&addr as *const libc::sockaddr_un).cast(),
            len,
        )
    };
    if rc != 0 {
        return None;
    }
    // SAFETY: ucred is plain data; getsockopt writes at most `size` bytes into it.
    let mut cred: libc::ucred = unsafe { std::mem::zeroed() };
    let mut size = std::mem::size_of::<libc::ucred>() as libc::socklen_t;
    let rc = unsafe {
        libc::getsockopt(
            fd.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_PEERCRED,
            (&mut cred as *mut libc::ucred).cast(),
            &mut size,
        )
    };
    if rc != 0 || cred.pid <= 0 {
        return None;
    }
    // Held by this very process: another of its arms, not some other program to stop.
    if cred.pid as u32 == std::process::id() {
        return Some("another arm of this same omnid process".into());
    }
    let command = std::fs::read(format!("/proc/{}/cmdline", cred.pid))
        .map(|raw| {
            let words: Vec<String> = raw
                .split(|b| *b == 0)
                .filter(|w| !w.is_empty())
                .map(|w| String::from_utf8_lossy(w).into_owned())
                .collect();
            crate::text::cut(&words.join(" "))
        })
        .unwrap_or_default();
    Some(if command.is_empty() {
        format!("omnid (pid {})", cred.pid)
    } else {
        format!("omnid (pid {}: {command})", cred.pid)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_holder_is_refused_with_the_first_named() {
        let name = format!("test-{}", std::process::id());
        let held = ArmLock::acquire(&name).unwrap();
        let e = ArmLock::acquire(&name).unwrap_err();
        // The holder is this very process (another process is named by pid: the CLI tests).
        assert!(e.contains("this same omnid process"), "{e}");
        assert!(e.contains(&name), "{e}");
        drop(held);
        // Released with its holder: the next one gets it.
        ArmLock::acquire(&name).unwrap();
    }

    #[test]
    fn a_simulated_arm_is_locked_per_user_and_a_real_one_host_wide() {
        // SAFETY: geteuid has no arguments and cannot fail.
        let uid = unsafe { libc::geteuid() };
        let sim = lock_id("left", true);
        let real = lock_id("left", false);
        assert_eq!(sim, format!("omnid-arm-u{uid}-left"));
        assert_eq!(real, "omnid-arm-left");
        assert!(!real.contains(&format!("u{uid}")), "{real}");
        // The two are different names: a simulated `left` does not hold a real `left`.
        let name = format!("test-scope-{}", std::process::id());
        let held = ArmLock::acquire_simulated(&name).unwrap();
        let real = ArmLock::acquire(&name).unwrap();
        let e = ArmLock::acquire_simulated(&name).unwrap_err();
        assert!(e.contains(&name), "{e}");
        drop((held, real));
    }
}
