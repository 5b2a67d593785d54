//! The live view: each served arm's ticks, as the channels of an MCAP log (docs/MCAP.md), sent
//! to Foxglove and Lichtblick over the Foxglove WebSocket protocol by the Foxglove SDK's
//! server (`omnid serve --foxglove [ADDR]`).
//!
//! Off the loop twice over: the station's tap only hands each tick record to a bounded channel
//! (a full channel drops the tick), and a thread per arm encodes the messages and
//! gives them to the server, which runs on a tokio runtime of its own thread. Each viewer has
//! its own queue in the server (1024 messages, the oldest dropped first), so a slow or stuck
//! viewer loses its own messages and nothing else.

use crate::omni::kinematics::Geometry;
use crate::station::Tap;
use crate::telemetry::mcap_log::write::TickEncoder;
use crate::telemetry::mcap_log::{Topic, TOPICS};
use crate::telemetry::record::{LogSchema, TickRecord};
use crossbeam_channel::{Receiver, Sender};
use std::net::SocketAddr;
use std::sync::Arc;
use std::thread::JoinHandle;
use thiserror::Error;

/// Where the live view listens unless told: loopback only.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8765";

/// How long a stopping live view waits for its viewers to close.
const STOP_GRACE: std::time::Duration = std::time::Duration::from_secs(1);

/// Ticks queued between an arm's station and its encoder thread (a quarter second at 1 kHz).
const QUEUE_TICKS: usize = 256;

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
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<JoinHandle<()>>,
    /// Channels shared by every arm (`/tf`).
    shared: std::sync::Mutex<Vec<(Topic, Arc<foxglove::RawChannel>)>>,
}

impl LiveView {
    /// Start the server on `addr` (port 0: any free port; [`LiveView::addr`] says which).
    pub fn start(addr: SocketAddr) -> Result<LiveView, LiveViewError> {
        let context = foxglove::Context::new();
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let ctx = context.clone();
        let start_error = |message: String| LiveViewError::Start { addr, message };
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
                    let server = ctx
                        .websocket_server()
                        .name(concat!("omnid ", env!("CARGO_PKG_VERSION")))
                        .bind(addr.ip().to_string(), addr.port())
                        .start()
                        .await;
                    let handle = match server {
                        Ok(h) => h,
                        Err(e) => {
                            let _ = ready_tx.send(Err(e.to_string()));
                            return;
                        }
                    };
                    let _ = ready_tx.send(Ok(handle.port()));
                    // Serve until told to stop (or the LiveView is gone). The graceful stop
                    // waits for each viewer's close; one that stopped reading never closes, so
                    // it gets a second, and then the runtime's end drops its connection.
                    let _ = stop_rx.await;
                    let _ = tokio::time::timeout(STOP_GRACE, handle.stop().wait()).await;
                });
            })
            .map_err(|e| start_error(e.to_string()))?;
        let port = match ready_rx.recv() {
            Ok(Ok(port)) => port,
            Ok(Err(message)) => {
                let _ = thread.join();
                return Err(start_error(message));
            }
            Err(_) => return Err(start_error("its thread ended".into())),
        };
        Ok(LiveView {
            context,
            addr: SocketAddr::new(addr.ip(), port),
            stop: Some(stop_tx),
            thread: Some(thread),
            shared: Default::default(),
        })
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
