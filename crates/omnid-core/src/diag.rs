//! The process's diagnostic lines (`errln!`), written to stderr by a thread of their own: a
//! stderr nobody drains (a paused pager, a stalled log collector) blocks that thread only,
//! never the hub, a writer or the stop path. Lines beyond what the queue holds are counted and
//! the count is written when stderr moves again; at exit the CLI waits a bounded time for the
//! lines still queued ([`flush`]). Failed writes to stdout are kept here too, so that output
//! lost to a full disk is not a success.

use crossbeam_channel::{bounded, Sender};
use std::io::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// Lines held for a stderr that does not drain.
const QUEUE: usize = 4096;

static LINES: OnceLock<Option<Sender<String>>> = OnceLock::new();
static QUEUED: AtomicU64 = AtomicU64::new(0);
static WRITTEN: AtomicU64 = AtomicU64::new(0);
static DROPPED: AtomicU64 = AtomicU64::new(0);
static STDOUT_FAILED: OnceLock<String> = OnceLock::new();

fn writer() -> Option<Sender<String>> {
    let (tx, rx) = bounded::<String>(QUEUE);
    std::thread::Builder::new()
        .name("omnid-stderr".into())
        .spawn(move || {
            for line in rx {
                let mut err = std::io::stderr().lock();
                let dropped = DROPPED.swap(0, Ordering::Relaxed);
                if dropped > 0 {
                    let _ = writeln!(
                        err,
                        "omnid: {dropped} diagnostic lines dropped (stderr was not drained)"
                    );
                }
                let _ = err.write_all(line.as_bytes());
                WRITTEN.fetch_add(1, Ordering::Release);
            }
        })
        .ok()?;
    Some(tx)
}

/// Queue `line` (with its newline) for stderr; never waits. Without the writer thread (it
/// could not be started) the line is written here.
pub fn line(line: String) {
    match LINES.get_or_init(writer) {
        Some(tx) => {
            QUEUED.fetch_add(1, Ordering::AcqRel);
            if tx.try_send(line).is_err() {
                QUEUED.fetch_sub(1, Ordering::AcqRel);
                DROPPED.fetch_add(1, Ordering::Relaxed);
            }
        }
        None => {
            let _ = std::io::stderr().write_all(line.as_bytes());
        }
    }
}

/// Wait at most `timeout` for every line queued so far to be written; false if some were
/// not (stderr does not drain: the process exits anyway).
pub fn flush(timeout: Duration) -> bool {
    let target = QUEUED.load(Ordering::Acquire);
    let until = Instant::now() + timeout;
    while WRITTEN.load(Ordering::Acquire) < target {
        if Instant::now() >= until {
            return false;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    true
}

/// Note a failed write to stdout (`out!`, `outln!`). A closed pipe is the reader's choice and
/// not kept; anything else (a full disk) is, the first one only.
pub fn stdout_error(e: std::io::Error) {
    if e.kind() != std::io::ErrorKind::BrokenPipe {
        let _ = STDOUT_FAILED.set(e.to_string());
    }
}

/// Why output to stdout was lost, if it was (for the exit code).
pub fn stdout_failed() -> Option<&'static str> {
    STDOUT_FAILED.get().map(String::as_str)
}
