//! The log writer thread: drains the bounded telemetry channel into a buffered CSV file. A
//! write error (disk full) is remembered and reported, but the thread keeps draining so the
//! servo loop never notices.
//!
//! The thread polls the channel (drain, then sleep `POLL`, 1 ms) instead of blocking in `recv`:
//! a receiver parked in `recv` must be woken by the sender, which would put a futex
//! syscall into every servo tick.

use super::mcap_log::LogFormat;
use super::record::{LogSchema, TickRecord};
use super::recorder::{Csv, Recorder};
use crate::output::{describe, OutputError};
use crossbeam_channel::{Receiver, TryRecvError};
use std::collections::VecDeque;
use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::os::fd::AsRawFd;
use std::os::unix::fs::{FileTypeExt, MetadataExt};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;

/// The recorder for logs of `schema` in `format`: the one place that chooses among the
/// formats (`recorder` defines the trait and CSV, `mcap_log::write` MCAP).
pub(crate) fn recorder(schema: LogSchema, format: LogFormat) -> Box<dyn Recorder> {
    match super::mcap_log::write::for_format(schema, format) {
        Some(mcap) => Box::new(mcap),
        None => Box::new(Csv { schema }),
    }
}

/// Ticks kept for the fault dump.
pub(crate) const DUMP_TICKS: usize = 500;

/// How long the writer sleeps when the channel is empty. At 1 kHz this leaves about one row
/// per wake-up; the channel (8192 rows by default) has seconds of slack.
pub(crate) const POLL: std::time::Duration = std::time::Duration::from_millis(1);

/// Hand every item to `each` until the senders are gone, sleeping `POLL` (1 ms) whenever the
/// channel is empty (never parked in `recv`, so a send never has to wake this thread).
pub fn for_each_polled<T>(rx: &Receiver<T>, mut each: impl FnMut(T)) {
    loop {
        match rx.try_recv() {
            Ok(item) => each(item),
            Err(TryRecvError::Empty) => std::thread::sleep(POLL),
            Err(TryRecvError::Disconnected) => return,
        }
    }
}

#[derive(Debug)]
pub(crate) struct WriterReport {
    pub(crate) path: PathBuf,
    pub(crate) schema: LogSchema,
    /// Rows that reached the file (whole rows: a row cut by a failed write is taken back).
    pub(crate) rows: u64,
    /// Rows the writer was given.
    pub(crate) received: u64,
    /// The first write error, if any; rows after it are lost.
    pub(crate) error: Option<io::Error>,
    /// The last [`DUMP_TICKS`] records received, oldest first (for the fault dump).
    pub(crate) tail: VecDeque<TickRecord>,
    /// The log, still open: its lock holds until the report is dropped, so no other omnid
    /// takes the log (or its fault dump) while the run finishes.
    pub(crate) file: File,
}

/// `run.csv` → `run-fault.csv`, beside the log.
pub(crate) fn dump_path(log: &Path) -> PathBuf {
    let stem = log
        .file_stem()
        .map(|s| s.to_string_lossy())
        .unwrap_or_default();
    let name = match log.extension() {
        Some(ext) => format!("{stem}-fault.{}", ext.to_string_lossy()),
        None => format!("{stem}-fault"),
    };
    log.with_file_name(name)
}

/// The last ticks before a fault, in the log's format (the same recorder as the log, so a
/// dump reads as a log does).
pub(crate) fn dump_rows(
    out: &mut impl Write,
    schema: &LogSchema,
    format: LogFormat,
    rows: &VecDeque<TickRecord>,
) -> io::Result<()> {
    let mut rec = recorder(*schema, format);
    let mut bytes = Vec::with_capacity(512);
    rec.header(&mut bytes)?;
    for r in rows {
        rec.row(r, &mut bytes)?;
        out.write_all(&bytes)?;
        bytes.clear();
    }
    rec.finish_rows(&mut bytes)?;
    rec.footer(&mut bytes)?;
    out.write_all(&bytes)
}

/// Where a fault dump goes.
pub(crate) enum DumpTo<'a> {
    /// This file (`run.csv` → `run-fault.csv`, beside a run's log).
    File(&'a Path),
    /// A new file `<dir>/<stem>.csv` (`-2`, `-3`, … when taken): a daemon's dumps.
    Unique { dir: &'a Path, stem: &'a str },
}

/// Write a fault dump, whole, through [`crate::output`] (a temporary file renamed into
/// place): `run`'s and `serve`'s dumps take this one path. The file written.
pub(crate) fn write_dump(
    to: DumpTo<'_>,
    schema: &LogSchema,
    format: LogFormat,
    rows: &VecDeque<TickRecord>,
) -> Result<PathBuf, OutputError> {
    match to {
        DumpTo::File(path) => crate::output::write_with(path, |w| {
            dump_rows(w, schema, format, rows).map_err(|source| OutputError::Write {
                path: path.to_path_buf(),
                source,
            })
        })
        .map(|()| path.to_path_buf()),
        DumpTo::Unique { dir, stem } => {
            crate::output::write_unique(dir, stem, format.extension(), |w| {
                dump_rows(w, schema, format, rows)
            })
        }
    }
}

/// Why a log could not be opened.
#[derive(Debug, Error)]
pub enum LogError {
    /// Creating or opening the file failed.
    #[error("cannot create log {}: {source}", path.display())]
    Io {
        /// The log's path.
        path: PathBuf,
        /// What the system reported.
        source: io::Error,
    },
    /// The path is something a log cannot be written to (a directory, a socket, …).
    #[error("cannot create log {}: it is {what}; a log is a file, a character device such as /dev/null, or a FIFO", path.display())]
    Unsuitable {
        /// The log's path.
        path: PathBuf,
        /// What it is instead, in words.
        what: &'static str,
    },
    /// A client's recording names a file that exists (or a symlink).
    #[error("cannot record to {}: it exists; a recording goes to a new file (nothing is replaced)", path.display())]
    Exists {
        /// The path given.
        path: PathBuf,
    },
    /// Another omnid process holds the log's lock.
    #[error("log {} is in use: another omnid writes it", path.display())]
    InUse {
        /// The log's path.
        path: PathBuf,
    },
}

/// Take an exclusive `flock` without waiting: false when another process holds one. A file
/// system that cannot lock does not stop a run (true).
fn try_lock(file: &File) -> bool {
    // SAFETY: flock on a descriptor we own; no pointers.
    let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
    rc == 0 || io::Error::last_os_error().kind() != io::ErrorKind::WouldBlock
}

/// Whether `path` (followed) still names the open `file`.
fn names(path: &Path, file: &File) -> bool {
    match (std::fs::metadata(path), file.metadata()) {
        (Ok(a), Ok(b)) => (a.dev(), a.ino()) == (b.dev(), b.ino()),
        _ => false,
    }
}

/// What may be a log: a regular file or nothing (the log is made), a character device
/// (/dev/null) or a FIFO, written as they are; `Ok(true)` for a regular file.
fn suitable(path: &Path) -> Result<Option<bool>, LogError> {
    match std::fs::metadata(path) {
        Ok(m) if m.is_file() => Ok(Some(true)),
        Ok(m) if m.file_type().is_char_device() || m.file_type().is_fifo() => Ok(Some(false)),
        Ok(m) => Err(LogError::Unsuitable {
            path: path.to_path_buf(),
            what: describe(m.file_type()),
        }),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(LogError::Io {
            path: path.to_path_buf(),
            source,
        }),
    }
}

/// A run's log, open for writing and locked (`flock`) against every other omnid while open.
#[derive(Debug)]
pub(crate) struct LogFile {
    pub(crate) path: PathBuf,
    file: File,
}

/// Open a device or FIFO for writing without waiting: opening a FIFO that nobody reads would
/// block until someone does (and no signal would end the wait), so it fails at once instead;
/// once open, writes block as usual.
fn open_special(path: &Path) -> io::Result<File> {
    use std::os::unix::fs::OpenOptionsExt;
    let file = OpenOptions::new()
        .write(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
        .map_err(|e| match e.raw_os_error() {
            Some(libc::ENXIO) => io::Error::new(
                e.kind(),
                "it is a FIFO that no process reads (start its reader first)",
            ),
            _ => e,
        })?;
    // It stays non-blocking: the writer waits for it in `poll`, where the operator's stop is
    // seen (a reader that stops reading cannot hold the run past a Ctrl-C).
    Ok(file)
}

impl LogFile {
    /// A log on an already open file (tests of what a writer does when its file fails).
    #[cfg(test)]
    pub(crate) fn on(path: PathBuf, file: File) -> LogFile {
        LogFile { path, file }
    }

    /// Check `path` as a log before the work starts: a suitable kind, its directory made, a
    /// file can be created there, and no other omnid writes it.
    pub(crate) fn check(path: &Path) -> Result<(), LogError> {
        let io_err = |source| LogError::Io {
            path: path.to_path_buf(),
            source,
        };
        match suitable(path)? {
            Some(false) => Ok(()),
            Some(true) => {
                let file = File::open(path).map_err(io_err)?;
                if !try_lock(&file) {
                    return Err(LogError::InUse {
                        path: path.to_path_buf(),
                    });
                }
                Ok(())
            }
            None => crate::output::check_file(path).map_err(|e| match e {
                OutputError::Unwritable { source, .. } | OutputError::Write { source, .. } => {
                    io_err(source)
                }
                OutputError::NotAFile { what, .. } => LogError::Unsuitable {
                    path: path.to_path_buf(),
                    what,
                },
            }),
        }
    }

    /// Create the log at `path` (its directory too), or take it over if no other omnid holds
    /// it. A regular file there (ours from an earlier run) is unlinked rather than truncated:
    /// ext4 flushes a file that was truncated and rewritten when it is closed, and the next
    /// file created then waits for those tens of MB to reach the disk (~25 ms at the end of a
    /// 60 s `--fast` run). What a symlink names is truncated, a device written as it is.
    pub(crate) fn create(path: &Path) -> Result<LogFile, LogError> {
        let io_err = |source| LogError::Io {
            path: path.to_path_buf(),
            source,
        };
        let in_use = || LogError::InUse {
            path: path.to_path_buf(),
        };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(io_err)?;
        }
        // Another process may replace the file between our open and our lock: then look again.
        for _ in 0..100 {
            if suitable(path)? == Some(false) {
                let file = open_special(path).map_err(io_err)?;
                return Ok(LogFile {
                    path: path.to_path_buf(),
                    file,
                });
            }
            let file = if std::fs::symlink_metadata(path).is_ok_and(|m| m.is_file()) {
                // Opened to read: locking needs no write permission (a read-only old log is
                // replaced, as before).
                let old = File::open(path).map_err(io_err)?;
                if !try_lock(&old) {
                    return Err(in_use());
                }
                if !names(path, &old) {
                    continue;
                }
                std::fs::remove_file(path).map_err(io_err)?;
                match OpenOptions::new().write(true).create_new(true).open(path) {
                    Ok(f) => f,
                    Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
                    Err(e) => return Err(io_err(e)),
                }
            } else {
                // New, or what a symlink names: not truncated before it is ours.
                OpenOptions::new()
                    .write(true)
                    .create(true)
                    .truncate(false)
                    .open(path)
                    .map_err(io_err)?
            };
            if !file.metadata().is_ok_and(|m| m.is_file()) {
                continue;
            }
            if !try_lock(&file) {
                return Err(in_use());
            }
            if !names(path, &file) {
                continue;
            }
            file.set_len(0).map_err(io_err)?;
            return Ok(LogFile {
                path: path.to_path_buf(),
                file,
            });
        }
        Err(in_use())
    }

    /// A new regular file at `path`, for a log a client names: never an existing file (nothing
    /// is replaced), never through a symlink, never a FIFO or device (nothing a stalled reader
    /// could block).
    pub(crate) fn create_new(path: &Path) -> Result<LogFile, LogError> {
        use std::os::unix::fs::OpenOptionsExt;
        let file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(path)
            .map_err(|source| match source.kind() {
                io::ErrorKind::AlreadyExists => LogError::Exists {
                    path: path.to_path_buf(),
                },
                _ => LogError::Io {
                    path: path.to_path_buf(),
                    source,
                },
            })?;
        if !try_lock(&file) {
            return Err(LogError::InUse {
                path: path.to_path_buf(),
            });
        }
        Ok(LogFile {
            path: path.to_path_buf(),
            file,
        })
    }

    /// A new log under a default name in `dir`: `stem.csv`, else `stem-2.csv`, … (never
    /// another run's file, even for runs started in the same second).
    pub(crate) fn create_unique(dir: &Path, stem: &str, ext: &str) -> Result<LogFile, LogError> {
        let (path, file) = crate::output::create_unique(dir, stem, ext).map_err(|e| match e {
            OutputError::Unwritable { path, source } | OutputError::Write { path, source } => {
                LogError::Io { path, source }
            }
            OutputError::NotAFile { path, what } => LogError::Unsuitable { path, what },
        })?;
        // Just created: only an omnid given this very path could hold it.
        if !try_lock(&file) {
            return Err(LogError::InUse { path });
        }
        Ok(LogFile { path, file })
    }
}

/// Rows on their way to the log file, written in 64 KiB blocks; counts the rows that reached
/// the file and, after a failed write, takes back a row cut part-way.
struct RowSink {
    file: File,
    buf: Vec<u8>,
    /// Where rows end in `buf`, and how many rows end there.
    ends: Vec<(usize, u64)>,
    /// Bytes in the file, and where its last whole row ends.
    written: u64,
    whole: u64,
    rows: u64,
    error: Option<io::Error>,
    /// The operator's stop, and since when a stopped run has waited on a sink that takes
    /// nothing.
    stop: Option<Arc<AtomicBool>>,
    stalled: Option<Instant>,
}

/// How long a stopped run waits for a log's reader that takes nothing.
const STOPPED_GRACE: Duration = Duration::from_secs(1);

/// Wait (100 ms at most) for `file`, a FIFO or device opened non-blocking, to take bytes. An
/// error once the operator has stopped the run and the file has taken nothing for
/// [`STOPPED_GRACE`] (`stalled`: since when).
fn wait_writable(
    file: &File,
    stop: Option<&AtomicBool>,
    stalled: &mut Option<Instant>,
) -> io::Result<()> {
    use std::os::fd::AsRawFd;
    let mut pfd = libc::pollfd {
        fd: file.as_raw_fd(),
        events: libc::POLLOUT,
        revents: 0,
    };
    // SAFETY: one valid pollfd.
    unsafe { libc::poll(&mut pfd, 1, 100) };
    if stop.is_some_and(|s| s.load(Ordering::Relaxed)) {
        let since = *stalled.get_or_insert_with(Instant::now);
        if since.elapsed() > STOPPED_GRACE {
            return Err(io::Error::new(
                io::ErrorKind::TimedOut,
                "its reader stopped reading, and the run was stopped",
            ));
        }
    }
    Ok(())
}

/// `write_all` that waits for a non-blocking FIFO or device as [`wait_writable`] does.
fn write_all_waiting(
    file: &mut File,
    mut bytes: &[u8],
    stop: Option<&AtomicBool>,
) -> io::Result<()> {
    let mut stalled = None;
    while !bytes.is_empty() {
        match file.write(bytes) {
            Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
            Ok(n) => {
                bytes = &bytes[n..];
                stalled = None;
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                wait_writable(file, stop, &mut stalled)?
            }
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

impl RowSink {
    const BLOCK: usize = 1 << 16;

    /// Queue `bytes`, which complete `rows` rows (0: they end inside one).
    fn push(&mut self, bytes: &[u8], rows: u64) {
        if !self.buf.is_empty() && self.buf.len() + bytes.len() > Self::BLOCK {
            self.flush();
        }
        self.buf.extend_from_slice(bytes);
        if rows > 0 {
            self.ends.push((self.buf.len(), rows));
        }
    }

    fn flush(&mut self) {
        let base = self.written;
        let mut done = 0;
        let mut next_end = 0;
        while done < self.buf.len() && self.error.is_none() {
            match self.file.write(&self.buf[done..]) {
                Ok(0) => self.error = Some(io::ErrorKind::WriteZero.into()),
                Ok(n) => {
                    done += n;
                    self.written += n as u64;
                    while let Some(&(end, rows)) = self.ends.get(next_end) {
                        if end > done {
                            break;
                        }
                        self.rows += rows;
                        self.whole = base + end as u64;
                        next_end += 1;
                    }
                    self.stalled = None;
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    if let Err(e) =
                        wait_writable(&self.file, self.stop.as_deref(), &mut self.stalled)
                    {
                        self.error = Some(e);
                    }
                }
                Err(e) => self.error = Some(e),
            }
        }
        self.buf.clear();
        self.ends.clear();
        if self.error.is_some() && self.whole < self.written {
            // Best effort (a device cannot be cut): the log then ends with its last whole row.
            if self.file.set_len(self.whole).is_ok() {
                self.written = self.whole;
            }
        }
    }

    fn fail(&mut self, e: io::Error) {
        if self.error.is_none() {
            self.error = Some(e);
        }
    }
}

/// Write the header now (so an unwritable log fails before torque is enabled) and start the
/// thread that fills the log (CSV, unwatched: the tests' writer).
#[cfg(test)]
pub(crate) fn spawn_writer(
    log: LogFile,
    schema: LogSchema,
    rx: Receiver<TickRecord>,
) -> io::Result<JoinHandle<WriterReport>> {
    spawn_writer_with(
        log,
        schema,
        recorder(schema, super::mcap_log::LogFormat::Csv),
        rx,
        Watch::default(),
    )
}

/// What a writer is watched by: where it reports its first error as it happens, and the
/// operator's stop (after which it waits only briefly for a sink that takes nothing).
#[derive(Default)]
pub(crate) struct Watch {
    pub(crate) fault: Option<WriterFault>,
    pub(crate) stop: Option<Arc<AtomicBool>>,
}

/// Where a writer says, the moment it happens, that its file stopped taking rows (a disk that
/// filled, a reader that went away): set once, read by whoever should tell someone.
pub(crate) type WriterFault = std::sync::Arc<std::sync::OnceLock<String>>;

/// Write the header now (so an unwritable log fails before torque is enabled) and start the
/// thread that fills the log in the format `rec` writes, watched by `watch`.
pub(crate) fn spawn_writer_with(
    log: LogFile,
    schema: LogSchema,
    mut rec: Box<dyn super::recorder::Recorder>,
    rx: Receiver<TickRecord>,
    watch: Watch,
) -> io::Result<JoinHandle<WriterReport>> {
    let LogFile { path, mut file } = log;
    let Watch { fault, stop } = watch;
    let mut header = Vec::new();
    rec.header(&mut header)?;
    write_all_waiting(&mut file, &header, stop.as_deref())?;
    std::thread::Builder::new()
        .name("omnid-log".into())
        .spawn(move || {
            let mut sink = RowSink {
                file,
                buf: Vec::with_capacity(RowSink::BLOCK),
                ends: Vec::with_capacity(1024),
                written: header.len() as u64,
                whole: header.len() as u64,
                rows: 0,
                error: None,
                stop,
                stalled: None,
            };
            let mut tail = VecDeque::with_capacity(DUMP_TICKS);
            let mut received = 0;
            let mut line = Vec::with_capacity(512);
            for_each_polled(&rx, |record| {
                if tail.len() == DUMP_TICKS {
                    tail.pop_front();
                }
                tail.push_back(record);
                received += 1;
                if sink.error.is_some() {
                    return; // keep draining: the loop must never block on us
                }
                line.clear();
                match rec.row(&record, &mut line) {
                    Ok(rows) => sink.push(&line, rows),
                    Err(e) => sink.fail(e),
                }
                if let (Some(e), Some(f)) = (&sink.error, &fault) {
                    let _ = f.set(e.to_string());
                }
            });
            if sink.error.is_none() {
                line.clear();
                match rec.finish_rows(&mut line) {
                    Ok(rows) => sink.push(&line, rows),
                    Err(e) => sink.fail(e),
                }
            }
            sink.flush();
            // The footer is not a row: written after the last whole one.
            line.clear();
            if sink.error.is_none() {
                let footer = rec
                    .footer(&mut line)
                    .and_then(|()| write_all_waiting(&mut sink.file, &line, sink.stop.as_deref()));
                if let Err(e) = footer {
                    sink.error = Some(e);
                }
            }
            WriterReport {
                path,
                schema,
                rows: sink.rows,
                received,
                error: sink.error,
                tail,
                file: sink.file,
            }
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::telemetry::record::Mode;

    #[test]
    fn an_old_log_is_replaced_by_a_new_file_and_a_symlink_is_followed() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.csv");
        std::fs::write(&path, "old contents\n").unwrap();
        let old_inode = std::fs::metadata(&path).unwrap().ino();
        // Hold the old file open so its inode cannot be reused for the new one.
        let _old = File::open(&path).unwrap();
        drop(LogFile::create(&path).unwrap());
        let new = std::fs::metadata(&path).unwrap();
        assert_eq!(new.len(), 0);
        assert_ne!(
            new.ino(),
            old_inode,
            "the old file was truncated, not replaced"
        );

        let target = dir.path().join("target.csv");
        std::fs::write(&target, "old contents\n").unwrap();
        let link = dir.path().join("link.csv");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        drop(LogFile::create(&link).unwrap());
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::metadata(&target).unwrap().len(), 0);
    }

    #[test]
    fn a_log_held_by_another_writer_is_refused_untouched() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.csv");
        let mut first = LogFile::create(&path).unwrap();
        first.file.write_all(b"rows of the first run\n").unwrap();
        let link = dir.path().join("link.csv");
        std::os::unix::fs::symlink(&path, &link).unwrap();
        for p in [&path, &link] {
            for e in [
                LogFile::check(p).unwrap_err(),
                LogFile::create(p).unwrap_err(),
            ] {
                assert!(matches!(e, LogError::InUse { .. }), "{e}");
                assert!(e.to_string().contains("another omnid"), "{e}");
            }
        }
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "rows of the first run\n"
        );
        assert!(names(&path, &first.file));
        drop(first);
        LogFile::create(&path).unwrap();
        // Devices are written as they are, by any number of runs at once.
        let a = LogFile::create(Path::new("/dev/null")).unwrap();
        let b = LogFile::create(Path::new("/dev/null")).unwrap();
        LogFile::check(Path::new("/dev/null")).unwrap();
        drop((a, b));
        let sub = dir.path().join("sub");
        std::fs::create_dir(&sub).unwrap();
        assert!(matches!(
            LogFile::check(&sub).unwrap_err(),
            LogError::Unsuitable { .. }
        ));
    }

    #[test]
    fn rows_that_did_not_reach_the_file_are_not_counted() {
        let file = OpenOptions::new().write(true).open("/dev/full").unwrap();
        let mut sink = RowSink {
            file,
            buf: Vec::new(),
            ends: Vec::new(),
            written: 0,
            whole: 0,
            rows: 0,
            error: None,
            stop: None,
            stalled: None,
        };
        sink.push(b"1,2,3\n", 1);
        sink.push(b"4,5,6\n", 1);
        sink.flush();
        assert_eq!(sink.rows, 0);
        assert_eq!(
            sink.error.map(|e| e.raw_os_error()),
            Some(Some(libc::ENOSPC))
        );
        // The header already fails: a log on a full disk is refused before the run.
        let (_tx, rx) = crossbeam_channel::bounded(1);
        let log = LogFile::create(Path::new("/dev/full")).unwrap();
        assert!(spawn_writer(log, LogSchema::new(false), rx).is_err());
    }

    #[test]
    fn writes_header_and_rows_that_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/run.csv");
        let (tx, rx) = crossbeam_channel::bounded(4);
        let schema = LogSchema::new(true);
        let handle = spawn_writer(LogFile::create(&path).unwrap(), schema, rx).unwrap();
        let rec = TickRecord {
            q: [0.1, 0.2, 1.0 / 3.0],
            tau: [1e-17, -0.0, 0.45],
            tau_model: [f64::NAN; 3],
            enc: [-5, 0, 70000],
            flags: 1,
            haptic: crate::telemetry::record::HapticRecord {
                tip_mm: [1.5, -2.0, 3.0],
                force: [0.25, 0.0, -1.0],
                hand: [0.0, 0.75, 0.0],
                fext: [-0.5, 0.125, 2.0],
            },
            tau_ext: [0.0, -0.03, 0.0],
            ..TickRecord::at(1, Mode::Track)
        };
        tx.send(rec).unwrap();
        drop(tx);
        let report = handle.join().unwrap();
        assert_eq!((report.rows, report.received), (1, 1));
        assert!(report.error.is_none());
        let text = std::fs::read_to_string(&path).unwrap();
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().unwrap().split(',').collect();
        assert_eq!(header.len(), schema.columns().len());
        let row: Vec<&str> = lines.next().unwrap().split(',').collect();
        assert_eq!(row.len(), header.len());
        // Shortest round-trip formatting: parsing gives back the exact bits.
        assert_eq!(row[3].parse::<f64>().unwrap(), 1.0 / 3.0);
        assert_eq!(row[4].parse::<f64>().unwrap(), 1e-17);
        assert_eq!(
            row[header.iter().position(|h| *h == "enc3").unwrap()],
            "70000"
        );
        assert_eq!(row[header.len() - 2], "track");
        let col = |name: &str| row[header.iter().position(|h| *h == name).unwrap()];
        assert_eq!(
            (col("tip2"), col("fcmd3"), col("fhand2")),
            ("-2.0", "-1.0", "0.75")
        );
        // The force estimate, beside the other tip forces and torques.
        assert_eq!(
            (col("fext1"), col("fext2"), col("fext3"), col("tau_ext2")),
            ("-0.5", "0.125", "2.0", "-0.03")
        );
        let at = |name: &str| header.iter().position(|h| *h == name).unwrap();
        assert_eq!(at("tau_ext1"), at("tau_model3") + 1);
        assert_eq!(at("fext1"), at("fhand3") + 1);
        assert_eq!(at("enc1"), at("fext3") + 1);
    }

    #[test]
    fn dump_sits_beside_the_log() {
        assert_eq!(
            dump_path(Path::new("/a/run.csv")),
            Path::new("/a/run-fault.csv")
        );
        assert_eq!(dump_path(Path::new("run")), Path::new("run-fault"));
    }

    #[test]
    fn unwritable_path_fails_before_anything_runs() {
        let path = Path::new("/proc/omnid/run.csv");
        assert!(LogFile::check(path).is_err());
        assert!(LogFile::create(path).is_err());
    }
}
