//! Unix SOCK_SEQPACKET sockets (std has only stream and datagram Unix sockets): every send is
//! one whole message or nothing, so a non-blocking fan-out never leaves half a message in a
//! socket. A client's connection ([`Conn`]), the peer's credentials (SO_PEERCRED and
//! SO_PEERGROUPS), and the few system calls the daemon's listener shares with it.

use std::io;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::os::unix::ffi::OsStrExt;
use std::path::Path;

/// A system call's return value as a result (-1: the errno as an error).
pub fn check(rc: libc::c_int) -> io::Result<libc::c_int> {
    if rc < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(rc)
    }
}

/// `sockaddr_un` for `path` (refused when longer than the kernel's 108 bytes).
pub fn address(path: &[u8]) -> io::Result<(libc::sockaddr_un, libc::socklen_t)> {
    // SAFETY: sockaddr_un is plain old data; all-zero is a valid value.
    let mut addr: libc::sockaddr_un = unsafe { std::mem::zeroed() };
    addr.sun_family = libc::AF_UNIX as libc::sa_family_t;
    if path.len() >= addr.sun_path.len() {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!(
                "socket path is {} bytes; Unix sockets allow at most {}",
                path.len(),
                addr.sun_path.len() - 1
            ),
        ));
    }
    for (dst, &src) in addr.sun_path.iter_mut().zip(path) {
        *dst = src as libc::c_char;
    }
    let len = std::mem::size_of::<libc::sa_family_t>() + path.len();
    Ok((addr, len as libc::socklen_t))
}

/// A new SOCK_SEQPACKET Unix socket (close-on-exec).
pub fn seqpacket() -> io::Result<OwnedFd> {
    // SAFETY: no pointers; the descriptor is checked and owned at once.
    let fd = check(unsafe {
        libc::socket(libc::AF_UNIX, libc::SOCK_SEQPACKET | libc::SOCK_CLOEXEC, 0)
    })?;
    // SAFETY: `fd` is new and owned by nothing else.
    Ok(unsafe { OwnedFd::from_raw_fd(fd) })
}

/// Make `fd` non-blocking.
pub fn set_nonblocking(fd: RawFd) -> io::Result<()> {
    // SAFETY: fcntl on a descriptor we own; no pointers.
    unsafe {
        let flags = check(libc::fcntl(fd, libc::F_GETFL))?;
        check(libc::fcntl(fd, libc::F_SETFL, flags | libc::O_NONBLOCK))?;
    }
    Ok(())
}

/// One connection: a whole message per `send`, one per `recv`.
#[derive(Debug)]
pub struct Conn(OwnedFd);

/// Whether a program is listening on the Unix socket at `path`. A socket file whose program
/// died refuses connections (stale); a live one accepts, or is busy, or is of another type
/// (a stream socket). Tried without blocking, and the connection is closed at once. When it
/// cannot be tried, it counts as live: a socket is only ever removed when it is known stale.
pub fn is_live(path: &Path) -> bool {
    let Ok(fd) = seqpacket() else {
        return true;
    };
    let Ok((addr, len)) = address(path.as_os_str().as_bytes()) else {
        return true;
    };
    if set_nonblocking(fd.as_raw_fd()).is_err() {
        return true;
    }
    // SAFETY: `addr` is a valid sockaddr_un of `len` bytes.
    let rc = unsafe {
        libc::connect(
            fd.as_raw_fd(),
            (&addr as *const libc::sockaddr_un).cast(),
            len,
        )
    };
    rc == 0
        || !matches!(
            io::Error::last_os_error().raw_os_error(),
            Some(libc::ECONNREFUSED) | Some(libc::ENOENT) | Some(libc::ENOTDIR)
        )
}

impl From<OwnedFd> for Conn {
    /// A connected SOCK_SEQPACKET socket (the daemon's listener hands its accepted ones over
    /// this way).
    fn from(fd: OwnedFd) -> Conn {
        Conn(fd)
    }
}

impl Conn {
    /// Connect to the daemon's socket at `path` (blocking).
    pub fn connect(path: &Path) -> io::Result<Conn> {
        let fd = seqpacket()?;
        let (addr, len) = address(path.as_os_str().as_bytes())?;
        // SAFETY: `addr` is a valid sockaddr_un of `len` bytes.
        check(unsafe {
            libc::connect(
                fd.as_raw_fd(),
                (&addr as *const libc::sockaddr_un).cast(),
                len,
            )
        })?;
        Ok(Conn(fd))
    }

    /// Two connected ends, as a client and the daemon hold them: a client library's protocol
    /// logic can be tested against a scripted daemon end without a running daemon.
    pub fn pair() -> io::Result<(Conn, Conn)> {
        let mut fds = [0; 2];
        // SAFETY: `fds` has room for the two descriptors socketpair writes.
        check(unsafe {
            libc::socketpair(
                libc::AF_UNIX,
                libc::SOCK_SEQPACKET | libc::SOCK_CLOEXEC,
                0,
                fds.as_mut_ptr(),
            )
        })?;
        // SAFETY: both descriptors are new and owned by nothing else.
        Ok(unsafe {
            (
                Conn(OwnedFd::from_raw_fd(fds[0])),
                Conn(OwnedFd::from_raw_fd(fds[1])),
            )
        })
    }

    /// Send one message. Non-blocking connections return `WouldBlock` when the peer's
    /// buffer is full (nothing was sent).
    pub fn send(&self, msg: &[u8]) -> io::Result<()> {
        // SAFETY: sends `msg.len()` bytes from a live slice; MSG_NOSIGNAL: a closed peer is
        // an EPIPE error, never a SIGPIPE.
        let n = unsafe {
            libc::send(
                self.0.as_raw_fd(),
                msg.as_ptr().cast(),
                msg.len(),
                libc::MSG_NOSIGNAL,
            )
        };
        if n < 0 {
            return Err(io::Error::last_os_error());
        }
        Ok(())
    }

    /// Receive one message into `buf`; returns its full length, which is larger than
    /// `buf` when the message was cut (MSG_TRUNC). 0 means the peer closed.
    pub fn recv(&self, buf: &mut [u8]) -> io::Result<usize> {
        // SAFETY: receives at most `buf.len()` bytes into a live mutable slice.
        let n = unsafe {
            libc::recv(
                self.0.as_raw_fd(),
                buf.as_mut_ptr().cast(),
                buf.len(),
                libc::MSG_TRUNC,
            )
        };
        if n < 0 {
            return Err(io::Error::last_os_error());
        }
        Ok(n as usize)
    }

    /// Wait until a message can be read, at most `timeout_ms` (negative: forever). False on
    /// time-out.
    pub fn wait_readable(&self, timeout_ms: i32) -> io::Result<bool> {
        let mut p = libc::pollfd {
            fd: self.0.as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        };
        loop {
            // SAFETY: one valid pollfd.
            let rc = unsafe { libc::poll(&mut p, 1, timeout_ms) };
            if rc < 0 {
                let e = io::Error::last_os_error();
                if e.kind() == io::ErrorKind::Interrupted {
                    continue;
                }
                return Err(e);
            }
            return Ok(rc > 0);
        }
    }

    /// The socket's file descriptor (to poll it).
    pub fn raw(&self) -> RawFd {
        self.0.as_raw_fd()
    }

    /// Who is on the other end (as the kernel saw it at connect time).
    pub fn peer(&self) -> io::Result<Peer> {
        let fd = self.0.as_raw_fd();
        // SAFETY: ucred is plain old data; getsockopt writes at most `len` bytes into it.
        let mut cred: libc::ucred = unsafe { std::mem::zeroed() };
        let mut len = std::mem::size_of::<libc::ucred>() as libc::socklen_t;
        check(unsafe {
            libc::getsockopt(
                fd,
                libc::SOL_SOCKET,
                libc::SO_PEERCRED,
                (&mut cred as *mut libc::ucred).cast(),
                &mut len,
            )
        })?;
        // Supplementary groups (Linux ≥ 4.13); without them only the primary group counts.
        let mut groups = vec![0 as libc::gid_t; 256];
        let mut glen = (groups.len() * std::mem::size_of::<libc::gid_t>()) as libc::socklen_t;
        // SAFETY: writes at most `glen` bytes into the live vector.
        let rc = unsafe {
            libc::getsockopt(
                fd,
                libc::SOL_SOCKET,
                libc::SO_PEERGROUPS,
                groups.as_mut_ptr().cast(),
                &mut glen,
            )
        };
        let n = if rc == 0 {
            glen as usize / std::mem::size_of::<libc::gid_t>()
        } else {
            0
        };
        groups.truncate(n);
        Ok(Peer {
            pid: cred.pid,
            uid: cred.uid,
            gid: cred.gid,
            groups,
        })
    }
}

/// A connected peer's credentials.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Peer {
    /// Process id.
    pub pid: i32,
    /// User id.
    pub uid: u32,
    /// Primary group id.
    pub gid: u32,
    /// Supplementary groups.
    pub groups: Vec<u32>,
}

impl Peer {
    /// Whether the peer is in group `gid` (primary or supplementary).
    pub fn in_group(&self, gid: u32) -> bool {
        self.gid == gid || self.groups.contains(&gid)
    }
}
