//! The Unix-socket port of `omnid serve` (docs/PROTOCOL.md): the arm's SOCK_SEQPACKET socket
//! on the station's host. It admits clients (peer credentials, connection limits, a hello
//! deadline), reads their JSON requests (`transport::json` turns them into the station's
//! ops), queues per client (a slow client loses its oldest samples, counted and reported to
//! it) and sends without ever blocking. The loop and the arm — lease, checks, taps — are the
//! host's and the station's.

use super::access::{Access, Policy};
use super::host::{Desk, Port};
use super::json;
use super::protocol::{Request, MAX_MESSAGE};
use super::socket::{Conn, Listener, Peer};
use crate::station::{FileRights, SessionId, SessionInfo};
use serde_json::{json, Value};
use std::collections::VecDeque;
use std::io;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Requests taken from one client per wake-up, so a flooding client cannot starve the rest.
const READS_PER_WAKE: usize = 64;

/// Bytes of replies and events a client may leave unread, counted as they are queued
/// (states are shared between clients, bounded by `serve.client_queue` and dropped oldest
/// first); past this the client is not reading and is disconnected. With every slot taken,
/// the port holds at most (max_clients + reserved) × this.
const MAX_UNREAD_BYTES: usize = 1 << 20;

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

/// What the socket's port is built with.
pub struct SocketSetup {
    pub(crate) listener: Listener,
    pub(crate) policy: Policy,
    /// `[serve]`: connection limits, hello deadline, lease lapse, queues.
    pub(crate) serve: super::ServeConfig,
}

impl SocketSetup {
    /// The socket's path.
    pub fn path(&self) -> &Path {
        self.listener.path()
    }
}

/// A connection kept until the daemon's socket is gone.
struct ClientConn(#[allow(dead_code)] Conn);

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

/// The arm's Unix socket as a port of its host (docs/PROTOCOL.md).
pub struct SocketPort {
    listener: Listener,
    policy: Policy,
    clients: Vec<Client>,
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
}

/// Say why to a client that will not be served, and take what it sent: closing with its hello
/// unread would reset the connection and could discard the reason before the client reads it.
fn refuse(conn: &Conn, message: String) {
    let _ = conn.send(&json::encode(&json!({
        "type": "error", "op": "connect", "message": message
    })));
    let mut sink = [0u8; 512];
    while conn.recv(&mut sink).is_ok_and(|n| n > 0) {}
}

impl Port for SocketPort {
    fn interest(&self, fds: &mut Vec<libc::pollfd>) {
        let resting = self.accept_paused_until.is_some_and(|t| Instant::now() < t);
        fds.push(libc::pollfd {
            // A negative descriptor is skipped by poll: the listener rests.
            fd: if resting { -1 } else { self.listener.raw() },
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
    }

    fn serve(&mut self, ready: &[libc::pollfd], desk: &mut Desk<'_>) {
        // Clients first (their indices match `ready[1..]`), then new connections.
        for (i, p) in ready[1..].iter().enumerate() {
            if p.revents & (libc::POLLIN | libc::POLLHUP | libc::POLLERR) != 0 {
                self.read_client(i, desk);
            }
        }
        self.reap(desk);
        if ready[0].revents & libc::POLLIN != 0 {
            self.accept_some();
        }
    }

    fn state(&mut self, seq: u64, message: &Arc<[u8]>) {
        let cap = self.client_queue;
        for c in self
            .clients
            .iter_mut()
            .filter(|c| !c.dead && c.every > 0 && seq.is_multiple_of(c.every))
        {
            push_state(c, message.clone(), cap);
        }
    }

    fn event(&mut self, message: &Arc<[u8]>) {
        for c in self
            .clients
            .iter_mut()
            .filter(|c| c.session.is_some() && !c.dead)
        {
            push_msg(c, message.to_vec());
        }
    }

    fn answer(&mut self, session: SessionId, message: Vec<u8>) {
        if let Some(c) = self.clients.iter_mut().find(|c| c.session == Some(session)) {
            push_msg(c, message);
        }
    }

    fn status(&self, status: &mut Value, local: bool) {
        // Where the arm's socket is says whose it is: only for those on this PC.
        if local {
            status["socket"] = json!(self.listener.path());
        }
    }

    fn local(&self) -> bool {
        true
    }

    fn flush(&mut self, desk: &mut Desk<'_>) {
        self.flush_all();
        self.reap(desk);
    }

    /// Close what has waited too long: a connection that never said hello, and the lease of
    /// a holder that stopped reading.
    fn expire(&mut self, now: Instant, desk: &mut Desk<'_>) {
        for c in self.clients.iter_mut().filter(|c| !c.dead) {
            if c.session.is_none() && !c.closing && now - c.connected > self.hello_timeout {
                let ms = self.hello_timeout.as_millis();
                refuse(
                    &c.conn,
                    format!("no hello within {ms} ms (serve.hello_timeout_ms); closing"),
                );
                c.dead = true;
                continue;
            }
            if let (Some(id), Some(since)) = (c.session, c.blocked_since) {
                if desk.station.lease_holder() == Some(id) && now - since > self.lease_lapse {
                    let ms = self.lease_lapse.as_millis();
                    desk.station
                        .lapse_lease(id, &format!("has not read its messages for {ms} ms"));
                    c.blocked_since = None;
                }
            }
        }
        self.reap(desk);
    }

    fn goodbye(&mut self, _desk: &mut Desk<'_>) {
        let bye = json::bye();
        for c in self.clients.iter_mut().filter(|c| c.session.is_some()) {
            push_msg(c, bye.clone());
        }
    }

    fn pending(&self) -> bool {
        self.clients.iter().any(|c| !c.queue.is_empty())
    }

    fn close(self: Box<Self>) -> Box<dyn Send> {
        let kept: Vec<ClientConn> = self
            .clients
            .into_iter()
            .map(|c| ClientConn(c.conn))
            .collect();
        Box::new(kept)
    }
}

impl SocketPort {
    /// The port of a socket that `cmd::serve::prepare_arm` bound and locked.
    pub fn new(s: SocketSetup) -> SocketPort {
        let serve = &s.serve;
        SocketPort {
            hello_timeout: Duration::from_secs_f64(serve.hello_timeout_ms * 1e-3),
            lease_lapse: Duration::from_secs_f64(serve.lease_lapse_ms * 1e-3),
            max_clients: serve.max_clients,
            max_per_user: serve.max_clients_per_user,
            client_queue: serve.client_queue,
            listener: s.listener,
            policy: s.policy,
            clients: Vec::new(),
            buf: vec![0; MAX_MESSAGE + 1],
            accept_failing: false,
            accept_paused_until: None,
        }
    }

    /// Forget clients that are gone: their sessions close on the station.
    fn reap(&mut self, desk: &mut Desk<'_>) {
        for c in self.clients.iter().filter(|c| c.dead) {
            if let Some(id) = c.session {
                desk.station.close_session(id);
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

    fn read_client(&mut self, i: usize, desk: &mut Desk<'_>) {
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
                let why = format!("message of {n} bytes is larger than {MAX_MESSAGE}; closing");
                push_msg(
                    &mut self.clients[i],
                    json::encode(&json::error("message", None, why)),
                );
                self.clients[i].closing = true;
                return;
            }
            let request = match json::parse(&self.buf[..n]) {
                Ok(r) => r,
                Err(error) => {
                    let greeted = self.clients[i].session.is_some();
                    push_msg(&mut self.clients[i], json::encode(&error));
                    if !greeted {
                        self.clients[i].closing = true;
                    }
                    continue;
                }
            };
            self.handle(i, request, desk);
            if self.clients[i].dead {
                return;
            }
        }
    }

    /// One request from client `i`: a hello first, then the station's ops.
    fn handle(&mut self, i: usize, request: Request, desk: &mut Desk<'_>) {
        let c = &mut self.clients[i];
        if let Err(error) = json::check_id(&request) {
            return push_msg(c, json::encode(&error));
        }
        let Some(session) = c.session else {
            return self.greet(i, request, desk);
        };
        let served = desk.serve(session, request);
        if let Some(every) = served.every {
            c.every = every;
        }
        if let Some(v) = served.reply {
            push_msg(c, json::encode(&v));
        }
    }

    /// A client's first message must be a hello in our protocol version; anything else
    /// closes the connection after a reply saying why.
    fn greet(&mut self, i: usize, request: Request, desk: &mut Desk<'_>) {
        let id = request.id().cloned();
        let c = &mut self.clients[i];
        let name = match json::greeting(request) {
            Ok(name) => name,
            Err(error) => {
                push_msg(c, json::encode(&error));
                c.closing = true;
                return;
            }
        };
        let info = SessionInfo {
            name,
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
        let session = desk.station.open_session(info);
        c.session = Some(session);
        let v = json::hello(desk.station, session, c.access, id.as_ref());
        push_msg(c, json::encode(&v));
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
                match c.conn.send(&json::encode(&lost)) {
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
