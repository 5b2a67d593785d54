//! The connection to `omnid serve` and who reads it. One thread at a time reads the socket:
//! the device's receiving thread, or — while the scheduler runs on this device's samples — the
//! scheduler's own thread, so a sample wakes the frame that answers it directly, with no
//! hand-over between threads on the way (docs/HDAPI.md, Scheduler). Every other thread waits
//! on the inbox for what the reader files there.

use omnid::serve::protocol::{State, MAX_MESSAGE};
use omnid::serve::socket::Conn;
use serde_json::Value;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};
use std::thread::{JoinHandle, ThreadId};
use std::time::{Duration, Instant};

/// Longest single wait of a reader on the socket (it then looks at its stop flag again).
const READ_SLICE_MS: i32 = 100;

/// Messages read in one go once the socket is readable: whatever has queued up, so a frame
/// after a slow one runs on the newest sample, but bounded so a flood cannot pin the reader.
const MAX_BATCH: usize = 256;

/// What the reader files for the other threads.
#[derive(Default)]
pub struct Inbox {
    pub latest: Option<State>,
    /// Samples received (the scheduler runs one frame per sample).
    pub samples: u64,
    /// The device time between the last two samples, s.
    pub dt: f64,
    /// The stylus has been seen in its inkwell since the device was opened.
    pub inkwell_seen: bool,
    pub replies: HashMap<u64, Value>,
    pub closed: bool,
}

/// Why a wait on the inbox ended without what it waited for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WaitEnd {
    Timeout,
    Closed,
}

pub struct Link {
    pub conn: Conn,
    inbox: Mutex<Inbox>,
    filed: Condvar,
    /// The receiving thread's id, once it runs.
    rx_id: OnceLock<ThreadId>,
    /// The thread that took over reading from the receiving thread, if any.
    reader: Mutex<Option<ThreadId>>,
    reader_back: Condvar,
    /// The receive buffer, held by whichever thread reads.
    buf: Mutex<Vec<u8>>,
    closing: AtomicBool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic elsewhere never poisons the library for good: the data are plain values.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Link {
    pub fn new(conn: Conn) -> Link {
        Link {
            conn,
            inbox: Mutex::new(Inbox::default()),
            filed: Condvar::new(),
            rx_id: OnceLock::new(),
            reader: Mutex::new(None),
            reader_back: Condvar::new(),
            buf: Mutex::new(vec![0u8; MAX_MESSAGE + 1]),
            closing: AtomicBool::new(false),
        }
    }

    /// Start the receiving thread: it reads whenever no other thread has taken over.
    pub fn spawn_receiver(self: &Arc<Self>) -> std::io::Result<JoinHandle<()>> {
        let link = self.clone();
        let handle = std::thread::Builder::new()
            .name("omnid-hd-rx".into())
            .spawn(move || link.receive())?;
        let _ = self.rx_id.set(handle.thread().id());
        Ok(handle)
    }

    /// A look at the inbox.
    pub fn inbox(&self) -> MutexGuard<'_, Inbox> {
        lock(&self.inbox)
    }

    /// The calling thread reads the socket from now on (the scheduler, as it starts).
    pub fn take_reading(&self) {
        *lock(&self.reader) = Some(std::thread::current().id());
    }

    /// The calling thread stops reading: the receiving thread reads again.
    pub fn give_back_reading(&self) {
        let mut r = lock(&self.reader);
        if *r == Some(std::thread::current().id()) {
            *r = None;
            self.reader_back.notify_all();
        }
    }

    fn reads_here(&self) -> bool {
        let me = std::thread::current().id();
        match *lock(&self.reader) {
            Some(t) => t == me,
            None => self.rx_id.get() == Some(&me),
        }
    }

    /// Wait until `take` finds what it looks for in the inbox. The reading thread reads the
    /// socket meanwhile; any other thread sleeps until the reader files something.
    pub fn wait_for<T>(
        &self,
        timeout: Duration,
        mut take: impl FnMut(&mut Inbox) -> Option<T>,
    ) -> Result<T, WaitEnd> {
        let until = Instant::now() + timeout;
        let mut inbox = lock(&self.inbox);
        loop {
            if let Some(found) = take(&mut inbox) {
                return Ok(found);
            }
            if inbox.closed {
                return Err(WaitEnd::Closed);
            }
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(WaitEnd::Timeout);
            }
            if self.reads_here() {
                drop(inbox);
                let slice = left.as_millis().clamp(1, READ_SLICE_MS as u128) as i32;
                self.read(slice);
                inbox = lock(&self.inbox);
            } else {
                inbox = self
                    .filed
                    .wait_timeout(inbox, left)
                    .unwrap_or_else(|e| e.into_inner())
                    .0;
            }
        }
    }

    /// The receiving thread: reads while nobody else does, until the device closes.
    fn receive(&self) {
        while !self.closing.load(Ordering::Relaxed) && !self.inbox().closed {
            {
                let r = lock(&self.reader);
                if r.is_some() {
                    let _ = self
                        .reader_back
                        .wait_timeout(r, Duration::from_millis(READ_SLICE_MS as u64));
                    continue;
                }
            }
            self.read(READ_SLICE_MS);
        }
        self.close_inbox();
    }

    /// Wait up to `timeout_ms` for the socket, then read and file everything queued.
    fn read(&self, timeout_ms: i32) {
        let mut buf = lock(&self.buf);
        match self.conn.wait_readable(timeout_ms) {
            Ok(true) => {}
            Ok(false) => return,
            Err(_) => return self.close_inbox(),
        }
        for _ in 0..MAX_BATCH {
            let n = match self.conn.recv(&mut buf) {
                Ok(0) | Err(_) => return self.close_inbox(),
                Ok(n) => n.min(buf.len()),
            };
            if !self.file(&buf[..n]) {
                return self.close_inbox();
            }
            if !self.conn.wait_readable(0).unwrap_or(false) {
                break;
            }
        }
        self.filed.notify_all();
    }

    /// File one message: a sample, or a reply by its id. False on the daemon's goodbye.
    fn file(&self, msg: &[u8]) -> bool {
        let Ok(v) = serde_json::from_slice::<Value>(msg) else {
            return true;
        };
        let mut i = lock(&self.inbox);
        match v["type"].as_str() {
            Some("state") => {
                if let Ok(s) = serde_json::from_value::<State>(v) {
                    if let Some(prev) = &i.latest {
                        let dt = s.t - prev.t;
                        if dt > 0.0 {
                            i.dt = dt;
                        }
                    }
                    i.inkwell_seen |= s.inkwell;
                    i.latest = Some(s);
                    i.samples += 1;
                }
            }
            Some("bye") => return false,
            _ => {
                if let Some(id) = v.get("id").and_then(Value::as_u64) {
                    i.replies.insert(id, v);
                }
            }
        }
        true
    }

    fn close_inbox(&self) {
        lock(&self.inbox).closed = true;
        self.filed.notify_all();
    }

    /// Stop the receiving thread and wake every waiter (the socket is shut down).
    pub fn shut(&self) {
        self.closing.store(true, Ordering::Relaxed);
        // SAFETY: shutdown on a descriptor we own; it wakes a reader's poll.
        unsafe { libc::shutdown(self.conn.raw(), libc::SHUT_RDWR) };
        self.reader_back.notify_all();
    }
}
