//! Files from outside the process, opened and read so that no wait is beyond the operator's
//! reach and no row or file takes unbounded memory.
//!
//! - [`open`] never blocks: it opens with `O_NONBLOCK` (opening a FIFO for reading otherwise
//!   waits for a writer). A regular file is then read as usual. Anything else (a FIFO, a pipe
//!   from `<(…)`, a character device) is read only when the caller has a stop flag: each read
//!   waits in `poll` for at most [`POLL_SLICE_MS`] at a time and checks the flag in between
//!   (a writer that goes quiet cannot hold it). Without a flag such a file is refused, since
//!   nothing could end the wait.
//! - Every read checks the stop flag first, so a long pass over a big regular file ends
//!   within one read of Ctrl-C too. A stop is an [`io::Error`] carrying [`Stopped`].
//! - [`RowBound`] caps the bytes a CSV reader may take for one row ([`MAX_ROW_BYTES`]), so a
//!   file without line ends (`/dev/zero`, a 1 GB single line) is an error naming the row, not
//!   an allocation as big as the file.
//! - [`read_capped`] reads a small file whole (config, weights, stored state) up to a size.

use std::fs::{File, OpenOptions};
use std::io::{self, Read};
use std::os::fd::AsRawFd;
use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use thiserror::Error;

/// The most bytes one CSV row (its line, or lines when a quoted field spans several) may
/// take. An omnid log row is under 1 kB; this leaves room for any recording with many or long
/// columns while keeping a reader's buffer small.
pub const MAX_ROW_BYTES: u64 = 1 << 20;

/// Longest single wait in `poll` between two looks at the stop flag, ms.
pub const POLL_SLICE_MS: i32 = 50;

/// The operator asked to stop (Ctrl-C or SIGTERM) while a read waited or went on.
#[derive(Debug, Error)]
#[error("stopped by the operator")]
pub struct Stopped;

/// A row ran past [`MAX_ROW_BYTES`].
#[derive(Debug, Error)]
#[error("row longer than {limit} bytes")]
pub struct RowTooLong {
    /// The cap, bytes.
    pub limit: u64,
}

/// A file read whole was bigger than its limit.
#[derive(Debug, Error)]
#[error("larger than {}, the most accepted for this file", size(*.limit))]
pub struct TooBig {
    /// The file's limit, bytes.
    pub limit: u64,
}

/// A special file where only a regular one will do (no stop flag to end a wait on it).
#[derive(Debug, Error)]
#[error("{kind}, not a regular file")]
pub struct NotRegular {
    /// What it is instead, e.g. `a character device`.
    pub kind: &'static str,
}

/// `1 MiB`, `64 KiB`, `100 bytes`.
fn size(bytes: u64) -> String {
    if bytes >= 1 << 20 && bytes.is_multiple_of(1 << 20) {
        format!("{} MiB", bytes >> 20)
    } else if bytes >= 1 << 10 && bytes.is_multiple_of(1 << 10) {
        format!("{} KiB", bytes >> 10)
    } else {
        format!("{bytes} bytes")
    }
}

/// The error was a stop (see [`Stopped`]).
pub fn is_stopped(e: &io::Error) -> bool {
    e.get_ref().is_some_and(|inner| inner.is::<Stopped>())
}

/// The limit, when the error was a row over it (see [`RowBound`]).
pub fn row_too_long(e: &io::Error) -> Option<u64> {
    e.get_ref()
        .and_then(|inner| inner.downcast_ref::<RowTooLong>())
        .map(|r| r.limit)
}

/// What kind of file this is, when it is not a regular one.
pub fn special_kind(file_type: std::fs::FileType) -> Option<&'static str> {
    if file_type.is_file() {
        None
    } else if file_type.is_fifo() {
        Some("a FIFO (named pipe) or pipe")
    } else if file_type.is_char_device() {
        Some("a character device")
    } else if file_type.is_block_device() {
        Some("a block device")
    } else if file_type.is_socket() {
        Some("a socket")
    } else if file_type.is_dir() {
        Some("a directory")
    } else {
        Some("a special file")
    }
}

/// An open input file (see the module documentation).
#[derive(Debug)]
pub struct Input {
    file: File,
    /// Not a regular file: reads wait in `poll`, in slices.
    special: bool,
    stop: Option<Arc<AtomicBool>>,
}

/// Open `path` for reading without blocking. `stop`: the operator's stop flag; without one,
/// only a regular file (which never makes a read wait) is accepted.
pub fn open(path: &Path, stop: Option<&Arc<AtomicBool>>) -> io::Result<Input> {
    let file = OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)?;
    let kind = special_kind(file.metadata()?.file_type());
    match (kind, stop) {
        (Some(kind), None) => return Err(io::Error::other(NotRegular { kind })),
        (Some(_), Some(_)) => {}
        // A regular file: blocking reads, as any other.
        (None, _) => {
            let fd = file.as_raw_fd();
            // SAFETY: fd is the open descriptor of `file`; F_GETFL/F_SETFL touch only its flags.
            let flags = unsafe { libc::fcntl(fd, libc::F_GETFL) };
            if flags < 0 || unsafe { libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_NONBLOCK) } < 0
            {
                return Err(io::Error::last_os_error());
            }
        }
    }
    Ok(Input {
        file,
        special: kind.is_some(),
        stop: stop.cloned(),
    })
}

impl Input {
    fn stopped(&self) -> bool {
        self.stop
            .as_ref()
            .is_some_and(|s| s.load(Ordering::Relaxed))
    }
}

impl Read for Input {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        loop {
            if self.stopped() {
                return Err(io::Error::other(Stopped));
            }
            if !self.special {
                return self.file.read(buf);
            }
            let mut fd = libc::pollfd {
                fd: self.file.as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            };
            // SAFETY: one valid pollfd, for the duration of the call.
            let rc = unsafe { libc::poll(&mut fd, 1, POLL_SLICE_MS) };
            if rc < 0 {
                let e = io::Error::last_os_error();
                if e.kind() == io::ErrorKind::Interrupted {
                    continue;
                }
                return Err(e);
            }
            if rc == 0 {
                continue;
            }
            // Readable, at its end, or in error: the read says which (or that it was a false
            // alarm, EAGAIN, and we wait again).
            match self.file.read(buf) {
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
                    ) => {}
                result => return result,
            }
        }
    }
}

/// A reader that refuses to hand a CSV parser more than [`MAX_ROW_BYTES`] past the start of the
/// row being parsed (the parser says where each row starts with [`RowBound::row_starts_at`]).
/// The parser reads ahead in small chunks, so its buffers stay within the limit and a chunk.
#[derive(Debug)]
pub struct RowBound<R> {
    inner: R,
    /// Bytes handed out so far.
    read: u64,
    /// Offset of the start of the row being parsed.
    row_start: u64,
}

impl<R> RowBound<R> {
    /// `inner` capped, the first row starting at byte 0.
    pub fn new(inner: R) -> Self {
        RowBound {
            inner,
            read: 0,
            row_start: 0,
        }
    }

    /// The next row starts at byte `offset` of the input.
    pub fn row_starts_at(&mut self, offset: u64) {
        self.row_start = offset;
    }
}

impl<R: Read> Read for RowBound<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.read.saturating_sub(self.row_start) > MAX_ROW_BYTES {
            return Err(io::Error::other(RowTooLong {
                limit: MAX_ROW_BYTES,
            }));
        }
        let n = self.inner.read(buf)?;
        self.read += n as u64;
        Ok(n)
    }
}

/// Read a small text file whole: at most `limit` bytes, UTF-8 (see [`open`] for `stop`).
pub fn read_capped(path: &Path, limit: u64, stop: Option<&Arc<AtomicBool>>) -> io::Result<String> {
    let input = open(path, stop)?;
    let mut bytes = Vec::new();
    input.take(limit + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(io::Error::other(TooBig { limit }));
    }
    String::from_utf8(bytes)
        .map_err(|_| io::Error::new(io::ErrorKind::InvalidData, "not UTF-8 text"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;
    use std::time::{Duration, Instant};

    fn fifo(dir: &Path) -> std::path::PathBuf {
        let path = dir.join("fifo");
        let c = std::ffi::CString::new(path.to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        path
    }

    #[test]
    fn a_fifo_without_a_writer_opens_at_once_and_its_read_ends_on_stop() {
        let dir = tempfile::tempdir().unwrap();
        let path = fifo(dir.path());
        let e = open(&path, None).unwrap_err();
        assert!(e.to_string().contains("FIFO"), "{e}");
        let stop = Arc::new(AtomicBool::new(false));
        let mut input = open(&path, Some(&stop)).unwrap();
        let flag = stop.clone();
        let setter = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(200));
            flag.store(true, Ordering::Relaxed);
        });
        let t0 = Instant::now();
        let e = input.read(&mut [0; 16]).unwrap_err();
        setter.join().unwrap();
        assert!(is_stopped(&e), "{e}");
        // Within about a second of the flag (the wait is in 50 ms slices).
        assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
    }

    #[test]
    fn a_fifo_is_read_to_its_end_when_the_writer_closes() {
        let dir = tempfile::tempdir().unwrap();
        let path = fifo(dir.path());
        let stop = Arc::new(AtomicBool::new(false));
        let mut input = open(&path, Some(&stop)).unwrap();
        let writer_path = path.clone();
        let writer = std::thread::spawn(move || {
            let mut w = OpenOptions::new().write(true).open(writer_path).unwrap();
            w.write_all(b"t,q1\n").unwrap();
            std::thread::sleep(Duration::from_millis(120));
            w.write_all(b"0,1\n").unwrap();
        });
        let mut text = String::new();
        input.read_to_string(&mut text).unwrap();
        writer.join().unwrap();
        assert_eq!(text, "t,q1\n0,1\n");
    }

    #[test]
    fn a_set_flag_stops_a_regular_file_too() {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(b"abc").unwrap();
        let stop = Arc::new(AtomicBool::new(true));
        let e = open(f.path(), Some(&stop))
            .unwrap()
            .read(&mut [0; 4])
            .unwrap_err();
        assert!(is_stopped(&e));
        let mut text = String::new();
        open(f.path(), None)
            .unwrap()
            .read_to_string(&mut text)
            .unwrap();
        assert_eq!(text, "abc");
    }

    #[test]
    fn rows_are_bounded_and_small_files_capped() {
        let long = vec![b'x'; MAX_ROW_BYTES as usize + 20_000];
        let mut bound = RowBound::new(&long[..]);
        let mut buf = [0u8; 8192];
        let mut total = 0u64;
        let e = loop {
            match bound.read(&mut buf) {
                Ok(0) => panic!("read to the end"),
                Ok(n) => total += n as u64,
                Err(e) => break e,
            }
        };
        assert_eq!(row_too_long(&e), Some(MAX_ROW_BYTES));
        assert!(total <= MAX_ROW_BYTES + 8192, "{total}");
        // A new row start lets it go on.
        bound.row_starts_at(total);
        assert!(bound.read(&mut buf).is_ok());

        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(&[b'a'; 100]).unwrap();
        assert_eq!(read_capped(f.path(), 100, None).unwrap().len(), 100);
        let e = read_capped(f.path(), 99, None).unwrap_err();
        assert_eq!(
            e.to_string(),
            "larger than 99 bytes, the most accepted for this file"
        );
        let e = read_capped(Path::new("/dev/zero"), 1 << 16, None).unwrap_err();
        assert_eq!(e.to_string(), "a character device, not a regular file");
        let stop = Arc::new(AtomicBool::new(false));
        let e = read_capped(Path::new("/dev/zero"), 1 << 16, Some(&stop)).unwrap_err();
        assert!(e.to_string().contains("64 KiB"), "{e}");
    }
}
