//! `omnid experiment teleop --out DIR` (docs/TELEOP.md §6): two simulated Omnis coupled in one
//! process, the simulated hand on the leader, a physical wall in the follower's simulator. Both
//! servos tick in lockstep, unpaced (the leader first, then the follower: the follower sees the
//! leader's packet of the same tick, the leader the follower's of the tick before), for each
//! architecture with and without time-domain passivity, each scene and each channel. Writes
//! `report.md`, `results.json` and figures.

use super::{write_figure, ExperimentError, ExperimentReport};
use crate::cmd::assembly::{assemble, RunOptions};
use crate::config::Config;
use crate::control::{ControllerKind, Trajectory};
use crate::haptics::{HandConfig, HandPattern};
use crate::plot::figures::Role;
use crate::plot::render::{Figure, Line, Panel};
use crate::servo::Servo;
use crate::telemetry::record::TickRecord;
use crate::teleop::channel::packet_flags;
use crate::teleop::{
    pair, Architecture, Coupling, DelayControl, Endpoint, Impairment, Operator, Packet, RemoteLine,
    Role as Side, TeleopConfig,
};
use crate::transport::zenoh::{ZenohConfig, ZenohNet};
use nalgebra::Vector3;
use serde::Serialize;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

type V3 = Vector3<f64>;

/// A channel the pair is run over: round trip (split evenly both ways), jitter as a fraction of
/// the one-way delay, loss.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Channel {
    /// Its name in the tables.
    pub name: &'static str,
    /// Round-trip delay, ms.
    pub rt_ms: f64,
    /// Each packet's delay varies by up to ± this fraction of the one-way delay.
    pub jitter: f64,
    /// Fraction of packets lost each way.
    pub loss: f64,
}

/// The channels: round trips from in-process to a second, jitter, and loss.
pub const CHANNELS: [Channel; 12] = [
    ch("0 ms", 0.0, 0.0, 0.0),
    ch("2 ms", 2.0, 0.0, 0.0),
    ch("10 ms", 10.0, 0.0, 0.0),
    ch("50 ms", 50.0, 0.0, 0.0),
    ch("100 ms", 100.0, 0.0, 0.0),
    ch("200 ms", 200.0, 0.0, 0.0),
    ch("500 ms", 500.0, 0.0, 0.0),
    ch("1000 ms", 1000.0, 0.0, 0.0),
    ch("100 ms ±50 %", 100.0, 0.5, 0.0),
    ch("10 ms, 1 % loss", 10.0, 0.0, 0.01),
    ch("10 ms, 10 % loss", 10.0, 0.0, 0.10),
    ch("10 ms, 50 % loss", 10.0, 0.0, 0.50),
];

const fn ch(name: &'static str, rt_ms: f64, jitter: f64, loss: f64) -> Channel {
    Channel {
        name,
        rt_ms,
        jitter,
        loss,
    }
}

/// What the hand does on the leader, and what the follower meets.
#[derive(Debug, Clone, Copy, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Scene {
    /// The hand traces a 3-D path at 0.1 m/s; no wall.
    Free,
    /// The hand pushes down with `force_n`; the follower meets a floor of `wall_n_per_mm`.
    Press {
        /// The hand's push, N.
        force_n: f64,
        /// The floor's stiffness, N/mm.
        wall_n_per_mm: f64,
    },
    /// The hand taps the floor (1 N/mm) at 1.5 Hz.
    Tap,
    /// The hand pushes with 1 N on the floor (1 N/mm) and lets go mid-contact.
    LetGo,
}

impl Scene {
    /// Its name in the tables.
    pub fn name(&self) -> String {
        match self {
            Scene::Free => "free path".into(),
            Scene::Press {
                force_n,
                wall_n_per_mm,
            } => format!("press {force_n} N, {wall_n_per_mm} N/mm"),
            Scene::Tap => "tapping".into(),
            Scene::LetGo => "let go".into(),
        }
    }

    fn wall(&self) -> Option<f64> {
        match self {
            Scene::Free => None,
            Scene::Press { wall_n_per_mm, .. } => Some(*wall_n_per_mm),
            Scene::Tap | Scene::LetGo => Some(1.0),
        }
    }

    fn secs(&self, quick: bool) -> f64 {
        let full = match self {
            Scene::Free => 6.0,
            Scene::Press { .. } => 4.0,
            Scene::Tap => 4.0,
            Scene::LetGo => 4.0,
        };
        if quick {
            full * 0.5
        } else {
            full
        }
    }

    /// When the hand lets go, s (let go only).
    fn release_s(&self, quick: bool) -> Option<f64> {
        matches!(self, Scene::LetGo).then(|| self.secs(quick) * 0.5)
    }
}

/// The follower's floor: this far below the workspace centre, mm (the hand pushes down, −y).
const FLOOR_MM: f64 = 10.0;
/// The hand's approach before each scene starts, s.
const APPROACH_S: f64 = 0.5;
/// A run is unstable when over its last second the follower's tip, less its 50 ms moving
/// average, moves more than this RMS, mm ...
const HF_TIP_MM: f64 = 0.2;
/// ... or the leader's force, less its moving average, more than this RMS, N.
const HF_FORCE_N: f64 = 0.15;

/// The numbers of one run (docs/TELEOP.md §6 defines each).
#[derive(Debug, Clone, Serialize)]
pub struct PairResult {
    /// pp or pf.
    pub architecture: &'static str,
    /// The control law both arms run (its compensation, and the model of the follower's
    /// external-force estimate: docs/TELEOP.md §2).
    pub controller: &'static str,
    /// Time-domain passivity on both ports.
    pub passivity: bool,
    /// The scene's name and parameters.
    pub scene: String,
    /// The channel's name.
    pub channel: &'static str,
    /// Round trip injected, ms.
    pub rt_ms: f64,
    /// Where the channel ran: `in_process` or `zenoh` (two sessions on loopback).
    pub link: &'static str,
    /// `[teleop] delay_control`: `gains` (delay-aware gains) or `wave` (wave variables).
    pub delay_control: &'static str,
    /// A thread spinning on a core beside the run (a CPU hog), zenoh rows only.
    pub cpu_hog: bool,
    /// The round trip the leader measured (the injected one plus the channel's own: a tick
    /// each way in process), median over the run, ms.
    pub measured_rt_ms: f64,
    /// Its largest value, ms.
    pub measured_rt_max_ms: f64,
    /// Follower vs the leader delayed by the forward delay (motion since engaging), mm.
    pub position_rms_mm: f64,
    /// Force displayed at the leader vs the environment's on the follower delayed by the
    /// backward delay, over the contact window, N (NaN without a wall).
    pub force_rms_n: f64,
    /// Perceived stiffness (leader force over the leader's depth past the mapped wall) over
    /// the environment's, in the press's last second (NaN where there is no steady press).
    pub stiffness_ratio: f64,
    /// No trip, and no sustained oscillation over the last second.
    pub stable: bool,
    /// Energy into the channel minus energy out of it at the end, J (≥ 0: passive).
    pub channel_energy_j: f64,
    /// Its lowest value over the run, J.
    pub channel_energy_min_j: f64,
    /// Packets delivered per second, both ways together.
    pub packets_per_s: f64,
    /// The follower's external-force estimate vs the true contact force over the contact
    /// window, N (NaN without a wall).
    pub fext_rms_n: f64,
    /// The leader's force less its 50 ms moving average over the last second, RMS, N: the
    /// vibration above about 20 Hz the hand feels.
    pub hf_force_n: f64,
    /// The follower's tip less its 50 ms moving average over the last second, RMS, mm.
    pub hf_tip_mm: f64,
    /// Why the run was unstable, when it was.
    pub why: Option<String>,
}

/// One run's time series (for figures).
#[derive(Debug, Default, Clone)]
pub struct Trace {
    /// Device time, s.
    pub t: Vec<f64>,
    /// Tips, mm.
    pub leader_tip: Vec<V3>,
    /// Follower tip, mm.
    pub follower_tip: Vec<V3>,
    /// The coupling's force on the leader (what the hand feels from the device), N.
    pub leader_force: Vec<V3>,
    /// The wall's force on the follower, N.
    pub environment: Vec<V3>,
    /// The follower's external-force estimate, N.
    pub fext: Vec<V3>,
    /// The channel's energy (in − out, both ports), J.
    pub energy: Vec<f64>,
}

/// The config of one side.
fn side_config(scene: &Scene, leader: bool, quick: bool) -> Config {
    let mut cfg = Config::default();
    cfg.sim.start_pose = cfg.reference.center;
    cfg.sim.docked = false;
    cfg.safety.persist_heat = false;
    // Both arms start coupled at the workspace centre: with the start-up ramp a side would
    // wait for its full authority before engaging (docs/TELEOP.md §3), and the runs measure
    // the coupling, not the ramp.
    cfg.safety.ramp_s = 0.0;
    if leader {
        cfg.haptics.hand = HandConfig {
            pattern: match scene {
                Scene::Free => HandPattern::Path,
                Scene::Press { .. } | Scene::LetGo => HandPattern::Push {
                    axis: 1,
                    sign: -1.0,
                },
                Scene::Tap => HandPattern::Tap {
                    axis: 1,
                    sign: -1.0,
                },
            },
            push_force_n: match scene {
                Scene::Press { force_n, .. } => *force_n,
                _ => 1.0,
            },
            speed_m_s: match scene {
                Scene::Free => 0.1,
                _ => 0.02,
            },
            path_radius_m: match scene {
                Scene::Tap => (FLOOR_MM + 2.0) * 1e-3,
                _ => 0.04,
            },
            release_s: scene.release_s(quick).unwrap_or(0.0),
            approach_s: APPROACH_S,
            ..HandConfig::default()
        };
    } else if let Some(k) = scene.wall() {
        cfg.sim.wall.enabled = true;
        cfg.sim.wall.side = "-y".into();
        cfg.sim.wall.distance_mm = FLOOR_MM;
        cfg.sim.wall.stiffness_n_per_mm = k;
    }
    cfg
}

/// A servo for one side (`controller`'s compensation: computed torque's parametric model
/// unless asked otherwise; the simulator at the workspace centre), its records drained by the
/// caller after every tick.
fn side_servo(
    name: &str,
    cfg: &Config,
    secs: f64,
    controller: ControllerKind,
) -> Result<(Servo, crossbeam_channel::Receiver<TickRecord>), ExperimentError> {
    let opts = RunOptions {
        controller,
        trajectory: Trajectory::Hold,
        duration_s: secs,
        fast: true,
        ..RunOptions::default()
    };
    let (tx, rx) = crossbeam_channel::bounded(64);
    let stop = Arc::new(AtomicBool::new(false));
    let p = assemble(&opts, cfg, &[], tx, stop).map_err(|source| ExperimentError::Run {
        name: name.to_string(),
        source: Box::new(source),
    })?;
    Ok((p.servo, rx))
}

/// Where a pair's channel runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Link {
    /// Both arms in one process, ticked unpaced (the daemon's in-process channel).
    InProcess,
    /// Each arm with its own zenoh session, as two daemons' (peer mode on TCP loopback, one
    /// connecting to the other), the channel opened as a daemon opens it to another daemon's
    /// arm; ticked in real time at 1 kHz.
    Zenoh,
}

impl Link {
    /// Its name in the results.
    pub fn as_str(self) -> &'static str {
        match self {
            Link::InProcess => "in_process",
            Link::Zenoh => "zenoh",
        }
    }
}

/// Two zenoh sessions on loopback (as two daemons' would be) and a channel's two network sides.
struct ZenohPair {
    follower_net: Option<ZenohNet>,
    _leader_net: ZenohNet,
    _lines: [Box<dyn RemoteLine>; 2],
}

/// Two simulated Omnis coupled in one process, ticked in lockstep (the leader first).
pub struct PairSim {
    /// The leader's servo (the simulated hand on it).
    pub leader: Servo,
    /// The follower's servo (a floor in its simulator, for the scenes with one).
    pub follower: Servo,
    lrx: crossbeam_channel::Receiver<TickRecord>,
    frx: crossbeam_channel::Receiver<TickRecord>,
    /// Over zenoh: the sessions, and the real-time pace (start, ticks so far).
    zenoh: Option<ZenohPair>,
    pace: Option<(Instant, u64)>,
    /// The channel's impairment each way (to the leader, to the follower).
    impairment: (Impairment, Impairment),
}

/// One lockstep tick's records.
pub struct PairTick {
    /// The leader's record.
    pub leader: TickRecord,
    /// The follower's record.
    pub follower: TickRecord,
}

impl PairSim {
    /// `arch` with passivity on or off, `scene` over `channel`, the coupling's other settings
    /// from `base`, for up to `secs` s.
    pub fn new(
        base: &TeleopConfig,
        arch: Architecture,
        passivity: bool,
        scene: &Scene,
        channel: &Channel,
        secs: f64,
        quick: bool,
    ) -> Result<PairSim, ExperimentError> {
        PairSim::build(
            base,
            arch,
            passivity,
            scene,
            channel,
            secs,
            quick,
            Link::InProcess,
        )
    }

    /// As [`PairSim::new`], the channel over `link`.
    #[allow(clippy::too_many_arguments)]
    pub fn build(
        base: &TeleopConfig,
        arch: Architecture,
        passivity: bool,
        scene: &Scene,
        channel: &Channel,
        secs: f64,
        quick: bool,
        link: Link,
    ) -> Result<PairSim, ExperimentError> {
        PairSim::build_under(
            base,
            arch,
            passivity,
            scene,
            channel,
            secs,
            quick,
            link,
            ControllerKind::Ct,
        )
    }

    /// As [`PairSim::build`], both arms under `controller` (computed torque elsewhere).
    #[allow(clippy::too_many_arguments)]
    pub fn build_under(
        base: &TeleopConfig,
        arch: Architecture,
        passivity: bool,
        scene: &Scene,
        channel: &Channel,
        secs: f64,
        quick: bool,
        link: Link,
        controller: ControllerKind,
    ) -> Result<PairSim, ExperimentError> {
        let name = format!(
            "{} {} {} {}",
            arch.as_str(),
            scene.name(),
            channel.name,
            link.as_str()
        );
        let lcfg = side_config(scene, true, quick);
        let fcfg = side_config(scene, false, quick);
        let one_way = channel.rt_ms / 2.0;
        let imp = Impairment {
            delay_ms: one_way,
            jitter_ms: one_way * channel.jitter,
            loss: channel.loss,
        };
        // Stability control is the passivity ports with the delay-aware gains or wave
        // variables (docs/TELEOP.md §5): off, the pair runs with fixed gains and no controller.
        let tcfg = TeleopConfig {
            architecture: arch,
            passivity,
            delay_gain_ms: if passivity { base.delay_gain_ms } else { 0.0 },
            delay_control: if passivity {
                base.delay_control
            } else {
                DelayControl::Gains
            },
            operator: Operator::Always,
            to_leader: imp,
            to_follower: imp,
            ..base.on_channel(link == Link::Zenoh)
        };
        let dt = 1.0 / lcfg.device.rate_hz;
        let (le, fe, zenoh) = match link {
            Link::InProcess => {
                let (le, fe) = pair(imp, imp, 0x7E1E);
                (le, fe, None)
            }
            Link::Zenoh => {
                let (le, fe, z) = zenoh_channel(&tcfg)
                    .map_err(|why| ExperimentError::Internal(format!("{name}: {why}")))?;
                (le, fe, Some(z))
            }
        };
        let (mut leader, lrx) = side_servo(&name, &lcfg, secs, controller)?;
        let (mut follower, frx) = side_servo(&name, &fcfg, secs, controller)?;
        leader.set_teleop(Box::new(Coupling::new(Side::Leader, &tcfg, le, dt)));
        follower.set_teleop(Box::new(Coupling::new(Side::Follower, &tcfg, fe, dt)));
        Ok(PairSim {
            leader,
            follower,
            lrx,
            frx,
            pace: zenoh.as_ref().map(|_| (Instant::now(), 0)),
            impairment: (imp, imp),
            zenoh,
        })
    }

    /// Over zenoh: close the follower's session, as a cut network or a daemon that died
    /// (both sides keep ticking; nothing crosses any more).
    pub fn cut_network(&mut self) {
        if let Some(net) = self.zenoh.as_mut().and_then(|z| z.follower_net.take()) {
            net.close();
        }
    }

    /// Lose every packet both ways from now (`true`: a dropout, both sides ticking on), or
    /// go back to the channel's own impairment (`false`).
    pub fn drop_packets(&mut self, on: bool) {
        let (to_leader, to_follower) = self.impairment;
        let lost = |imp: Impairment| {
            if on {
                Impairment { loss: 1.0, ..imp }
            } else {
                imp
            }
        };
        if let Some(c) = self.leader.teleop_mut() {
            c.set_impairment(lost(to_leader));
        }
        if let Some(c) = self.follower.teleop_mut() {
            c.set_impairment(lost(to_follower));
        }
    }

    /// The round trip the leader measures, ms.
    pub fn round_trip_ms(&self) -> f64 {
        self.leader
            .teleop()
            .map_or(f64::NAN, |c| c.round_trip_s() * 1e3)
    }

    /// Over zenoh, wait for the next millisecond (the servos tick in real time).
    fn pace(&mut self) {
        if let Some((start, k)) = self.pace.as_mut() {
            *k += 1;
            let due = *start + Duration::from_micros(*k * 1000);
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
    }

    /// Tick both sides (the leader first); `Err` names why either loop ended.
    pub fn tick(&mut self) -> Result<PairTick, String> {
        self.pace();
        let ends = [self.leader.tick(), self.follower.tick()];
        if let Some(end) = ends.iter().flatten().next() {
            return Err(format!("{end:?}"));
        }
        match (self.lrx.try_recv(), self.frx.try_recv()) {
            (Ok(leader), Ok(follower)) => Ok(PairTick { leader, follower }),
            _ => Err("a side sent no record".into()),
        }
    }

    /// Tick the leader alone (the follower has gone silent: a cut link).
    pub fn tick_leader(&mut self) -> Result<TickRecord, String> {
        self.pace();
        if let Some(end) = self.leader.tick() {
            return Err(format!("{end:?}"));
        }
        self.lrx.try_recv().map_err(|e| e.to_string())
    }

    /// The channel's energy, in less out over both ports, J.
    pub fn channel_energy(&self) -> f64 {
        self.leader
            .teleop()
            .zip(self.follower.teleop())
            .map_or(0.0, |(a, b)| {
                a.port().energy_in + b.port().energy_in - a.port().energy_out - b.port().energy_out
            })
    }
}

/// The zenoh settings of one of the experiment's two daemons: peer mode on loopback, nothing
/// else served, commands allowed (the channel moves the arm), the pair's key `key`.
fn zenoh_side(listen: &str, connect: Option<&str>, key: &str) -> ZenohConfig {
    ZenohConfig {
        teleop_keys: [(
            "leader/follower".to_string(),
            crate::transport::zenoh::config::Secret::from(key.to_string()),
        )]
        .into(),
        enabled: true,
        listen: vec![listen.to_string()],
        connect: connect.map(|c| vec![c.to_string()]).unwrap_or_default(),
        multicast_scouting: false,
        ros2: false,
        bridge: false,
        protocol: false,
        allow_commands: true,
        ..ZenohConfig::default()
    }
}

/// Two sessions on loopback, the leader's and the follower's ends of a channel between them
/// opened as a daemon opens one to another daemon's arm, and the link checked up both ways.
fn zenoh_channel(tcfg: &TeleopConfig) -> Result<(Endpoint, Endpoint, ZenohPair), String> {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map_err(|e| format!("no free loopback port: {e}"))?
        .port();
    let at = format!("tcp/127.0.0.1:{port}");
    // The pair's key, fresh for the run, as `head -c32 /dev/urandom | base64` makes one.
    let key = {
        use base64::Engine;
        let bytes: [u8; 32] = rand::random();
        base64::engine::general_purpose::STANDARD.encode(bytes)
    };
    let lnet = ZenohNet::start(&zenoh_side(&at, None, &key)).map_err(|e| e.to_string())?;
    let fnet = ZenohNet::start(&zenoh_side("tcp/127.0.0.1:0", Some(&at), &key))
        .map_err(|e| e.to_string())?;
    let (mut le, ll) = lnet
        .teleop()
        .open("leader", "follower", Side::Leader, tcfg, 0x7E1E)?;
    let (mut fe, fl) = fnet
        .teleop()
        .open("follower", "leader", Side::Follower, tcfg, 0x7E1F)?;
    // The sessions meet and the subscriptions spread: a packet each way before the run.
    let (to_leader, to_follower) = (tcfg.to_leader, tcfg.to_follower);
    le.set_impairment(Impairment::default());
    fe.set_impairment(Impairment::default());
    let until = Instant::now() + Duration::from_secs(10);
    let (mut l_heard, mut f_heard) = (false, false);
    while !(l_heard && f_heard) {
        if Instant::now() > until {
            return Err("the two zenoh sessions on loopback did not connect within 10 s".into());
        }
        let probe = Packet {
            flags: packet_flags::DOWN,
            ..Packet::default()
        };
        le.send(probe);
        fe.send(probe);
        std::thread::sleep(Duration::from_millis(5));
        l_heard |= le.receive(0.0).is_some();
        f_heard |= fe.receive(0.0).is_some();
    }
    le.clear();
    fe.clear();
    le.set_impairment(to_leader);
    fe.set_impairment(to_follower);
    Ok((
        le,
        fe,
        ZenohPair {
            follower_net: Some(fnet),
            _leader_net: lnet,
            _lines: [ll, fl],
        },
    ))
}

/// Run one pair: `arch`, passivity on or off, `scene` over `channel`, the coupling's other
/// settings from `base`.
pub fn run_pair(
    base: &TeleopConfig,
    arch: Architecture,
    passivity: bool,
    scene: &Scene,
    channel: &Channel,
    quick: bool,
) -> Result<(PairResult, Trace), ExperimentError> {
    run_pair_over(
        base,
        arch,
        passivity,
        scene,
        channel,
        quick,
        Link::InProcess,
    )
}

/// As [`run_pair`], the channel over `link`.
pub fn run_pair_over(
    base: &TeleopConfig,
    arch: Architecture,
    passivity: bool,
    scene: &Scene,
    channel: &Channel,
    quick: bool,
    link: Link,
) -> Result<(PairResult, Trace), ExperimentError> {
    run_pair_under(
        base,
        arch,
        passivity,
        scene,
        channel,
        quick,
        link,
        ControllerKind::Ct,
    )
}

/// As [`run_pair_over`], both arms under `controller` (the others run computed torque).
#[allow(clippy::too_many_arguments)]
pub fn run_pair_under(
    base: &TeleopConfig,
    arch: Architecture,
    passivity: bool,
    scene: &Scene,
    channel: &Channel,
    quick: bool,
    link: Link,
    controller: ControllerKind,
) -> Result<(PairResult, Trace), ExperimentError> {
    let secs = scene.secs(quick);
    let mut sim = PairSim::build_under(
        base, arch, passivity, scene, channel, secs, quick, link, controller,
    )?;
    let mut tr = Trace::default();
    let mut rtt = Vec::with_capacity((secs * 1000.0) as usize);
    let mut why = None;
    let ticks = (secs * 1000.0).round() as usize;
    for _ in 0..ticks {
        let PairTick {
            leader: l,
            follower: f,
        } = match sim.tick() {
            Ok(t) => t,
            Err(e) => {
                // A safety trip ends an unattached loop: unstable.
                why = Some(e);
                break;
            }
        };
        tr.t.push(l.t);
        tr.leader_tip.push(l.haptic.tip_mm.into());
        tr.follower_tip.push(f.haptic.tip_mm.into());
        tr.leader_force.push(l.haptic.force.into());
        tr.environment.push(
            sim.follower
                .device()
                .contact_force()
                .unwrap_or([0.0; 3])
                .into(),
        );
        tr.fext.push(sim.follower.external_force().into());
        tr.energy.push(sim.channel_energy());
        rtt.push(sim.round_trip_ms());
    }
    let delivered = [&sim.leader, &sim.follower]
        .iter()
        .filter_map(|s| s.teleop())
        .map(|c| c.channel().delivered)
        .sum::<u64>();
    let mut result = measure(arch, passivity, scene, channel, &tr, why, delivered, quick);
    result.link = link.as_str();
    result.controller = controller.as_str();
    result.delay_control = base.delay_control.as_str();
    // The leader's measured round trip over the run, once the link was up.
    let mut rtt: Vec<f64> = rtt.into_iter().filter(|v| *v > 0.0).collect();
    rtt.sort_by(f64::total_cmp);
    result.measured_rt_ms = rtt.get(rtt.len() / 2).copied().unwrap_or(f64::NAN);
    result.measured_rt_max_ms = rtt.last().copied().unwrap_or(f64::NAN);
    Ok((result, tr))
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    if n == 0 {
        f64::NAN
    } else {
        (s / n as f64).sqrt()
    }
}

/// RMS of `x` less its centred moving average over `w` samples, over `from..`.
fn high_pass_rms(x: &[V3], from: usize, w: usize) -> f64 {
    let h = w / 2;
    rms((from.max(h)..x.len().saturating_sub(h)).map(|k| {
        let mean = x[k - h..=k + h].iter().sum::<V3>() / (2 * h + 1) as f64;
        (x[k] - mean).norm()
    }))
}

#[allow(clippy::too_many_arguments)]
fn measure(
    arch: Architecture,
    passivity: bool,
    scene: &Scene,
    channel: &Channel,
    tr: &Trace,
    mut why: Option<String>,
    delivered: u64,
    quick: bool,
) -> PairResult {
    let n = tr.t.len();
    let shift = (channel.rt_ms / 2.0).round() as usize;
    let rate = 1000.0;
    let at = |s: f64| ((s * rate) as usize).min(n);
    let (xl0, xf0) = match (tr.leader_tip.first(), tr.follower_tip.first()) {
        (Some(l), Some(f)) => (*l, *f),
        _ => (V3::zeros(), V3::zeros()),
    };
    let secs = scene.secs(quick);
    // Position: after the approach, the whole scene.
    let position_rms_mm = rms((at(APPROACH_S).max(shift)..n)
        .map(|k| ((tr.follower_tip[k] - xf0) - (tr.leader_tip[k - shift] - xl0)).norm()));
    // Contact window: the press's steady last second, the tapping's whole, let-go's pushing
    // half after it settled.
    let window = match scene {
        Scene::Free => None,
        Scene::Press { .. } => Some((at(secs - 1.0), n)),
        Scene::Tap => Some((at(APPROACH_S), n)),
        Scene::LetGo => {
            let r = scene.release_s(quick).unwrap_or(secs);
            Some((at(r - 0.5), at(r)))
        }
    };
    let (force_rms_n, fext_rms_n) = match window {
        Some((a, b)) if b > a => (
            rms((a.max(shift)..b).map(|k| (tr.leader_force[k] - tr.environment[k - shift]).norm())),
            rms((a..b).map(|k| (tr.fext[k] - tr.environment[k]).norm())),
        ),
        _ => (f64::NAN, f64::NAN),
    };
    let stiffness_ratio = match (scene, window) {
        (Scene::Press { wall_n_per_mm, .. }, Some((a, b))) if b > a => {
            // Normal out of the floor: +y. The leader's depth past where the floor maps.
            let f: f64 = (a..b).map(|k| tr.leader_force[k][1]).sum::<f64>() / (b - a) as f64;
            let depth: f64 = (a..b)
                .map(|k| -(tr.leader_tip[k][1] - xl0[1]) - FLOOR_MM)
                .sum::<f64>()
                / (b - a) as f64;
            if depth > 0.05 {
                f / depth / wall_n_per_mm
            } else {
                f64::NAN
            }
        }
        _ => f64::NAN,
    };
    let last = n.saturating_sub(1000);
    let hf_tip = high_pass_rms(&tr.follower_tip, last, 51);
    let hf_force = high_pass_rms(&tr.leader_force, last, 51);
    if why.is_none() && n < (secs * rate) as usize {
        why = Some("ended early".into());
    }
    if why.is_none() && !(hf_tip <= HF_TIP_MM && hf_force <= HF_FORCE_N) {
        why = Some(format!(
            "oscillating over the last second: follower tip {hf_tip:.2} mm RMS, leader force \
             {hf_force:.2} N RMS above their 50 ms averages"
        ));
    }
    let channel_energy_j = tr.energy.last().copied().unwrap_or(0.0);
    let channel_energy_min_j = tr.energy.iter().copied().fold(0.0, f64::min);
    PairResult {
        architecture: arch.as_str(),
        controller: ControllerKind::Ct.as_str(),
        passivity,
        scene: scene.name(),
        channel: channel.name,
        rt_ms: channel.rt_ms,
        link: Link::InProcess.as_str(),
        delay_control: "gains",
        cpu_hog: false,
        measured_rt_ms: f64::NAN,
        measured_rt_max_ms: f64::NAN,
        position_rms_mm,
        force_rms_n,
        stiffness_ratio,
        stable: why.is_none(),
        channel_energy_j,
        channel_energy_min_j,
        packets_per_s: delivered as f64 / (n.max(1) as f64 / rate),
        fext_rms_n,
        hf_force_n: hf_force,
        hf_tip_mm: hf_tip,
        why,
    }
}

/// The scenes run over every channel, and those run over the first channels only.
fn scenes(quick: bool) -> (Vec<Scene>, Vec<Scene>) {
    let main = vec![
        Scene::Free,
        Scene::Press {
            force_n: 1.0,
            wall_n_per_mm: 1.0,
        },
        Scene::Tap,
        Scene::LetGo,
    ];
    let mut presses = Vec::new();
    if !quick {
        for force_n in [1.0, 2.0] {
            for wall_n_per_mm in [0.5, 1.0, 2.0] {
                if !(force_n == 1.0 && wall_n_per_mm == 1.0) {
                    presses.push(Scene::Press {
                        force_n,
                        wall_n_per_mm,
                    });
                }
            }
        }
    }
    (main, presses)
}

/// The experiment: every architecture with and without passivity, every scene and channel.
pub fn run_teleop(out: &Path, quick: bool) -> Result<ExperimentReport, ExperimentError> {
    crate::output::check_dir(out).map_err(ExperimentError::OutDir)?;
    for f in ["report.md", "results.json"] {
        crate::output::check_file(&out.join(f))?;
    }
    let plan = Plan::new(quick);
    // *Before*: the delay-aware gains everywhere (the default `auto` runs them in one daemon
    // and wave variables across daemons: docs/TELEOP.md §5).
    let base = TeleopConfig {
        delay_control: DelayControl::Gains,
        ..TeleopConfig::default()
    };
    let mut results = Vec::new();
    let traces = gains_runs(&plan, &base, &mut results)?;
    nnidc_rows(&plan, &base, &mut results)?;
    zenoh_rows(&plan, &base, &mut results)?;
    let wave = TeleopConfig {
        delay_control: DelayControl::Wave,
        ..base.clone()
    };
    wave_runs(&plan, &wave, &mut results)?;
    wave_zenoh_rows(&plan, &wave, &mut results)?;
    write_outputs(out, &plan, &results, &traces)
}

/// What one run of the experiment covers: its channels and scenes (fewer under `--quick`).
struct Plan {
    quick: bool,
    channels: Vec<Channel>,
    main: Vec<Scene>,
    presses: Vec<Scene>,
    /// The scenes run between two daemons over zenoh.
    zenoh_scenes: Vec<Scene>,
}

impl Plan {
    fn new(quick: bool) -> Plan {
        let channels: Vec<Channel> = if quick {
            [0usize, 4, 6, 10].iter().map(|&i| CHANNELS[i]).collect()
        } else {
            CHANNELS.to_vec()
        };
        let (main, presses) = scenes(quick);
        let zenoh_scenes: Vec<Scene> = if quick { vec![main[1]] } else { main.clone() };
        Plan {
            quick,
            channels,
            main,
            presses,
            zenoh_scenes,
        }
    }
}

/// The in-process runs under `base`'s gains: every architecture with and without passivity
/// control, every main scene and channel, and the press sweep at 0 and 100 ms. Returns the
/// figure's traces.
fn gains_runs(
    plan: &Plan,
    base: &TeleopConfig,
    results: &mut Vec<PairResult>,
) -> Result<Vec<(&'static str, Trace)>, ExperimentError> {
    let quick = plan.quick;
    let mut traces: Vec<(&'static str, Trace)> = Vec::new();
    for arch in [Architecture::Pp, Architecture::Pf] {
        for passivity in [true, false] {
            for scene in &plan.main {
                for c in &plan.channels {
                    let (r, tr) = run_pair(base, arch, passivity, scene, c, quick)?;
                    if let Some(title) = figure_panel(arch, passivity, scene, c) {
                        traces.push((title, tr));
                    }
                    results.push(r);
                }
            }
            for scene in &plan.presses {
                for c in [CHANNELS[0], CHANNELS[4]] {
                    results.push(run_pair(base, arch, passivity, scene, &c, quick)?.0);
                }
            }
        }
    }
    Ok(traces)
}

/// The 1 N press in process, control on, under nnidc beside the ct rows: the compensation and
/// the follower's force estimate then come from the learned model.
fn nnidc_rows(
    plan: &Plan,
    base: &TeleopConfig,
    results: &mut Vec<PairResult>,
) -> Result<(), ExperimentError> {
    for arch in [Architecture::Pp, Architecture::Pf] {
        let (r, _) = run_pair_under(
            base,
            arch,
            true,
            &plan.main[1],
            &CHANNELS[0],
            plan.quick,
            Link::InProcess,
            ControllerKind::Nnidc,
        )?;
        results.push(r);
    }
    Ok(())
}

/// The gains' rows between two daemons over zenoh on loopback, at 0 and 100 ms, with control
/// on (real time: these take as long as they last).
fn zenoh_rows(
    plan: &Plan,
    base: &TeleopConfig,
    results: &mut Vec<PairResult>,
) -> Result<(), ExperimentError> {
    for arch in [Architecture::Pp, Architecture::Pf] {
        for scene in &plan.zenoh_scenes {
            for c in [CHANNELS[0], CHANNELS[4]] {
                results
                    .push(run_pair_over(base, arch, true, scene, &c, plan.quick, Link::Zenoh)?.0);
            }
        }
    }
    Ok(())
}

/// Wave variables (docs/TELEOP.md §5) beside the delay-aware gains: every main scene and
/// channel, and the press sweep at 0 and 100 ms, with control on.
fn wave_runs(
    plan: &Plan,
    wave: &TeleopConfig,
    results: &mut Vec<PairResult>,
) -> Result<(), ExperimentError> {
    let quick = plan.quick;
    for arch in [Architecture::Pp, Architecture::Pf] {
        for scene in &plan.main {
            for c in &plan.channels {
                results.push(run_pair(wave, arch, true, scene, c, quick)?.0);
            }
        }
        for scene in &plan.presses {
            for c in [CHANNELS[0], CHANNELS[4]] {
                results.push(run_pair(wave, arch, true, scene, &c, quick)?.0);
            }
        }
    }
    Ok(())
}

/// pf with wave variables over zenoh at 100 ms, alone and with a thread spinning beside it (a
/// CPU hog: on a 2-core machine it takes a core from the two servo threads).
fn wave_zenoh_rows(
    plan: &Plan,
    wave: &TeleopConfig,
    results: &mut Vec<PairResult>,
) -> Result<(), ExperimentError> {
    for hog in [false, true] {
        let _spin = hog.then(Spinner::start);
        for scene in &plan.zenoh_scenes {
            let (mut r, _) = run_pair_over(
                wave,
                Architecture::Pf,
                true,
                scene,
                &CHANNELS[4],
                plan.quick,
                Link::Zenoh,
            )?;
            r.cpu_hog = hog;
            results.push(r);
        }
    }
    Ok(())
}

/// The press figure, `results.json` and `report.md` in `out`.
fn write_outputs(
    out: &Path,
    plan: &Plan,
    results: &[PairResult],
    traces: &[(&'static str, Trace)],
) -> Result<ExperimentReport, ExperimentError> {
    let mut figures = Vec::new();
    press_figure(out, traces, &mut figures)?;
    let md = report(results, &plan.channels, plan.quick);
    let json = serde_json::json!({
        "quick": plan.quick,
        "floor_mm": FLOOR_MM,
        "channels": plan.channels,
        "runs": results,
    });
    let text = serde_json::to_string_pretty(&json)
        .map_err(|e| ExperimentError::Internal(e.to_string()))?;
    crate::output::write_bytes(&out.join("results.json"), text.as_bytes())?;
    let report_path = out.join("report.md");
    crate::output::write_bytes(&report_path, md.as_bytes())?;
    Ok(ExperimentReport {
        report: report_path,
        figures,
        markdown: md,
    })
}

/// A thread spinning until dropped: a CPU hog beside a run.
struct Spinner {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Spinner {
    fn start() -> Spinner {
        let stop = Arc::new(AtomicBool::new(false));
        let s = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut x = 0u64;
            while !s.load(std::sync::atomic::Ordering::Relaxed) {
                x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
            }
        });
        Spinner {
            stop,
            thread: Some(thread),
        }
    }
}

impl Drop for Spinner {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Wave variables beside the delay-aware gains, in process with control on.
/// Issue #42's acceptance beside its *before*: at 100 ms, pf's 1 N press k ratio (≥ 0.5) and
/// free path (≤ 2 mm) under the delay-aware gains (before) and wave variables (after), in
/// process and over zenoh with and without a CPU hog beside it; and how many runs with control
/// are stable, per delay control and link.
fn acceptance_table(md: &mut String, all: &[PairResult]) {
    let find = |dc: &str, link: &str, hog: bool, scene: &str| {
        all.iter().find(|r| {
            r.architecture == "pf"
                && r.passivity
                && r.controller == "ct"
                && r.delay_control == dc
                && r.link == link
                && r.cpu_hog == hog
                && r.rt_ms == 100.0
                && r.channel == "100 ms"
                && r.scene.starts_with(scene)
        })
    };
    md.push_str(
        "## Acceptance at 100 ms (issue #42)\n\nPosition–force, 100 ms round trip, control on: \
         the hand should feel at least 0.5 of the floor's stiffness (1 N press into 1 N/mm) with \
         a free path within 2 mm. *Before* is the delay-aware gains, *after* wave variables, \
         the default across daemons (`delay_control = \"auto\"`: docs/TELEOP.md §5).\n\n\
         | delay control | link | CPU hog | press k ratio | free path mm | press stable | free stable | meets |\n\
         |---|---|---|---|---|---|---|---|\n",
    );
    for (dc, link, hog) in [
        ("gains", "in_process", false),
        ("gains", "zenoh", false),
        ("wave", "in_process", false),
        ("wave", "zenoh", false),
        ("wave", "zenoh", true),
    ] {
        let (press, free) = (
            find(dc, link, hog, "press 1 N, 1 N/mm"),
            find(dc, link, hog, "free"),
        );
        if press.is_none() && free.is_none() {
            continue;
        }
        let k = press.map_or(f64::NAN, |r| r.stiffness_ratio);
        let x = free.map_or(f64::NAN, |r| r.position_rms_mm);
        let st = |r: Option<&PairResult>| match r {
            Some(r) if r.stable => "yes",
            Some(_) => "**no**",
            None => "–",
        };
        let meets = k >= 0.5
            && x <= 2.0
            && press.is_some_and(|r| r.stable)
            && free.is_some_and(|r| r.stable);
        let _ = writeln!(
            md,
            "| {dc} | {} | {} | {} | {} | {} | {} | {} |",
            link.replace('_', " "),
            if hog { "yes" } else { "no" },
            num(k, 2),
            num(x, 2),
            st(press),
            st(free),
            if meets { "yes" } else { "**no**" }
        );
    }
    md.push_str("\nStable with control, every run of the experiment:\n\n| delay control | link | stable runs |\n|---|---|---|\n");
    for dc in ["gains", "wave"] {
        for link in ["in_process", "zenoh"] {
            let runs: Vec<&PairResult> = all
                .iter()
                .filter(|r| r.passivity && r.delay_control == dc && r.link == link)
                .collect();
            if runs.is_empty() {
                continue;
            }
            let _ = writeln!(
                md,
                "| {dc} | {} | {} of {} |",
                link.replace('_', " "),
                runs.iter().filter(|r| r.stable).count(),
                runs.len()
            );
        }
    }
    md.push('\n');
}

fn wave_table(md: &mut String, all: &[PairResult]) {
    let local = |dc: &str| {
        all.iter()
            .filter(move |r| {
                r.link == "in_process"
                    && r.controller == "ct"
                    && r.passivity
                    && r.delay_control == dc
            })
            .collect::<Vec<_>>()
    };
    let (gains, wave) = (local("gains"), local("wave"));
    if wave.is_empty() {
        return;
    }
    md.push_str(
        "## Wave variables beside the delay-aware gains

`[teleop] delay_control = \"wave\"` \
         (wave variables with drift compensation, docs/TELEOP.md §5) against the default \
         delay-aware gains (*before*), passivity control on, in process. Each cell is *gains / \
         wave*.\n\n\
         | architecture | scene | channel | position mm | force N | k ratio | stable | min energy mJ |\n\
         |---|---|---|---|---|---|---|---|\n",
    );
    for w in &wave {
        let g = gains.iter().find(|r| {
            r.architecture == w.architecture && r.scene == w.scene && r.channel == w.channel
        });
        let pair = |f: fn(&PairResult) -> f64, d: usize| {
            format!(
                "{} / {}",
                num(g.map_or(f64::NAN, |r| f(r)), d),
                num(f(w), d)
            )
        };
        let yes = |r: &PairResult| if r.stable { "yes" } else { "**no**" };
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} / {} | {} |",
            w.architecture,
            w.scene,
            w.channel,
            pair(|r| r.position_rms_mm, 2),
            pair(|r| r.force_rms_n, 3),
            pair(|r| r.stiffness_ratio, 2),
            g.map_or("–", |r| yes(r)),
            yes(w),
            pair(|r| r.channel_energy_min_j * 1e3, 1),
        );
    }
    md.push('\n');
}

/// The press figure's panel a run is drawn in, if any: 1 N into 1 N/mm with passivity control,
/// in-process and at 200 ms round trip.
fn figure_panel(
    arch: Architecture,
    passivity: bool,
    scene: &Scene,
    c: &Channel,
) -> Option<&'static str> {
    let press = matches!(scene, Scene::Press { force_n, wall_n_per_mm } if *force_n == 1.0 && *wall_n_per_mm == 1.0);
    if !(passivity && press && c.loss == 0.0 && c.jitter == 0.0) {
        return None;
    }
    match (arch, c.rt_ms as u32) {
        (Architecture::Pp, 0) => Some("position–position, in process"),
        (Architecture::Pf, 0) => Some("position–force, in process"),
        (Architecture::Pp, 200) => Some("position–position, 200 ms round trip"),
        (Architecture::Pf, 200) => Some("position–force, 200 ms round trip"),
        _ => None,
    }
}

fn press_figure(
    out: &Path,
    traces: &[(&'static str, Trace)],
    files: &mut Vec<PathBuf>,
) -> Result<(), ExperimentError> {
    if traces.is_empty() {
        return Ok(());
    }
    let mut x_max: f64 = 0.0;
    let panels = traces
        .iter()
        .map(|(title, tr)| {
            x_max = tr.t.last().copied().unwrap_or(0.0).max(x_max);
            let series = |v: &[V3]| tr.t.iter().zip(v).map(|(t, f)| (*t, f[1])).collect();
            Panel {
                title,
                lines: vec![
                    Line {
                        points: series(&tr.environment),
                        role: Role::Target,
                    },
                    Line {
                        points: series(&tr.leader_force),
                        role: Role::Measured,
                    },
                    Line {
                        points: series(&tr.fext),
                        role: Role::Estimate,
                    },
                ],
            }
        })
        .collect();
    let fig = Figure {
        size: (crate::plot::render::WIDTH, crate::plot::render::HEIGHT),
        font_scale: 1.0,
        title: "Press with 1 N into a 1 N/mm floor: the force felt at the leader",
        y_desc: "force up (+y), N",
        x_range: (0.0, x_max.max(1e-3)),
        shade_until: None,
        zero_line: true,
        legend: vec![
            ("the floor's force on the follower", Role::Target),
            ("the force the leader puts on the hand", Role::Measured),
            (
                "the follower's estimate of the floor's force",
                Role::Estimate,
            ),
        ],
        panels,
    };
    write_figure(&fig, out, "teleop-press", files)
}

fn num(v: f64, digits: usize) -> String {
    if v.is_finite() {
        format!("{v:.digits$}")
    } else {
        "–".into()
    }
}

fn report(all: &[PairResult], channels: &[Channel], quick: bool) -> String {
    let local: Vec<&PairResult> = all
        .iter()
        .filter(|r| r.link == "in_process" && r.controller == "ct" && r.delay_control == "gains")
        .collect();
    let mut md = String::new();
    intro(&mut md, quick);
    summary_table(&mut md, &local);
    architecture_tables(&mut md, &local, channels);
    press_table(&mut md, &local);
    md.push_str("![press](teleop-press.png)\n\n");
    controller_table(&mut md, all);
    acceptance_table(&mut md, all);
    wave_table(&mut md, all);
    zenoh_table(&mut md, all);
    unstable_list(&mut md, all);
    md
}

/// The title, the setup, the `--quick` warning and what the columns mean.
fn intro(md: &mut String, quick: bool) {
    md.push_str(
        "# Teleoperation between two simulated Omnis\n\n\
         Two simulated Omnis in one process, ticking in lockstep at 1 kHz: the simulated hand on \
         the leader, a floor 10 mm below the workspace centre inside the follower's simulator \
         (a physical spring-damper, not a rendered effect). Each side's coupling runs in its \
         arm's servo (docs/TELEOP.md). Channels are injected in both directions (half the round \
         trip each way).\n\n",
    );
    if quick {
        md.push_str("*`--quick`: shortened runs, fewer channels and no press sweep; the numbers are not the full experiment's.*\n\n");
    }
    md.push_str(
        "Columns: *position* is the follower's motion against the leader's delayed by the \
         forward delay (RMS, mm); *force* is the force the leader puts on the hand against the \
         floor's force on the follower delayed by the backward delay, over the contact window \
         (RMS, N); *k ratio* is the stiffness the hand feels (leader force over the leader's \
         depth past where the floor maps) over the floor's; *energy* is the channel's energy in \
         less out at the end (≥ 0: the channel made no energy); *stable*: no trip and no \
         sustained oscillation over the last second.\n\n",
    );
}

/// Stable runs and the worst channel energy per architecture and passivity control, over the
/// in-process runs of the fixed gains (`local`).
fn summary_table(md: &mut String, local: &[&PairResult]) {
    md.push_str("## Summary\n\n| architecture | passivity control | stable runs | worst channel energy (mJ) |\n|---|---|---|---|\n");
    for arch in ["pp", "pf"] {
        for pc in [true, false] {
            let runs: Vec<&PairResult> = local
                .iter()
                .copied()
                .filter(|r| r.architecture == arch && r.passivity == pc)
                .collect();
            let stable = runs.iter().filter(|r| r.stable).count();
            let worst = runs
                .iter()
                .map(|r| r.channel_energy_min_j)
                .fold(0.0, f64::min);
            let _ = writeln!(
                md,
                "| {arch} | {} | {stable} of {} | {} |",
                if pc { "on" } else { "off" },
                runs.len(),
                num(worst * 1e3, 1)
            );
        }
    }
    md.push('\n');
}

/// One table per architecture and passivity control: each channel's scenes.
fn architecture_tables(md: &mut String, results: &[&PairResult], channels: &[Channel]) {
    for arch in ["pp", "pf"] {
        for pc in [true, false] {
            let _ = writeln!(
                md,
                "## {} {} passivity control\n",
                if arch == "pp" {
                    "Position–position"
                } else {
                    "Position–force"
                },
                if pc { "with" } else { "without" }
            );
            md.push_str("| channel | free: position mm | free: stable | press 1 N: force N | press: k ratio | press: stable | tapping: stable | let go: stable | min energy mJ |\n|---|---|---|---|---|---|---|---|---|\n");
            for c in channels {
                channel_row(md, results, arch, pc, c);
            }
            md.push('\n');
        }
    }
}

/// One channel's row in its architecture's table.
fn channel_row(md: &mut String, results: &[&PairResult], arch: &str, pc: bool, c: &Channel) {
    let find = |scene: &str| {
        results.iter().copied().find(|r| {
            r.architecture == arch
                && r.passivity == pc
                && r.channel == c.name
                && r.scene.starts_with(scene)
        })
    };
    let st = |r: Option<&PairResult>| match r {
        Some(r) if r.stable => "yes".to_string(),
        Some(_) => "**no**".to_string(),
        None => "–".to_string(),
    };
    let free = find("free");
    let press = find("press 1 N, 1 N/mm");
    let min_e = results
        .iter()
        .copied()
        .filter(|r| r.architecture == arch && r.passivity == pc && r.channel == c.name)
        .map(|r| r.channel_energy_min_j)
        .fold(0.0, f64::min);
    let _ = writeln!(
        md,
        "| {} | {} | {} | {} | {} | {} | {} | {} | {} |",
        c.name,
        num(free.map_or(f64::NAN, |r| r.position_rms_mm), 2),
        st(free),
        num(press.map_or(f64::NAN, |r| r.force_rms_n), 3),
        num(press.map_or(f64::NAN, |r| r.stiffness_ratio), 2),
        st(press),
        st(find("tapping")),
        st(find("let go")),
        num(min_e * 1e3, 2),
    );
}

/// The press sweep on the in-process channel with passivity control (absent under `--quick`).
fn press_table(md: &mut String, results: &[&PairResult]) {
    let presses: Vec<&PairResult> = results
        .iter()
        .copied()
        .filter(|r| r.scene.starts_with("press") && r.passivity && r.rt_ms == 0.0)
        .collect();
    if presses.is_empty() {
        return;
    }
    md.push_str("## Presses, in-process channel, with passivity control\n\n| architecture | scene | force RMS N | k ratio | estimate RMS N | stable |\n|---|---|---|---|---|---|\n");
    for r in presses {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} |",
            r.architecture,
            r.scene,
            num(r.force_rms_n, 3),
            num(r.stiffness_ratio, 2),
            num(r.fext_rms_n, 3),
            if r.stable { "yes" } else { "**no**" }
        );
    }
    md.push('\n');
}

/// Each unstable run and why it was called so.
fn unstable_list(md: &mut String, all: &[PairResult]) {
    let unstable: Vec<&PairResult> = all.iter().filter(|r| !r.stable).collect();
    if unstable.is_empty() {
        return;
    }
    md.push_str("## Why the unstable runs were called so\n\n");
    for r in unstable {
        let _ = writeln!(
            md,
            "- {} {} passivity, {}, {}{}{}{}: {}",
            r.architecture,
            if r.passivity { "with" } else { "without" },
            r.scene,
            r.channel,
            if r.link == "zenoh" { " over zenoh" } else { "" },
            if r.delay_control == "wave" {
                " (wave variables)"
            } else {
                ""
            },
            if r.cpu_hog {
                " (CPU hog beside it)"
            } else {
                ""
            },
            r.why.as_deref().unwrap_or("")
        );
    }
}

/// The 1 N press into 1 N/mm in process under each model-based controller.
fn controller_table(md: &mut String, all: &[PairResult]) {
    let rows: Vec<&PairResult> = all
        .iter()
        .filter(|r| {
            r.link == "in_process"
                && r.passivity
                && r.channel == CHANNELS[0].name
                && r.scene == "press 1 N, 1 N/mm"
        })
        .collect();
    if !rows.iter().any(|r| r.controller != "ct") {
        return;
    }
    md.push_str(
        "## The press under each controller\n\n\
         The 1 N press into 1 N/mm in process with passivity control, both arms under the \
         controller: its compensation holds them, and the follower's force estimate (*estimate*, \
         against the floor's true force) is the momentum observer on its model — the parametric \
         one under ct, the learned one under nnidc (docs/TELEOP.md §2). *vibration* is the \
         leader's force above its 50 ms average over the last second (RMS): what the hand feels \
         above about 20 Hz.\n\n\
         | controller | architecture | force RMS N | estimate RMS N | vibration N | follower tip \
         jitter mm | stable |\n|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} |",
            r.controller,
            r.architecture,
            num(r.force_rms_n, 3),
            num(r.fext_rms_n, 3),
            num(r.hf_force_n, 3),
            num(r.hf_tip_mm, 3),
            if r.stable { "yes" } else { "**no**" }
        );
    }
    md.push('\n');
}

/// The rows run between two daemons over zenoh, each beside the same row in process.
fn zenoh_table(md: &mut String, all: &[PairResult]) {
    let over: Vec<&PairResult> = all.iter().filter(|r| r.link == "zenoh").collect();
    if over.is_empty() {
        return;
    }
    md.push_str(
        "## Two daemons over zenoh\n\nThe same rows with each arm behind its own zenoh \
         session, as two daemons' (peer mode on TCP loopback, one connecting to the other), \
         the channel opened as a daemon opens one to another daemon's arm (docs/TELEOP.md §9), \
         ticked in real time at 1 kHz; passivity control on. Beside each, the same row in \
         process (unpaced lockstep). *measured RTT* is the round trip the leader measured from \
         the echoed packet times (median over the run, and its largest): the injected delay \
         plus what the channel itself adds.\n\n\
         | architecture | delay control | CPU hog | scene | channel | position mm (zenoh / local) | force N (zenoh / local) \
         | k ratio (zenoh / local) | stable (zenoh / local) | measured RTT ms (zenoh / local) \
         | largest measured RTT ms (zenoh) | packets/s (zenoh) |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for z in over {
        let local = all.iter().find(|r| {
            r.link == "in_process"
                && r.passivity
                && r.controller == "ct"
                && r.delay_control == z.delay_control
                && r.architecture == z.architecture
                && r.scene == z.scene
                && r.channel == z.channel
        });
        let pair = |f: fn(&PairResult) -> f64, d: usize| {
            format!("{} / {}", num(f(z), d), num(local.map_or(f64::NAN, f), d))
        };
        let yes = |r: &PairResult| if r.stable { "yes" } else { "**no**" };
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} / {} | {} | {} | {} |",
            z.architecture,
            z.delay_control,
            if z.cpu_hog { "yes" } else { "no" },
            z.scene,
            z.channel,
            pair(|r| r.position_rms_mm, 2),
            pair(|r| r.force_rms_n, 3),
            pair(|r| r.stiffness_ratio, 2),
            yes(z),
            local.map_or("–", yes),
            pair(|r| r.measured_rt_ms, 1),
            num(z.measured_rt_max_ms, 1),
            num(z.packets_per_s, 0),
        );
    }
    md.push('\n');
}
