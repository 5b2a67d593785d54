//! A teleoperation channel between two daemons over zenoh (docs/TELEOP.md §9). Each side
//! puts its packet every tick on `omnid/teleop/<leader>/<follower>/to_<other role>/<its zid>`
//! and takes the other's from `…/to_<own role>/*`, a fixed frame (`teleop::wire`). The servo
//! thread never touches zenoh: it hands its packet to a bounded queue that a publishing thread
//! drains, and zenoh's subscriber callback checks each frame and hands the packet to the
//! endpoint's bounded queue, where the delay line and the coupling take it as in one daemon.
//!
//! What arrives is checked before it can move an arm: a frame that is malformed, from a side
//! with other settings, or from a second session while the first is still sending, is refused
//! and counted (and said on stderr at most once a second); a flood beyond the queue is dropped.
//! The peer's silence is the coupling's heartbeat: past `[teleop] link_timeout_ms` the leader's
//! force fades and the follower holds, as for a cut link in one daemon.

use super::ZenohConfig;
use crate::teleop::wire::{self, Agreement};
use crate::teleop::{Endpoint, LineStats, Packet, RemoteChannels, RemoteLine, Role, TeleopConfig};
use crossbeam_channel::{Sender, TrySendError};
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
        let base = format!("omnid/teleop/{leader}/{follower}");
        let agreement = Agreement::of(config);
        let zid = self.session.zid().to_string();
        let (to_net, from_servo) = crossbeam_channel::bounded::<Packet>(QUEUE);
        let (to_servo, from_net) = crossbeam_channel::bounded::<Packet>(QUEUE);
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
                to_servo,
                shared.clone(),
            ))
            .wait()
            .map_err(|e| declare_err(&in_key, e))?;
        let sent = shared.clone();
        std::thread::Builder::new()
            .name(format!("omnid-teleop-{me}"))
            .spawn(move || {
                // Ends when the endpoint (the coupling) is dropped.
                while let Ok(p) = from_servo.recv() {
                    if publisher
                        .put(wire::encode(&p, agreement).to_vec())
                        .wait()
                        .is_ok()
                    {
                        sent.sent.fetch_add(1, Ordering::Relaxed);
                    }
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

/// The subscriber's callback: check a frame, admit its sender, queue its packet.
fn receiver(
    arm: String,
    agreement: Agreement,
    to_servo: Sender<Packet>,
    shared: Arc<Shared>,
) -> impl Fn(zenoh::sample::Sample) + Send + Sync + 'static {
    move |sample| {
        let sender = sample.key_expr().as_str().rsplit('/').next().unwrap_or("");
        let bytes = sample.payload().to_bytes();
        let packet = match wire::decode(&bytes, agreement) {
            Ok(p) => p,
            Err(e) => return shared.refuse(&arm, e.to_string()),
        };
        if let Err(why) = shared.admit(sender) {
            return shared.refuse(&arm, why);
        }
        match to_servo.try_send(packet) {
            Ok(()) => {
                shared.received.fetch_add(1, Ordering::Relaxed);
            }
            Err(TrySendError::Full(_)) => {
                shared.refuse(&arm, "the queue to the arm is full (a flood)".into())
            }
            // This side has ended; the subscriber goes with it.
            Err(TrySendError::Disconnected(_)) => {}
        }
    }
}
