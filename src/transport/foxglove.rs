//! The live view: each served arm's ticks, as the channels of an MCAP log (docs/MCAP.md), sent
//! to Foxglove and Lichtblick over the Foxglove WebSocket protocol by the Foxglove SDK's
//! server (`omnid serve --foxglove [ADDR]`).
//!
//! Off the loop twice over: the station's tap only hands each tick record to a bounded channel
//! (a full channel drops the tick), and a thread per arm encodes the messages and
//! gives them to the server, which runs on a tokio runtime of its own thread. Each viewer has
//! its own queue in the server (1024 messages, the oldest dropped first), so a slow or stuck
//! viewer loses its own messages and nothing else.
//!
//! The port viewers reach is omnid's own gate, not the SDK's listener: it holds at most
//! [`MAX_CONNECTIONS`] connections (viewers and handshakes in progress), at most
//! [`MAX_HANDSHAKES_PER_HOST`] handshakes from one address, and closes a connection that has
//! not sent its whole WebSocket upgrade request within [`HANDSHAKE_DEADLINE`]; a connection
//! past a cap is closed as soon as it is accepted. What passes is relayed to the SDK's server
//! on a loopback port of its own. So connections that never finish their handshake cost the
//! daemon a bounded number of descriptors, and the Unix socket keeps its own (docs/ZENOH.md,
//! "Ports and descriptors").

use crate::omni::kinematics::Geometry;
use crate::station::Tap;
use crate::telemetry::mcap_log::write::TickEncoder;
use crate::telemetry::mcap_log::{Topic, TOPICS};
use crate::telemetry::record::{LogSchema, TickRecord};
use crossbeam_channel::{Receiver, Sender};
use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;
use thiserror::Error;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Where the live view listens unless told: loopback only.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8765";

/// How long a stopping live view waits for its viewers to close.
const STOP_GRACE: std::time::Duration = std::time::Duration::from_secs(1);

/// Ticks queued between an arm's station and its encoder thread (a quarter second at 1 kHz).
const QUEUE_TICKS: usize = 256;

/// Connections the live view holds at once: viewers, and connections still in their handshake
/// (each viewer costs the daemon three descriptors: its own and both ends of the relay).
pub const MAX_CONNECTIONS: usize = 32;

/// Handshakes in progress from one address: a host that opens connections and sends nothing
/// leaves the other slots to other hosts.
pub const MAX_HANDSHAKES_PER_HOST: usize = 4;

/// A connection must have sent its whole WebSocket upgrade request within this, or is closed.
pub const HANDSHAKE_DEADLINE: Duration = Duration::from_secs(5);

/// The largest upgrade request (request line and headers) taken, bytes.
const MAX_REQUEST_HEAD: usize = 16 * 1024;

/// A failed accept (out of descriptors, say) pauses the gate this long instead of spinning.
const ACCEPT_PAUSE: Duration = Duration::from_millis(50);

/// How often what is sent once or on change (the URDF, mode, flags, …) is sent again, for
/// viewers that connect later.
const REPEAT_EVERY_TICKS: u64 = 1000;

/// Why the live view could not start.
#[derive(Debug, Error)]
pub enum LiveViewError {
    /// `--foxglove` is not `HOST:PORT`.
    #[error("--foxglove {0}: expected HOST:PORT (e.g. {DEFAULT_ADDR}, or 0.0.0.0:8765 to be reached from other machines)")]
    Address(String),
    /// The server did not start (the port taken, the address not this machine's).
    #[error(
        "the Foxglove live view cannot listen on {addr}: {message} (if another program holds \
         the port, choose another with --foxglove HOST:PORT, e.g. 127.0.0.1:{})",
        addr.port().wrapping_add(1).max(1024)
    )]
    Start {
        /// The address asked for.
        addr: SocketAddr,
        /// What the server said.
        message: String,
    },
}

/// Parse `--foxglove`'s value.
pub fn parse_addr(s: &str) -> Result<SocketAddr, LiveViewError> {
    s.parse().map_err(|_| LiveViewError::Address(s.to_string()))
}

/// A running live view server.
pub struct LiveView {
    context: Arc<foxglove::Context>,
    addr: SocketAddr,
    gate: Arc<Gate>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<JoinHandle<()>>,
    /// Channels shared by every arm (`/tf`).
    shared: std::sync::Mutex<Vec<(Topic, Arc<foxglove::RawChannel>)>>,
}

impl LiveView {
    /// Start the server on `addr` (port 0: any free port; [`LiveView::addr`] says which).
    pub fn start(addr: SocketAddr) -> Result<LiveView, LiveViewError> {
        let start_error = |message: String| LiveViewError::Start { addr, message };
        // The gate's port is bound here, so a port that cannot be had is said at once.
        let outer = std::net::TcpListener::bind(addr)
            .and_then(|l| l.set_nonblocking(true).map(|()| l))
            .map_err(|e| start_error(e.to_string()))?;
        let bound = outer.local_addr().map_err(|e| start_error(e.to_string()))?;
        let context = foxglove::Context::new();
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let ctx = context.clone();
        let gate = Arc::new(Gate::default());
        let gate_counts = gate.clone();
        let thread = std::thread::Builder::new()
            .name("omnid-foxglove".into())
            .spawn(move || {
                let runtime = match tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                {
                    Ok(r) => r,
                    Err(e) => {
                        let _ = ready_tx.send(Err(e.to_string()));
                        return;
                    }
                };
                runtime.block_on(async move {
                    let outer = match tokio::net::TcpListener::from_std(outer) {
                        Ok(l) => l,
                        Err(e) => {
                            let _ = ready_tx.send(Err(e.to_string()));
                            return;
                        }
                    };
                    // The SDK's server listens on loopback only, for the gate's relays.
                    let server = ctx
                        .websocket_server()
                        .name(concat!("omnid ", env!("CARGO_PKG_VERSION")))
                        .bind("127.0.0.1", 0)
                        .start()
                        .await;
                    let handle = match server {
                        Ok(h) => h,
                        Err(e) => {
                            let _ = ready_tx.send(Err(e.to_string()));
                            return;
                        }
                    };
                    let inner = SocketAddr::from(([127, 0, 0, 1], handle.port()));
                    let _ = ready_tx.send(Ok(()));
                    // Serve until told to stop (or the LiveView is gone). The graceful stop
                    // waits for each viewer's close; one that stopped reading never closes, so
                    // it gets a second, and then the runtime's end drops its connection (and
                    // every relay with it).
                    tokio::select! {
                        () = run_gate(outer, inner, gate) => {}
                        _ = stop_rx => {}
                    }
                    let _ = tokio::time::timeout(STOP_GRACE, handle.stop().wait()).await;
                });
            })
            .map_err(|e| start_error(e.to_string()))?;
        match ready_rx.recv() {
            Ok(Ok(())) => {}
            Ok(Err(message)) => {
                let _ = thread.join();
                return Err(start_error(message));
            }
            Err(_) => return Err(start_error("its thread ended".into())),
        };
        Ok(LiveView {
            context,
            addr: bound,
            gate: gate_counts,
            stop: Some(stop_tx),
            thread: Some(thread),
            shared: Default::default(),
        })
    }

    /// What the gate has let in and turned away so far.
    pub fn counts(&self) -> GateCounts {
        self.gate.counts()
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// One channel of the server.
    fn channel(&self, topic: &str, t: Topic) -> Arc<foxglove::RawChannel> {
        let schema = foxglove::Schema::new(t.ty.name, "ros2msg", t.ty.definition.as_bytes());
        self.context
            .channel_builder(topic)
            .message_encoding("cdr")
            .schema(schema)
            .build_raw()
            .expect("a new topic with a schema")
    }

    /// The tap that shows an arm (its topics under `/<arm>` and frames under `<arm>/` when
    /// `prefixed`, as with several arms; else the plain names of an MCAP log).
    pub fn tap_for(&self, s: &crate::station::StationSetup, prefixed: bool) -> Box<dyn Tap> {
        self.tap(&s.arm.name, prefixed, s.schema, s.geometry)
    }

    fn tap(
        &self,
        arm: &str,
        prefixed: bool,
        schema: LogSchema,
        geometry: Geometry,
    ) -> Box<dyn Tap> {
        let prefix = if prefixed { arm } else { "" };
        let encoder = TickEncoder::new(schema, geometry, prefix);
        let mut channels: Vec<Option<Arc<foxglove::RawChannel>>> = vec![None; TOPICS.len()];
        for (i, t) in TOPICS.iter().enumerate() {
            if !encoder.writes(t) {
                continue;
            }
            channels[i] = Some(if t.name == "/tf" {
                // One `/tf` for every arm: viewers read transforms there.
                let mut shared = self.shared.lock().unwrap_or_else(|p| p.into_inner());
                match shared.iter().find(|(s, _)| s == t) {
                    Some((_, c)) => c.clone(),
                    None => {
                        let c = self.channel(t.name, *t);
                        shared.push((*t, c.clone()));
                        c
                    }
                }
            } else if prefixed {
                self.channel(&format!("/{arm}{}", t.name), *t)
            } else {
                self.channel(t.name, *t)
            });
        }
        let (tx, rx) = crossbeam_channel::bounded(QUEUE_TICKS);
        let thread = std::thread::Builder::new()
            .name(format!("omnid-view-{arm}"))
            .spawn(move || encode_ticks(rx, encoder, channels))
            .ok();
        Box::new(ViewTap {
            tx: Some(tx),
            thread,
        })
    }
}

impl Drop for LiveView {
    fn drop(&mut self) {
        drop(self.stop.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The encoder thread of one arm: every tick's messages to the server's channels.
fn encode_ticks(
    rx: Receiver<TickRecord>,
    mut encoder: TickEncoder,
    channels: Vec<Option<Arc<foxglove::RawChannel>>>,
) {
    let mut ticks = 0u64;
    for r in rx {
        ticks += 1;
        if ticks.is_multiple_of(REPEAT_EVERY_TICKS) {
            encoder.repeat();
        }
        let _ = encoder.encode(&r, &mut |topic, log_time, bytes| {
            if let Some(c) = &channels[topic.id] {
                c.log_with_meta(bytes, foxglove::PartialMetadata::with_log_time(log_time));
            }
            Ok(())
        });
    }
}

/// The station's side: hand the tick on, never wait.
struct ViewTap {
    tx: Option<Sender<TickRecord>>,
    thread: Option<JoinHandle<()>>,
}

impl Tap for ViewTap {
    fn on_tick(&mut self, record: &TickRecord) {
        if let Some(tx) = &self.tx {
            // A full queue (the encoder behind) drops the tick: viewers see a gap, nothing
            // else waits.
            let _ = tx.try_send(*record);
        }
    }

    fn finish(&mut self) {
        drop(self.tx.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// What the live view's gate has done (`LiveView::counts`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GateCounts {
    /// Connections held now (viewers and handshakes in progress).
    pub held: usize,
    /// Connections closed at once: a cap was reached.
    pub refused: u64,
    /// Connections closed because their handshake did not come within the deadline (or was
    /// too large, or the connection ended first).
    pub timed_out: u64,
}

/// The gate's book: connections held, handshakes in progress per address, and counts.
#[derive(Default)]
struct Gate {
    held: AtomicUsize,
    handshaking: Mutex<HashMap<IpAddr, usize>>,
    refused: AtomicU64,
    timed_out: AtomicU64,
}

impl Gate {
    fn counts(&self) -> GateCounts {
        GateCounts {
            held: self.held.load(Ordering::Relaxed),
            refused: self.refused.load(Ordering::Relaxed),
            timed_out: self.timed_out.load(Ordering::Relaxed),
        }
    }

    /// A slot for a connection from `host`, or none (a cap reached: the caller closes it).
    fn admit(self: &Arc<Gate>, host: IpAddr) -> Option<Ticket> {
        let mut handshaking = self.handshaking.lock().unwrap_or_else(|p| p.into_inner());
        let from_host = handshaking.get(&host).copied().unwrap_or(0);
        if self.held.load(Ordering::Relaxed) >= MAX_CONNECTIONS
            || from_host >= MAX_HANDSHAKES_PER_HOST
        {
            self.refused.fetch_add(1, Ordering::Relaxed);
            return None;
        }
        self.held.fetch_add(1, Ordering::Relaxed);
        handshaking.insert(host, from_host + 1);
        Some(Ticket {
            gate: self.clone(),
            host,
            handshaking: true,
        })
    }
}

/// A held connection's slot, given back when dropped.
struct Ticket {
    gate: Arc<Gate>,
    host: IpAddr,
    handshaking: bool,
}

impl Ticket {
    /// The handshake came: the host's handshake slot is free again.
    fn handshake_done(&mut self) {
        if !std::mem::replace(&mut self.handshaking, false) {
            return;
        }
        let mut handshaking = self
            .gate
            .handshaking
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        if let Some(n) = handshaking.get_mut(&self.host) {
            *n -= 1;
            if *n == 0 {
                handshaking.remove(&self.host);
            }
        }
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        self.handshake_done();
        self.gate.held.fetch_sub(1, Ordering::Relaxed);
    }
}

/// Take connections on the viewers' port for ever: each within the caps is relayed to the
/// SDK's server at `inner` once its upgrade request has come; any other is closed at once.
async fn run_gate(outer: tokio::net::TcpListener, inner: SocketAddr, gate: Arc<Gate>) {
    loop {
        let (stream, peer) = match outer.accept().await {
            Ok(c) => c,
            Err(_) => {
                // Out of descriptors (or a connection gone before it was taken): pause
                // rather than spin on a listener that stays readable.
                tokio::time::sleep(ACCEPT_PAUSE).await;
                continue;
            }
        };
        match gate.admit(peer.ip()) {
            Some(ticket) => {
                tokio::spawn(relay(stream, inner, ticket));
            }
            None => drop(stream),
        }
    }
}

/// One viewer: its upgrade request within the deadline, then every byte both ways.
async fn relay(mut outer: TcpStream, inner: SocketAddr, mut ticket: Ticket) {
    let mut head = Vec::with_capacity(1024);
    let came = tokio::time::timeout(HANDSHAKE_DEADLINE, read_head(&mut outer, &mut head)).await;
    if !matches!(came, Ok(true)) {
        ticket.gate.timed_out.fetch_add(1, Ordering::Relaxed);
        return;
    }
    ticket.handshake_done();
    if let Some(refusal) = old_subprotocol_refusal(&head) {
        let _ = outer.write_all(refusal.as_bytes()).await;
        let _ = outer.shutdown().await;
        return;
    }
    let Ok(mut back) = TcpStream::connect(inner).await else {
        return;
    };
    let _ = outer.set_nodelay(true);
    let _ = back.set_nodelay(true);
    if back.write_all(&head).await.is_err() {
        return;
    }
    let _ = tokio::io::copy_bidirectional(&mut outer, &mut back).await;
}

/// A viewer that offers only the old `foxglove.websocket.v1` subprotocol (the open-source
/// Foxglove Studio, older Lichtblick) is answered with a 400 that says what to use, instead of
/// the SDK's bare refusal; None for any other request (the SDK's server decides).
fn old_subprotocol_refusal(head: &[u8]) -> Option<String> {
    let text = String::from_utf8_lossy(head);
    let offered: Vec<&str> = text
        .lines()
        .filter_map(|l| l.split_once(':'))
        .filter(|(k, _)| k.trim().eq_ignore_ascii_case("sec-websocket-protocol"))
        .flat_map(|(_, v)| v.split(','))
        .map(str::trim)
        .collect();
    let old = offered.contains(&"foxglove.websocket.v1");
    let new = offered.iter().any(|p| p.starts_with("foxglove.sdk."));
    (old && !new).then(|| {
        let body = "omnid's live view speaks the Foxglove SDK's protocol (foxglove.sdk.v1); this \
                    viewer offered only foxglove.websocket.v1. Open it with Foxglove, or \
                    Lichtblick 1.22.1 or later (docs/ARCHITECTURE.md, the live view).\n";
        format!(
            "HTTP/1.1 400 Bad Request\r\nContent-Type: text/plain; charset=utf-8\r\n\
             Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
            body.len()
        )
    })
}

/// Read until the end of an HTTP request's head (a blank line) into `head`: false if the
/// connection ended first or the head is larger than [`MAX_REQUEST_HEAD`].
async fn read_head(stream: &mut TcpStream, head: &mut Vec<u8>) -> bool {
    let mut chunk = [0u8; 2048];
    loop {
        let n = match stream.read(&mut chunk).await {
            Ok(0) | Err(_) => return false,
            Ok(n) => n,
        };
        // Look for the blank line from a little before the new bytes (it may straddle).
        let from = head.len().saturating_sub(3);
        head.extend_from_slice(&chunk[..n]);
        if head[from..].windows(4).any(|w| w == b"\r\n\r\n") {
            return true;
        }
        if head.len() > MAX_REQUEST_HEAD {
            return false;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_viewer_offering_only_the_old_subprotocol_is_told_what_to_use() {
        let old =
            b"GET / HTTP/1.1\r\nHost: x\r\nSec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n";
        let r = old_subprotocol_refusal(old).expect("refused with a reason");
        assert!(
            r.starts_with("HTTP/1.1 400 ") && r.contains("Lichtblick 1.22.1"),
            "{r}"
        );
        let (head, body) = r.split_once("\r\n\r\n").unwrap();
        assert!(
            head.contains(&format!("Content-Length: {}", body.len())),
            "{r}"
        );
        let both = b"GET / HTTP/1.1\r\nsec-websocket-protocol: foxglove.websocket.v1, foxglove.sdk.v1\r\n\r\n";
        assert_eq!(old_subprotocol_refusal(both), None);
        assert_eq!(old_subprotocol_refusal(b"GET / HTTP/1.1\r\n\r\n"), None);
    }
}
