//! The thread that serves clients: one `poll` loop over the servo's wake-up eventfd, the
//! listening socket and every client. It turns each tick's record into one JSON state
//! message shared by every streaming client, queues it per client (a slow client loses its
//! oldest samples, counted and reported to it), sends without ever blocking, and turns
//! clients' requests into servo commands. Everything that allocates happens here, never on
//! the servo thread.

use super::access::{Access, Policy};
use super::protocol::{Hello, Request, State, MAX_MESSAGE, PROTOCOL_VERSION};
use super::socket::{Conn, Listener, Peer};
use crate::control::{ControllerKind, Trajectory};
use crate::identifier::{Identifier, IdentifierConfig};
use crate::omni::kinematics::{tip_position_mm, Geometry};
use crate::servo::summary::{FaultEntry, IdentifierState, RunSummary, SummaryLabels};
use crate::servo::{Activity, ServoCommand, ServoEvent, ServoReply, Snapshot, Wake};
use crate::telemetry::record::{LogSchema, Mode, TickRecord};
use crate::telemetry::writer::dump_rows;
use crate::telemetry::{spawn_writer, LogError, LogFile, WriterReport};
use crossbeam_channel::{Receiver, Sender, TryRecvError};
use serde_json::{json, Value};
use std::collections::VecDeque;
use std::io;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;

/// How long `poll` waits when nothing happens: the stop flag is seen this soon.
const POLL_MS: i32 = 50;

/// Requests taken from one client per wake-up, so a flooding client cannot starve the rest.
const READS_PER_WAKE: usize = 64;

/// Replies and events a client may leave unread (states are bounded separately and dropped
/// oldest first); past this the client is not reading and is disconnected.
const MAX_UNREAD_REPLIES: usize = 4096;

/// Write `ring` (the last ticks) to a new file `<dir>/faults/omnid-serve-<UTC>-<why>-fault.csv`
/// (a new name for every dump: two faults in one second keep both) and say where; `None`
/// when it cannot be written (said too).
pub(crate) fn write_fault_dump(
    dir: &std::path::Path,
    schema: &LogSchema,
    ring: &VecDeque<TickRecord>,
    why: &str,
) -> Option<PathBuf> {
    let written = crate::output::write_unique(
        &dir.join("faults"),
        &format!("omnid-serve-{}-{why}-fault", utc_stamp()),
        "csv",
        |w| dump_rows(w, schema, ring),
    );
    match written {
        Ok(path) => {
            crate::errln!(
                "omnid serve: the last ticks before the fault are in {}",
                path.display()
            );
            Some(path)
        }
        Err(e) => {
            crate::errln!("omnid serve: cannot write the fault dump: {e}");
            None
        }
    }
}

/// What the hub was built with.
pub struct HubSetup {
    pub(crate) listener: Listener,
    pub(crate) wake: Arc<Wake>,
    pub(crate) records: Receiver<TickRecord>,
    pub(crate) commands: Sender<ServoCommand>,
    pub(crate) replies: Receiver<ServoReply>,
    pub(crate) stop: Arc<AtomicBool>,
    pub(crate) policy: Policy,
    pub(crate) serve: super::ServeConfig,
    pub(crate) device: String,
    /// The device's serial number, when its backend knows one.
    pub(crate) serial: Option<String>,
    pub(crate) rate_hz: f64,
    pub(crate) period_ns: u64,
    pub(crate) schema: LogSchema,
    pub(crate) geometry: Geometry,
    pub(crate) identifier_cfg: IdentifierConfig,
    /// The identifier as the servo started with it (shape for weight snapshots).
    pub(crate) identifier: Identifier,
    pub(crate) controller: ControllerKind,
    pub(crate) weights_label: String,
    pub(crate) seed: u64,
    /// Where recordings without a path and fault dumps go.
    pub(crate) state_dir: PathBuf,
    /// The realtime steps the servo thread took (set before its first tick).
    pub(crate) realtime: Arc<std::sync::OnceLock<crate::servo::realtime::RealtimeReport>>,
}

/// What the hub saw, for the daemon's exit.
pub struct HubReport {
    pub(crate) shutdown_requested: bool,
    /// Safety trips the daemon survived (it went idle).
    pub(crate) faults: Vec<FaultEntry>,
    /// Fault dumps written.
    pub(crate) dumps: Vec<PathBuf>,
    /// The last tick records, oldest first (for a dump at the end).
    pub(crate) ring: VecDeque<TickRecord>,
    /// An error of the recording in progress at the end, if any.
    pub(crate) recording_error: Option<String>,
    /// Clients told goodbye (their connections are closed when the report is dropped).
    pub(crate) clients: Vec<ClientConn>,
}

/// A connection kept until the daemon's socket is gone.
pub(crate) struct ClientConn(#[allow(dead_code)] Conn);

/// One message waiting for a client.
enum Out {
    /// A state sample (shared by every client that gets it; may be dropped when late).
    State(Arc<[u8]>),
    /// Anything else: never dropped.
    Msg(Vec<u8>),
}

struct Client {
    id: u64,
    conn: Conn,
    peer: Peer,
    name: String,
    access: Access,
    greeted: bool,
    /// Every `every`-th tick is streamed (0: not streaming).
    every: u64,
    queue: VecDeque<Out>,
    states: usize,
    lost_total: u64,
    lost_unreported: u64,
    /// Flush what is queued, then drop the connection.
    closing: bool,
    dead: bool,
}

/// A request waiting for the servo's answer.
enum Waiting {
    Status {
        client: u64,
        id: Option<Value>,
    },
    Save {
        client: u64,
        id: Option<Value>,
        path: PathBuf,
    },
}

struct Recording {
    tx: Option<Sender<TickRecord>>,
    writer: JoinHandle<WriterReport>,
    path: PathBuf,
    dropped: u64,
}

/// The thread that serves clients of `omnid serve`: admits them, streams states, passes
/// their commands to the servo and answers them (docs/PROTOCOL.md).
pub struct Hub {
    s: HubSetup,
    clients: Vec<Client>,
    next_id: u64,
    lease: Option<u64>,
    /// The stream fallback the holder chose (`lease` with `fallback`), if it did.
    lease_fallback: Option<Activity>,
    /// One snapshot box circulates: here when `Some`, at the servo otherwise.
    spare: Option<Box<Snapshot>>,
    waiting: Vec<Waiting>,
    /// Weight loads sent to the servo, answered when the old identifier comes back.
    loads: VecDeque<(u64, Option<Value>, String)>,
    adapt: bool,
    last: Option<TickRecord>,
    ring: VecDeque<TickRecord>,
    ring_cap: usize,
    recording: Option<Recording>,
    faults: Vec<FaultEntry>,
    dumps: Vec<PathBuf>,
    shutdown_requested: bool,
    buf: Vec<u8>,
    /// Accepting fails (said once per episode, not once per wake-up).
    accept_failing: bool,
    /// After an accept error nothing could answer, the listener rests until then.
    accept_paused_until: Option<std::time::Instant>,
}

/// How long the listener rests after an accept error that could not be answered.
const ACCEPT_PAUSE: std::time::Duration = std::time::Duration::from_millis(100);

/// Say why to a client that will not be served, and take what it sent: closing with its hello
/// unread would reset the connection and could discard the reason before the client reads it.
fn refuse(conn: &Conn, message: String) {
    let _ = conn.send(&encode(&json!({
        "type": "error", "op": "connect", "message": message
    })));
    let mut sink = [0u8; 512];
    while conn.recv(&mut sink).is_ok_and(|n| n > 0) {}
}

fn encode(v: &Value) -> Vec<u8> {
    serde_json::to_vec(v).unwrap_or_default()
}

fn utc_stamp() -> String {
    crate::telemetry::utc_stamp(std::time::SystemTime::now())
}

impl Hub {
    /// A hub over the socket and the servo mailbox that `daemon::prepare` set up.
    pub fn new(s: HubSetup) -> Hub {
        let ring_cap = (s.serve.ring_s * s.rate_hz).round().max(1.0) as usize;
        let spare = Some(Box::new(Snapshot::new(
            s.period_ns,
            Some(s.identifier.clone()),
        )));
        let adapt = s.identifier.config().adapt;
        Hub {
            clients: Vec::new(),
            next_id: 1,
            lease: None,
            lease_fallback: None,
            spare,
            waiting: Vec::new(),
            loads: VecDeque::new(),
            adapt,
            last: None,
            ring: VecDeque::with_capacity(ring_cap),
            ring_cap,
            recording: None,
            faults: Vec::new(),
            dumps: Vec::new(),
            shutdown_requested: false,
            buf: vec![0; MAX_MESSAGE + 1],
            accept_failing: false,
            accept_paused_until: None,
            s,
        }
    }

    /// Serve until the servo thread has ended (its record channel closes).
    pub fn run(mut self) -> HubReport {
        loop {
            let servo_done = self.drain_records();
            self.drain_replies();
            self.flush_all();
            if servo_done {
                break;
            }
            if let Err(e) = self.poll_once() {
                crate::errln!("omnid serve: poll: {e}");
                std::thread::sleep(std::time::Duration::from_millis(POLL_MS as u64));
            }
        }
        self.finish()
    }

    /// Tell the servo which ticks to wake us for: the gcd of the streaming clients' sample
    /// intervals.
    fn publish_every(&self) {
        fn gcd(a: u64, b: u64) -> u64 {
            if b == 0 {
                a
            } else {
                gcd(b, a % b)
            }
        }
        let every = self
            .clients
            .iter()
            .filter(|c| c.greeted && !c.dead && c.every > 0)
            .fold(0, |g, c| gcd(g, c.every));
        self.s.wake.set_every(every);
    }

    fn poll_once(&mut self) -> io::Result<()> {
        let mut fds = Vec::with_capacity(2 + self.clients.len());
        fds.push(libc::pollfd {
            fd: self.s.wake.fd().as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        });
        let resting = self
            .accept_paused_until
            .is_some_and(|t| std::time::Instant::now() < t);
        fds.push(libc::pollfd {
            // A negative descriptor is skipped by poll: the listener rests.
            fd: if resting { -1 } else { self.s.listener.raw() },
            events: libc::POLLIN,
            revents: 0,
        });
        for c in &self.clients {
            let out = if c.queue.is_empty() { 0 } else { libc::POLLOUT };
            fds.push(libc::pollfd {
                fd: c.conn.raw(),
                events: libc::POLLIN | out,
                revents: 0,
            });
        }
        // SAFETY: `fds` is a live array of `fds.len()` pollfd structs.
        let rc = unsafe { libc::poll(fds.as_mut_ptr(), fds.len() as libc::nfds_t, POLL_MS) };
        if rc < 0 {
            let e = io::Error::last_os_error();
            return if e.kind() == io::ErrorKind::Interrupted {
                Ok(())
            } else {
                Err(e)
            };
        }
        if fds[0].revents != 0 {
            self.s.wake.clear();
        }
        // Clients first (their indices match `fds`), then new connections.
        for (i, p) in fds[2..].iter().enumerate() {
            if p.revents & (libc::POLLIN | libc::POLLHUP | libc::POLLERR) != 0 {
                self.read_client(i);
            }
        }
        self.clients.retain(|c| !c.dead);
        if fds[1].revents & libc::POLLIN != 0 {
            self.accept_all();
        }
        self.publish_every();
        Ok(())
    }

    fn accept_all(&mut self) {
        loop {
            let conn = match self.s.listener.accept() {
                Ok(Some(c)) => {
                    self.accept_failing = false;
                    c
                }
                Ok(None) => return,
                Err(e) => {
                    if !self.accept_failing {
                        crate::errln!(
                            "omnid serve: accept: {e} ({} clients connected); new clients are \
                             refused until it clears",
                            self.clients.len()
                        );
                        self.accept_failing = true;
                    }
                    let out_of_descriptors =
                        matches!(e.raw_os_error(), Some(libc::EMFILE | libc::ENFILE));
                    let message = format!(
                        "the daemon cannot take a connection now ({e}; {} clients connected)",
                        self.clients.len()
                    );
                    if out_of_descriptors && self.s.listener.shed_one(|c| refuse(c, message)) {
                        continue;
                    }
                    self.accept_paused_until = Some(std::time::Instant::now() + ACCEPT_PAUSE);
                    return;
                }
            };
            let peer = match conn.peer() {
                Ok(p) => p,
                Err(_) => continue,
            };
            let access = match self.s.policy.decide(&peer) {
                Ok(a) => a,
                Err(message) => {
                    refuse(&conn, message);
                    continue;
                }
            };
            if self.clients.len() >= self.s.serve.max_clients {
                refuse(
                    &conn,
                    format!(
                        "too many clients ({}; serve.max_clients)",
                        self.s.serve.max_clients
                    ),
                );
                continue;
            }
            let id = self.next_id;
            self.next_id += 1;
            self.clients.push(Client {
                id,
                conn,
                peer,
                name: String::new(),
                access,
                greeted: false,
                every: 0,
                queue: VecDeque::new(),
                states: 0,
                lost_total: 0,
                lost_unreported: 0,
                closing: false,
                dead: false,
            });
        }
    }

    fn read_client(&mut self, i: usize) {
        for _ in 0..READS_PER_WAKE {
            if self.clients[i].dead || self.clients[i].closing {
                return;
            }
            let n = match self.clients[i].conn.recv(&mut self.buf) {
                Ok(0) => {
                    self.drop_client(i);
                    return;
                }
                Ok(n) => n,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(_) => {
                    self.drop_client(i);
                    return;
                }
            };
            if n > MAX_MESSAGE {
                self.fail(
                    i,
                    None,
                    "message",
                    format!("message of {n} bytes is larger than {MAX_MESSAGE}; closing"),
                );
                self.clients[i].closing = true;
                return;
            }
            let request = match serde_json::from_slice::<Request>(&self.buf[..n]) {
                Ok(r) => r,
                Err(e) => {
                    let op = serde_json::from_slice::<Value>(&self.buf[..n])
                        .ok()
                        .and_then(|v| v.get("op").and_then(|o| o.as_str()).map(String::from))
                        .unwrap_or_else(|| "?".into());
                    let hello = self.clients[i].greeted;
                    let why = crate::text::cut(&e.to_string());
                    self.fail(i, None, &op, format!("bad request: {why}"));
                    if !hello {
                        self.clients[i].closing = true;
                    }
                    continue;
                }
            };
            self.handle(i, request);
            let c = &mut self.clients[i];
            if c.queue.len() - c.states > MAX_UNREAD_REPLIES && !c.closing {
                let message = format!(
                    "more than {MAX_UNREAD_REPLIES} replies unread: disconnecting a client that \
                     does not read"
                );
                crate::errln!("omnid serve: client {}: {message}", c.id);
                self.fail(i, None, "message", message);
                self.clients[i].closing = true;
                // Its socket is full: what cannot be sent now is not waited for.
                self.clients[i].dead = true;
                self.drop_client(i);
                return;
            }
        }
    }

    /// The client leaves: its lease goes, and a stream it fed falls back.
    fn drop_client(&mut self, i: usize) {
        let c = &mut self.clients[i];
        c.dead = true;
        let id = c.id;
        if self.lease == Some(id) {
            self.end_lease();
            self.broadcast(json!({
                "type": "event", "event": "lease", "holder": null,
                "message": format!("client {id} left; the command lease is free"),
            }));
        }
    }

    fn queue_msg(&mut self, i: usize, v: Value) {
        self.clients[i].queue.push_back(Out::Msg(encode(&v)));
    }

    fn reply(&mut self, i: usize, op: &str, id: Option<&Value>, mut extra: Value) {
        extra["type"] = json!("reply");
        extra["op"] = json!(op);
        if let Some(id) = id {
            extra["id"] = id.clone();
        }
        self.queue_msg(i, extra);
    }

    fn fail(&mut self, i: usize, id: Option<&Value>, op: &str, message: String) {
        let mut v = json!({ "type": "error", "op": op, "message": message });
        if let Some(id) = id {
            v["id"] = id.clone();
        }
        self.queue_msg(i, v);
    }

    fn index_of(&self, client: u64) -> Option<usize> {
        self.clients.iter().position(|c| c.id == client && !c.dead)
    }

    fn broadcast(&mut self, v: Value) {
        let bytes = encode(&v);
        for c in self.clients.iter_mut().filter(|c| c.greeted && !c.dead) {
            c.queue.push_back(Out::Msg(bytes.clone()));
        }
    }

    /// One request from client `i`. Long only in its match: one arm per request op, each a
    /// call or a few lines, so the whole protocol reads in one place.
    fn handle(&mut self, i: usize, request: Request) {
        let op = request.op();
        let id = request.id().cloned();
        let id = id.as_ref();
        if !self.clients[i].greeted {
            return self.greet(i, id, op, request);
        }
        if request.commands() {
            if self.clients[i].access != Access::Control {
                let why = self.s.policy.read_only_reason(&self.clients[i].peer);
                return self.fail(i, id, op, why);
            }
            if let Err(why) = self.take_lease(i) {
                return self.fail(i, id, op, why);
            }
        }
        match request {
            Request::Hello { .. } => self.fail(i, id, op, "already greeted".into()),
            Request::Stream { rate_hz, .. } => self.set_stream(i, id, op, rate_hz),
            Request::Status { .. } => {
                let client = self.clients[i].id;
                self.ask_snapshot(Waiting::Status {
                    client,
                    id: id.cloned(),
                });
            }
            Request::Lease { fallback, .. } => self.lease(i, id, op, fallback.as_deref()),
            Request::Release { .. } => self.release(i, id, op),
            Request::Mode {
                mode, trajectory, ..
            } => self.mode(i, id, &mode, trajectory.as_deref()),
            Request::Hold { .. } => self.mode(i, id, "hold", None),
            Request::Free { .. } => self.mode(i, id, "free", None),
            Request::ServoJp { seq, q, ttl_ms, .. } => {
                if let Some(ttl_s) = self.stream_check(i, id, op, &q, ttl_ms) {
                    self.send_servo(i, id, op, ServoCommand::ServoJp { seq, q, ttl_s }, None);
                }
            }
            Request::ServoJf {
                seq, tau, ttl_ms, ..
            } => {
                if let Some(ttl_s) = self.stream_check(i, id, op, &tau, ttl_ms) {
                    self.send_servo(i, id, op, ServoCommand::ServoJf { seq, tau, ttl_s }, None);
                }
            }
            Request::ServoCf {
                seq, force, ttl_ms, ..
            } => {
                if let Some(ttl_s) = self.stream_check(i, id, op, &force, ttl_ms) {
                    let cmd = ServoCommand::ServoCf { seq, force, ttl_s };
                    self.send_servo(i, id, op, cmd, None);
                }
            }
            Request::Effect { slot, effect, .. } => self.effect(i, id, op, slot, effect),
            Request::Passivity { on, .. } => self.send_servo(
                i,
                id,
                op,
                ServoCommand::Passivity(on),
                Some(json!({ "passivity": on })),
            ),
            Request::Controller { controller, .. } => match ControllerKind::parse(&controller) {
                Some(kind) => self.send_servo(
                    i,
                    id,
                    op,
                    ServoCommand::Controller(kind),
                    Some(json!({ "controller": kind.as_str() })),
                ),
                None => self.fail(
                    i,
                    id,
                    op,
                    format!("unknown controller `{controller}`: expected pd, ct, nnidc or off"),
                ),
            },
            Request::Adapt { on, .. } => {
                self.adapt = on;
                self.send_servo(
                    i,
                    id,
                    op,
                    ServoCommand::Adapt(on),
                    Some(json!({ "adapt": on })),
                );
            }
            Request::WeightsSave { path, .. } => {
                let client = self.clients[i].id;
                self.ask_snapshot(Waiting::Save {
                    client,
                    id: id.cloned(),
                    path: PathBuf::from(path),
                });
            }
            Request::WeightsLoad { path, .. } => self.weights_load(i, id, op, path),
            Request::RecordStart { path, .. } => self.record_start(i, id, path),
            Request::RecordStop { .. } => match self.record_stop() {
                Some((path, rows, error)) => {
                    let reply = json!({ "path": path, "rows": rows, "error": error });
                    self.reply(i, op, id, reply)
                }
                None => self.fail(i, id, op, "not recording".into()),
            },
            Request::Shutdown { .. } => {
                self.shutdown_requested = true;
                self.s.stop.store(true, Ordering::SeqCst);
                self.reply(i, op, id, json!({}));
            }
        }
    }

    /// A client's first message must be a hello in our protocol version; anything else
    /// closes the connection after a reply saying why.
    fn greet(&mut self, i: usize, id: Option<&Value>, op: &'static str, request: Request) {
        match request {
            Request::Hello { protocol, name, .. } if protocol == PROTOCOL_VERSION => {
                let c = &mut self.clients[i];
                c.greeted = true;
                c.name = name.unwrap_or_default().chars().take(64).collect();
                let hello = Hello {
                    protocol: PROTOCOL_VERSION,
                    server: format!("omnid {}", env!("CARGO_PKG_VERSION")),
                    device: self.s.device.clone(),
                    rate_hz: self.s.rate_hz,
                    access: c.access.as_str().into(),
                    client: c.id,
                    stream_ttl_ms: self.s.serve.stream_ttl_ms,
                    controllers: ControllerKind::ALL.map(|k| k.as_str().into()).into(),
                    modes: [
                        "idle", "hold", "track", "free", "servo_jp", "servo_jf", "servo_cf",
                    ]
                    .map(String::from)
                    .into(),
                    model: super::device_info::model(&self.s.device).into(),
                    vendor: super::device_info::VENDOR.into(),
                    serial: self.s.serial.clone(),
                    firmware: None,
                };
                let mut v = serde_json::to_value(hello).unwrap_or_default();
                v["type"] = json!("hello");
                if let Some(id) = id {
                    v["id"] = id.clone();
                }
                self.queue_msg(i, v);
            }
            Request::Hello { protocol, .. } => {
                self.fail(
                    i,
                    id,
                    op,
                    format!(
                        "protocol {protocol} is not supported: this daemon speaks \
                         {PROTOCOL_VERSION}"
                    ),
                );
                self.clients[i].closing = true;
            }
            _ => {
                self.fail(
                    i,
                    id,
                    op,
                    "say hello first: {\"op\":\"hello\",\"protocol\":1}".into(),
                );
                self.clients[i].closing = true;
            }
        }
    }

    /// Start (every `rate / rate_hz`-th tick) or stop (0) this client's state stream.
    fn set_stream(&mut self, i: usize, id: Option<&Value>, op: &'static str, rate_hz: f64) {
        if !(rate_hz.is_finite() && rate_hz >= 0.0) {
            return self.fail(i, id, op, format!("rate_hz {rate_hz}: allowed ≥ 0"));
        }
        let every = if rate_hz == 0.0 {
            0
        } else {
            (self.s.rate_hz / rate_hz).round().max(1.0) as u64
        };
        self.clients[i].every = every;
        let actual = if every == 0 {
            0.0
        } else {
            self.s.rate_hz / every as f64
        };
        self.reply(i, op, id, json!({ "rate_hz": actual, "every": every }));
    }

    /// The lease (taken before any command runs), with this holder's stream fallback.
    fn lease(&mut self, i: usize, id: Option<&Value>, op: &'static str, fallback: Option<&str>) {
        let to = match fallback {
            None => None,
            Some("hold") => Some(Activity::Hold),
            Some("idle") => Some(Activity::Idle),
            Some("free") => Some(Activity::Free),
            Some(other) => {
                let why = format!("fallback `{other}`: expected hold, idle or free");
                return self.fail(i, id, op, why);
            }
        };
        if let Some(to) = to {
            if self
                .s
                .commands
                .try_send(ServoCommand::Fallback(to))
                .is_err()
            {
                return self.fail(i, id, op, "the servo is not taking commands".into());
            }
            self.lease_fallback = Some(to);
        }
        let client = self.clients[i].id;
        let fallback = self.current_fallback();
        self.reply(i, op, id, json!({ "holder": client, "fallback": fallback }));
    }

    /// The fallback's name: the holder's choice, else the config's.
    fn current_fallback(&self) -> &'static str {
        let to = self.lease_fallback;
        to.unwrap_or(self.s.serve.stale_fallback.activity())
            .mode()
            .as_str()
    }

    /// The lease is free again: a stream falls back (the holder's choice), then the config's
    /// fallback is back for the next holder.
    fn end_lease(&mut self) {
        self.lease = None;
        let _ = self.s.commands.try_send(ServoCommand::StreamEnded);
        if self.lease_fallback.take().is_some() {
            let to = self.s.serve.stale_fallback.activity();
            let _ = self.s.commands.try_send(ServoCommand::Fallback(to));
        }
    }

    /// Give the command lease back: a stream mode falls back as if its stream ended.
    fn release(&mut self, i: usize, id: Option<&Value>, op: &'static str) {
        self.end_lease();
        self.reply(i, op, id, json!({}));
        let client = self.clients[i].id;
        self.broadcast(json!({
            "type": "event", "event": "lease", "holder": null,
            "message": format!("client {client} released the command lease"),
        }));
    }

    /// Put `effect` in `slot` (None clears it), checked here so the servo gets only valid ones.
    fn effect(
        &mut self,
        i: usize,
        id: Option<&Value>,
        op: &'static str,
        slot: usize,
        effect: Option<crate::haptics::Effect>,
    ) {
        if slot >= crate::haptics::MAX_EFFECTS {
            let max = crate::haptics::MAX_EFFECTS - 1;
            return self.fail(i, id, op, format!("slot {slot}: allowed 0 ..= {max}"));
        }
        if let Some(Err(why)) = effect.map(|e| e.validate("effect.")) {
            return self.fail(i, id, op, why);
        }
        let reply = json!({ "slot": slot, "effect": effect });
        self.send_servo(
            i,
            id,
            op,
            ServoCommand::Effect { slot, effect },
            Some(reply),
        );
    }

    /// Read a weights file here, off the servo thread, and hand the servo a ready identifier.
    fn weights_load(&mut self, i: usize, id: Option<&Value>, op: &'static str, path: String) {
        // No stop flag: the hub never waits on a client's pipe (it is refused).
        let mut loaded = match Identifier::from_weights_file(
            &self.s.identifier_cfg,
            std::path::Path::new(&path),
            None,
        ) {
            Ok(id) => id,
            Err(e) => return self.fail(i, id, op, e.to_string()),
        };
        loaded.set_adapt(self.adapt);
        let client = self.clients[i].id;
        if self
            .s
            .commands
            .try_send(ServoCommand::LoadIdentifier(Box::new(loaded)))
            .is_ok()
        {
            self.loads.push_back((client, id.cloned(), path));
        } else {
            self.fail(i, id, op, "the servo is not taking commands".into());
        }
    }

    /// Any command takes the lease while it is free; another client's lease refuses it.
    fn take_lease(&mut self, i: usize) -> Result<(), String> {
        let me = self.clients[i].id;
        match self.lease {
            Some(holder) if holder == me => Ok(()),
            Some(holder) => {
                let who = self
                    .clients
                    .iter()
                    .find(|c| c.id == holder)
                    .map(|c| {
                        format!(
                            "client {holder} `{}` (pid {}, uid {})",
                            c.name, c.peer.pid, c.peer.uid
                        )
                    })
                    .unwrap_or_else(|| format!("client {holder}"));
                Err(format!(
                    "the command lease is held by {who}; it is free when that client releases \
                     it or disconnects"
                ))
            }
            None => {
                self.lease = Some(me);
                let name = self.clients[i].name.clone();
                self.broadcast(json!({
                    "type": "event", "event": "lease", "holder": me,
                    "message": format!("client {me} `{name}` holds the command lease"),
                }));
                Ok(())
            }
        }
    }

    fn mode(&mut self, i: usize, id: Option<&Value>, mode: &str, trajectory: Option<&str>) {
        let command = match mode {
            "idle" | "disable" => ServoCommand::Idle,
            "hold" => ServoCommand::Hold,
            "free" => ServoCommand::Free,
            "track" => {
                let t = match trajectory.unwrap_or("sine") {
                    "sine" => Trajectory::Sine,
                    "multisine" => Trajectory::Multisine,
                    "hold" => Trajectory::Hold,
                    other => {
                        return self.fail(
                            i,
                            id,
                            "mode",
                            format!(
                                "unknown trajectory `{other}`: expected sine, multisine or hold"
                            ),
                        )
                    }
                };
                ServoCommand::Track(t)
            }
            "servo_jp" | "servo_jf" | "servo_cf" => {
                return self.fail(
                    i,
                    id,
                    "mode",
                    format!("{mode} starts with its first `{mode}` command (a stream)"),
                )
            }
            other => {
                return self.fail(
                    i,
                    id,
                    "mode",
                    format!("unknown mode `{other}`: expected idle, hold, track or free"),
                )
            }
        };
        self.send_servo(i, id, "mode", command, Some(json!({ "mode": mode })));
    }

    /// Validate a stream command's values; its time to live in seconds.
    fn stream_check(
        &mut self,
        i: usize,
        id: Option<&Value>,
        op: &str,
        values: &[f64; 3],
        ttl_ms: Option<f64>,
    ) -> Option<f64> {
        if let Some(j) = values.iter().position(|v| !v.is_finite()) {
            self.fail(i, id, op, format!("value {} is not a finite number", j + 1));
            return None;
        }
        let ttl = ttl_ms.unwrap_or(self.s.serve.stream_ttl_ms);
        if !(ttl.is_finite() && ttl > 0.0 && ttl <= 10_000.0) {
            self.fail(i, id, op, format!("ttl_ms {ttl}: allowed > 0 and ≤ 10000"));
            return None;
        }
        Some(ttl * 1e-3)
    }

    /// Hand a command to the servo; reply `ok` when given (stream commands get no reply).
    fn send_servo(
        &mut self,
        i: usize,
        id: Option<&Value>,
        op: &str,
        command: ServoCommand,
        ok: Option<Value>,
    ) {
        match self.s.commands.try_send(command) {
            Ok(()) => {
                if let Some(ok) = ok {
                    self.reply(i, op, id, ok);
                }
            }
            Err(_) => self.fail(
                i,
                id,
                op,
                "the servo is not taking commands (queue full or stopped)".into(),
            ),
        }
    }

    fn ask_snapshot(&mut self, w: Waiting) {
        self.waiting.push(w);
        if let Some(spare) = self.spare.take() {
            if let Err(e) = self.s.commands.try_send(ServoCommand::Snapshot(spare)) {
                if let ServoCommand::Snapshot(b) = e.into_inner() {
                    self.spare = Some(b);
                }
            }
        }
    }

    fn drain_replies(&mut self) {
        while let Ok(reply) = self.s.replies.try_recv() {
            match reply {
                ServoReply::Snapshot(snap) => self.answer_snapshot(snap),
                ServoReply::Identifier(_old) => {
                    if let Some((client, id, path)) = self.loads.pop_front() {
                        if let Some(i) = self.index_of(client) {
                            self.reply(i, "weights_load", id.as_ref(), json!({ "path": path }));
                        }
                        self.broadcast(json!({
                            "type": "event", "event": "weights",
                            "message": format!("weights loaded from {path}"),
                        }));
                    }
                }
            }
        }
    }

    fn status_json(&self, snap: &Snapshot) -> Value {
        let last = self.last.as_ref();
        let mut summary = RunSummary::from_results(
            &SummaryLabels {
                device: &self.s.device,
                controller: last
                    .and_then(|r| r.live.controller)
                    .unwrap_or(self.s.controller)
                    .as_str(),
                trajectory: "serve".into(),
                weights: self.s.weights_label.clone(),
                seed: self.s.seed,
                fast: false,
            },
            &snap.stats,
            &snap.timing,
            IdentifierState {
                adapt: snap.adapt,
                fault: snap.ident_fault,
            },
            snap.telemetry_dropped,
            snap.missed_packets,
        );
        summary.faults = self.faults.clone();
        summary.realtime = self.s.realtime.get().cloned();
        let mut v = serde_json::to_value(&summary).unwrap_or_default();
        let lease = self
            .lease
            .and_then(|h| self.clients.iter().find(|c| c.id == h));
        v["mode"] = json!(last.map(|r| r.mode.as_str()));
        v["lease"] = match lease {
            Some(c) => {
                json!({ "client": c.id, "name": c.name, "pid": c.peer.pid, "uid": c.peer.uid })
            }
            None => Value::Null,
        };
        v["clients"] = json!(self.clients.iter().filter(|c| !c.dead).count());
        v["recording"] = match &self.recording {
            Some(r) => json!({ "path": r.path, "dropped": r.dropped }),
            None => Value::Null,
        };
        v["socket"] = json!(self.s.listener.path());
        v["heat"] = json!(snap.heat);
        v["protocol"] = json!(PROTOCOL_VERSION);
        v
    }

    fn answer_snapshot(&mut self, snap: Box<Snapshot>) {
        let waiting = std::mem::take(&mut self.waiting);
        let status = self.status_json(&snap);
        for w in waiting {
            match w {
                Waiting::Status { client, id } => {
                    if let Some(i) = self.index_of(client) {
                        self.reply(i, "status", id.as_ref(), json!({ "status": status }));
                    }
                }
                Waiting::Save { client, id, path } => {
                    let result = match (&snap.weights, snap.weights_copied) {
                        (Some(w), true) => {
                            crate::identifier::weights::save(w, &path).map_err(|e| e.to_string())
                        }
                        _ => Err("the servo has no identifier of the configured sizes".into()),
                    };
                    if let Some(i) = self.index_of(client) {
                        match result {
                            Ok(()) => {
                                self.reply(i, "weights_save", id.as_ref(), json!({ "path": path }))
                            }
                            Err(e) => self.fail(i, id.as_ref(), "weights_save", e),
                        }
                    }
                }
            }
        }
        self.spare = Some(snap);
    }

    fn record_start(&mut self, i: usize, id: Option<&Value>, path: Option<String>) {
        if let Some(r) = &self.recording {
            let msg = format!("already recording to {}", r.path.display());
            return self.fail(i, id, "record_start", msg);
        }
        // A default name never replaces an earlier recording; a path another omnid writes
        // is refused.
        let log = match path {
            Some(p) => LogFile::create(Path::new(&p)),
            None => LogFile::create_unique(
                &self.s.state_dir.join("recordings"),
                &format!("omnid-serve-{}", utc_stamp()),
            ),
        };
        let (tx, rx) = crossbeam_channel::bounded(8192);
        let started = log.and_then(|log| {
            let path = log.path.clone();
            spawn_writer(log, self.s.schema, rx)
                .map(|writer| (path.clone(), writer))
                .map_err(|source| LogError::Io { path, source })
        });
        match started {
            Ok((path, writer)) => {
                self.recording = Some(Recording {
                    tx: Some(tx),
                    writer,
                    path: path.clone(),
                    dropped: 0,
                });
                self.reply(i, "record_start", id, json!({ "path": path }));
            }
            Err(e) => self.fail(i, id, "record_start", e.to_string()),
        }
    }

    /// End the recording: (path, rows written, error).
    fn record_stop(&mut self) -> Option<(PathBuf, u64, Option<String>)> {
        let mut r = self.recording.take()?;
        r.tx = None;
        let report = r.writer.join().ok();
        let rows = report.as_ref().map_or(0, |w| w.rows);
        let mut error = report.and_then(|w| {
            w.error.map(|e| {
                format!(
                    "{} of {} rows did not reach the file: {e}",
                    w.received - w.rows,
                    w.received
                )
            })
        });
        if r.dropped > 0 {
            error.get_or_insert(format!("{} rows dropped (the disk fell behind)", r.dropped));
        }
        Some((r.path, rows, error))
    }

    /// Take every record the servo has sent; true once the servo has ended.
    fn drain_records(&mut self) -> bool {
        loop {
            match self.s.records.try_recv() {
                Ok(r) => self.on_record(r),
                Err(TryRecvError::Empty) => return false,
                Err(TryRecvError::Disconnected) => return true,
            }
        }
    }

    fn on_record(&mut self, r: TickRecord) {
        if self.ring.len() == self.ring_cap {
            self.ring.pop_front();
        }
        self.ring.push_back(r);
        if let Some(rec) = &mut self.recording {
            if let Some(tx) = &rec.tx {
                if tx.try_send(r).is_err() {
                    rec.dropped += 1;
                }
            }
        }
        // Changes are against the state the servo started in (idle, the configured law), so
        // one applied at the very first tick is announced too.
        let (mode_before, controller_before) = match self.last.replace(r) {
            Some(b) => (b.mode, b.live.controller),
            None => (Mode::Idle, Some(self.s.controller)),
        };
        if let Some(ev) = r.live.event {
            self.on_event(&r, ev);
        }
        if mode_before != r.mode && !(mode_before == Mode::Blend && r.mode == Mode::Track) {
            self.broadcast(json!({
                "type": "event", "event": "mode", "mode": r.mode.as_str(), "seq": r.live.seq, "t": r.t,
            }));
        }
        if controller_before != r.live.controller {
            self.broadcast(json!({
                "type": "event", "event": "controller",
                "controller": r.live.controller.map(|k| k.as_str()), "seq": r.live.seq,
            }));
        }
        let seq = r.live.seq;
        if !self
            .clients
            .iter()
            .any(|c| c.greeted && c.every > 0 && seq % c.every == 0)
        {
            return;
        }
        let state = self.state(&r);
        let mut v = serde_json::to_value(&state).unwrap_or_default();
        v["type"] = json!("state");
        let bytes: Arc<[u8]> = encode(&v).into();
        let cap = self.s.serve.client_queue;
        for c in self
            .clients
            .iter_mut()
            .filter(|c| c.greeted && c.every > 0 && seq % c.every == 0)
        {
            if c.states >= cap {
                // Drop the oldest sample (never a reply or an event).
                if let Some(k) = c.queue.iter().position(|o| matches!(o, Out::State(_))) {
                    c.queue.remove(k);
                    c.states -= 1;
                    c.lost_total += 1;
                    c.lost_unreported += 1;
                }
            }
            c.queue.push_back(Out::State(bytes.clone()));
            c.states += 1;
        }
    }

    fn state(&self, r: &TickRecord) -> State {
        State {
            seq: r.live.seq,
            t: r.t,
            q: r.q,
            qd: r.qd,
            tip_mm: tip_position_mm(&self.s.geometry, &r.q.into()).into(),
            buttons: r.live.buttons,
            inkwell: r.live.inkwell,
            gimbal: super::device_info::gimbal_angles(r.live.gimbal),
            tau: r.tau,
            tau_hat: r.tau_hat,
            controller: r.live.controller.map_or("none", |k| k.as_str()).to_string(),
            mode: r.mode.as_str().to_string(),
            amps: r.amps,
            flags: r.flags,
            cmd_seq: r.live.cmd_seq,
            heat: r.live.heat,
        }
    }

    fn on_event(&mut self, r: &TickRecord, ev: ServoEvent) {
        let ttl = self.s.serve.stream_ttl_ms;
        let (name, message) = match ev {
            ServoEvent::StreamStale { fallback } => (
                "stream-stale",
                format!(
                    "no servo_jp/servo_jf/servo_cf command within its time to live (default {ttl} ms): \
                     now {}",
                    fallback.as_str()
                ),
            ),
            ServoEvent::StreamEnded { fallback } => (
                "stream-ended",
                format!(
                    "the stream's owner left or released the lease: now {}",
                    fallback.as_str()
                ),
            ),
            ServoEvent::SafetyTrip(trip) => {
                let message = format!("safety: {trip}; zero torque, amplifiers off, mode idle");
                self.faults.push(FaultEntry {
                    tick: r.live.seq,
                    t: r.t,
                    class: "safety-fault".into(),
                    message: message.clone(),
                });
                self.dump("safety");
                ("safety-trip", message)
            }
        };
        crate::errln!("omnid serve: {message}");
        self.broadcast(json!({
            "type": "event", "event": name, "mode": r.mode.as_str(), "seq": r.live.seq,
            "t": r.t, "message": message,
        }));
    }

    /// Write the ring of recent ticks beside the other dumps.
    fn dump(&mut self, why: &str) {
        let dump = write_fault_dump(&self.s.state_dir, &self.s.schema, &self.ring, why);
        self.dumps.extend(dump);
    }

    /// Send what each client has queued until its socket is full; never blocks.
    fn flush_all(&mut self) {
        for c in &mut self.clients {
            if c.dead {
                continue;
            }
            // The loss notice goes before the next message, once: while the socket is full it
            // stays pending and its count grows (it is not queued again and again).
            if c.lost_unreported > 0 {
                let lost = json!({
                    "type": "lost", "count": c.lost_unreported, "total": c.lost_total,
                });
                match c.conn.send(&encode(&lost)) {
                    Ok(()) => c.lost_unreported = 0,
                    Err(e)
                        if matches!(
                            e.kind(),
                            io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
                        ) =>
                    {
                        continue
                    }
                    Err(_) => {
                        c.dead = true;
                        continue;
                    }
                }
            }
            while let Some(front) = c.queue.front() {
                let bytes: &[u8] = match front {
                    Out::State(b) => b,
                    Out::Msg(b) => b,
                };
                match c.conn.send(bytes) {
                    Ok(()) => {
                        if let Some(Out::State(_)) = c.queue.pop_front() {
                            c.states -= 1;
                        }
                    }
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(_) => {
                        c.dead = true;
                        break;
                    }
                }
            }
            if c.closing && c.queue.is_empty() {
                c.dead = true;
            }
        }
        let gone: Vec<usize> = (0..self.clients.len())
            .filter(|&i| self.clients[i].dead)
            .collect();
        for &i in &gone {
            if self.lease == Some(self.clients[i].id) {
                self.drop_client(i);
            }
        }
        if !gone.is_empty() {
            self.clients.retain(|c| !c.dead);
        }
    }

    /// The servo has ended: finish the recording, say goodbye, hand back the report.
    fn finish(mut self) -> HubReport {
        let recording_error = self.record_stop().and_then(|(_, _, e)| e);
        let bye = json!({ "type": "bye", "message": "omnid serve is stopping" });
        self.broadcast(bye);
        // A moment for the goodbye to leave, never blocking on a stuck client.
        let until = std::time::Instant::now() + std::time::Duration::from_millis(100);
        while self.clients.iter().any(|c| !c.queue.is_empty()) && std::time::Instant::now() < until
        {
            self.flush_all();
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
        HubReport {
            shutdown_requested: self.shutdown_requested,
            faults: self.faults,
            dumps: self.dumps,
            ring: self.ring,
            recording_error,
            clients: self
                .clients
                .into_iter()
                .map(|c| ClientConn(c.conn))
                .collect(),
        }
    }
}
