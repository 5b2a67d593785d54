//! The hub's side of zenoh (docs/ZENOH.md): remote clients are sessions on the station like a
//! socket's, fed from the door's inbox and answered through its outbox; ROS 2 commands are one
//! more session, "ROS 2 over zenoh", that holds the lease while its commands keep coming.

use super::{answer, encode, id_too_long, not_greeted, parse_request, to_op, Access, Hub};
use crate::station::{Answer, FileRights, Op, Reply, SessionId, SessionInfo};
use crate::transport::protocol::{Request, MAX_MESSAGE, PROTOCOL_VERSION};
use crate::transport::zenoh::door::{Door, Inbound};
use serde_json::{json, Value};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Requests taken from the inbox per wake-up (a flood waits its turn behind the sockets).
const INBOX_PER_WAKE: usize = 256;

/// Most remote clients of one arm at once.
const MAX_REMOTE: usize = 64;

/// One client over zenoh.
pub(super) struct RemoteClient {
    cid: Arc<str>,
    session: Option<SessionId>,
    /// Every `every`-th tick is streamed to it (0: not streaming).
    pub(super) every: u64,
    /// Its liveliness token has been seen.
    alive: bool,
    since: Instant,
}

/// The ROS 2 commander's session and when it last commanded.
struct RosCommander {
    session: SessionId,
    last: Instant,
}

/// What the hub keeps for an arm's zenoh transport.
pub(crate) struct Remote {
    door: Door,
    pub(super) clients: Vec<RemoteClient>,
    ros: Option<RosCommander>,
    /// Refusals of ROS 2 commands said on stderr, at most one a second.
    said: Option<Instant>,
}

impl Remote {
    pub(crate) fn new(door: Door) -> Remote {
        Remote {
            door,
            clients: Vec::new(),
            ros: None,
            said: None,
        }
    }

    pub(super) fn wake_fd(&self) -> std::os::fd::RawFd {
        use std::os::fd::AsRawFd;
        self.door.wake.fd().as_raw_fd()
    }

    pub(super) fn clear_wake(&self) {
        self.door.wake.clear();
    }

    /// A message for remote client `k`.
    pub(super) fn send(&self, k: usize, bytes: Arc<[u8]>) {
        self.door.to_client(&self.clients[k].cid, bytes);
    }

    fn send_value(&self, k: usize, v: &Value) {
        self.send(k, encode(v).into());
    }

    /// The status's `zenoh` object: the counters.
    pub(super) fn status(&self) -> Value {
        serde_json::to_value(self.door.stats.snapshot()).unwrap_or_default()
    }

    /// Remote client `k` has said hello.
    pub(super) fn greeted(&self, k: usize) -> bool {
        self.clients[k].session.is_some()
    }

    pub(super) fn session_of(&self, session: SessionId) -> Option<usize> {
        self.clients.iter().position(|c| c.session == Some(session))
    }
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
            "a client over the network names no files on the daemon's PC; record without a \
             path (into the daemon's recordings directory)"
                .into(),
        ),
    }
}

fn error(op: &str, id: Option<&Value>, message: String) -> Value {
    let mut v = json!({ "type": "error", "op": op, "message": message });
    if let Some(id) = id {
        v["id"] = id.clone();
    }
    v
}

impl Hub {
    /// Serve this arm over zenoh too (`transport::zenoh`).
    pub fn add_zenoh(&mut self, door: Door) {
        self.remote = Some(Remote::new(door));
    }

    /// Take what the network sent, a bounded number per wake-up.
    pub(super) fn serve_remote(&mut self) {
        let Some(r) = self.remote.as_ref() else {
            return;
        };
        let batch: Vec<Inbound> = r.door.inbox.try_iter().take(INBOX_PER_WAKE).collect();
        if !r.door.inbox.is_empty() {
            // More waits: come back at once.
            r.door.wake.notify();
        }
        for m in batch {
            match m {
                Inbound::Message { cid, bytes } => self.remote_message(cid, &bytes),
                Inbound::Joined(cid) => self.remote_joined(cid),
                Inbound::Gone(cid) => self.remote_gone(&cid),
                Inbound::Ros(op) => self.ros_command(op),
            }
        }
    }

    fn remote_joined(&mut self, cid: Arc<str>) {
        let Some(r) = self.remote.as_mut() else {
            return;
        };
        let n = r.clients.len();
        match r.clients.iter_mut().find(|c| c.cid == cid) {
            Some(c) => c.alive = true,
            None if n < MAX_REMOTE => r.clients.push(RemoteClient {
                cid,
                session: None,
                every: 0,
                alive: true,
                since: Instant::now(),
            }),
            None => {}
        }
    }

    fn remote_gone(&mut self, cid: &str) {
        let Some(r) = self.remote.as_mut() else {
            return;
        };
        if let Some(k) = r.clients.iter().position(|c| &*c.cid == cid) {
            let c = r.clients.remove(k);
            r.door.forget(&c.cid);
            if let Some(s) = c.session {
                self.station.close_session(s);
            }
        }
    }

    fn remote_message(&mut self, cid: Arc<str>, bytes: &[u8]) {
        let Some(r) = self.remote.as_mut() else {
            return;
        };
        let k = match r.clients.iter().position(|c| c.cid == cid) {
            Some(k) => k,
            None if r.clients.len() < MAX_REMOTE => {
                // Its token may still be on its way: it has the hello deadline to show it.
                r.clients.push(RemoteClient {
                    cid,
                    session: None,
                    every: 0,
                    alive: false,
                    since: Instant::now(),
                });
                r.clients.len() - 1
            }
            None => {
                crate::transport::zenoh::ZenohStats::count(&r.door.stats.refused);
                // A hello is answered (then forgotten, so the network side keeps nothing for
                // it): the client learns why instead of waiting.
                if parse_request(bytes).is_ok_and(|q| q.op() == "hello") {
                    let why = format!(
                        "no room: this arm serves {MAX_REMOTE} remote clients at once and all \
                         slots are taken; try again later"
                    );
                    r.door
                        .to_client(&cid, encode(&error("hello", None, why)).into());
                    r.door.forget(&cid);
                }
                return;
            }
        };
        if bytes.len() > MAX_MESSAGE {
            let n = bytes.len();
            let why = format!("message of {n} bytes is larger than {MAX_MESSAGE}");
            return r.send_value(k, &error("message", None, why));
        }
        let request = match parse_request(bytes) {
            Ok(q) => q,
            Err(why) => return r.send_value(k, &error("?", None, why)),
        };
        let op_name = request.op();
        let id = request.id().cloned();
        if let Some(why) = id_too_long(id.as_ref()) {
            return r.send_value(k, &error(op_name, None, why));
        }
        let Some(session) = r.clients[k].session else {
            return self.remote_greet(k, id.as_ref(), op_name, request);
        };
        let op = match to_op(request) {
            Ok(op) => op,
            Err(e) => return r.send_value(k, &error(op_name, id.as_ref(), e.to_string())),
        };
        let socket = self.listener.path().to_path_buf();
        match self.station.request(session, op) {
            Ok(Answer::Now(Reply::Silent)) => {}
            Ok(Answer::Now(reply)) => {
                let Some(r) = self.remote.as_mut() else {
                    return;
                };
                if let Reply::Stream { every, .. } = reply {
                    r.clients[k].every = every;
                }
                let v = answer(op_name, id.as_ref(), Ok(reply), &socket);
                r.send_value(k, &v);
            }
            Ok(Answer::Later(ticket)) => {
                self.later.insert(ticket, (session, id));
            }
            Err(e) => {
                if let Some(r) = self.remote.as_ref() {
                    r.send_value(k, &error(op_name, id.as_ref(), e.to_string()));
                }
            }
        }
    }

    fn remote_greet(&mut self, k: usize, id: Option<&Value>, op: &str, request: Request) {
        let Some(r) = self.remote.as_ref() else {
            return;
        };
        let control = r.door.allow_commands;
        match request {
            Request::Hello { protocol, name, .. } if protocol == PROTOCOL_VERSION => {
                let name = format!("{} (zenoh)", name.unwrap_or_default());
                let session = self.station.open_session(info(&name, control));
                let access = if control {
                    Access::Control
                } else {
                    Access::Read
                };
                let v = self.hello(session, access, id);
                if let Some(r) = self.remote.as_mut() {
                    r.clients[k].session = Some(session);
                    r.send_value(k, &v);
                }
            }
            other => r.send_value(k, &error(op, id, not_greeted(&other))),
        }
    }

    /// A ROS 2 command: the ROS 2 session's op, taking the lease when it is free.
    fn ros_command(&mut self, op: Op) {
        let Some(r) = self.remote.as_mut() else {
            return;
        };
        if !r.door.allow_commands {
            crate::transport::zenoh::ZenohStats::count(&r.door.stats.refused);
            return;
        }
        let now = Instant::now();
        let known = r.ros.as_mut().map(|c| {
            c.last = now;
            c.session
        });
        let session = match known {
            Some(s) => s,
            None => {
                let session = self.station.open_session(info("ROS 2 over zenoh", true));
                if let Some(r) = self.remote.as_mut() {
                    r.ros = Some(RosCommander { session, last: now });
                }
                session
            }
        };
        if let Err(e) = self.station.request(session, op) {
            let Some(r) = self.remote.as_mut() else {
                return;
            };
            crate::transport::zenoh::ZenohStats::count(&r.door.stats.refused);
            let now = Instant::now();
            if r.said.is_none_or(|t| now - t >= Duration::from_secs(1)) {
                r.said = Some(now);
                crate::errln!(
                    "omnid serve: arm `{}`: a ROS 2 command over zenoh was refused: {e}",
                    self.station.arm().name
                );
            }
        }
    }

    /// Close remote clients that never showed their token, and take the lease from a ROS 2
    /// commander that has gone quiet.
    pub(super) fn expire_remote(&mut self) {
        let now = Instant::now();
        let hello_timeout = self.hello_timeout;
        let Some(r) = self.remote.as_mut() else {
            return;
        };
        let mut closed = Vec::new();
        r.clients.retain(|c| {
            let stale = !c.alive && now - c.since > hello_timeout;
            if stale {
                closed.push((c.cid.clone(), c.session));
            }
            !stale
        });
        for (cid, session) in closed {
            if let Some(s) = session {
                self.station.close_session(s);
            }
            let Some(r) = self.remote.as_ref() else {
                return;
            };
            let ms = hello_timeout.as_millis();
            r.door.to_client(
                &cid,
                encode(&error(
                    "connect",
                    None,
                    format!("no liveliness token omnid/<arm>/client/{cid} within {ms} ms; closing"),
                ))
                .into(),
            );
            r.door.forget(&cid);
        }
        let Some(r) = self.remote.as_ref() else {
            return;
        };
        let lapse = Duration::from_secs_f64(r.door.lease_lapse_ms * 1e-3);
        if let Some(c) = &r.ros {
            if self.station.lease_holder() == Some(c.session) && now - c.last > lapse {
                let ms = lapse.as_millis();
                let session = c.session;
                self.station
                    .lapse_lease(session, &format!("no ROS 2 command over zenoh for {ms} ms"));
            }
        }
    }

    /// The servo has ended: say goodbye to remote clients.
    pub(super) fn finish_remote(&mut self) {
        let Some(r) = self.remote.as_ref() else {
            return;
        };
        let z = r.door.stats.snapshot();
        crate::errln!(
            "omnid serve: arm `{}` over zenoh: {} samples published, {} received ({} refused, \
             {} dropped on a full inbox), {} dropped on the way out",
            self.station.arm().name,
            z.published,
            z.received,
            z.refused,
            z.dropped_in,
            z.dropped_out
        );
        let bye: Arc<[u8]> =
            encode(&json!({ "type": "bye", "message": "omnid serve is stopping" })).into();
        for k in 0..r.clients.len() {
            if r.clients[k].session.is_some() {
                r.send(k, bye.clone());
            }
        }
    }
}
