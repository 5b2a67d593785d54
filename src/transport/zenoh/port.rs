//! zenoh as a port of the station's host (docs/ZENOH.md): remote clients are sessions on the
//! station like a socket's, fed from the door's inbox and answered through its outbox; ROS 2
//! commands are one more session, "ROS 2 over zenoh", that holds the lease while its commands
//! keep coming. The network side (subscribers, publishers) is `zenoh::remote` and `zenoh::ros`
//! on their own thread; this side runs on the host's.

use super::bind::{self, Binding};
use super::door::ZenohStats;
use super::door::{Door, Inbound};
use crate::station::{FileRights, Op, SessionId, SessionInfo};
use crate::transport::access::Access;
use crate::transport::host::{Desk, Port};
use crate::transport::json;
use crate::transport::protocol::MAX_MESSAGE;
use serde_json::Value;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Requests taken from the inbox per wake-up (a flood waits its turn behind the sockets).
const INBOX_PER_WAKE: usize = 256;

/// Most remote clients of one arm at once.
const MAX_REMOTE: usize = 64;

/// Liveliness tokens of clients that have not said hello remembered at most (a token alone
/// takes no slot: only a hello does).
const MAX_TOKENS: usize = 65536;

/// Time the port spends on the inbox per wake-up before it lets the host serve its other
/// ports (the local clients' streams) and comes back: the network's requests cost the arm's
/// host bounded time, however many arrive.
const WAKE_BUDGET: Duration = Duration::from_micros(500);

/// Requests that the station answers later (a `status`, a weights save: each goes through the
/// servo's mailbox) one remote client may have waiting at once, and all of them together. A
/// request past these is refused as throttled and counted, so no peer's flood fills the
/// mailbox the local clients' commands go through.
const MAX_LATER_PER_CLIENT: u32 = 2;
const MAX_LATER: u32 = 8;

/// A throttled client is told so at most this often (the rest are counted, silently).
const TELL_THROTTLED_EVERY: Duration = Duration::from_millis(100);

/// One client over zenoh.
struct RemoteClient {
    cid: Arc<str>,
    session: Option<SessionId>,
    /// Every `every`-th tick is streamed to it (0: not streaming).
    every: u64,
    /// Its liveliness token has been seen.
    alive: bool,
    since: Instant,
    /// Its requests the station answers later, waiting now.
    later: u32,
    /// Its requests refused as throttled.
    throttled: u64,
    /// When it was last told it is throttled.
    told: Option<Instant>,
    /// The secret agreed at its hello: every later request must carry its code.
    binding: Option<Binding>,
}

impl RemoteClient {
    fn new(cid: Arc<str>, alive: bool) -> RemoteClient {
        RemoteClient {
            cid,
            session: None,
            every: 0,
            alive,
            since: Instant::now(),
            later: 0,
            throttled: 0,
            told: None,
            binding: None,
        }
    }
}

/// The ROS 2 commander's session and when it last commanded.
struct RosCommander {
    session: SessionId,
    last: Instant,
}

/// An arm's zenoh transport as a port of its host.
pub struct ZenohPort {
    door: Door,
    clients: Vec<RemoteClient>,
    ros: Option<RosCommander>,
    /// Refusals of ROS 2 commands said on stderr, at most one a second.
    said: Option<Instant>,
    /// A client must show its liveliness token within this (`[serve] hello_timeout_ms`).
    hello_timeout: Duration,
    /// Requests of this port's clients the station answers later, waiting now.
    later: u32,
    /// Client tokens seen for ids that have no slot (yet): a hello on one of them is alive.
    tokens: std::collections::HashSet<Arc<str>>,
}

fn info(name: &str, control: bool) -> SessionInfo {
    SessionInfo {
        name: crate::text::printable(&name.chars().take(64).collect::<String>()),
        pid: 0,
        uid: u32::MAX,
        control,
        privileged: false,
        read_only_reason: "commands over zenoh are off ([zenoh] allow_commands = false)".into(),
        files: FileRights::Refused(
            "a client over the network names no files on the daemon's PC".into(),
        ),
    }
}

impl Port for ZenohPort {
    fn interest(&self, fds: &mut Vec<libc::pollfd>) {
        use std::os::fd::AsRawFd;
        fds.push(libc::pollfd {
            fd: self.door.wake.fd().as_raw_fd(),
            events: libc::POLLIN,
            revents: 0,
        });
    }

    /// Take what the network sent, a bounded number per wake-up.
    fn serve(&mut self, ready: &[libc::pollfd], desk: &mut Desk<'_>) {
        if ready[0].revents != 0 {
            self.door.wake.clear();
        }
        let start = Instant::now();
        for _ in 0..INBOX_PER_WAKE {
            if start.elapsed() > WAKE_BUDGET {
                break;
            }
            let Some(m) = self.door.inbox.pop() else {
                break;
            };
            match m {
                Inbound::Message { cid, bytes, tag } => {
                    self.message(cid, &bytes, tag.as_ref().map(|t| &t[..]), desk)
                }
                Inbound::Joined(cid) => self.joined(cid),
                Inbound::Gone(cid) => self.gone(&cid, desk),
                Inbound::Ros(op) => self.ros_command(op, desk),
            }
        }
        if !self.door.inbox.is_empty() {
            // More waits: come back after the host's other ports had their turn.
            self.door.wake.notify();
        }
    }

    fn state(&mut self, seq: u64, message: &Arc<[u8]>) {
        for c in &self.clients {
            if c.every > 0 && seq.is_multiple_of(c.every) {
                self.door.to_client(&c.cid, message.clone());
            }
        }
    }

    fn event(&mut self, message: &Arc<[u8]>) {
        for c in self.clients.iter().filter(|c| c.session.is_some()) {
            self.door.to_client(&c.cid, message.clone());
        }
    }

    fn answer(&mut self, session: SessionId, message: Vec<u8>) {
        // Every answer here is one of this port's later ones (the host routes them back).
        self.later = self.later.saturating_sub(1);
        if let Some(c) = self.clients.iter_mut().find(|c| c.session == Some(session)) {
            c.later = c.later.saturating_sub(1);
            self.door.to_client(&c.cid, message.into());
        }
    }

    fn status(&self, status: &mut Value, _local: bool) {
        status["zenoh"] = serde_json::to_value(self.door.stats.snapshot()).unwrap_or_default();
        // Who was throttled: each remote client still here with its count.
        let by_client: serde_json::Map<String, Value> = self
            .clients
            .iter()
            .filter(|c| c.throttled > 0)
            .map(|c| (c.cid.to_string(), Value::from(c.throttled)))
            .collect();
        status["zenoh"]["throttled_clients"] = Value::Object(by_client);
    }

    fn local(&self) -> bool {
        false
    }

    fn flush(&mut self, _desk: &mut Desk<'_>) {
        // The outbox is the network thread's: messages leave as they are put there.
    }

    /// Close remote clients that never showed their token, and take the lease from a ROS 2
    /// commander that has gone quiet.
    fn expire(&mut self, now: Instant, desk: &mut Desk<'_>) {
        let hello_timeout = self.hello_timeout;
        let mut closed = Vec::new();
        self.clients.retain(|c| {
            // No token, or no hello, within the deadline: the slot is given back.
            let stale = (!c.alive || c.session.is_none()) && now - c.since > hello_timeout;
            if stale {
                closed.push((c.cid.clone(), c.session));
            }
            !stale
        });
        for (cid, session) in closed {
            if let Some(s) = session {
                desk.station.close_session(s);
            }
            let ms = hello_timeout.as_millis();
            let why = if session.is_some() {
                format!("no liveliness token omnid/<arm>/client/{cid} within {ms} ms; closing")
            } else {
                format!("no hello within {ms} ms; closing")
            };
            self.send(&cid, &json::error("connect", None, why));
            self.door.forget(&cid);
        }
        let lapse = Duration::from_secs_f64(self.door.lease_lapse_ms * 1e-3);
        if let Some(c) = &self.ros {
            if desk.station.lease_holder() == Some(c.session) && now - c.last > lapse {
                let ms = lapse.as_millis();
                desk.station.lapse_lease(
                    c.session,
                    &format!("no ROS 2 command over zenoh for {ms} ms"),
                );
            }
        }
    }

    fn goodbye(&mut self, desk: &mut Desk<'_>) {
        let z = self.door.stats.snapshot();
        crate::errln!(
            "omnid serve: arm `{}` over zenoh: {} samples published, {} received ({} refused, \
             {} dropped on a full inbox), {} dropped on the way out",
            desk.station.arm().name,
            z.published,
            z.received,
            z.refused,
            z.dropped_in,
            z.dropped_out
        );
        let bye: Arc<[u8]> = json::bye().into();
        for c in self.clients.iter().filter(|c| c.session.is_some()) {
            self.door.to_client(&c.cid, bye.clone());
        }
    }

    fn close(self: Box<Self>) -> Box<dyn Send> {
        self
    }
}

impl ZenohPort {
    /// The port of an arm's door (`ZenohNet::arm`); a client has `hello_timeout` to show its
    /// liveliness token.
    pub fn new(door: Door, hello_timeout_ms: f64) -> ZenohPort {
        ZenohPort {
            door,
            clients: Vec::new(),
            ros: None,
            said: None,
            hello_timeout: Duration::from_secs_f64(hello_timeout_ms * 1e-3),
            later: 0,
            tokens: Default::default(),
        }
    }

    fn send(&self, cid: &Arc<str>, v: &Value) {
        self.door.to_client(cid, json::encode(v).into());
    }

    /// A client's token appeared. It takes no slot: a peer that declares tokens and never
    /// says hello leaves every slot to clients that do.
    fn joined(&mut self, cid: Arc<str>) {
        match self.clients.iter_mut().find(|c| c.cid == cid) {
            Some(c) => c.alive = true,
            None if self.tokens.len() < MAX_TOKENS => {
                self.tokens.insert(cid);
            }
            None => {}
        }
    }

    fn gone(&mut self, cid: &str, desk: &mut Desk<'_>) {
        self.tokens.remove(cid);
        if let Some(k) = self.clients.iter().position(|c| &*c.cid == cid) {
            let c = self.clients.remove(k);
            self.door.forget(&c.cid);
            if let Some(s) = c.session {
                desk.station.close_session(s);
            }
        }
    }

    fn message(&mut self, cid: Arc<str>, bytes: &[u8], tag: Option<&[u8]>, desk: &mut Desk<'_>) {
        let k = match self.clients.iter().position(|c| c.cid == cid) {
            Some(k) => k,
            None if self.clients.len() < MAX_REMOTE => {
                // Its token may still be on its way: it has the hello deadline to show it.
                let alive = self.tokens.remove(&cid);
                self.clients.push(RemoteClient::new(cid, alive));
                self.clients.len() - 1
            }
            None => return self.no_room(&cid, bytes),
        };
        let cid = self.clients[k].cid.clone();
        if bytes.len() > MAX_MESSAGE {
            let n = bytes.len();
            let why = format!("message of {n} bytes is larger than {MAX_MESSAGE}");
            return self.send(&cid, &json::error("message", None, why));
        }
        // A greeted client's requests carry the code of the secret agreed at its hello: any
        // other session's (or one put again) is refused before it is read, and counted.
        if let Some(b) = self.clients[k].binding.as_mut() {
            if b.check(bytes, tag).is_err() {
                ZenohStats::count(&self.door.stats.forged);
                return;
            }
        }
        let request = match json::parse(bytes) {
            Ok(q) => q,
            Err(error) => return self.send(&cid, &error),
        };
        if let Err(error) = json::check_id(&request) {
            return self.send(&cid, &error);
        }
        let Some(session) = self.clients[k].session else {
            return self.greet(k, request, desk);
        };
        if self.clients[k].later >= MAX_LATER_PER_CLIENT || self.later >= MAX_LATER {
            return self.throttle(k, request.op());
        }
        let served = desk.serve(session, request);
        if served.later.is_some() {
            self.clients[k].later += 1;
            self.later += 1;
        }
        if let Some(every) = served.every {
            self.clients[k].every = every;
        }
        if let Some(v) = served.reply {
            self.send(&cid, &v);
        }
    }

    /// Client `k` asks for more than its share of the station's time: refused and counted
    /// (told at most every [`TELL_THROTTLED_EVERY`]).
    fn throttle(&mut self, k: usize, op: &str) {
        ZenohStats::count(&self.door.stats.throttled);
        let now = Instant::now();
        let c = &mut self.clients[k];
        c.throttled += 1;
        if c.told.is_some_and(|t| now - t < TELL_THROTTLED_EVERY) {
            return;
        }
        c.told = Some(now);
        let cid = c.cid.clone();
        let why = format!(
            "throttled: {MAX_LATER_PER_CLIENT} requests of this client (or {MAX_LATER} of all \
             remote clients) already wait for the arm; wait for their answers ({} refused so \
             far)",
            c.throttled
        );
        self.send(&cid, &json::error(op, None, why));
    }

    /// Every slot is taken: a hello is answered (then forgotten, so the network side keeps
    /// nothing for it), so the client learns why instead of waiting.
    fn no_room(&self, cid: &Arc<str>, bytes: &[u8]) {
        ZenohStats::count(&self.door.stats.refused);
        if json::parse_request(bytes).is_ok_and(|q| q.op() == "hello") {
            let why = format!(
                "no room: this arm serves {MAX_REMOTE} remote clients at once and all slots are \
                 taken; try again later"
            );
            self.send(cid, &json::error("hello", None, why));
            self.door.forget(cid);
        }
    }

    fn greet(
        &mut self,
        k: usize,
        request: crate::transport::protocol::Request,
        desk: &mut Desk<'_>,
    ) {
        let id = request.id().cloned();
        let cid = self.clients[k].cid.clone();
        let key = match &request {
            crate::transport::protocol::Request::Hello { key, .. } => key.clone(),
            _ => None,
        };
        let name = match json::greeting(request) {
            Ok(name) => name,
            Err(error) => return self.send(&cid, &error),
        };
        // The key agreement that binds the client to its owner; one slot per key.
        let refused = match bind::accept(&cid, key.as_deref()) {
            Ok((daemon_key, binding)) => {
                let taken = self.clients.iter().any(|c| {
                    c.binding
                        .as_ref()
                        .is_some_and(|b| b.client_key() == binding.client_key())
                });
                if !taken {
                    self.clients[k].binding = Some(binding);
                    return self.open(k, name, daemon_key, id, desk);
                }
                "this key already holds a slot on this arm: one client per key".to_string()
            }
            Err(e) => e.to_string(),
        };
        // Refused: the slot is given back at once.
        ZenohStats::count(&self.door.stats.forged);
        self.send(&cid, &json::error("hello", id.as_ref(), refused));
        self.clients.remove(k);
        self.door.forget(&cid);
    }

    /// Client `k`'s session, opened and answered with the daemon's key.
    fn open(
        &mut self,
        k: usize,
        name: String,
        daemon_key: String,
        id: Option<Value>,
        desk: &mut Desk<'_>,
    ) {
        let cid = self.clients[k].cid.clone();
        let control = self.door.allow_commands;
        // A nameless client is still told apart from a local one.
        let name = if name.is_empty() {
            "a client over zenoh".to_string()
        } else {
            format!("{name} (zenoh)")
        };
        let session = desk.station.open_session(info(&name, control));
        let access = if control {
            Access::Control
        } else {
            Access::Read
        };
        self.clients[k].session = Some(session);
        let mut v = json::hello(desk.station, session, access, id.as_ref());
        v["key"] = Value::from(daemon_key);
        self.send(&cid, &v);
    }

    /// A ROS 2 command: the ROS 2 session's op, taking the lease when it is free.
    fn ros_command(&mut self, op: Op, desk: &mut Desk<'_>) {
        if !self.door.allow_commands {
            ZenohStats::count(&self.door.stats.refused);
            return;
        }
        let now = Instant::now();
        let session = match self.ros.as_mut() {
            Some(c) => {
                c.last = now;
                c.session
            }
            None => {
                let session = desk.station.open_session(info("ROS 2 over zenoh", true));
                self.ros = Some(RosCommander { session, last: now });
                session
            }
        };
        if let Err(e) = desk.station.request(session, op) {
            ZenohStats::count(&self.door.stats.refused);
            if self.said.is_none_or(|t| now - t >= Duration::from_secs(1)) {
                self.said = Some(now);
                crate::errln!(
                    "omnid serve: arm `{}`: a ROS 2 command over zenoh was refused: {e}",
                    desk.station.arm().name
                );
            }
        }
    }
}
