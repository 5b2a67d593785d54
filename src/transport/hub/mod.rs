//! The Unix-socket transport of `omnid serve`: one thread, one `poll` loop over the servo's
//! wake-up eventfd, the listening socket and every client. It admits clients (peer
//! credentials, connection limits, a hello deadline), turns their JSON requests into the
//! station's typed ops (`crate::station`), encodes each streamed state once for every client
//! that wants it, queues per client (a slow client loses its oldest samples, counted and
//! reported to it) and sends without ever blocking. The arm itself — lease, checks, taps — is
//! the station's.

mod remote;

use super::access::{Access, Policy};
use super::protocol::{Hello, Request, MAX_MESSAGE, PROTOCOL_VERSION};
use super::socket::{Conn, Listener, Peer};
use crate::control::ControllerKind;
use crate::station::{
    ops, Answer, FileRights, ModeRequest, Op, OpError, Output, Reply, SessionId, SessionInfo,
    Station, StationReport, StationSetup,
};
use serde_json::{json, Value};
use std::collections::{HashMap, VecDeque};
use std::io;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How long `poll` waits when nothing happens: the stop flag is seen this soon.
const POLL_MS: i32 = 50;

/// Requests taken from one client per wake-up, so a flooding client cannot starve the rest.
const READS_PER_WAKE: usize = 64;

/// Bytes of replies and events a client may leave unread, counted as they are queued
/// (states are shared between clients, bounded by `serve.client_queue` and dropped oldest
/// first); past this the client is not reading and is disconnected. With every slot taken,
/// the hub holds at most (max_clients + reserved) × this.
const MAX_UNREAD_BYTES: usize = 1 << 20;

/// The longest request `id` echoed back, bytes of JSON: a longer one is refused (an id is a
/// tag to match a reply, not a payload).
const MAX_ID_BYTES: usize = 256;

/// Connections taken per wake-up: clients already connected are read before more are let in,
/// so a flood of new connections cannot push out one that has just said hello.
const ACCEPTS_PER_WAKE: usize = 16;

/// Connections that have not said hello yet; the oldest is closed to admit a new one, so
/// silent connections can never keep a client out.
const MAX_UNGREETED: usize = 32;

/// Slots kept beyond `serve.max_clients` for root and the daemon's own user: the one who
/// can stop the arm always gets in.
const RESERVED_SLOTS: usize = 8;

/// How long the listener rests after an accept error that could not be answered.
const ACCEPT_PAUSE: Duration = Duration::from_millis(100);

/// What the hub was built with.
pub struct HubSetup {
    pub(crate) listener: Listener,
    pub(crate) policy: Policy,
    /// `[serve]`: connection limits, hello deadline, lease lapse, queues.
    pub(crate) serve: super::ServeConfig,
    /// The arm this socket serves.
    pub(crate) station: StationSetup,
}

/// What the hub saw, for the daemon's exit.
pub struct HubReport {
    /// The station's report (faults, dumps, the ring, the recording's end).
    pub(crate) station: StationReport,
    /// Clients told goodbye (their connections are closed when the report is dropped).
    _clients: Vec<ClientConn>,
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
    /// The station's session, once greeted.
    session: Option<SessionId>,
    /// Every `every`-th tick is streamed to it (0: not streaming; as the station set it).
    every: u64,
    conn: Conn,
    peer: Peer,
    access: Access,
    privileged: bool,
    connected: Instant,
    queue: VecDeque<Out>,
    states: usize,
    /// Bytes of the replies and events in `queue`.
    unread_bytes: usize,
    lost_total: u64,
    lost_unreported: u64,
    /// Since when its socket has been full with messages waiting (it is not reading).
    blocked_since: Option<Instant>,
    /// Flush what is queued, then drop the connection.
    closing: bool,
    dead: bool,
}

/// The thread that serves clients of one arm over its Unix socket (docs/PROTOCOL.md).
pub struct Hub {
    listener: Listener,
    policy: Policy,
    station: Station,
    clients: Vec<Client>,
    /// Answers the station will give later: ticket → (session, the request's id).
    later: HashMap<u64, (SessionId, Option<Value>)>,
    buf: Vec<u8>,
    /// Accepting fails (said once per episode, not once per wake-up).
    accept_failing: bool,
    /// After an accept error nothing could answer, the listener rests until then.
    accept_paused_until: Option<Instant>,
    hello_timeout: Duration,
    lease_lapse: Duration,
    max_clients: usize,
    max_per_user: usize,
    client_queue: usize,
    /// The arm over zenoh, when served there.
    remote: Option<remote::Remote>,
}

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

/// Why an `id` is refused: longer than is echoed back (an id tags a reply, it is no payload).
fn id_too_long(id: Option<&Value>) -> Option<String> {
    let long = id?.to_string().len();
    (long > MAX_ID_BYTES).then(|| {
        format!(
            "`id` is {long} bytes of JSON; at most {MAX_ID_BYTES} are echoed (an id tags a reply)"
        )
    })
}

/// Why a first message that is not a hello in our version opens no session.
fn not_greeted(request: &Request) -> String {
    match request {
        Request::Hello { protocol, .. } => {
            format!("protocol {protocol} is not supported: this daemon speaks {PROTOCOL_VERSION}")
        }
        _ => "say hello first: {\"op\":\"hello\",\"protocol\":1}".into(),
    }
}

/// One client message decoded, or the one-line refusal the client gets (the user's quoted
/// value cut, the list of choices kept).
fn parse_request(bytes: &[u8]) -> Result<Request, String> {
    serde_json::from_slice::<Request>(bytes)
        .map_err(|e| format!("bad request: {}", crate::text::cut_quoted(&e.to_string())))
}

/// One client message as the hub reads it, up to the station: `parse_request` and its turn
/// into the station's op, the same two steps the hub takes (public for the fuzz target and its
/// smoke test).
pub fn decode_request(bytes: &[u8]) -> Result<Op, String> {
    to_op(parse_request(bytes)?).map_err(|e| e.to_string())
}

/// A request as the station's op (names parsed, with the station's messages).
pub(crate) fn to_op(request: Request) -> Result<Op, OpError> {
    Ok(match request {
        Request::Hello { .. } => return Err(OpError::Invalid("already greeted".into())),
        Request::Stream { rate_hz, .. } => Op::Stream { rate_hz },
        Request::Status { .. } => Op::Status,
        Request::Lease { fallback, .. } => Op::Lease {
            fallback: fallback.as_deref().map(ops::parse_fallback).transpose()?,
        },
        Request::Release { .. } => Op::Release,
        Request::Mode {
            mode, trajectory, ..
        } => Op::Mode(ModeRequest::parse(&mode, trajectory.as_deref())?),
        Request::Hold { .. } => Op::Mode(ModeRequest::Hold),
        Request::Free { .. } => Op::Mode(ModeRequest::Free),
        Request::ServoJp { seq, q, ttl_ms, .. } => Op::ServoJp { seq, q, ttl_ms },
        Request::ServoJf {
            seq, tau, ttl_ms, ..
        } => Op::ServoJf { seq, tau, ttl_ms },
        Request::ServoCf {
            seq, force, ttl_ms, ..
        } => Op::ServoCf { seq, force, ttl_ms },
        Request::Effect { slot, effect, .. } => Op::Effect { slot, effect },
        Request::Passivity { on, .. } => Op::Passivity(on),
        Request::Controller { controller, .. } => {
            Op::Controller(ops::parse_controller(&controller)?)
        }
        Request::Adapt { on, .. } => Op::Adapt(on),
        Request::WeightsSave { path, .. } => Op::WeightsSave(PathBuf::from(path)),
        Request::WeightsLoad { path, .. } => Op::WeightsLoad(PathBuf::from(path)),
        Request::WeightsReset { .. } => Op::WeightsReset,
        Request::RecordStart { path, .. } => Op::RecordStart(path.map(PathBuf::from)),
        Request::RecordStop { .. } => Op::RecordStop,
        Request::Shutdown { .. } => Op::Shutdown,
        Request::Teleop {
            role,
            peer,
            architecture,
            motion_scale,
            force_scale,
            operator,
            passivity,
            ..
        } => Op::Teleop(ops::TeleopRequest {
            motion_scale,
            force_scale,
            passivity,
            ..ops::parse_teleop(&role, peer, architecture.as_deref(), operator.as_deref())?
        }),
        Request::TeleopStop { .. } => Op::TeleopStop,
        Request::TeleopScale { motion_scale, .. } => Op::TeleopScale(motion_scale),
        Request::Stylus { action, button, .. } => Op::Stylus(
            crate::device::StylusAction::parse(&action, button).map_err(|(field, allowed)| {
                let value = match field {
                    "button" => button.map_or("none".into(), |b| b.to_string()),
                    _ => format!("`{}`", crate::text::cut(&action)),
                };
                OpError::Invalid(format!(
                    "stylus {field} {value} (action `{}`): expected {allowed}",
                    crate::text::cut(&action)
                ))
            })?,
        ),
    })
}

impl Hub {
    /// A hub over the socket and the arm's station that `daemon::prepare` set up.
    pub fn new(s: HubSetup) -> Hub {
        let serve = &s.serve;
        Hub {
            hello_timeout: Duration::from_secs_f64(serve.hello_timeout_ms * 1e-3),
            lease_lapse: Duration::from_secs_f64(serve.lease_lapse_ms * 1e-3),
            max_clients: serve.max_clients,
            max_per_user: serve.max_clients_per_user,
            client_queue: serve.client_queue,
            listener: s.listener,
            policy: s.policy,
            station: Station::new(s.station),
            clients: Vec::new(),
            later: HashMap::new(),
            buf: vec![0; MAX_MESSAGE + 1],
            accept_failing: false,
            accept_paused_until: None,
            remote: None,
        }
    }

    /// Add a consumer of every tick and event of this arm (a recorder, another transport's
    /// feed) before serving.
    pub fn add_tap(&mut self, tap: Box<dyn crate::station::Tap>) {
        self.station.add_tap(tap);
    }

    /// Serve until the servo thread has ended (its record channel closes).
    pub fn run(mut self) -> HubReport {
        loop {
            let servo_done = self.pump();
            self.flush_all();
            if servo_done {
                break;
            }
            if let Err(e) = self.poll_once() {
                crate::errln!("omnid serve: poll: {e}");
                std::thread::sleep(Duration::from_millis(POLL_MS as u64));
            }
            self.expire();
        }
        self.finish()
    }

    /// Hand what the station has to the clients: states to those streaming, events to all,
    /// late answers to who asked.
    fn pump(&mut self) -> bool {
        let Hub {
            station,
            clients,
            later,
            client_queue,
            listener,
            remote,
            ..
        } = self;
        let cap = *client_queue;
        let socket = listener.path();
        station.pump(&mut |o| match o {
            Output::State(state) => {
                let mut v = serde_json::to_value(state).unwrap_or_default();
                v["type"] = json!("state");
                let bytes: Arc<[u8]> = encode(&v).into();
                let seq = state.seq;
                for c in clients
                    .iter_mut()
                    .filter(|c| !c.dead && c.every > 0 && seq % c.every == 0)
                {
                    push_state(c, bytes.clone(), cap);
                }
                if let Some(r) = remote.as_ref() {
                    for k in 0..r.clients.len() {
                        let every = r.clients[k].every;
                        if every > 0 && seq % every == 0 {
                            r.send(k, bytes.clone());
                        }
                    }
                }
            }
            Output::Event(e) => {
                let mut v = serde_json::to_value(e).unwrap_or_default();
                v["type"] = json!("event");
                let bytes = encode(&v);
                for c in clients
                    .iter_mut()
                    .filter(|c| c.session.is_some() && !c.dead)
                {
                    push_msg(c, bytes.clone());
                }
                if let Some(r) = remote.as_ref() {
                    let shared: Arc<[u8]> = bytes.into();
                    for k in (0..r.clients.len()).filter(|&k| r.greeted(k)) {
                        r.send(k, shared.clone());
                    }
                }
            }
            Output::Done {
                ticket, op, result, ..
            } => {
                if let Some((session, id)) = later.remove(&ticket) {
                    let mut v = answer(op, id.as_ref(), result, socket);
                    if let (Some(r), true) = (remote.as_ref(), v["status"].is_object()) {
                        v["status"]["zenoh"] = r.status();
                    }
                    if let Some(c) = clients.iter_mut().find(|c| c.session == Some(session)) {
                        push_msg(c, encode(&v));
                    } else if let Some(r) = remote.as_ref() {
                        if let Some(k) = r.session_of(session) {
                            r.send(k, encode(&v).into());
                        }
                    }
                }
            }
        })
    }

    fn poll_once(&mut self) -> io::Result<()> {
        let mut fds = Vec::with_capacity(3 + self.clients.len());
        fds.push(libc::pollfd {
            fd: self.station.wake().fd().as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        });
        let resting = self.accept_paused_until.is_some_and(|t| Instant::now() < t);
        fds.push(libc::pollfd {
            // A negative descriptor is skipped by poll: the listener rests.
            fd: if resting { -1 } else { self.listener.raw() },
            events: libc::POLLIN,
            revents: 0,
        });
        // The zenoh inbox's wake-up (or nothing: a negative descriptor is skipped).
        fds.push(libc::pollfd {
            fd: self.remote.as_ref().map_or(-1, |r| r.wake_fd()),
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
            self.station.wake().clear();
        }
        if fds[2].revents != 0 {
            if let Some(r) = self.remote.as_ref() {
                r.clear_wake();
            }
        }
        self.serve_remote();
        // Clients first (their indices match `fds`), then new connections.
        for (i, p) in fds[3..].iter().enumerate() {
            if p.revents & (libc::POLLIN | libc::POLLHUP | libc::POLLERR) != 0 {
                self.read_client(i);
            }
        }
        self.reap();
        if fds[1].revents & libc::POLLIN != 0 {
            self.accept_some();
        }
        Ok(())
    }

    /// Close what has waited too long: a connection that never said hello, and the lease of
    /// a holder that stopped reading.
    fn expire(&mut self) {
        let now = Instant::now();
        for i in 0..self.clients.len() {
            let c = &self.clients[i];
            if c.dead {
                continue;
            }
            if c.session.is_none() && !c.closing && now - c.connected > self.hello_timeout {
                let ms = self.hello_timeout.as_millis();
                refuse(
                    &self.clients[i].conn,
                    format!("no hello within {ms} ms (serve.hello_timeout_ms); closing"),
                );
                self.clients[i].dead = true;
                continue;
            }
            if let (Some(id), Some(since)) = (c.session, c.blocked_since) {
                if self.station.lease_holder() == Some(id) && now - since > self.lease_lapse {
                    let ms = self.lease_lapse.as_millis();
                    self.station
                        .lapse_lease(id, &format!("has not read its messages for {ms} ms"));
                    self.clients[i].blocked_since = None;
                }
            }
        }
        self.reap();
        self.expire_remote();
    }

    /// Forget clients that are gone: their sessions close on the station.
    fn reap(&mut self) {
        for c in self.clients.iter().filter(|c| c.dead) {
            if let Some(id) = c.session {
                self.station.close_session(id);
            }
        }
        self.clients.retain(|c| !c.dead);
    }

    fn accept_some(&mut self) {
        for _ in 0..ACCEPTS_PER_WAKE {
            let conn = match self.listener.accept() {
                Ok(Some(c)) => {
                    self.accept_failing = false;
                    c
                }
                Ok(None) => return,
                Err(e) => return self.accept_failed(e),
            };
            let Ok(peer) = conn.peer() else { continue };
            let access = match self.policy.decide(&peer) {
                Ok(a) => a,
                Err(message) => {
                    refuse(&conn, message);
                    continue;
                }
            };
            let privileged = peer.uid == 0 || peer.uid == self.policy.own_uid;
            if let Err(message) = self.admit(&peer, privileged) {
                refuse(&conn, message);
                continue;
            }
            self.clients.push(Client {
                session: None,
                every: 0,
                conn,
                peer,
                access,
                privileged,
                connected: Instant::now(),
                queue: VecDeque::new(),
                unread_bytes: 0,
                states: 0,
                lost_total: 0,
                lost_unreported: 0,
                blocked_since: None,
                closing: false,
                dead: false,
            });
        }
    }

    /// Room for one more connection from `peer`: silent connections make room by closing the
    /// oldest of them; greeted ones are bounded per user and in all, with slots kept for root
    /// and the daemon's user.
    fn admit(&mut self, peer: &Peer, privileged: bool) -> Result<(), String> {
        let ungreeted: Vec<usize> = (0..self.clients.len())
            .filter(|&i| self.clients[i].session.is_none() && !self.clients[i].dead)
            .collect();
        if ungreeted.len() >= MAX_UNGREETED {
            let oldest = ungreeted[0];
            refuse(
                &self.clients[oldest].conn,
                "closed without a hello to make room for a new connection".into(),
            );
            self.clients[oldest].dead = true;
        }
        let live = self.clients.iter().filter(|c| !c.dead).count();
        let limit = self.max_clients + if privileged { RESERVED_SLOTS } else { 0 };
        if live >= limit {
            return Err(format!(
                "too many clients ({}; serve.max_clients)",
                self.max_clients
            ));
        }
        if !privileged {
            let mine = self
                .clients
                .iter()
                .filter(|c| !c.dead && c.peer.uid == peer.uid)
                .count();
            if mine >= self.max_per_user {
                return Err(format!(
                    "too many connections from uid {} ({}; serve.max_clients_per_user)",
                    peer.uid, self.max_per_user
                ));
            }
        }
        Ok(())
    }

    fn accept_failed(&mut self, e: io::Error) {
        if !self.accept_failing {
            crate::errln!(
                "omnid serve: accept: {e} ({} clients connected); new clients are refused \
                 until it clears",
                self.clients.len()
            );
            self.accept_failing = true;
        }
        let out_of_descriptors = matches!(e.raw_os_error(), Some(libc::EMFILE | libc::ENFILE));
        let message = format!(
            "the daemon cannot take a connection now ({e}; {} clients connected)",
            self.clients.len()
        );
        if out_of_descriptors && self.listener.shed_one(|c| refuse(c, message)) {
            return;
        }
        self.accept_paused_until = Some(Instant::now() + ACCEPT_PAUSE);
    }

    fn read_client(&mut self, i: usize) {
        for _ in 0..READS_PER_WAKE {
            if self.clients[i].dead || self.clients[i].closing {
                return;
            }
            let n = match self.clients[i].conn.recv(&mut self.buf) {
                Ok(0) => {
                    self.clients[i].dead = true;
                    return;
                }
                Ok(n) => n,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(_) => {
                    self.clients[i].dead = true;
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
            let request = match parse_request(&self.buf[..n]) {
                Ok(r) => r,
                Err(why) => {
                    let op = serde_json::from_slice::<Value>(&self.buf[..n])
                        .ok()
                        .and_then(|v| v.get("op").and_then(|o| o.as_str()).map(String::from))
                        .unwrap_or_else(|| "?".into());
                    let greeted = self.clients[i].session.is_some();
                    self.fail(i, None, &crate::text::cut(&op), why);
                    if !greeted {
                        self.clients[i].closing = true;
                    }
                    continue;
                }
            };
            self.handle(i, request);
            if self.clients[i].dead {
                return;
            }
        }
    }

    /// One request from client `i`: a hello first, then the station's ops.
    fn handle(&mut self, i: usize, request: Request) {
        let op_name = request.op();
        let id = request.id().cloned();
        if let Some(message) = id_too_long(id.as_ref()) {
            return self.fail(i, None, op_name, message);
        }
        let Some(session) = self.clients[i].session else {
            return self.greet(i, id.as_ref(), op_name, request);
        };
        let op = match to_op(request) {
            Ok(op) => op,
            Err(e) => return self.fail(i, id.as_ref(), op_name, e.to_string()),
        };
        match self.station.request(session, op) {
            Ok(Answer::Now(Reply::Silent)) => {}
            Ok(Answer::Now(reply)) => {
                if let Reply::Stream { every, .. } = reply {
                    self.clients[i].every = every;
                }
                let v = answer(op_name, id.as_ref(), Ok(reply), self.listener.path());
                self.queue_msg(i, v);
            }
            Ok(Answer::Later(ticket)) => {
                self.later.insert(ticket, (session, id));
            }
            Err(e) => self.fail(i, id.as_ref(), op_name, e.to_string()),
        }
    }

    /// A client's first message must be a hello in our protocol version; anything else
    /// closes the connection after a reply saying why.
    fn greet(&mut self, i: usize, id: Option<&Value>, op: &'static str, request: Request) {
        match request {
            Request::Hello { protocol, name, .. } if protocol == PROTOCOL_VERSION => {
                let c = &self.clients[i];
                let info = SessionInfo {
                    // Shown to other clients (events, `omnid watch`): printable, cut.
                    name: crate::text::printable(
                        &name
                            .unwrap_or_default()
                            .chars()
                            .take(64)
                            .collect::<String>(),
                    ),
                    pid: c.peer.pid,
                    uid: c.peer.uid,
                    control: c.access == Access::Control,
                    privileged: c.privileged,
                    read_only_reason: self.policy.read_only_reason(&c.peer),
                    files: FileRights::for_peer(
                        self.policy.own_uid,
                        c.peer.uid,
                        c.peer.gid,
                        &c.peer.groups,
                    ),
                };
                let session = self.station.open_session(info);
                let c = &mut self.clients[i];
                c.session = Some(session);
                let access = c.access;
                let v = self.hello(session, access, id);
                self.queue_msg(i, v);
            }
            other => {
                self.fail(i, id, op, not_greeted(&other));
                self.clients[i].closing = true;
            }
        }
    }

    /// The hello reply of a new session.
    fn hello(&self, session: SessionId, access: Access, id: Option<&Value>) -> Value {
        let arm = self.station.arm();
        let hello = Hello {
            protocol: PROTOCOL_VERSION,
            server: format!("omnid {}", env!("CARGO_PKG_VERSION")),
            device: arm.kind.to_string(),
            arm: arm.name.clone(),
            aliases: arm.aliases.clone(),
            rate_hz: self.station.rate_hz(),
            access: access.as_str().into(),
            client: session,
            stream_ttl_ms: self.station.stream_ttl_ms(),
            controllers: ControllerKind::ALL.map(|k| k.as_str().into()).into(),
            modes: [
                "idle", "hold", "track", "free", "servo_jp", "servo_jf", "servo_cf",
            ]
            .map(String::from)
            .into(),
            model: crate::station::device_info::model(arm.kind).into(),
            vendor: crate::station::device_info::VENDOR.into(),
            serial: arm.serial.clone(),
            firmware: None,
        };
        let mut v = serde_json::to_value(hello).unwrap_or_default();
        v["type"] = json!("hello");
        if let Some(id) = id {
            v["id"] = id.clone();
        }
        v
    }

    fn queue_msg(&mut self, i: usize, v: Value) {
        push_msg(&mut self.clients[i], encode(&v));
    }

    fn fail(&mut self, i: usize, id: Option<&Value>, op: &str, message: String) {
        let mut v = json!({ "type": "error", "op": op, "message": message });
        if let Some(id) = id {
            v["id"] = id.clone();
        }
        self.queue_msg(i, v);
    }

    /// Send what each client has queued until its socket is full; never blocks.
    fn flush_all(&mut self) {
        let now = Instant::now();
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
                        c.blocked_since.get_or_insert(now);
                        continue;
                    }
                    Err(_) => {
                        c.dead = true;
                        continue;
                    }
                }
            }
            let mut blocked = false;
            while let Some(front) = c.queue.front() {
                let bytes: &[u8] = match front {
                    Out::State(b) => b,
                    Out::Msg(b) => b,
                };
                match c.conn.send(bytes) {
                    Ok(()) => match c.queue.pop_front() {
                        Some(Out::State(_)) => c.states -= 1,
                        Some(Out::Msg(b)) => c.unread_bytes -= b.len(),
                        None => {}
                    },
                    Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                        blocked = true;
                        break;
                    }
                    Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                    Err(_) => {
                        c.dead = true;
                        break;
                    }
                }
            }
            if blocked {
                c.blocked_since.get_or_insert(now);
            } else {
                c.blocked_since = None;
            }
            if c.closing && c.queue.is_empty() {
                c.dead = true;
            }
        }
        self.reap();
    }

    /// The servo has ended: finish the station, say goodbye, hand back the report.
    fn finish(mut self) -> HubReport {
        let bye = encode(&json!({ "type": "bye", "message": "omnid serve is stopping" }));
        for c in self.clients.iter_mut().filter(|c| c.session.is_some()) {
            push_msg(c, bye.clone());
        }
        self.finish_remote();
        // A moment for the goodbye to leave, never blocking on a stuck client.
        let until = Instant::now() + Duration::from_millis(100);
        while self.clients.iter().any(|c| !c.queue.is_empty()) && Instant::now() < until {
            self.flush_all();
            std::thread::sleep(Duration::from_millis(1));
        }
        let clients = std::mem::take(&mut self.clients)
            .into_iter()
            .map(|c| ClientConn(c.conn))
            .collect();
        HubReport {
            station: self.station.finish(),
            _clients: clients,
        }
    }
}

/// Queue a reply or an event for a client, counted in bytes: a client that leaves more than
/// [`MAX_UNREAD_BYTES`] unread is not reading, and is disconnected (its queue freed at once).
fn push_msg(c: &mut Client, bytes: Vec<u8>) {
    if c.dead {
        return;
    }
    if c.unread_bytes + bytes.len() > MAX_UNREAD_BYTES {
        crate::errln!(
            "omnid serve: client {:?} (pid {}): more than {MAX_UNREAD_BYTES} bytes of replies \
             and events unread: disconnecting a client that does not read",
            c.session,
            c.peer.pid
        );
        c.queue.clear();
        c.states = 0;
        c.unread_bytes = 0;
        c.dead = true;
        return;
    }
    c.unread_bytes += bytes.len();
    c.queue.push_back(Out::Msg(bytes));
}

/// Queue a state for a client, dropping its oldest state (never a reply or an event) when
/// its queue is full.
fn push_state(c: &mut Client, bytes: Arc<[u8]>, cap: usize) {
    if c.states >= cap {
        if let Some(k) = c.queue.iter().position(|o| matches!(o, Out::State(_))) {
            c.queue.remove(k);
            c.states -= 1;
            c.lost_total += 1;
            c.lost_unreported += 1;
        }
    }
    c.queue.push_back(Out::State(bytes));
    c.states += 1;
}

/// A reply or an error for `op`, echoing the request's `id`.
fn answer(op: &str, id: Option<&Value>, result: Result<Reply, OpError>, socket: &Path) -> Value {
    let mut v = match result {
        Ok(reply) => {
            let mut v = serde_json::to_value(&reply).unwrap_or_else(|_| json!({}));
            if let Reply::Status { .. } = reply {
                v["status"]["socket"] = json!(socket);
                v["status"]["protocol"] = json!(PROTOCOL_VERSION);
            }
            v["type"] = json!("reply");
            v
        }
        Err(e) => json!({ "type": "error", "message": e.to_string() }),
    };
    v["op"] = json!(op);
    if let Some(id) = id {
        v["id"] = id.clone();
    }
    v
}
