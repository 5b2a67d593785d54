//! A teleoperation channel between two daemons over zenoh (docs/TELEOP.md §9). Each side
//! puts its packet every tick on `omnid/teleop/<leader>/<follower>/to_<other role>/<its zid>`
//! and takes the other's from `…/to_<own role>/*`, a fixed frame (`teleop::wire`). The servo
//! thread never touches zenoh: it hands its packet to a bounded queue that a publishing thread
//! drains, and zenoh's subscriber callback checks each frame and hands the packet to the
//! endpoint's bounded queue, where the delay line and the coupling take it as in one daemon.
//!
//! Frames are sealed with the pair's pre-shared key (`[zenoh.teleop_keys]`, `wire::seal`): a
//! pair without a key is refused at the start, and a frame whose code does not match its key
//! expression, or whose counter was already taken, is refused before it is read.
//!
//! What arrives is checked before it can move an arm: a frame that is malformed, from a side
//! with other settings, or from a second session while the first is still sending, is refused
//! and counted (and said on stderr at most once a second); a flood beyond the queue is dropped.
//! The peer's silence is the coupling's heartbeat: past `[teleop] link_timeout_ms` the leader's
//! force fades and the follower holds, as for a cut link in one daemon.

use super::ZenohConfig;
use crate::handoff::{self, Bell, Refused, SharedInlet};
use crate::teleop::wire::{self, Agreement, PairKey, ReplayWindow};
use crate::teleop::{Endpoint, LineStats, Packet, RemoteChannels, RemoteLine, Role, TeleopConfig};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// Packets queued each way between a servo and the network.
const QUEUE: usize = 256;
/// A sending session silent this long may be replaced by another (a peer daemon restarted).
const PEER_SILENT: Duration = Duration::from_secs(1);

/// Opens channels to other daemons' arms on the daemon's zenoh session.
pub(super) struct TeleopNet {
    pub(super) session: zenoh::Session,
    pub(super) allow_commands: bool,
    cfg: ZenohConfig,
    seals: Arc<Seals>,
}

/// Senders' counters remembered (only senders whose code matched are added).
const WINDOWS: usize = 64;

/// The session's sealing state, shared by every channel it opens so a counter is never
/// reused while the session lives: this side's counter, and each sender's replay window
/// (by the key expression it puts on, which names its pair, direction and session).
#[derive(Default)]
struct Seals {
    counter: AtomicU64,
    windows: Mutex<HashMap<String, (ReplayWindow, Instant)>>,
}

impl Seals {
    /// Take counter `seq` from the sender on `key` (call after its code matched).
    fn accept(&self, key: &str, seq: u64) -> Result<(), wire::WireError> {
        let mut w = self.windows.lock().unwrap_or_else(|e| e.into_inner());
        let now = Instant::now();
        if let Some((window, heard)) = w.get_mut(key) {
            *heard = now;
            return window.accept(seq);
        }
        if w.len() >= WINDOWS {
            // Forget the sender heard longest ago.
            if let Some(oldest) = w
                .iter()
                .min_by_key(|(_, (_, t))| *t)
                .map(|(k, _)| k.clone())
            {
                w.remove(&oldest);
            }
        }
        let mut window = ReplayWindow::default();
        window.accept(seq)?;
        w.insert(key.to_string(), (window, now));
        Ok(())
    }
}

/// The checked key chunk of an arm name (it must not be a key expression's wildcard).
fn arm_chunk(name: &str) -> Result<&str, String> {
    omnid_client::find::check_arm_name(name).map(|()| name)
}

/// What the subscriber and `status` share.
#[derive(Default)]
struct Shared {
    sent: AtomicU64,
    received: AtomicU64,
    refused: AtomicU64,
    /// The sending session and when it was last heard; the last refusal; when one was last
    /// said on stderr.
    peer: Mutex<Peer>,
}

#[derive(Default)]
struct Peer {
    session: Option<(String, Instant)>,
    last_refusal: Option<String>,
    said: Option<Instant>,
}

impl Shared {
    fn refuse(&self, arm: &str, why: String) {
        self.refused.fetch_add(1, Ordering::Relaxed);
        let mut p = self.peer.lock().unwrap_or_else(|e| e.into_inner());
        if p.said.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
            p.said = Some(Instant::now());
            crate::errln!("omnid: {arm}: teleop over zenoh: refused a frame: {why}");
        }
        p.last_refusal = Some(why);
    }

    /// Whether `sender` may speak for the peer now (the first, or one after a silence).
    fn admit(&self, sender: &str) -> Result<(), String> {
        let mut p = self.peer.lock().unwrap_or_else(|e| e.into_inner());
        let now = Instant::now();
        match &p.session {
            Some((s, at)) if s != sender && now.duration_since(*at) < PEER_SILENT => Err(format!(
                "session {} sends as the peer while session {s} does",
                crate::text::cut(sender)
            )),
            _ => {
                p.session = Some((sender.to_string(), now));
                Ok(())
            }
        }
    }
}

/// A channel's network side: the subscriber (undeclared when this drops) and the counters.
struct Line {
    shared: Arc<Shared>,
    _subscriber: zenoh::pubsub::Subscriber<()>,
}

impl RemoteLine for Line {
    fn stats(&self) -> LineStats {
        let p = self.shared.peer.lock().unwrap_or_else(|e| e.into_inner());
        LineStats {
            peer_session: p.session.as_ref().map(|(s, _)| s.clone()),
            sent: self.shared.sent.load(Ordering::Relaxed),
            received: self.shared.received.load(Ordering::Relaxed),
            refused: self.shared.refused.load(Ordering::Relaxed),
            last_refusal: p.last_refusal.clone(),
        }
    }
}

impl TeleopNet {
    /// For a daemon's session as `[zenoh]` configures it.
    pub(super) fn new(session: zenoh::Session, cfg: &ZenohConfig) -> TeleopNet {
        TeleopNet {
            session,
            allow_commands: cfg.allow_commands,
            cfg: cfg.clone(),
            seals: Arc::new(Seals::default()),
        }
    }
}

impl RemoteChannels for TeleopNet {
    fn open(
        &self,
        me: &str,
        peer: &str,
        role: Role,
        config: &TeleopConfig,
        seed: u64,
    ) -> Result<(Endpoint, Box<dyn RemoteLine>), String> {
        let peer = arm_chunk(peer).map_err(|e| format!("the peer's {e}"))?;
        if !self.allow_commands {
            return Err(format!(
                "`{peer}` is not an arm of this daemon; a pair with another daemon's arm \
                 moves this arm from the network, which `[zenoh] allow_commands = false` refuses \
                 here (set it to true on both daemons; docs/ZENOH.md, docs/TELEOP.md §9)"
            ));
        }
        let (leader, follower, mine, theirs, impairment) = match role {
            Role::Leader => (me, peer, "to_follower", "to_leader", config.to_leader),
            Role::Follower => (peer, me, "to_leader", "to_follower", config.to_follower),
        };
        let key = match self.cfg.teleop_key(leader, follower) {
            Some(Ok(key)) => key,
            Some(Err(e)) => {
                return Err(format!(
                    "teleop: `[zenoh.teleop_keys] \"{leader}/{follower}\"`: {e}"
                ))
            }
            None => {
                return Err(format!(
                    "teleop: `{peer}` is another daemon's arm and the pair has no key: add \
                     `\"{leader}/{follower}\" = \"<key>\"` under `[zenoh.teleop_keys]` on both \
                     daemons, the same key on each (make one with \
                     `head -c32 /dev/urandom | base64`; docs/TELEOP.md §9)"
                ))
            }
        };
        let base = format!("omnid/teleop/{leader}/{follower}");
        // A channel to another daemon: `auto` is wave variables (docs/TELEOP.md §5).
        let agreement = Agreement::of(&config.on_channel(true));
        let zid = self.session.zid().to_string();
        // The servo's side of both queues never waits for this side (docs/DESIGN.md §4.7):
        // the publishing thread sleeps on a bell the servo rings, zenoh's callbacks take turns
        // on the inlet toward the servo.
        let bell = Arc::new(Bell::new().map_err(|e| format!("eventfd: {e}"))?);
        let (to_net, mut from_servo) = handoff::queue::<Packet>(QUEUE);
        let to_net = to_net.ringing(bell.clone());
        let (to_servo, from_net) = handoff::queue::<Packet>(QUEUE);
        let shared = Arc::new(Shared::default());
        let declare_err = |what: &str, e: zenoh::Error| format!("zenoh: {what}: {e}");
        let out_key = format!("{base}/{mine}/{zid}");
        let publisher = self
            .session
            .declare_publisher(out_key.clone())
            .congestion_control(zenoh::qos::CongestionControl::Drop)
            .priority(zenoh::qos::Priority::RealTime)
            .express(true)
            .wait()
            .map_err(|e| declare_err(&out_key, e))?;
        let in_key = format!("{base}/{theirs}/*");
        let subscriber = self
            .session
            .declare_subscriber(in_key.clone())
            .callback(receiver(
                me.to_string(),
                agreement,
                key.clone(),
                self.seals.clone(),
                to_servo.shared(),
                shared.clone(),
            ))
            .wait()
            .map_err(|e| declare_err(&in_key, e))?;
        let sent = shared.clone();
        let seals = self.seals.clone();
        std::thread::Builder::new()
            .name(format!("omnid-teleop-{me}"))
            .spawn(move || {
                // Ends when the endpoint (the coupling) is dropped.
                loop {
                    while let Some(p) = from_servo.pop() {
                        let seq = seals.counter.fetch_add(1, Ordering::Relaxed) + 1;
                        let frame = wire::seal(&wire::encode(&p, agreement), seq, &out_key, &key);
                        if publisher.put(frame.to_vec()).wait().is_ok() {
                            sent.sent.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    if from_servo.is_closed() {
                        break;
                    }
                    bell.wait(Duration::from_millis(100));
                }
            })
            .map_err(|e| format!("cannot start the network thread: {e}"))?;
        Ok((
            Endpoint::new(to_net, from_net, impairment, seed),
            Box::new(Line {
                shared,
                _subscriber: subscriber,
            }),
        ))
    }
}

/// The subscriber's callback: check a frame's code and counter, then the frame, admit its
/// sender, queue its packet.
fn receiver(
    arm: String,
    agreement: Agreement,
    key: PairKey,
    seals: Arc<Seals>,
    to_servo: SharedInlet<Packet>,
    shared: Arc<Shared>,
) -> impl Fn(zenoh::sample::Sample) + Send + Sync + 'static {
    move |sample| {
        let on = sample.key_expr().as_str();
        let sender = on.rsplit('/').next().unwrap_or("");
        let bytes = sample.payload().to_bytes();
        let frame = match wire::unseal(&bytes, on, &key) {
            Ok((seq, frame)) => match seals.accept(on, seq) {
                Ok(()) => frame,
                Err(e) => return shared.refuse(&arm, e.to_string()),
            },
            Err(e) => return shared.refuse(&arm, e.to_string()),
        };
        let packet = match wire::decode(&frame, agreement) {
            Ok(p) => p,
            Err(e) => return shared.refuse(&arm, e.to_string()),
        };
        if let Err(why) = shared.admit(sender) {
            return shared.refuse(&arm, why);
        }
        match to_servo.push(packet) {
            Ok(()) => {
                shared.received.fetch_add(1, Ordering::Relaxed);
            }
            Err(Refused::Full) => {
                shared.refuse(&arm, "the queue to the arm is full (a flood)".into())
            }
            // This side has ended; the subscriber goes with it.
            Err(Refused::Closed) => {}
        }
    }
}
