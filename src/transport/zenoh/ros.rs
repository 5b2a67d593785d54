//! One arm as a ROS 2 device on rmw_zenoh, with CRTK's names (docs/ZENOH.md, ROS 2 topics):
//! out `measured_js`, `measured_cp`, `measured_cv`, `operating_state`, `button1`, `button2`;
//! in (when commands are allowed) `servo_cf`, `servo_jp`, `state_command`. And the thread that
//! feeds them and remote clients from the arm's taps.

use super::config::ZenohConfig;
use super::door::{Feed, Inbound, NetSide, Outbound, Outbox, ZenohStats};
use super::remote::RemoteArm;
use super::ZenohError;
use crate::handoff::Inlet;
use crate::omni::kinematics::Geometry;
use crate::ros2::msgs::{self, Header, Stamp};
use crate::ros2::rmw_zenoh::{self as rmw, HashForm, Kind, Node, Qos, RosType};
use crate::station::{ModeRequest, Op, Tap};
use crate::telemetry::record::{Mode, TickRecord};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use zenoh::Wait;

/// `operating_state` is sent again this often, ticks of device time (for late subscribers:
/// omnid's topics are volatile).
const STATE_REPEAT_S: f64 = 1.0;

/// The joints' names in `measured_js` (as the log's `/joint_states`).
const JOINTS: [&str; 3] = ["joint1", "joint2", "joint3"];

/// The forms a topic is published in.
#[derive(Clone, Copy)]
enum Form {
    Rmw(HashForm),
    Bridge,
}

fn forms(cfg: &ZenohConfig) -> Vec<Form> {
    let mut f = Vec::new();
    if cfg.ros2 {
        f.push(Form::Rmw(HashForm::Rihs01));
        if cfg.humble {
            f.push(Form::Rmw(HashForm::Humble));
        }
    }
    if cfg.bridge {
        f.push(Form::Bridge);
    }
    f
}

/// zenoh-bridge-ros2dds's discovery token for a topic (docs/ZENOH.md, Bridge form).
fn bridge_token(zid: &str, kind: Kind, topic: &str, t: &RosType) -> String {
    format!(
        "@/{zid}/@ros2_lv/{}/{}/{}/:1:0:0,100:typehash={};",
        kind.as_str(),
        topic.trim_matches('/').replace('/', "§"),
        t.msg.name.replace('/', "§"),
        t.hash
    )
}

fn declare_err(what: &str, e: impl std::fmt::Display) -> ZenohError {
    ZenohError::Declare {
        what: what.to_string(),
        why: e.to_string(),
    }
}

/// Where a ROS topic's samples go, in one form.
struct RosPub {
    publisher: zenoh::pubsub::Publisher<'static>,
    /// `None`: the bridge form carries no attachment.
    gid: Option<[u8; 16]>,
    seq: i64,
    matching: Arc<AtomicBool>,
    _token: zenoh::liveliness::LivelinessToken,
}

/// One topic in every form.
struct RosTopic {
    pubs: Vec<RosPub>,
}

impl RosTopic {
    /// Someone subscribes (encoding is skipped when no one does).
    fn wanted(&self) -> bool {
        self.pubs.iter().any(|p| p.matching.load(Ordering::Relaxed))
    }

    fn put(&mut self, bytes: &[u8], stats: &ZenohStats) {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as i64)
            .unwrap_or(0);
        for p in &mut self.pubs {
            if !p.matching.load(Ordering::Relaxed) {
                continue;
            }
            let put = p.publisher.put(bytes.to_vec());
            let put = match p.gid {
                Some(gid) => {
                    p.seq += 1;
                    put.attachment(rmw::attachment(p.seq, now, &gid).to_vec())
                }
                None => put,
            };
            if put.wait().is_ok() {
                ZenohStats::count(&stats.published);
            } else {
                ZenohStats::count(&stats.dropped_out);
            }
        }
    }
}

/// What a command topic decodes into.
#[derive(Clone, Copy)]
enum Command {
    ServoCf,
    ServoJp,
    State,
}

/// CRTK's `state_command` as a station op (docs/ZENOH.md).
fn state_command(s: &str) -> Result<Op, String> {
    let mode = match s {
        "enable" | "resume" | "pause" => "hold",
        "disable" => "idle",
        "home" | "unhome" => {
            return Err(format!(
                "`{s}`: the Omni homes in its inkwell; nothing to do over the network"
            ))
        }
        other => {
            return Err(format!(
                "{:?} is not a CRTK state command (enable, disable, pause, resume)",
                crate::text::cut(other)
            ))
        }
    };
    ModeRequest::parse(mode, None)
        .map(Op::Mode)
        .map_err(|e| e.to_string())
}

/// One sample of a command topic as a station op (`seq`: the command's number).
fn decode_command(c: Command, bytes: &[u8], seq: u64) -> Result<Op, String> {
    match c {
        Command::ServoCf => {
            let (_, force, _) = msgs::read_wrench_stamped(bytes).map_err(|e| e.to_string())?;
            if !force.iter().all(|f| f.is_finite()) {
                return Err("servo_cf: a force that is not finite".into());
            }
            Ok(Op::ServoCf {
                seq,
                force,
                ttl_ms: None,
            })
        }
        Command::ServoJp => {
            let q = msgs::read_joint_positions_n::<3>(bytes).map_err(|e| e.to_string())?;
            if !q.iter().all(|v| v.is_finite()) {
                return Err("servo_jp: a position that is not finite".into());
            }
            Ok(Op::ServoJp {
                seq,
                q,
                ttl_ms: None,
            })
        }
        Command::State => {
            let (_, s) = msgs::read_string_stamped(bytes).map_err(|e| e.to_string())?;
            state_command(s)
        }
    }
}

/// The arm's ROS 2 side.
pub(super) struct RosArm {
    measured_js: RosTopic,
    measured_cp: RosTopic,
    measured_cv: RosTopic,
    operating_state: RosTopic,
    buttons: [RosTopic; 2],
    _commands: Vec<zenoh::pubsub::Subscriber<()>>,
    _command_tokens: Vec<zenoh::liveliness::LivelinessToken>,
    js_every: u64,
    cp_every: u64,
    geometry: Geometry,
    frame: String,
    /// Device time 0 on the system clock, ns.
    epoch_ns: Option<u64>,
    last_state: Option<(&'static str, f64)>,
    last_buttons: Option<[bool; 2]>,
    ticks: u64,
    msg: Vec<u8>,
    stats: Arc<ZenohStats>,
}

/// The subscriptions of the command topics (servo_cf, servo_jp, state_command) in every form,
/// with their liveliness tokens. A sample on a command topic under another type or type hash
/// (a node built against other message definitions) is counted as refused and said, at most
/// once a minute: it would otherwise never reach a subscriber, and no one would know why.
fn declare_commands(
    session: &zenoh::Session,
    forms: &[Form],
    node: &Node,
    next_entity: &AtomicU64,
    topic_name: &dyn Fn(&str) -> String,
    net: &NetSide,
) -> Result<
    (
        Vec<zenoh::pubsub::Subscriber<()>>,
        Vec<zenoh::liveliness::LivelinessToken>,
    ),
    ZenohError,
> {
    let mut commands = Vec::new();
    let mut command_tokens = Vec::new();
    let seq = Arc::new(AtomicU64::new(0));
    for (leaf, t, c) in [
        ("servo_cf", rmw::WRENCH_STAMPED, Command::ServoCf),
        ("servo_jp", rmw::JOINT_STATE, Command::ServoJp),
        ("state_command", rmw::STRING_STAMPED, Command::State),
    ] {
        let topic = topic_name(leaf);
        for form in forms {
            let (key, token) = match *form {
                Form::Rmw(h) => {
                    let eid = next_entity.fetch_add(1, Ordering::Relaxed);
                    (
                        rmw::data_key(node.domain, &topic, &t, h),
                        node.endpoint_token(eid, Kind::Subscription, &topic, &t, h, Qos::CRTK),
                    )
                }
                Form::Bridge => (
                    topic.trim_matches('/').to_string(),
                    bridge_token(&node.zid, Kind::Subscription, &topic, &t),
                ),
            };
            let (net, seq) = (net.clone(), seq.clone());
            let sub = session
                .declare_subscriber(key.clone())
                .callback(move |sample: zenoh::sample::Sample| {
                    let payload = sample.payload();
                    if payload.len() > net.max_sample_bytes {
                        return net.refuse();
                    }
                    let n = seq.fetch_add(1, Ordering::Relaxed) + 1;
                    match decode_command(c, &payload.to_bytes(), n) {
                        Ok(op) => net.send(Inbound::Ros(op)),
                        Err(_) => net.refuse(),
                    }
                })
                .wait()
                .map_err(|e| declare_err(&key, e))?;
            commands.push(sub);
            command_tokens.push(
                session
                    .liveliness()
                    .declare_token(token.clone())
                    .wait()
                    .map_err(|e| declare_err(&token, e))?,
            );
        }
        // The rmw keys this topic is served under; anything else under its name is a
        // mismatch.
        let ours: Vec<String> = forms
            .iter()
            .filter_map(|f| match *f {
                Form::Rmw(h) => Some(rmw::data_key(node.domain, &topic, &t, h)),
                Form::Bridge => None,
            })
            .collect();
        if let Some(first) = ours.first() {
            commands.push(declare_mismatch(session, first, ours.clone(), net.clone())?);
        }
    }
    Ok((commands, command_tokens))
}

/// A subscriber on every type and hash of `key`'s topic that counts and says the samples not
/// under one of `ours`.
fn declare_mismatch(
    session: &zenoh::Session,
    key: &str,
    ours: Vec<String>,
    net: NetSide,
) -> Result<zenoh::pubsub::Subscriber<()>, ZenohError> {
    // `<domain>/<topic>/<type>/<hash>`: the topic's every type and hash.
    let topic = key.rsplitn(3, '/').nth(2).unwrap_or(key);
    let any = format!("{topic}/*/*");
    let said = Arc::new(AtomicU64::new(0));
    session
        .declare_subscriber(any.clone())
        .callback(move |sample: zenoh::sample::Sample| {
            let k = sample.key_expr().as_str();
            if ours.iter().any(|o| o == k) {
                return;
            }
            net.refuse();
            let now_s = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs());
            let last = said.load(Ordering::Relaxed);
            if (last == 0 || now_s >= last + 60)
                && said
                    .compare_exchange(last, now_s, Ordering::Relaxed, Ordering::Relaxed)
                    .is_ok()
            {
                crate::errln!(
                    "omnid serve: a ROS 2 command on {} was refused: its type or type hash is \
                     not this daemon's ({}); the sending node's message definitions differ \
                     (docs/ZENOH.md)",
                    crate::text::cut(k),
                    ours.join(" or ")
                );
            }
        })
        .wait()
        .map_err(|e| declare_err(&any, e))
}

/// Every `every`-th tick gives `rate_hz` out of `device_hz` (0: every tick).
fn every(device_hz: f64, rate_hz: f64) -> u64 {
    if rate_hz <= 0.0 || rate_hz >= device_hz {
        1
    } else {
        (device_hz / rate_hz).round().max(1.0) as u64
    }
}

impl RosArm {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn declare(
        session: &zenoh::Session,
        cfg: &ZenohConfig,
        node: &Node,
        next_entity: &AtomicU64,
        arm: &str,
        device_hz: f64,
        geometry: Geometry,
        net: NetSide,
    ) -> Result<RosArm, ZenohError> {
        let forms = forms(cfg);
        let topic_name = |leaf: &str| format!("{}/{arm}/{leaf}", cfg.namespace);
        let publisher = |leaf: &str, t: RosType| -> Result<RosTopic, ZenohError> {
            let topic = topic_name(leaf);
            let mut pubs = Vec::new();
            for form in &forms {
                let (key, token, gid) = match *form {
                    Form::Rmw(h) => {
                        let eid = next_entity.fetch_add(1, Ordering::Relaxed);
                        let token =
                            node.endpoint_token(eid, Kind::Publisher, &topic, &t, h, Qos::CRTK);
                        let gid = rmw::gid(&token);
                        (rmw::data_key(node.domain, &topic, &t, h), token, Some(gid))
                    }
                    Form::Bridge => (
                        topic.trim_matches('/').to_string(),
                        bridge_token(&node.zid, Kind::Publisher, &topic, &t),
                        None,
                    ),
                };
                let publisher = session
                    .declare_publisher(key.clone())
                    .congestion_control(zenoh::qos::CongestionControl::Drop)
                    .wait()
                    .map_err(|e| declare_err(&key, e))?;
                let matching = Arc::new(AtomicBool::new(false));
                let flag = matching.clone();
                publisher
                    .matching_listener()
                    .callback(move |s| flag.store(s.matching(), Ordering::Relaxed))
                    .background()
                    .wait()
                    .map_err(|e| declare_err(&key, e))?;
                let token = session
                    .liveliness()
                    .declare_token(token.clone())
                    .wait()
                    .map_err(|e| declare_err(&token, e))?;
                pubs.push(RosPub {
                    publisher,
                    gid,
                    seq: 0,
                    matching,
                    _token: token,
                });
            }
            Ok(RosTopic { pubs })
        };
        let measured_js = publisher("measured_js", rmw::JOINT_STATE)?;
        let measured_cp = publisher("measured_cp", rmw::POSE_STAMPED)?;
        let measured_cv = publisher("measured_cv", rmw::TWIST_STAMPED)?;
        let operating_state = publisher("operating_state", rmw::OPERATING_STATE)?;
        let buttons = [
            publisher("button1", rmw::JOY)?,
            publisher("button2", rmw::JOY)?,
        ];
        let (commands, command_tokens) = if cfg.allow_commands {
            declare_commands(session, &forms, node, next_entity, &topic_name, &net)?
        } else {
            (Vec::new(), Vec::new())
        };
        Ok(RosArm {
            measured_js,
            measured_cp,
            measured_cv,
            operating_state,
            buttons,
            _commands: commands,
            _command_tokens: command_tokens,
            js_every: every(device_hz, cfg.joint_rate_hz),
            cp_every: every(device_hz, cfg.cartesian_rate_hz),
            geometry,
            frame: format!("{arm}_base"),
            epoch_ns: None,
            last_state: None,
            last_buttons: None,
            ticks: 0,
            msg: Vec::with_capacity(512),
            stats: net.stats.clone(),
        })
    }

    /// CRTK's operating state of a tick.
    fn operating_state(r: &TickRecord) -> &'static str {
        match r.mode {
            Mode::Stop => "FAULT",
            _ if r.amps => "ENABLED",
            _ => "DISABLED",
        }
    }

    fn on_tick(&mut self, r: &TickRecord) {
        let t = r.t.max(0.0);
        let device_ns = (t * 1e9) as u64;
        // Device time 0 on the system clock: the least of (now − device time) seen so far. A
        // tick reaches this thread late, never early, so the least is the truest (within the
        // quickest tick's delay) and the stamps say when each tick happened.
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0);
        let seen = now.saturating_sub(device_ns);
        let epoch = *self
            .epoch_ns
            .insert(self.epoch_ns.map_or(seen, |e| e.min(seen)));
        let header = Header {
            stamp: Stamp::from_nanos(epoch.saturating_add(device_ns)),
            frame_id: "",
        };
        let based = Header {
            frame_id: &self.frame,
            ..header
        };
        let m = &mut self.msg;
        let stats = &*self.stats;
        if self.ticks.is_multiple_of(self.js_every) && self.measured_js.wanted() {
            m.clear();
            msgs::write_joint_state(m, &header, &JOINTS, &r.q, &r.qd, &r.tau);
            self.measured_js.put(m, stats);
        }
        if self.ticks.is_multiple_of(self.cp_every) {
            if self.measured_cp.wanted() {
                m.clear();
                let p = r.haptic.tip_mm.map(|v| v * 1e-3);
                msgs::write_pose_stamped(m, &based, p, [0.0, 0.0, 0.0, 1.0]);
                self.measured_cp.put(m, stats);
            }
            if self.measured_cv.wanted() {
                let j = crate::omni::kinematics::jacobian(&self.geometry, &r.q.into());
                let v = j * nalgebra::Vector3::from(r.qd);
                m.clear();
                msgs::write_twist_stamped(m, &based, [v[0], v[1], v[2]], [0.0; 3]);
                self.measured_cv.put(m, stats);
            }
        }
        let state = Self::operating_state(r);
        let repeat = self
            .last_state
            .is_none_or(|(s, at)| s != state || t - at >= STATE_REPEAT_S);
        if repeat {
            self.last_state = Some((state, t));
            m.clear();
            msgs::write_operating_state(m, &header, state, true, false);
            self.operating_state.put(m, stats);
        }
        let buttons = r.live.buttons;
        let last = self.last_buttons.replace(buttons);
        for i in 0..2 {
            if last.is_none_or(|l| l[i] != buttons[i]) {
                m.clear();
                msgs::write_joy(m, &header, &[], &[i32::from(buttons[i])]);
                self.buttons[i].put(m, stats);
            }
        }
        self.ticks += 1;
    }
}

/// The station's side of an arm's zenoh transport: ticks onto the network thread's queue.
pub(super) struct NetTap {
    /// Ticks to the network thread (dropped at the end: the thread then stops).
    tx: Option<Inlet<Outbound>>,
    stats: Arc<ZenohStats>,
    thread: Option<JoinHandle<()>>,
}

impl NetTap {
    pub(super) fn start(
        arm: &str,
        ros: Option<RosArm>,
        remote: Option<RemoteArm>,
        net: NetSide,
        outbox: Outbox,
    ) -> Box<dyn Tap> {
        let Outbox { ticks, feed: rx } = outbox;
        let thread = std::thread::Builder::new()
            .name(format!("omnid-zenoh-{arm}"))
            .spawn(move || feed(rx, ros, remote))
            .ok();
        Box::new(NetTap {
            tx: Some(ticks),
            stats: net.stats.clone(),
            thread,
        })
    }
}

/// The network thread of one arm: ticks to the ROS topics, messages to remote clients, until
/// the tap finishes.
fn feed(mut rx: Feed, mut ros: Option<RosArm>, mut remote: Option<RemoteArm>) {
    while let Some(m) = rx.next() {
        match m {
            Outbound::Tick(r) => {
                if let Some(ros) = ros.as_mut() {
                    ros.on_tick(&r);
                }
            }
            Outbound::ToClient { cid, bytes } => {
                if let Some(remote) = remote.as_mut() {
                    remote.send(&cid, &bytes);
                }
            }
            Outbound::Forget(cid) => {
                if let Some(remote) = remote.as_mut() {
                    remote.forget(&cid);
                }
            }
        }
    }
}

impl Tap for NetTap {
    fn on_tick(&mut self, record: &TickRecord) {
        // A full queue (the network behind) drops the tick: subscribers see a sequence gap
        // in rmw_zenoh's attachment, nothing else waits.
        let Some(tx) = self.tx.as_mut() else { return };
        if tx.push(Outbound::Tick(Box::new(*record))).is_err() {
            ZenohStats::count(&self.stats.dropped_out);
        }
    }

    fn prompt(&self) -> bool {
        // ROS 2 subscribers get each tick as it happens, not in the station's batches.
        true
    }

    fn finish(&mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commands_decode_into_station_ops_and_bad_ones_say_why() {
        let h = Header {
            stamp: Stamp { sec: 1, nanosec: 0 },
            frame_id: "left_base",
        };
        let mut b = Vec::new();
        msgs::write_wrench_stamped(&mut b, &h, [0.5, -0.25, 1.0], [0.0; 3]);
        assert!(matches!(
            decode_command(Command::ServoCf, &b, 7),
            Ok(Op::ServoCf { seq: 7, force, ttl_ms: None }) if force == [0.5, -0.25, 1.0]
        ));
        for cut in 0..b.len() {
            assert!(decode_command(Command::ServoCf, &b[..cut], 1).is_err());
        }
        b.clear();
        msgs::write_wrench_stamped(&mut b, &h, [f64::NAN, 0.0, 0.0], [0.0; 3]);
        assert!(decode_command(Command::ServoCf, &b, 1)
            .unwrap_err()
            .contains("not finite"));
        b.clear();
        msgs::write_joint_state(&mut b, &h, &["a", "b", "c"], &[0.1, 0.2, 0.3], &[], &[]);
        assert!(matches!(
            decode_command(Command::ServoJp, &b, 2),
            Ok(Op::ServoJp { q, .. }) if q == [0.1, 0.2, 0.3]
        ));
        // A JointState is not a wrench: the wrong type on a command key is refused.
        assert!(decode_command(Command::ServoCf, &b, 1).is_err());
        b.clear();
        msgs::write_string_stamped(&mut b, &h, "disable");
        assert!(matches!(
            decode_command(Command::State, &b, 3),
            Ok(Op::Mode(_))
        ));
        b.clear();
        msgs::write_string_stamped(&mut b, &h, "explode");
        assert!(decode_command(Command::State, &b, 3)
            .unwrap_err()
            .contains("not a CRTK state command"));
    }

    #[test]
    fn rates_become_tick_intervals() {
        assert_eq!(every(1000.0, 0.0), 1);
        assert_eq!(every(1000.0, 250.0), 4);
        assert_eq!(every(1000.0, 5000.0), 1);
        assert_eq!(every(1000.0, 300.0), 3);
    }

    #[test]
    fn bridge_tokens_name_the_topic_and_type_with_section_signs() {
        assert_eq!(
            bridge_token(
                "abc",
                Kind::Publisher,
                "/left/measured_js",
                &rmw::JOINT_STATE
            ),
            "@/abc/@ros2_lv/MP/left§measured_js/sensor_msgs§msg§JointState/:1:0:0,100:\
             typehash=RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e;"
        );
    }
}
