//! The daemon's side of the Unix SOCK_SEQPACKET socket (the connection itself, shared with
//! clients, is `omnid_client::socket`): the listener, and the locks that keep a second daemon
//! off the same socket or device.

use omnid_client::socket::{address, check, is_live, seqpacket, set_nonblocking};
pub use omnid_client::socket::{Conn, Peer};
use std::ffi::CString;
use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};

/// The daemon's listening socket. Removed from the file system when dropped.
#[derive(Debug)]
pub(crate) struct Listener {
    fd: OwnedFd,
    path: PathBuf,
    /// The socket file's device and inode: removed at the end only while it is still ours.
    file_id: (u64, u64),
    /// A descriptor held in reserve (on /dev/null) for [`Listener::shed_one`].
    reserve: std::sync::Mutex<Option<OwnedFd>>,
}

/// A descriptor on /dev/null to hold in reserve.
fn reserve_fd() -> Option<OwnedFd> {
    std::fs::File::open("/dev/null").ok().map(OwnedFd::from)
}

impl Listener {
    /// Bind `path` (permission bits `mode`, group `group` when given) and listen,
    /// non-blocking. A socket left at `path` by a daemon that died is replaced; a live one
    /// (another program's: the caller holds the path's lock) and any other file are left alone
    /// and refused.
    pub(crate) fn bind(
        path: &Path,
        group: Option<u32>,
        mode: libc::mode_t,
    ) -> io::Result<Listener> {
        let fd = seqpacket()?;
        let bytes = path.as_os_str().as_bytes();
        let (addr, len) = address(bytes)?;
        match std::fs::symlink_metadata(path) {
            Ok(m) if std::os::unix::fs::FileTypeExt::is_socket(&m.file_type()) => {
                if is_live(path) {
                    return Err(io::Error::new(
                        io::ErrorKind::AddrInUse,
                        "another program is listening on this socket (not replaced)",
                    ));
                }
                std::fs::remove_file(path)?
            }
            Ok(_) => {
                return Err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    "a file that is not a socket is in the way (not replaced)",
                ))
            }
            Err(_) => {}
        }
        // SAFETY: `addr` is a valid sockaddr_un of `len` bytes.
        check(unsafe {
            libc::bind(
                fd.as_raw_fd(),
                (&addr as *const libc::sockaddr_un).cast(),
                len,
            )
        })?;
        let meta = std::fs::symlink_metadata(path)?;
        let listener = Listener {
            fd,
            path: path.to_path_buf(),
            file_id: (
                std::os::unix::fs::MetadataExt::dev(&meta),
                std::os::unix::fs::MetadataExt::ino(&meta),
            ),
            reserve: std::sync::Mutex::new(reserve_fd()),
        };
        // Before listen(): nobody can connect yet, so nobody ever sees wider permissions.
        let c = CString::new(bytes).map_err(|_| io::ErrorKind::InvalidInput)?;
        // SAFETY: `c` is a valid NUL-terminated path.
        check(unsafe { libc::chmod(c.as_ptr(), mode) })?;
        if let Some(gid) = group {
            // SAFETY: as above; uid -1 leaves the owner.
            check(unsafe { libc::chown(c.as_ptr(), u32::MAX, gid) })?;
        }
        // SAFETY: no pointers.
        check(unsafe { libc::listen(listener.fd.as_raw_fd(), 128) })?;
        set_nonblocking(listener.fd.as_raw_fd())?;
        Ok(listener)
    }

    /// The next waiting connection (non-blocking, close-on-exec), or `None`.
    pub(crate) fn accept(&self) -> io::Result<Option<Conn>> {
        // SAFETY: null address pointers are allowed (the peer's address is not wanted).
        let fd = unsafe {
            libc::accept4(
                self.fd.as_raw_fd(),
                std::ptr::null_mut(),
                std::ptr::null_mut(),
                libc::SOCK_NONBLOCK | libc::SOCK_CLOEXEC,
            )
        };
        if fd < 0 {
            let e = io::Error::last_os_error();
            return match e.kind() {
                io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted => Ok(None),
                _ => Err(e),
            };
        }
        // SAFETY: `fd` is new and owned by nothing else.
        Ok(Some(Conn::from(unsafe { OwnedFd::from_raw_fd(fd) })))
    }

    /// The process is out of descriptors (accept failed with EMFILE/ENFILE) and a client
    /// waits: give up the reserve descriptor, accept that client so `tell` can say why, close
    /// it, and take the reserve again. Else the connection would wait unanswered and the
    /// listener stay readable, so the daemon's poll would spin. False when there was no
    /// reserve to give up or nobody waited.
    pub fn shed_one(&self, tell: impl FnOnce(&Conn)) -> bool {
        let mut reserve = self.reserve.lock().unwrap_or_else(|e| e.into_inner());
        if reserve.take().is_none() {
            *reserve = reserve_fd();
            return false;
        }
        let shed = match self.accept() {
            Ok(Some(conn)) => {
                tell(&conn);
                true
            }
            _ => false,
        };
        *reserve = reserve_fd();
        shed
    }

    pub fn raw(&self) -> RawFd {
        self.fd.as_raw_fd()
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for Listener {
    /// Remove the socket file, unless something else has taken its place meanwhile.
    fn drop(&mut self) {
        if let Ok(m) = std::fs::symlink_metadata(&self.path) {
            use std::os::unix::fs::MetadataExt;
            if (m.dev(), m.ino()) == self.file_id {
                let _ = std::fs::remove_file(&self.path);
            }
        }
    }
}

/// Held while this daemon serves a socket path, so that a second daemon asked for the same
/// path is refused with the first one named. A name in the abstract namespace derived from
/// the path's canonical form (`crate::arm::lock::hold`): no lock file to create beside the
/// socket, follow through a symlink, truncate, or leave behind.
#[derive(Debug)]
pub(crate) struct SocketLock {
    _held: OwnedFd,
    /// The socket's directory as given: the directories this process created for it are
    /// removed, when empty, as the lock goes ([`remove_created_dirs`]).
    dir: Option<PathBuf>,
}

impl Drop for SocketLock {
    fn drop(&mut self) {
        if let Some(dir) = &self.dir {
            remove_created_dirs(dir);
        }
    }
}

/// The directories this process created for its sockets (`create_socket_dir`), shallowest
/// first: the daemon leaves no runtime directory of its own behind.
static CREATED_DIRS: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

/// Create the socket directory `dir` and any missing parents, remembering each one this
/// process made (one that appeared meanwhile, made by someone else, is not ours).
pub(crate) fn create_socket_dir(dir: &Path) -> io::Result<()> {
    let missing: Vec<&Path> = dir
        .ancestors()
        .take_while(|d| !d.as_os_str().is_empty() && !d.is_dir())
        .collect();
    for d in missing.into_iter().rev() {
        match std::fs::create_dir(d) {
            Ok(()) => {
                let mut created = CREATED_DIRS.lock().unwrap_or_else(|e| e.into_inner());
                if !created.iter().any(|c| c == d) {
                    created.push(d.to_path_buf());
                }
            }
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists && d.is_dir() => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

/// Remove, deepest first, the directories holding `dir` (itself included) that this process
/// created, while they are empty: one still holding another arm's or another daemon's socket
/// (or anything else) stays, and so does every directory this process did not create.
pub(crate) fn remove_created_dirs(dir: &Path) {
    let mut created = CREATED_DIRS.lock().unwrap_or_else(|e| e.into_inner());
    for d in dir.ancestors() {
        let Some(i) = created.iter().position(|c| c == d) else {
            continue;
        };
        if std::fs::remove_dir(d).is_err() {
            // Not empty (or gone): its parents are not empty either.
            break;
        }
        created.remove(i);
    }
}

impl SocketLock {
    /// Lock the socket path `path` (its directory must exist), or say which process holds it.
    pub(crate) fn acquire(path: &Path) -> Result<SocketLock, String> {
        let dir = match path.parent().filter(|d| !d.as_os_str().is_empty()) {
            Some(d) => d.canonicalize(),
            None => std::env::current_dir(),
        }
        .map_err(|e| format!("cannot resolve its directory: {e}"))?;
        let name = path.file_name().ok_or("the path names no file")?;
        let id = format!(
            "omnid-sock-{:016x}",
            fnv1a(dir.join(name).as_os_str().as_bytes())
        );
        let held = crate::arm::lock::hold(&id).map_err(|holder| {
            if holder.starts_with("another arm of this same") {
                format!("already served by {holder}: give each arm its own socket")
            } else {
                format!("already served by {holder}; stop it first")
            }
        })?;
        Ok(SocketLock {
            _held: held,
            dir: path.parent().map(Path::to_path_buf),
        })
    }
}

/// 64-bit FNV-1a: a short, stable name for a path of any length.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// A group's id by name.
pub(crate) fn group_id(name: &str) -> Option<u32> {
    let c = CString::new(name).ok()?;
    let mut grp: libc::group = unsafe { std::mem::zeroed() };
    let mut buf = vec![0 as libc::c_char; 16 * 1024];
    let mut out: *mut libc::group = std::ptr::null_mut();
    // SAFETY: every pointer refers to live storage of the stated size.
    let rc =
        unsafe { libc::getgrnam_r(c.as_ptr(), &mut grp, buf.as_mut_ptr(), buf.len(), &mut out) };
    (rc == 0 && !out.is_null()).then_some(grp.gr_gid)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_keep_their_boundaries_and_oversize_is_seen() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.sock");
        let listener = Listener::bind(&path, None, 0o660).unwrap();
        let mode = std::fs::metadata(&path).unwrap();
        assert_eq!(
            std::os::unix::fs::PermissionsExt::mode(&mode.permissions()) & 0o777,
            0o660
        );
        let client = Conn::connect(&path).unwrap();
        let server = loop {
            if let Some(c) = listener.accept().unwrap() {
                break c;
            }
        };
        client.send(b"one").unwrap();
        client.send(b"two!").unwrap();
        client.send(&[7u8; 100]).unwrap();
        let mut buf = [0u8; 16];
        assert_eq!(server.recv(&mut buf).unwrap(), 3);
        assert_eq!(&buf[..3], b"one");
        assert_eq!(server.recv(&mut buf).unwrap(), 4);
        // A message longer than the buffer reports its real length.
        assert_eq!(server.recv(&mut buf).unwrap(), 100);
        let me = server.peer().unwrap();
        assert_eq!(me.pid as u32, std::process::id());
        // SAFETY: no arguments.
        assert_eq!(me.uid, unsafe { libc::geteuid() });
        drop(client);
        assert_eq!(server.recv(&mut buf).unwrap(), 0);
        drop(listener);
        assert!(!path.exists(), "the socket is removed with the listener");
    }

    #[test]
    fn a_second_lock_is_refused_naming_the_holder_and_no_file_is_made() {
        let dir = tempfile::tempdir().unwrap();
        // The file a lock beside `Cargo` would have been (and truncated).
        std::fs::write(dir.path().join("Cargo.lock"), "keep").unwrap();
        let path = dir.path().join("Cargo");
        let held = SocketLock::acquire(&path).unwrap();
        // The same place by another spelling is the same lock.
        let other = dir.path().join(".").join("Cargo");
        let e = SocketLock::acquire(&other).unwrap_err();
        assert!(e.contains("this same omnid process"), "{e}");
        assert!(e.contains("give each arm its own socket"), "{e}");
        drop(held);
        SocketLock::acquire(&other).unwrap();
        let files: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(files.len(), 1, "only Cargo.lock: {files:?}");
        assert_eq!(
            std::fs::read_to_string(dir.path().join("Cargo.lock")).unwrap(),
            "keep"
        );
    }

    #[test]
    fn a_live_socket_of_another_program_is_refused_and_a_stale_one_replaced() {
        use std::os::unix::net::UnixListener;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sock");
        let theirs = UnixListener::bind(&path).unwrap();
        let e = Listener::bind(&path, None, 0o660).unwrap_err();
        assert!(e.to_string().contains("another program"), "{e}");
        assert!(is_live(&path), "their socket still works");
        drop(theirs);
        // Now stale: replaced.
        let ours = Listener::bind(&path, None, 0o660).unwrap();
        assert!(Conn::connect(&path).is_ok());
        // Something else takes the path while we serve: ours goes, theirs stays.
        std::fs::remove_file(&path).unwrap();
        let _theirs = UnixListener::bind(&path).unwrap();
        drop(ours);
        assert!(is_live(&path), "their socket was left in place");
    }

    #[test]
    fn a_socket_directory_this_process_created_goes_with_its_last_socket() {
        let root = tempfile::tempdir().unwrap();
        // Made here (two levels): removed once the last socket in it has gone.
        let dir = root.path().join("run").join("omnid");
        create_socket_dir(&dir).unwrap();
        let (a, b) = (dir.join("a.sock"), dir.join("b.sock"));
        let (lock_a, lock_b) = (
            SocketLock::acquire(&a).unwrap(),
            SocketLock::acquire(&b).unwrap(),
        );
        let (sock_a, sock_b) = (
            Listener::bind(&a, None, 0o660).unwrap(),
            Listener::bind(&b, None, 0o660).unwrap(),
        );
        drop(sock_a);
        drop(lock_a);
        assert!(dir.is_dir(), "b's socket is still in it");
        drop(sock_b);
        drop(lock_b);
        assert!(!root.path().join("run").exists(), "both levels were ours");

        // Already there: left alone, though empty.
        let theirs = root.path().join("theirs");
        std::fs::create_dir(&theirs).unwrap();
        create_socket_dir(&theirs).unwrap();
        let path = theirs.join("c.sock");
        let lock = SocketLock::acquire(&path).unwrap();
        drop(Listener::bind(&path, None, 0o660).unwrap());
        drop(lock);
        assert!(
            theirs.is_dir(),
            "a directory this process did not create stays"
        );

        // Ours, but something else was put in it: it stays, with what it holds.
        let dir = root.path().join("shared");
        create_socket_dir(&dir).unwrap();
        let path = dir.join("d.sock");
        let lock = SocketLock::acquire(&path).unwrap();
        let other = std::os::unix::net::UnixListener::bind(dir.join("other.sock")).unwrap();
        drop(Listener::bind(&path, None, 0o660).unwrap());
        drop(lock);
        assert!(
            is_live(&dir.join("other.sock")),
            "another daemon's socket is kept"
        );
        drop(other);
    }

    #[test]
    fn a_regular_file_in_the_way_is_not_replaced() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        std::fs::write(&path, "keep").unwrap();
        assert!(Listener::bind(&path, None, 0o660).is_err());
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "keep");
    }
}
