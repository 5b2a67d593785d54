//! The connection to `omnid serve` and who reads it. One thread at a time reads the socket:
//! the device's receiving thread, or — while the scheduler runs on this device's samples — the
//! scheduler's own thread, so a sample wakes the frame that answers it directly, with no
//! hand-over between threads on the way (docs/HDAPI.md, Scheduler). Every other thread waits
//! on the inbox for what the reader files there.

use omnid_client::protocol::{State, MAX_MESSAGE};
use omnid_client::socket::Conn;
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

/// The state's `flags` bits set on one tick only (docs/PROTOCOL.md): the safety layer's speed
/// trip and a servo stall. The reader keeps them until a frame takes them.
pub const ONE_TICK: u32 = (1 << 11) | (1 << 12);

/// What the reader files for the other threads.
#[derive(Default)]
pub struct Inbox {
    pub latest: Option<State>,
    /// Samples received (the scheduler runs one frame per sample).
    pub samples: u64,
    /// The time between the last two samples' arrival on this host, s (what a program's
    /// servo loop sees, jitter included).
    pub dt: f64,
    /// When the last sample arrived.
    pub received_at: Option<Instant>,
    /// The stylus has been seen in its inkwell since the device was opened.
    pub inkwell_seen: bool,
    /// `flags` bits of [`ONE_TICK`] any sample carried since the last frame took them: a bit
    /// set on one tick only is seen even by a frame that runs on a later sample.
    pub one_tick_flags: u32,
    pub replies: HashMap<u64, Value>,
    pub closed: bool,
    /// The thread that filed the last message (which thread reads is the point of [`Link`]).
    pub filed_by: Option<ThreadId>,
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
        if !self.reads_here() {
            // Taken over while we waited: the new reader is waiting for this message.
            return;
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
        i.filed_by = Some(std::thread::current().id());
        match v["type"].as_str() {
            Some("state") => {
                if let Ok(s) = serde_json::from_value::<State>(v) {
                    let now = Instant::now();
                    if let Some(prev) = i.received_at.replace(now) {
                        // Samples read in one batch (within 50 µs) arrived together: keep the
                        // last real interval.
                        let dt = (now - prev).as_secs_f64();
                        if dt > 50e-6 {
                            i.dt = dt;
                        }
                    }
                    i.inkwell_seen |= s.inkwell;
                    i.one_tick_flags |= s.flags & ONE_TICK;
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

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn state(seq: u64) -> Vec<u8> {
        let zero = [0.0; 3];
        json!({"type": "state", "seq": seq, "t": seq as f64 * 1e-3, "q": zero, "qd": zero,
               "tip_mm": zero, "buttons": [false, false], "inkwell": false, "tau": zero,
               "tau_hat": zero, "controller": "pd", "mode": "idle", "amps": false,
               "flags": 0, "cmd_seq": 0})
        .to_string()
        .into_bytes()
    }

    /// A connected pair: (the library's link, the daemon's end).
    fn pair() -> (Arc<Link>, Conn) {
        let (client, daemon) = Conn::pair().unwrap();
        (Arc::new(Link::new(client)), daemon)
    }

    const WAIT: Duration = Duration::from_secs(5);

    #[test]
    fn the_thread_that_takes_over_reads_files_replies_for_others_and_hands_back() {
        let (link, daemon) = pair();
        let rx = link.spawn_receiver().unwrap();
        let rx_id = rx.thread().id();

        // Nobody took over: the receiving thread files, another thread is woken.
        daemon.send(&state(1)).unwrap();
        link.wait_for(WAIT, |i| (i.samples >= 1).then_some(()))
            .unwrap();
        assert_eq!(link.inbox().filed_by, Some(rx_id));

        // A "scheduler" takes over: it reads its samples itself, and a reply another thread
        // waits for is filed for that thread on the way.
        let (took_over, go) = (
            Arc::new(std::sync::Barrier::new(2)),
            Arc::new(std::sync::Barrier::new(2)),
        );
        let scheduler = {
            let (link, took_over, go) = (link.clone(), took_over.clone(), go.clone());
            std::thread::spawn(move || {
                link.take_reading();
                took_over.wait();
                go.wait();
                let n = link.wait_for(WAIT, |i| (i.samples >= 3).then_some(i.samples));
                let by = link.inbox().filed_by;
                link.give_back_reading();
                (n, by, std::thread::current().id())
            })
        };
        took_over.wait();
        let requester = {
            let link = link.clone();
            std::thread::spawn(move || link.wait_for(WAIT, |i| i.replies.remove(&7)))
        };
        go.wait();
        daemon
            .send(&json!({"type": "ok", "id": 7}).to_string().into_bytes())
            .unwrap();
        daemon.send(&state(2)).unwrap();
        daemon.send(&state(3)).unwrap();
        let (n, by, scheduler_id) = scheduler.join().unwrap();
        assert_eq!(n, Ok(3));
        assert_eq!(by, Some(scheduler_id), "the scheduler read its own samples");
        assert_eq!(requester.join().unwrap().unwrap()["id"], 7);

        // Handed back: the receiving thread reads again (a waiter that is not the reader).
        daemon.send(&state(4)).unwrap();
        link.wait_for(WAIT, |i| (i.samples >= 4).then_some(()))
            .unwrap();
        assert_eq!(link.inbox().filed_by, Some(rx_id));

        // The daemon's goodbye closes the link for every waiter.
        daemon.send(br#"{"type":"bye"}"#).unwrap();
        assert_eq!(link.wait_for(WAIT, |_| None::<()>), Err(WaitEnd::Closed));
        link.shut();
        rx.join().unwrap();
    }
}
