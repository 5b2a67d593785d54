//! The 1 kHz servo loop: device → decode → estimate → control → safety → encode → device, once
//! per packet. Everything it touches is allocated before the first tick; telemetry leaves
//! through a bounded channel with `try_send`.

pub mod command;
pub mod realtime;
pub(crate) mod safety;
pub mod summary;
pub mod thermal_store;
pub mod timing;

use crate::clock;
use crate::control::ReferenceConfig;
use crate::control::{ControlInput, ControllerSet, RefPoint, Reference};
use crate::device::DeviceConfig;
use crate::device::{
    decode_state, encode_command, DacScale, Device, DeviceError, EncoderUnwrap, MotorCommand,
    COMMAND_LEN,
};
use crate::estimate::kalman::{AccelLag, Estimate, KalmanConfig};
use crate::estimate::KalmanBank;
use crate::haptics::external::ExternalForce;
use crate::haptics::HapticsConfig;
use crate::haptics::{
    held_back, limit_force, near_walls, tip_force_torque, Effect, ExternalModel, Force3,
    HapticLoop, InertiaGate,
};
use crate::identifier::Identifier;
use crate::identifier::IdentifierConfig;
use crate::omni::Joint3;
use crate::omni::{jacobian, tip_position_mm, Dynamics, Geometry};
use crate::servo::summary::{FaultEntry, RunStats};
use crate::telemetry::record::{flags, HapticRecord, Live, Mode, TickRecord};
pub use command::Activity;
pub use command::{
    ArmSignals, ServoCommand, ServoEvent, ServoLink, ServoReply, Snapshot, Stamped, Wake,
};
use crossbeam_channel::{Sender, TrySendError};
use safety::SafetyConfig;
use safety::SafetyLayer;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use timing::TickTiming;

/// Link-quality floor: more than `LINK_MAX_BAD` bad packets in the last `LINK_WINDOW` is a
/// device fault; fewer are counted, held over and survived.
const LINK_WINDOW: u32 = 100;
const LINK_MAX_BAD: u32 = 10;
const LINK_WINDOW_MASK: u128 = (1u128 << LINK_WINDOW) - 1;

/// The time a teleoperation side runs on at device time `t`, s: in a paced loop the monotonic
/// clock — a loop that fell behind and catches up runs its ticks faster than real time, and a
/// peer's silence, a fade or a delay is real time (docs/TELEOP.md §4) — and device time in an
/// unpaced run, which has no real time.
fn teleop_clock(paced: bool, t: f64) -> f64 {
    if paced {
        clock::now_ns() as f64 * 1e-9
    } else {
        t
    }
}

/// The identifier learns nothing for this long after the stylus leaves its inkwell, s
/// (docs/IDENTIFIER.md, "Across the workspace"): the arm pressed into the inkwell by a growing
/// torque jumps free when the inkwell lets go, a step the estimated q̈ lags; learning from those
/// ticks swung M̂ and Ĝ so far that at centre 5 joint 3 passed the safety layer's 10 rad/s.
pub const UNDOCK_SETTLE_S: f64 = 0.1;

/// A paced loop whose next sample comes more than this after the previous one has stalled
/// (the log's and the state's `flags` bit [`flags::STALL`]; libHD raises `HD_TIMER_ERROR`,
/// docs/HDAPI.md, Errors), ns. Fifty periods at 1 kHz: far beyond a loaded machine's
/// scheduling hiccups (a few ms), short of anything a hand would not feel.
pub const STALL_NS: u64 = 50_000_000;

/// Why a run ended. Each class has its own exit code (see `main.rs` and the README).
#[derive(Debug, Clone, PartialEq)]
pub enum EndReason {
    /// The requested duration was reached.
    Completed,
    /// A replayed log ran out.
    EndOfData,
    /// Ctrl-C or SIGTERM.
    OperatorStop,
    /// The device failed, vanished or stopped answering.
    DeviceFault(String),
    /// A safety check tripped.
    SafetyFault(String),
}

impl EndReason {
    /// The name the summary and the fault list use (`completed`, `end-of-data`,
    /// `operator-stop`, `device-fault`, `safety-fault`).
    pub fn as_str(&self) -> &'static str {
        match self {
            EndReason::Completed => "completed",
            EndReason::EndOfData => "end-of-data",
            EndReason::OperatorStop => "operator-stop",
            EndReason::DeviceFault(_) => "device-fault",
            EndReason::SafetyFault(_) => "safety-fault",
        }
    }
}

/// What the loop hands back when it ends.
pub struct ServoReport {
    /// Why the loop ended.
    pub end: EndReason,
    /// The summary's running sums.
    pub stats: RunStats,
    /// Per-tick timing histograms.
    pub timing: TickTiming,
    /// Faults, in order (a daemon survives some).
    pub faults: Vec<FaultEntry>,
    /// Log records dropped because the telemetry channel was full.
    pub telemetry_dropped: u64,
    /// Packets lost or corrupt.
    pub missed_packets: u64,
    /// Times the estimator restarted across a gap in the device time, and the longest gap, s.
    pub estimator_restarts: u64,
    /// The longest gap in device time the estimator restarted across, s.
    pub longest_gap_s: f64,
    /// The last command packet sent (always the safe one after a clean shutdown).
    pub last_command: MotorCommand,
    /// A device error while sending the final safe packet or closing, if any.
    pub shutdown_error: Option<String>,
    /// The identifier as it ended (learned weights, fault state).
    pub identifier: Option<Identifier>,
    /// Motor heat at the end (for the thermal model of the next run).
    pub heat: [f64; 3],
    /// Joints whose heat reached the warning level.
    pub thermal_warned: [bool; 3],
}

/// Where the reference comes from. Held inline (a multisine's tables are ~2 kB): boxing it
/// would allocate on the servo thread whenever a client asks for `track`.
#[derive(Debug, Clone, Copy)]
#[allow(clippy::large_enum_variant)]
enum Target {
    /// A trajectory started at loop time `t0`.
    Trajectory { reference: Reference, t0: f64 },
    /// A fixed point (hold, the latest `servo_jp` setpoint).
    Point(RefPoint),
}

/// One sample from the device: measured angles and counts, time since the first sample and
/// device time, the stylus switches, and when the host woke with it.
struct Sample {
    q: Joint3,
    enc: [i64; 3],
    t: f64,
    t_dev: f64,
    buttons: [bool; 2],
    inkwell: bool,
    /// Gimbal potentiometer words, raw.
    gimbal: [u16; 3],
    wake: u64,
}

/// What one tick computed, for its log row.
struct Outcome {
    reference: [f64; 3],
    tau_cmd: [f64; 3],
    tau_hat: [f64; 3],
    tau_model: [f64; 3],
    /// What the plant got.
    tau_plant: [f64; 3],
    flags: u32,
}

/// The servo loop's state. Build it, then call [`Servo::run`] (or [`Servo::tick`] by hand).
pub struct Servo {
    device: Box<dyn Device>,
    controllers: ControllerSet,
    /// The adaptive identifier: runs every tick, whatever the controller.
    identifier: Option<Identifier>,
    activity: Activity,
    target: Target,
    reference_cfg: ReferenceConfig,
    seed: u64,
    wall_lower: [f64; 3],
    wall_upper: [f64; 3],
    /// `omnid serve`: commands in, replies and wake-ups out.
    link: Option<ServoLink>,
    /// The client stream's torque (servo_jf) or tip force (servo_cf, clamped to
    /// `max_force_n`), its last sequence number and its deadline.
    stream_tau: crate::omni::Joint3,
    stream_force: Force3,
    /// The client's tip force was beyond the peak (held to it).
    stream_force_limited: bool,
    max_force_n: f64,
    /// Forces at the tip: effects, passivity, Jᵀ F (docs/HAPTICS.md).
    haptics: HapticLoop,
    /// The haptic modes' partial inertia compensation: the fraction of the law's inertia
    /// times q̈ they add, gated off in contact (docs/HAPTICS.md §3).
    inertia: InertiaGate,
    /// This tick's estimated q̈ can be believed: not in the inkwell nor just out of it, not
    /// just after the estimator restarted across a gap.
    qdd_trusted: bool,
    /// The outside's force on the tip, from the motors and a model (docs/TELEOP.md §2).
    external: ExternalForce,
    external_model: ExternalModel,
    /// The parametric rigid-body model, for that estimate (and its geometry for the
    /// coupling's tip and Jᵀ F).
    parametric: Dynamics,
    /// This arm's side of a teleoperation pair (docs/TELEOP.md), and the force it put on the
    /// tip this tick.
    teleop: Option<Box<crate::teleop::Coupling>>,
    teleop_force: Force3,
    /// The coupling's own fast velocity estimate (`[teleop] velocity_jerk_psd`), and the
    /// measurement variance it was built with.
    teleop_kalman: KalmanBank,
    measurement_var: f64,
    /// The stylus buttons at this tick's sample.
    buttons: [bool; 2],
    /// The time of the last sample with the stylus in its inkwell, where the inkwell holds the
    /// arm (−∞: never docked).
    docked_t: f64,
    cmd_seq: u64,
    /// A reply went to the station this tick (its record wakes the station's host).
    replied: bool,
    stream_deadline: f64,
    event: Option<ServoEvent>,
    /// The owner epoch and stop count last read from the link's signals.
    owner_epoch: u64,
    halts_seen: u64,
    /// A safety trip left the arm idle: streams do not re-arm it until a mode is asked for.
    latched: bool,
    /// A wall or a torque limit acted on the last command: what acted was not the
    /// controller's, so nothing adapts on it (anti-windup).
    limited: bool,
    /// When each announced limit (FORCE_LIMIT, THERMAL, EFFECT_SKIPPED) last acted, s: an
    /// episode starts after 0.1 s without it.
    limit_last: [f64; 3],
    /// The setpoint a servo_jp stream asked for; the target moves to it at `slew_rad_s`.
    setpoint: Joint3,
    slew_rad_s: f64,
    kalman: KalmanBank,
    /// The estimator's acceleration response at the servo rate (the identifier's lag-matched
    /// e1, docs/IDENTIFIER.md).
    accel_lag: AccelLag,
    unwrap: EncoderUnwrap,
    dac: DacScale,
    rad_per_count: f64,
    safety: SafetyLayer,
    blend_s: f64,
    settle_s: f64,
    max_missed: u32,
    telemetry: Sender<TickRecord>,
    stop: Arc<AtomicBool>,
    max_ticks: Option<u64>,
    paced: bool,
    period_ns: u64,
    // Running state.
    command: MotorCommand,
    tick: u64,
    t0: Option<f64>,
    last_t: f64,
    last_q: [f64; 3],
    last_enc: [i64; 3],
    /// The torque that acted over the interval ending at this sample (the previous command,
    /// or the recording's for replays): what the identifier learns from.
    acting_tau: Option<[f64; 3]>,
    last_tau_hat: [f64; 3],
    last_reference: [f64; 3],
    last_tau_model: [f64; 3],
    consecutive_missed: u32,
    /// One bit per recent exchange, 1 = lost or corrupt (newest in bit 0).
    link_history: u128,
    held: bool,
    /// When the host woke with the last sample, ns (a stall: [`Servo::stalled`]).
    last_wake: u64,
    // Results.
    stats: RunStats,
    timing: TickTiming,
    dropped: u64,
    missed: u64,
}

/// The sections of the configuration the loop is built from (a `&Config` gives them).
#[derive(Debug, Clone, Copy)]
pub struct ServoSetup<'a> {
    /// Servo rate, encoder resolution, DAC scale.
    pub device: &'a DeviceConfig,
    /// The identifier's shape and learning settings.
    pub identifier: &'a IdentifierConfig,
    /// Reference trajectories a client may ask for, and the blend into them.
    pub reference: &'a ReferenceConfig,
    /// Torque, speed and heat limits, walls.
    pub safety: &'a SafetyConfig,
    /// The velocity estimator.
    pub kalman: &'a KalmanConfig,
    /// Seeds the trajectories a client asks for (`[sim] seed`).
    pub seed: u64,
    /// Haptic effects and the force limit.
    pub haptics: &'a HapticsConfig,
    /// Link lengths, for the tip position and τ = Jᵀ F.
    pub geometry: &'a Geometry,
    /// The parametric rigid-body model (the external-force estimate's, unless learned).
    pub model: &'a crate::omni::ModelParams,
}

impl Servo {
    /// A loop over `device` driven by `controllers` toward `reference`, its records sent on
    /// `telemetry`. It ends when `stop` is set, after `max_ticks` (if any) or on a fault;
    /// `paced` measures lateness against the device's schedule (off for `--fast` runs).
    #[allow(clippy::too_many_arguments)]
    pub fn new<'a>(
        cfg: impl Into<ServoSetup<'a>>,
        device: Box<dyn Device>,
        controllers: ControllerSet,
        reference: Reference,
        telemetry: Sender<TickRecord>,
        stop: Arc<AtomicBool>,
        max_ticks: Option<u64>,
        paced: bool,
    ) -> Self {
        let cfg = cfg.into();
        let period_ns = (1e9 / cfg.device.rate_hz).round() as u64;
        Servo {
            device,
            controllers,
            identifier: Identifier::new(cfg.identifier).ok(),
            activity: Activity::Track,
            target: Target::Trajectory { reference, t0: 0.0 },
            reference_cfg: cfg.reference.clone(),
            seed: cfg.seed,
            wall_lower: cfg.safety.wall_lower,
            wall_upper: cfg.safety.wall_upper,
            link: None,
            stream_tau: Joint3::zeros(),
            stream_force: Force3::zeros(),
            stream_force_limited: false,
            max_force_n: cfg.haptics.max_force_n,
            haptics: HapticLoop::new(cfg.haptics, *cfg.geometry),
            inertia: InertiaGate::new(cfg.haptics.inertia_compensation),
            qdd_trusted: false,
            external: ExternalForce::new(cfg.haptics.external_cutoff_hz, 1.0 / cfg.device.rate_hz),
            external_model: cfg.haptics.external_model,
            parametric: {
                let mut m = Dynamics::new(*cfg.model, *cfg.geometry);
                m.friction = true;
                m
            },
            teleop: None,
            teleop_force: Force3::zeros(),
            teleop_kalman: KalmanBank::new(cfg.kalman),
            measurement_var: cfg.kalman.measurement_var,
            buttons: [false; 2],
            docked_t: f64::NEG_INFINITY,
            cmd_seq: 0,
            replied: false,
            stream_deadline: f64::NEG_INFINITY,
            event: None,
            owner_epoch: 0,
            halts_seen: 0,
            latched: false,
            limited: false,
            limit_last: [f64::NEG_INFINITY; 3],
            setpoint: Joint3::zeros(),
            slew_rad_s: cfg.reference.slew_rad_s,
            kalman: KalmanBank::new(cfg.kalman),
            accel_lag: AccelLag::of(cfg.kalman, 1.0 / cfg.device.rate_hz),
            unwrap: EncoderUnwrap::new(),
            dac: DacScale {
                nm_per_count: cfg.device.nm_per_count,
            },
            rad_per_count: cfg.device.rad_per_count(),
            safety: SafetyLayer::new(cfg.safety, 1.0 / cfg.device.rate_hz, [0.0; 3])
                .with_encoder_step(cfg.device.rad_per_count()),
            blend_s: cfg.reference.blend_s,
            settle_s: cfg.reference.settle_s,
            max_missed: cfg.safety.max_missed_ticks,
            telemetry,
            stop,
            max_ticks,
            paced,
            period_ns,
            // Amplifiers stay off until the first valid sample has been seen.
            command: MotorCommand::safe(0),
            tick: 0,
            t0: None,
            last_t: 0.0,
            last_q: [0.0; 3],
            last_enc: [0; 3],
            acting_tau: None,
            last_tau_hat: [0.0; 3],
            last_reference: cfg.reference.center,
            last_tau_model: [0.0; 3],
            consecutive_missed: 0,
            link_history: 0,
            held: false,
            last_wake: 0,
            stats: RunStats::default(),
            timing: TickTiming::new(period_ns),
            dropped: 0,
            missed: 0,
        }
    }

    /// Serve clients: take commands from `link` and start in `Idle` (amplifiers off) instead
    /// of tracking; a safety trip then drops to `Idle` instead of ending the run.
    pub fn attach(&mut self, link: ServoLink) {
        self.owner_epoch = link.signals.owner().0;
        self.halts_seen = link.signals.halts();
        self.link = Some(link);
        self.activity = Activity::Idle;
    }

    /// The device's serial number, when its backend knows one (the daemon's hello).
    pub fn device_serial(&self) -> Option<String> {
        self.device.serial().map(String::from)
    }

    /// What the loop is doing now.
    pub fn activity(&self) -> Activity {
        self.activity
    }

    /// Replace the identifier (pre-tuned weights, adaptation off, …).
    pub fn set_identifier(&mut self, identifier: Identifier) {
        self.identifier = Some(identifier);
    }

    /// The online identifier, if it could be built from the configuration.
    pub fn identifier(&self) -> Option<&Identifier> {
        self.identifier.as_ref()
    }

    /// Start from warm motors (heat carried over from earlier runs).
    pub(crate) fn set_initial_heat(&mut self, heat: [f64; 3]) {
        self.safety.set_heat(heat);
    }

    /// Ticks completed so far.
    pub fn ticks(&self) -> u64 {
        self.tick
    }

    fn next_watchdog(&mut self) -> u8 {
        self.command.watchdog = self.command.watchdog.wrapping_add(1);
        self.command.watchdog
    }

    /// One exchange with the device and one control step. Returns `Some` when the run must end.
    pub fn tick(&mut self) -> Option<EndReason> {
        if self.stop.load(Ordering::Relaxed) {
            return Some(EndReason::OperatorStop);
        }
        if self.max_ticks.is_some_and(|n| self.tick >= n) {
            return Some(EndReason::Completed);
        }
        let s = match self.sense() {
            Ok(s) => s,
            Err(end) => return end,
        };
        // Estimate (the safety layer keeps what the encoders said, too).
        let est = self.kalman.update(s.t_dev, &s.q);
        self.safety.observe(s.t, &s.q);
        // Clients' commands that arrived while the loop waited for this sample.
        if self.link.is_some() {
            self.read_owner(s.t, &est.q);
            self.take_commands(s.t, &est.q);
            self.expire_stream(s.t, &est.q);
        }
        // Control, with the weights as they are; the update below then learns from this
        // sample at the same point (one network pass serves both).
        self.buttons = s.buttons;
        if s.inkwell {
            self.docked_t = s.t;
        }
        // The estimated q̈ lags a step: the inkwell letting go, or the filter restarting from
        // rest across a gap; it is believed again UNDOCK_SETTLE_S after either.
        self.qdd_trusted = s.t - self.docked_t >= UNDOCK_SETTLE_S
            && !self
                .kalman
                .last_gap()
                .is_some_and(|(at, _)| s.t_dev - at < UNDOCK_SETTLE_S);
        let (reference, tau_cmd) = self.control(s.t, &s.q, &est);
        let (tau_hat, ident_flag) = self.identify(s.t, &est);
        let tau_model = self.oracle(&est);
        self.estimate_external(&est);
        let limited = match self.limit(&tau_cmd, &est, s.t, s.t_dev) {
            Ok(l) => l,
            Err(end) => return Some(end),
        };
        let tau_plant = self.actuate(&limited.tau);
        self.limited = limited.flags & (flags::WALL | flags::CLAMPED | flags::THERMAL) != 0;
        let flags = limited.flags
            | ident_flag
            | self.haptic_flags()
            | if self.held { flags::HELD } else { 0 }
            | self.stalled(s.wake);
        self.announce_limits(s.t, flags);
        self.held = false;
        self.record(
            &s,
            &est,
            Outcome {
                reference: reference.q.into(),
                tau_cmd: tau_cmd.into(),
                tau_hat,
                tau_model,
                tau_plant,
                flags,
            },
        );
        None
    }

    /// Exchange one packet: send the command, decode the reply into joint angles and device
    /// time. `Err` when there is no sample this tick (`Some`: the run ends; `None`: a missed
    /// packet, survived).
    fn sense(&mut self) -> Result<Sample, Option<EndReason>> {
        self.next_watchdog();
        let bytes = encode_command(&self.command);
        let result = self.device.exchange(&bytes);
        let wake = clock::now_ns();
        let raw = match result {
            Ok(raw) => raw,
            Err(DeviceError::EndOfData) => return Err(Some(EndReason::EndOfData)),
            Err(DeviceError::Missed(_)) | Err(DeviceError::Malformed(_)) => {
                return Err(self.missed_packet());
            }
            Err(e) => return Err(Some(self.fault_device(e))),
        };
        let packet = match decode_state(raw.packet()) {
            Ok(p) => p,
            Err(_) => return Err(self.missed_packet()),
        };
        self.consecutive_missed = 0;
        self.link_history <<= 1;
        // Decode: continuous counts → joint angles.
        let enc = self.unwrap.update(packet.encoder);
        let q = Joint3::new(
            enc[0] as f64 * self.rad_per_count,
            enc[1] as f64 * self.rad_per_count,
            enc[2] as f64 * self.rad_per_count,
        );
        let t_dev = raw.device_time_s;
        Ok(Sample {
            q,
            enc,
            t: t_dev - *self.t0.get_or_insert(t_dev),
            t_dev,
            buttons: packet.buttons,
            inkwell: packet.inkwell,
            gimbal: packet.gimbal,
            wake,
        })
    }

    /// Identify: learn from the torque that acted up to this sample. The prediction, and the
    /// flag when the identifier has stopped.
    fn identify(&mut self, t: f64, est: &Estimate) -> ([f64; 3], u32) {
        let dt = if self.tick == 0 { 0.0 } else { t - self.last_t };
        let mut tau_hat = [0.0; 3];
        let mut ident_flag = 0;
        let Some(id) = self.identifier.as_mut() else {
            return (tau_hat, ident_flag);
        };
        id.match_estimator(&self.accel_lag);
        match self.acting_tau {
            // Amplifiers off, or a hand moving the arm (free, servo_cf): whatever holds or
            // moves it is not in the torque, so there is nothing true to learn from
            // (docs/HAPTICS.md §3). Predict only.
            // A wall or a limit acted: the torque was not the controller's, and learning from a
            // wall's push teaches the model the wall (anti-windup).
            // The stylus in its inkwell: the inkwell holds the arm up, and learning there
            // teaches the model that nothing is needed to hold it (then the first motion out of
            // the inkwell runs on a model without gravity), and for UNDOCK_SETTLE_S after it
            // let go (the arm's jump out of it is not in the torque either).
            Some(_)
                if !self.activity.learns()
                    || self.limited
                    || t - self.docked_t < UNDOCK_SETTLE_S =>
            {
                tau_hat = id.predict(&est.q, &est.qd, &est.qdd).into()
            }
            Some(acting) => {
                let predicted = id.update(&est.q, &est.qd, &est.qdd, &acting.into(), dt);
                if id.healthy() {
                    tau_hat = predicted.into();
                    self.stats.identifier.record(&acting, &tau_hat);
                }
            }
            // First sample: nothing has acted yet; log the prediction alone.
            None => tau_hat = id.predict(&est.q, &est.qd, &est.qdd).into(),
        }
        if !id.healthy() {
            // Stopped (whether or not it would learn now): said every tick, so the station
            // announces it.
            ident_flag = flags::IDENT_FAULT;
            // Stopped on a non-finite value: its last good weights still predict.
            let p: [f64; 3] = id.predict(&est.q, &est.qd, &est.qdd).into();
            if p.iter().all(|v| v.is_finite()) {
                tau_hat = p;
            }
        }
        (tau_hat, ident_flag)
    }

    /// The outside's force on the tip: the momentum observer on the learned model (under
    /// nnidc, or when asked for) or the parametric one, fed the motors' torque over the
    /// interval ending at this sample (docs/TELEOP.md §2).
    fn estimate_external(&mut self, est: &Estimate) {
        let learned = match self.external_model {
            ExternalModel::Learned => true,
            ExternalModel::Parametric => false,
            ExternalModel::Active => {
                self.controllers.active() == crate::control::ControllerKind::Nnidc
            }
        };
        let acting = Joint3::from(self.acting_tau.unwrap_or([0.0; 3]));
        match self.identifier.as_mut() {
            // A stopped identifier's model is not believed: the parametric one stands in.
            Some(id) if learned && id.healthy() => self.external.observe_learned(
                id,
                &self.parametric.geometry,
                &est.q,
                &est.qd,
                &acting,
            ),
            _ => self
                .external
                .observe(&self.parametric, &est.q, &est.qd, &acting),
        }
    }

    /// Simulator: the plant's exact inverse dynamics on the estimated states (NaN elsewhere).
    fn oracle(&mut self, est: &Estimate) -> [f64; 3] {
        match self.device.plant_model() {
            Some(m) => {
                let tm: [f64; 3] = m.inverse_dynamics(&est.q, &est.qd, &est.qdd).into();
                if let Some(acting) = self.acting_tau {
                    self.stats.record_oracle(&acting, &tm);
                }
                tm
            }
            None => [f64::NAN; 3],
        }
    }

    /// Safety: every command passes through the limits; a trip ends the run (under `serve`:
    /// zero torque, amplifiers off, mode idle, every client told).
    fn limit(
        &mut self,
        tau_cmd: &Joint3,
        est: &Estimate,
        t: f64,
        t_dev: f64,
    ) -> Result<safety::Limited, EndReason> {
        let rest = safety::Limited {
            tau: Joint3::zeros(),
            flags: 0,
        };
        if self.activity == Activity::Idle {
            self.safety.rest();
            return Ok(rest);
        }
        match self.safety.apply(tau_cmd, &est.q, &est.qd) {
            Ok(l) => Ok(l),
            Err(trip) if self.link.is_some() => {
                self.enter(Activity::Idle, &est.q);
                self.latched = true;
                self.safety.rest();
                self.event = Some(ServoEvent::SafetyTrip(trip));
                let speed = matches!(
                    trip,
                    safety::SafetyTrip::Velocity { .. }
                        | safety::SafetyTrip::MeasuredVelocity { .. }
                );
                Ok(safety::Limited {
                    flags: if speed { flags::SPEED_TRIP } else { 0 },
                    ..rest
                })
            }
            Err(trip) => {
                self.last_t = t;
                Err(EndReason::SafetyFault(self.explain(trip, t_dev)))
            }
        }
    }

    /// Encode: the next exchange sends it, amplifiers on from now (unless idle). Returns what
    /// the plant got: the DAC's torque, or on a replay the recorded torque (ours cannot reach
    /// it; it is still logged as `tau_cmd`).
    fn actuate(&mut self, tau: &Joint3) -> [f64; 3] {
        let words = self.dac.to_words(&(*tau).into());
        let tau_applied = self.dac.to_torque(&words);
        self.command.dac = words;
        self.command.amps_on = self.activity != Activity::Idle;
        self.device.recorded_torque().unwrap_or(tau_applied)
    }

    /// Record: the mode and the statistics of this tick, its log row, and what the next tick
    /// needs to remember.
    fn record(&mut self, s: &Sample, est: &Estimate, o: Outcome) {
        let t = s.t;
        let mode = match (self.activity, self.target) {
            (Activity::Track, Target::Trajectory { t0, .. }) => {
                if t - t0 < self.blend_s {
                    Mode::Blend
                } else {
                    if t - t0 >= self.settle_s {
                        let e = Joint3::from(o.reference) - est.q;
                        self.stats.record_tracking(&e.into());
                    }
                    Mode::Track
                }
            }
            (activity, _) => activity.mode(),
        };
        self.stats.record_time(t);
        self.stats.record_torque(&o.tau_plant);
        if matches!(self.activity, Activity::Free | Activity::ServoCf) {
            self.stats.haptic.record(
                &self.haptics.force,
                self.device.hand_force(),
                &self.haptics.depths,
            );
        }
        let event = self.event.take();
        if o.flags & flags::CLAMPED != 0 {
            self.stats.clamped_ticks += 1;
        }
        self.emit(TickRecord {
            t,
            q: s.q.into(),
            tau: o.tau_plant,
            qf: est.q.into(),
            qd: est.qd.into(),
            qdd: est.qdd.into(),
            reference: o.reference,
            tau_cmd: o.tau_cmd,
            tau_hat: o.tau_hat,
            tau_model: o.tau_model,
            tau_ext: self.external.tau.into(),
            enc: s.enc,
            amps: self.command.amps_on,
            mode,
            flags: o.flags,
            haptic: self.haptic_record(),
            live: Live {
                seq: self.tick,
                buttons: s.buttons,
                inkwell: s.inkwell,
                gimbal: s.gimbal,
                controller: Some(self.controllers.active()),
                cmd_seq: self.cmd_seq,
                event,
                heat: self.safety.heat(),
                teleop: self.teleop.as_ref().map(|c| c.state().as_str()),
                teleop_round_trip_s: self.teleop.as_ref().map_or(0.0, |c| c.round_trip_s()),
            },
        });
        self.last_t = t;
        self.last_q = s.q.into();
        self.last_enc = s.enc;
        self.last_reference = o.reference;
        self.last_tau_model = o.tau_model;
        self.acting_tau = Some(o.tau_plant);
        self.last_tau_hat = o.tau_hat;
        self.timing
            .record(s.wake, clock::now_ns(), s.t_dev, self.paced);
        self.tick += 1;
    }

    /// [`flags::STALL`] when this sample came more than [`STALL_NS`] after the previous one
    /// (paced runs: the loop missed its deadlines that long), else 0.
    fn stalled(&mut self, wake: u64) -> u32 {
        let gap = wake.saturating_sub(std::mem::replace(&mut self.last_wake, wake));
        if self.paced && self.tick > 0 && gap > STALL_NS {
            flags::STALL
        } else {
            0
        }
    }

    /// What acted on the tip force this tick (the haptic modes only).
    fn haptic_flags(&self) -> u32 {
        match self.activity {
            Activity::Free => self.haptics.flags,
            Activity::ServoCf if self.stream_force_limited => {
                self.haptics.flags | flags::FORCE_LIMIT
            }
            Activity::ServoCf => self.haptics.flags,
            _ => 0,
        }
    }

    /// A force limit that starts acting (after 0.1 s without it) is said once, as an event,
    /// and counted for the summary every tick it acts.
    fn announce_limits(&mut self, t: f64, acted: u32) {
        const ANNOUNCED: [u32; 3] = [flags::FORCE_LIMIT, flags::THERMAL, flags::EFFECT_SKIPPED];
        let mut started = 0;
        for (k, bit) in ANNOUNCED.into_iter().enumerate() {
            if acted & bit != 0 {
                if t - self.limit_last[k] > 0.1 {
                    started |= bit;
                }
                self.limit_last[k] = t;
            }
        }
        if acted & flags::FORCE_LIMIT != 0 {
            self.stats.force_limited_ticks += 1;
        }
        if acted & flags::THERMAL != 0 {
            self.stats.thermal_ticks += 1;
        }
        if started != 0 && self.event.is_none() {
            self.event = Some(ServoEvent::Limit { flags: started });
        }
    }

    /// This tick's haptic columns: the tip, the force commanded there, the simulated hand's.
    fn haptic_record(&self) -> HapticRecord {
        HapticRecord {
            tip_mm: self.haptics.tip_mm,
            force: if self.activity == Activity::Teleop {
                self.teleop_force.into()
            } else {
                self.haptics.force
            },
            hand: self.device.hand_force().unwrap_or([f64::NAN; 3]),
            fext: self.external.force.into(),
        }
    }

    /// Couple this arm as one side of a teleoperation pair now (the loop enters `teleop`);
    /// the coupling it replaces, if any.
    pub fn set_teleop(
        &mut self,
        coupling: Box<crate::teleop::Coupling>,
    ) -> Option<Box<crate::teleop::Coupling>> {
        self.activity = Activity::Teleop;
        self.teleop_kalman = KalmanBank::new(&KalmanConfig {
            jerk_psd: coupling.config().velocity_jerk_psd,
            measurement_var: self.measurement_var,
        });
        self.teleop.replace(coupling)
    }

    /// This arm's side of a teleoperation pair, if coupled.
    pub fn teleop(&self) -> Option<&crate::teleop::Coupling> {
        self.teleop.as_deref()
    }

    /// This arm's side of a teleoperation pair, to change (an experiment's channel).
    pub fn teleop_mut(&mut self) -> Option<&mut crate::teleop::Coupling> {
        self.teleop.as_deref_mut()
    }

    /// The outside's force on the tip as last estimated, N.
    pub fn external_force(&self) -> [f64; 3] {
        self.external.force.into()
    }

    /// The device under the loop (the experiment reads a simulator's true forces).
    pub fn device(&self) -> &dyn Device {
        self.device.as_ref()
    }

    /// Run in free mode (the compensation and the scene's effects) instead of tracking.
    pub fn start_free(&mut self) {
        self.activity = Activity::Free;
    }

    /// Put `effects` in the scene's first slots (they fade in from the first tick).
    pub fn set_effects(&mut self, effects: &[Effect]) {
        for (slot, e) in effects.iter().enumerate() {
            self.haptics.set_effect(slot, Some(*e), 0.0);
        }
    }

    /// Hand a row to the writer. Paced: never wait (a full channel drops the row and counts
    /// it). Unpaced (`--fast`): there is no deadline to keep, so wait for the writer and lose
    /// nothing.
    fn emit(&mut self, record: TickRecord) {
        let sent = if self.paced {
            match self.telemetry.try_send(record) {
                Ok(()) => true,
                Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => false,
            }
        } else {
            self.telemetry.send(record).is_ok()
        };
        if !sent {
            self.dropped += 1;
        }
        let replied = std::mem::take(&mut self.replied);
        if let Some(link) = &self.link {
            // A reply sent this tick is answered with this record (a snapshot's status).
            if record.live.event.is_some() || record.mode == Mode::Stop || replied {
                link.wake.notify();
            } else {
                link.wake.tick(record.live.seq);
            }
        }
    }

    /// The reference and the controller's torque for this tick, by activity (`q`: the
    /// measured pose, where a tip force is mapped to joint torque).
    fn control(&mut self, t: f64, q: &Joint3, est: &Estimate) -> (RefPoint, Joint3) {
        let here = RefPoint {
            q: est.q,
            ..RefPoint::default()
        };
        let mut reference = match &mut self.target {
            Target::Trajectory { reference, t0 } => reference.at(t - *t0, &est.q),
            Target::Point(p) => {
                // A setpoint is approached at a bounded speed, never as a step.
                let step = self.slew_rad_s * 1e-9 * self.period_ns as f64;
                for j in 0..3 {
                    let d = (self.setpoint[j] - p.q[j]).clamp(-step, step);
                    p.q[j] += d;
                }
                *p
            }
        };
        // Never a reference beyond the soft walls (a blend from a pose beyond one starts at
        // the wall): the controller and the wall pull the same way.
        reference.q = self.inside_walls(&reference.q);
        let input = ControlInput {
            t,
            estimate: est,
            reference: &reference,
        };
        let id = self.identifier.as_mut();
        let dt = 1e-9 * self.period_ns as f64;
        if !matches!(self.activity, Activity::Free | Activity::ServoCf) {
            self.haptics.observe(q);
            self.inertia.reset();
        }
        self.teleop_force = Force3::zeros();
        let teleop_t = teleop_clock(self.paced, t);
        if let Some(c) = self.teleop.as_mut() {
            // Every tick, coupled or not: a side that is not in teleop tells the other so. The
            // tip where the encoders put it, its velocity from the coupling's own fast filter.
            let fast = self.teleop_kalman.update(t, q);
            let side = crate::teleop::SideInput {
                t: teleop_t,
                tip_mm: tip_position_mm(&self.parametric.geometry, q),
                vel_mm_s: jacobian(&self.parametric.geometry, q) * fast.qd * 1e3,
                fext_n: self.external.force,
                buttons: self.buttons,
                active: self.activity == Activity::Teleop,
                ready: self.safety.full_authority(),
            };
            self.teleop_force = c.step(&side);
        }
        match self.activity {
            Activity::Idle => (here, Joint3::zeros()),
            Activity::Teleop => (
                here,
                self.controllers.coupling_compensation(t, est, id)
                    + tip_force_torque(&self.parametric.geometry, q, &self.teleop_force),
            ),
            Activity::Track | Activity::Hold | Activity::ServoJp => {
                (reference, self.controllers.torque(&input, id))
            }
            // The haptic modes: the compensation plus the tip force (effects and a client's).
            // The compensation takes the gated fraction of q̈ (partial inertia compensation,
            // off in contact: docs/HAPTICS.md §3).
            Activity::Free | Activity::ServoCf => {
                let force = self
                    .haptics
                    .torque(t, dt, q, &est.qd, &self.stream_force, true);
                // The soft walls are a contact too: a bounce on one with the lagged q̈ fed
                // back gains energy, and a released arm bounced ever faster between them.
                let at_wall = near_walls(q, &self.wall_lower, &self.wall_upper)
                    || near_walls(&est.q, &self.wall_lower, &self.wall_upper);
                let beta = self.inertia.step(
                    dt,
                    Force3::from(self.haptics.force).norm(),
                    self.haptics.dissipating() || at_wall,
                    self.qdd_trusted,
                );
                let accel = est.qdd * beta;
                (
                    here,
                    self.controllers.compensation(t, est, &accel, id) + force,
                )
            }
            Activity::ServoJf => (
                here,
                self.controllers.compensation(t, est, &Joint3::zeros(), id) + self.stream_tau,
            ),
        }
    }

    /// Change activity at the pose `q`: hold and setpoint modes start from it, tracking blends
    /// in from it, and authority ramps up again after idle.
    fn enter(&mut self, activity: Activity, q: &Joint3) {
        if self.activity == Activity::Idle && activity != Activity::Idle {
            self.safety.restart_ramp();
        }
        if matches!(activity, Activity::Hold | Activity::Idle) {
            self.target = Target::Point(RefPoint {
                q: *q,
                ..RefPoint::default()
            });
            self.setpoint = self.inside_walls(q);
        }
        if !activity.is_stream() {
            self.latched = false;
        }
        if activity == Activity::ServoJp && self.activity != Activity::ServoJp {
            // The slew starts from where the arm is.
            self.target = Target::Point(RefPoint {
                q: *q,
                ..RefPoint::default()
            });
        }
        self.activity = activity;
    }

    /// A target beyond the soft walls would only fight them: the nearest pose inside.
    fn inside_walls(&self, q: &Joint3) -> Joint3 {
        Joint3::from_fn(|j, _| q[j].clamp(self.wall_lower[j], self.wall_upper[j]))
    }

    /// Apply the commands that arrived since the last tick (at most
    /// [`command::MAX_COMMANDS_PER_TICK`]; the rest wait).
    fn take_commands(&mut self, t: f64, q: &Joint3) {
        for _ in 0..command::MAX_COMMANDS_PER_TICK {
            let Some(Stamped {
                epoch,
                halts,
                command,
            }) = self.link.as_mut().and_then(|l| l.commands.pop())
            else {
                break;
            };
            if self.admit(epoch, halts, &command, q) {
                self.apply_command(command, t, q);
            }
        }
        self.apply_halts(q);
    }

    /// A stop sent before this command comes first (the arm goes idle). False for a void
    /// command: one that would move the arm, sent before a stop already applied, or force an
    /// owner set up who has since left.
    #[inline]
    fn admit(&mut self, epoch: u64, halts: u64, command: &ServoCommand, q: &Joint3) -> bool {
        let moves = matches!(
            command,
            ServoCommand::Hold | ServoCommand::Track(_) | ServoCommand::Free
        );
        // Force an owner set up is theirs: once they have left, what they sent is void.
        let makes_force = matches!(
            command,
            ServoCommand::ServoJp { .. }
                | ServoCommand::ServoJf { .. }
                | ServoCommand::ServoCf { .. }
                | ServoCommand::Effect { .. }
                | ServoCommand::Free
                | ServoCommand::Teleop(_)
        );
        if halts > self.halts_seen {
            self.halts_seen = halts;
            self.enter(Activity::Idle, q);
        } else if halts < self.halts_seen && (moves || makes_force) {
            return false;
        }
        !(makes_force && epoch != self.owner_epoch)
    }

    /// One admitted command, by family: modes, streams, teleoperation, the servo's settings,
    /// and the requests answered by a reply.
    fn apply_command(&mut self, command: ServoCommand, t: f64, q: &Joint3) {
        match command {
            ServoCommand::Idle => self.enter(Activity::Idle, q),
            ServoCommand::Hold => self.enter(Activity::Hold, q),
            ServoCommand::Free => self.enter(Activity::Free, q),
            ServoCommand::Track(kind) => {
                self.enter(Activity::Track, q);
                self.target = Target::Trajectory {
                    reference: Reference::new(kind, &self.reference_cfg, self.seed),
                    t0: t,
                };
            }
            ServoCommand::ServoJp { .. }
            | ServoCommand::ServoJf { .. }
            | ServoCommand::ServoCf { .. }
                if self.latched => {}
            ServoCommand::ServoJp { seq, q: sp, ttl_s } => {
                if self.stream_starts(Activity::ServoJp, &sp, seq, ttl_s, t, q) {
                    self.setpoint = self.inside_walls(&sp.into());
                }
            }
            ServoCommand::ServoJf { seq, tau, ttl_s } => {
                if self.stream_starts(Activity::ServoJf, &tau, seq, ttl_s, t, q) {
                    self.stream_tau = tau.into();
                }
            }
            ServoCommand::ServoCf { seq, force, ttl_s } => {
                if self.stream_starts(Activity::ServoCf, &force, seq, ttl_s, t, q) {
                    let asked = Force3::from(force);
                    self.stream_force = limit_force(&asked, self.max_force_n);
                    self.stream_force_limited = held_back(&asked, &self.stream_force);
                }
            }
            ServoCommand::Teleop(coupling) => {
                self.enter(Activity::Teleop, q);
                if let Some(old) = self.set_teleop(coupling) {
                    self.reply(ServoReply::Teleop(old));
                }
            }
            ServoCommand::TeleopEnd => self.teleop_end(t, q),
            ServoCommand::TeleopScale(scale) => {
                if let Some(c) = self.teleop.as_mut() {
                    c.set_motion_scale(scale);
                }
            }
            ServoCommand::Effect { slot, effect } => self.haptics.set_effect(slot, effect, t),
            ServoCommand::Passivity(on) => self.haptics.set_passivity(on),
            ServoCommand::Stylus(action) => {
                self.device.stylus(action);
            }
            ServoCommand::Controller(kind) => self.controllers.switch(kind, t),
            ServoCommand::Adapt(on) => {
                if let Some(id) = self.identifier.as_mut() {
                    id.set_adapt(on);
                }
            }
            ServoCommand::LoadIdentifier(mut incoming) => {
                if let Some(id) = self.identifier.as_mut() {
                    std::mem::swap(id, &mut *incoming);
                }
                self.reply(ServoReply::Identifier(incoming));
            }
            ServoCommand::Snapshot(mut snap) => {
                self.fill(&mut snap);
                self.reply(ServoReply::Snapshot(snap));
            }
        }
    }

    /// A stream command's common part: finite `values` and a time to live, or it is void
    /// (false). Enters `activity` and keeps the stream's sequence number and deadline.
    #[inline]
    fn stream_starts(
        &mut self,
        activity: Activity,
        values: &[f64; 3],
        seq: u64,
        ttl_s: f64,
        t: f64,
        q: &Joint3,
    ) -> bool {
        if !(values.iter().all(|v| v.is_finite()) && ttl_s > 0.0) {
            return false;
        }
        self.enter(activity, q);
        self.cmd_seq = seq;
        self.stream_deadline = t + ttl_s;
        true
    }

    /// `TeleopEnd`: the other side hears that this one ended (docs/TELEOP.md §4); an arm
    /// still in teleop holds.
    fn teleop_end(&mut self, t: f64, q: &Joint3) {
        if let Some(mut old) = self.teleop.take() {
            old.end(teleop_clock(self.paced, t));
            if self.activity == Activity::Teleop {
                self.enter(Activity::Hold, q);
            }
            self.reply(ServoReply::Teleop(old));
        }
    }

    /// Ownership, read before the commands: an owner who left takes everything they set up
    /// that makes force with them (streams and free fall back; the effects are removed).
    fn read_owner(&mut self, t: f64, q: &Joint3) {
        let Some(link) = self.link.as_ref() else {
            return;
        };
        let (epoch, _) = link.signals.owner();
        if epoch != self.owner_epoch {
            self.owner_epoch = epoch;
            for slot in 0..crate::haptics::MAX_EFFECTS {
                self.haptics.set_effect(slot, None, t);
            }
            if self.activity.is_stream() {
                let fallback = self.stream_fallback(q);
                self.event = Some(ServoEvent::StreamEnded { fallback });
            } else if self.activity == Activity::Free && self.owner_fallback() != Activity::Free {
                // Free mode is the owner's haptic scene: without its owner the arm rests
                // (amplifiers off), unless the owner asked to be left in free mode.
                self.enter(Activity::Idle, q);
                self.event = Some(ServoEvent::StreamEnded {
                    fallback: Mode::Idle,
                });
            } else if self.activity == Activity::Teleop {
                // The pair was its owner's: without them this side holds (or rests) and
                // tells the other side it is down.
                let fallback = self.owner_fallback();
                self.enter(fallback, q);
                self.event = Some(ServoEvent::StreamEnded {
                    fallback: fallback.mode(),
                });
            }
        }
    }

    /// Stop requests not yet met among the commands: idle now, whatever is queued.
    fn apply_halts(&mut self, q: &Joint3) {
        let Some(link) = self.link.as_ref() else {
            return;
        };
        let halts = link.signals.halts();
        if halts > self.halts_seen {
            self.halts_seen = halts;
            self.enter(Activity::Idle, q);
        }
    }

    /// Where the owner's streams fall back to (hold without a link).
    fn owner_fallback(&self) -> Activity {
        self.link
            .as_ref()
            .map_or(Activity::Hold, |l| l.signals.owner().1)
    }

    /// Leave a stream mode for the owner's fallback; returns the mode fallen back to.
    fn stream_fallback(&mut self, q: &Joint3) -> Mode {
        let to = self.owner_fallback();
        self.stream_tau = Joint3::zeros();
        self.stream_force = Force3::zeros();
        self.stream_force_limited = false;
        self.enter(to, q);
        to.mode()
    }

    /// A stream whose last command is older than its time to live is stale: never hold a
    /// stale torque or setpoint.
    fn expire_stream(&mut self, t: f64, q: &Joint3) {
        if self.activity.is_stream() && t > self.stream_deadline {
            let fallback = self.stream_fallback(q);
            self.event = Some(ServoEvent::StreamStale { fallback });
        }
    }

    fn reply(&mut self, reply: ServoReply) {
        if let Some(link) = &mut self.link {
            // The receiver keeps far more room than requests in flight; should it be gone,
            // the box is dropped here (the daemon is shutting down anyway).
            let _ = link.replies.push(reply);
            self.replied = true;
            link.wake.notify();
        }
    }

    fn fill(&self, snap: &mut Snapshot) {
        snap.seq = self.tick;
        snap.stats.copy_from(&self.stats);
        snap.timing.copy_from(&self.timing);
        snap.weights_copied = match (&mut snap.weights, &self.identifier) {
            (Some(out), Some(id)) => out.copy_weights_from(id),
            _ => false,
        };
        snap.adapt = self.identifier.as_ref().is_some_and(|id| id.config().adapt);
        snap.ident_fault = self.identifier.as_ref().and_then(|id| id.fault());
        snap.telemetry_dropped = self.dropped;
        snap.missed_packets = self.missed;
        snap.heat = self.safety.heat();
    }

    /// A packet did not arrive or was corrupt: hold the last torque, count, and give up after
    /// `max_missed` in a row.
    fn missed_packet(&mut self) -> Option<EndReason> {
        self.missed += 1;
        self.consecutive_missed += 1;
        self.held = true;
        self.link_history = (self.link_history << 1) | 1;
        if self.consecutive_missed >= self.max_missed {
            return Some(EndReason::DeviceFault(format!(
                "watchdog: {} consecutive packets missed or corrupt",
                self.consecutive_missed
            )));
        }
        let bad = (self.link_history & LINK_WINDOW_MASK).count_ones();
        if bad > LINK_MAX_BAD {
            return Some(EndReason::DeviceFault(format!(
                "link quality: {bad} of the last {LINK_WINDOW} packets lost or corrupt"
            )));
        }
        None
    }

    /// A trip's message, naming a gap in the device time just before it (the run is ending:
    /// formatting is allowed here).
    fn explain(&self, trip: safety::SafetyTrip, t_dev: f64) -> String {
        match self.kalman.last_gap() {
            Some((after, len)) if t_dev - after < 0.2 => format!(
                "{trip} ({:.3} s after a {len:.3} s gap in the device time at t = {:.3} s; the \
                 estimator restarted there)",
                t_dev - after,
                after - self.t0.unwrap_or(0.0)
            ),
            _ => trip.to_string(),
        }
    }

    fn fault_device(&mut self, e: DeviceError) -> EndReason {
        EndReason::DeviceFault(e.to_string())
    }

    /// Send zero torque with the amplifiers off, log that packet, and release the device.
    fn shutdown(&mut self) -> Option<String> {
        let watchdog = self.next_watchdog();
        self.command = MotorCommand::safe(watchdog);
        let bytes: [u8; COMMAND_LEN] = encode_command(&self.command);
        let mut error = None;
        // The stop row: the reply's state when one comes back, else the last known state.
        let period = 1e-9 * self.period_ns as f64;
        let (mut t, mut q, mut enc) = (self.last_t + period, self.last_q, self.last_enc);
        // Mid-scale (0 rad) unless the reply says otherwise.
        let mut gimbal = [0x8000; 3];
        match self.device.exchange(&bytes) {
            Ok(raw) => {
                if let Some(t0) = self.t0 {
                    t = (raw.device_time_s - t0).max(self.last_t);
                }
                if let Ok(p) = decode_state(raw.packet()) {
                    gimbal = p.gimbal;
                    enc = self.unwrap.update(p.encoder);
                    q = enc.map(|c| c as f64 * self.rad_per_count);
                }
            }
            // The packet went out; only its reply is missing, or a replay has nowhere to send it.
            Err(DeviceError::Missed(_)) | Err(DeviceError::EndOfData) => {}
            Err(e) => error = Some(format!("sending the final zero-torque packet: {e}")),
        }
        let est = self.kalman.estimate();
        self.emit(TickRecord {
            t,
            q,
            tau: [0.0; 3],
            qf: est.q.into(),
            qd: est.qd.into(),
            qdd: est.qdd.into(),
            reference: self.last_reference,
            tau_cmd: [0.0; 3],
            tau_hat: self.last_tau_hat,
            tau_model: self.last_tau_model,
            tau_ext: self.external.tau.into(),
            enc,
            amps: false,
            mode: Mode::Stop,
            flags: 0,
            haptic: HapticRecord {
                force: [0.0; 3],
                ..self.haptic_record()
            },
            live: Live {
                seq: self.tick,
                controller: Some(self.controllers.active()),
                cmd_seq: self.cmd_seq,
                gimbal,
                ..Live::default()
            },
        });
        if let Err(e) = self.device.close() {
            error.get_or_insert(format!("closing the device: {e}"));
        }
        error
    }

    /// Run until the duration, the data, an operator stop or a fault ends it; always finishes
    /// with the safe packet.
    pub fn run(mut self) -> ServoReport {
        let end = loop {
            if let Some(end) = self.tick() {
                break end;
            }
        };
        self.finish(end)
    }

    /// End the run for `end`: record the fault if any, send the safe packet, release the
    /// device, and hand back the results.
    pub fn finish(mut self, end: EndReason) -> ServoReport {
        let mut faults = Vec::new();
        if let EndReason::DeviceFault(m) | EndReason::SafetyFault(m) = &end {
            faults.push(FaultEntry {
                tick: self.tick,
                t: self.last_t,
                class: end.as_str().to_string(),
                message: m.clone(),
            });
        }
        let shutdown_error = self.shutdown();
        ServoReport {
            end,
            stats: self.stats,
            timing: self.timing,
            faults,
            telemetry_dropped: self.dropped,
            missed_packets: self.missed,
            estimator_restarts: self.kalman.restarts(),
            longest_gap_s: self.kalman.longest_gap_s(),
            last_command: self.command,
            shutdown_error,
            identifier: self.identifier.take(),
            heat: self.safety.heat(),
            thermal_warned: self.safety.thermal_warned(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::control::{ControllerKind, Trajectory};
    use crate::device::sim::SimOmni;

    /// Ticks `n` times into a 16-row channel that nobody reads until it is full (unpaced: else
    /// the loop would wait forever) or until the run is over (paced).
    fn run_with_slow_writer(paced: bool, n: u64) -> (u64, u64) {
        let cfg = Config::default();
        let (tx, rx) = crossbeam_channel::bounded(16);
        let done = Arc::new(AtomicBool::new(false));
        let reader = {
            let done = done.clone();
            std::thread::spawn(move || {
                while !(if paced {
                    done.load(Ordering::SeqCst)
                } else {
                    rx.is_full()
                }) {
                    std::thread::yield_now();
                }
                rx.iter().count() as u64
            })
        };
        let mut servo = Servo::new(
            &cfg,
            Box::new(SimOmni::new(&cfg, false)),
            ControllerSet::new(&cfg, ControllerKind::Pd, 0.0),
            Reference::new(Trajectory::Sine, &cfg.reference, 1),
            tx,
            Arc::new(AtomicBool::new(false)),
            Some(n),
            paced,
        );
        while servo.tick().is_none() {}
        let report = servo.finish(EndReason::Completed);
        done.store(true, Ordering::SeqCst);
        (report.telemetry_dropped, reader.join().unwrap())
    }

    #[test]
    fn unpaced_runs_wait_for_the_writer_instead_of_dropping() {
        // 200 ticks and the stop row through a channel of 16 that fills before anyone reads.
        assert_eq!(run_with_slow_writer(false, 200), (0, 201));
    }

    /// A servo on the simulator with `Off` (no compensation, so the commanded torque is the
    /// stream's alone), attached to a link; its record channel and the command sender.
    /// The station's side of a test link: commands stamped with the current owner epoch.
    struct Commands(std::cell::RefCell<crate::handoff::Inlet<Stamped>>);

    impl Commands {
        fn send(&self, command: ServoCommand) -> Result<(), ()> {
            self.0
                .borrow_mut()
                .push(Stamped {
                    epoch: 0,
                    halts: 0,
                    command,
                })
                .map_err(|_| ())
        }
    }

    fn linked_servo() -> (Servo, crossbeam_channel::Receiver<TickRecord>, Commands) {
        linked_servo_docked(true)
    }

    /// A served servo on the simulator, its stylus starting in the inkwell or not.
    fn linked_servo_docked(
        docked: bool,
    ) -> (Servo, crossbeam_channel::Receiver<TickRecord>, Commands) {
        let mut cfg = Config::default();
        cfg.sim.torque_noise_nm = 0.0;
        if !docked {
            cfg.sim.start_pose = cfg.reference.center;
            cfg.sim.docked = false;
        }
        let (mut servo, rx) = sim_servo(&cfg, ControllerKind::Off, Trajectory::Hold);
        let (ctx, crx) = crate::handoff::queue(8);
        let (rtx, _rrx) = crate::handoff::queue(8);
        servo.attach(ServoLink {
            commands: crx,
            replies: rtx,
            wake: Arc::new(Wake::new().unwrap()),
            signals: Arc::new(ArmSignals::new(Activity::Hold)),
        });
        (servo, rx, Commands(std::cell::RefCell::new(ctx)))
    }

    /// An unpaced servo on the simulator under `kind` following `trajectory`, and its records.
    fn sim_servo(
        cfg: &Config,
        kind: ControllerKind,
        trajectory: Trajectory,
    ) -> (Servo, crossbeam_channel::Receiver<TickRecord>) {
        let (tx, rx) = crossbeam_channel::unbounded();
        let servo = Servo::new(
            cfg,
            Box::new(SimOmni::new(cfg, false)),
            ControllerSet::new(cfg, kind, 0.0),
            Reference::new(trajectory, &cfg.reference, 1),
            tx,
            Arc::new(AtomicBool::new(false)),
            None,
            false,
        );
        (servo, rx)
    }

    fn next(servo: &mut Servo, rx: &crossbeam_channel::Receiver<TickRecord>) -> TickRecord {
        assert!(servo.tick().is_none());
        rx.try_recv().unwrap()
    }

    /// τ = Jᵀ F with J by central differences of the forward kinematics (metres per rad).
    fn jt_f_by_differences(q: &[f64; 3], f: &[f64; 3]) -> [f64; 3] {
        let g = crate::omni::Geometry::default();
        let f = Force3::from(*f);
        std::array::from_fn(|j| {
            let (mut qp, mut qm) = (Joint3::from(*q), Joint3::from(*q));
            qp[j] += 1e-6;
            qm[j] -= 1e-6;
            let dp = (crate::omni::tip_position_mm(&g, &qp)
                - crate::omni::tip_position_mm(&g, &qm))
                * (1e-3 / 2e-6);
            f.dot(&dp)
        })
    }

    #[test]
    fn servo_cf_maps_the_tip_force_through_jt_and_clamps_its_norm() {
        let (mut servo, rx, cmd) = linked_servo();
        next(&mut servo, &rx);
        // Not finite: never passed on (the hub refuses it first; the servo ignores it too).
        cmd.send(ServoCommand::ServoCf {
            seq: 1,
            force: [f64::NAN, 0.0, 0.0],
            ttl_s: 1.0,
        })
        .unwrap();
        let r = next(&mut servo, &rx);
        assert_eq!(
            (r.mode, r.live.cmd_seq, r.tau_cmd),
            (Mode::Idle, 0, [0.0; 3])
        );
        // Within the peak: τ = Jᵀ F at the measured pose.
        let f = [0.4, -0.9, 0.3];
        cmd.send(ServoCommand::ServoCf {
            seq: 2,
            force: f,
            ttl_s: 1.0,
        })
        .unwrap();
        let r = next(&mut servo, &rx);
        assert_eq!((r.mode, r.live.cmd_seq), (Mode::ServoCf, 2));
        let want = jt_f_by_differences(&r.q, &f);
        for j in 0..3 {
            assert!(
                (r.tau_cmd[j] - want[j]).abs() < 1e-8,
                "{:?} {want:?}",
                r.tau_cmd
            );
        }
        // Huge: the same direction at the configured peak, 3.3 N.
        let huge = [0.0, -1e300, 0.0];
        cmd.send(ServoCommand::ServoCf {
            seq: 3,
            force: huge,
            ttl_s: 1.0,
        })
        .unwrap();
        let r = next(&mut servo, &rx);
        let want = jt_f_by_differences(&r.q, &[0.0, -3.3, 0.0]);
        for j in 0..3 {
            assert!(
                (r.tau_cmd[j] - want[j]).abs() < 1e-8,
                "{:?} {want:?}",
                r.tau_cmd
            );
        }
    }

    #[test]
    fn a_force_held_to_its_limit_is_flagged_every_tick_and_announced_once() {
        let (mut servo, rx, cmd) = linked_servo();
        next(&mut servo, &rx);
        let mut seen = Vec::new();
        for seq in 1..200 {
            cmd.send(ServoCommand::ServoCf {
                seq,
                force: [0.0, -50.0, 0.0],
                ttl_s: 1.0,
            })
            .unwrap();
            seen.push(next(&mut servo, &rx));
        }
        assert!(seen[1..].iter().all(|r| r.flags & flags::FORCE_LIMIT != 0));
        // A client that scaled its force to the peak itself (libHD clamps to 3.3 N) is at the
        // limit, not held by it, even when its norm is a last bit above 3.3 N.
        let at_peak = [1.0, -4.0, 2.0].map(|v: f64| v * 3.3 / 21f64.sqrt());
        assert!(
            Force3::from(at_peak).norm() > 3.3,
            "the case rounding makes"
        );
        cmd.send(ServoCommand::ServoCf {
            seq: 500,
            force: at_peak,
            ttl_s: 1.0,
        })
        .unwrap();
        let r = next(&mut servo, &rx);
        assert_eq!(r.flags & flags::FORCE_LIMIT, 0, "{:#x}", r.flags);
        let announced: Vec<_> = seen
            .iter()
            .filter(|r| matches!(r.live.event, Some(ServoEvent::Limit { .. })))
            .collect();
        assert_eq!(announced.len(), 1, "one event per episode");
        assert!(servo.stats.force_limited_ticks >= 198);
    }

    #[test]
    fn a_stale_servo_cf_falls_back_and_never_holds_the_force() {
        let (mut servo, rx, cmd) = linked_servo();
        next(&mut servo, &rx);
        cmd.send(ServoCommand::ServoCf {
            seq: 9,
            force: [0.5, 0.0, 0.0],
            ttl_s: 0.005,
        })
        .unwrap();
        let first = next(&mut servo, &rx);
        assert_eq!(first.mode, Mode::ServoCf);
        let mut seen = Vec::new();
        for _ in 0..10 {
            seen.push(next(&mut servo, &rx));
        }
        // Applied at t0: in effect up to t0 + 5 ms, the hold fallback the tick after.
        let k = seen.iter().position(|r| r.mode != Mode::ServoCf).unwrap();
        assert!(
            seen[k].t - first.t <= 0.006 + 1e-9,
            "{}",
            seen[k].t - first.t
        );
        assert_eq!(seen[k].mode, Mode::Hold);
        assert_eq!(
            seen[k].live.event,
            Some(ServoEvent::StreamStale {
                fallback: Mode::Hold
            })
        );
        // Off holds with nothing: the force is gone, not held.
        assert!(seen[k..].iter().all(|r| r.tau_cmd == [0.0; 3]));
    }

    /// The identifier's prediction at a fixed state.
    fn prediction(servo: &Servo) -> Joint3 {
        let mut id = servo.identifier().unwrap().clone();
        let q = Joint3::new(0.1, 0.6, 0.3);
        id.predict(
            &q,
            &Joint3::new(0.2, -0.1, 0.3),
            &Joint3::new(1.0, 0.5, -0.5),
        )
    }

    #[test]
    fn the_identifier_learns_nothing_while_a_hand_moves_the_arm() {
        // In hold the torque is all that moves the arm: the identifier learns. In free and
        // servo_cf a hand may move it with a force nobody measures: it must not.
        let mut learned = Vec::new();
        for cmd in [
            ServoCommand::Hold,
            ServoCommand::Free,
            ServoCommand::ServoCf {
                seq: 1,
                force: [0.0, 0.3, 0.0],
                ttl_s: 10.0,
            },
        ] {
            let (mut servo, rx, tx) = linked_servo_docked(false);
            tx.send(cmd).unwrap();
            next(&mut servo, &rx);
            let before = prediction(&servo);
            for _ in 0..300 {
                next(&mut servo, &rx);
            }
            learned.push((prediction(&servo) - before).norm());
        }
        assert!(learned[0] > 0.0, "hold: learned {}", learned[0]);
        assert_eq!(&learned[1..], &[0.0, 0.0], "free, servo_cf");
    }

    #[test]
    fn the_identifier_learns_nothing_while_the_inkwell_holds_the_arm() {
        // Holding with the stylus in its inkwell, the inkwell carries the arm's weight: what
        // the motors give is not what the arm needs, and a model learnt there has no gravity
        // (a daemon's first move out of the inkwell then ran on it and tripped).
        let (mut servo, rx, tx) = linked_servo_docked(true);
        tx.send(ServoCommand::Hold).unwrap();
        let first = next(&mut servo, &rx);
        assert!(first.live.inkwell, "the simulator starts docked");
        let before = prediction(&servo);
        for _ in 0..300 {
            assert!(next(&mut servo, &rx).live.inkwell);
        }
        assert_eq!((prediction(&servo) - before).norm(), 0.0);
    }

    #[test]
    fn the_identifier_learns_nothing_just_after_the_inkwell_lets_go() {
        // A run's blend out of the inkwell under NNIDC: the arm jumps free when the inkwell lets
        // go, and learning from that jump tripped the safety layer (docs/IDENTIFIER.md,
        // "Across the workspace"). Nothing is learnt for UNDOCK_SETTLE_S, then learning resumes.
        let mut cfg = Config::default();
        cfg.sim.torque_noise_nm = 0.0;
        let (mut servo, rx) = sim_servo(&cfg, ControllerKind::Nnidc, Trajectory::Sine);
        assert!(
            next(&mut servo, &rx).live.inkwell,
            "the simulator starts docked"
        );
        let mut docked_t = 0.0;
        let free_t = loop {
            let r = next(&mut servo, &rx);
            if !r.live.inkwell {
                break r.t;
            }
            docked_t = r.t;
            assert!(r.t < 1.0, "the blend never left the inkwell");
        };
        let before = prediction(&servo);
        let mut t = free_t;
        while t + 1e-3 < docked_t + UNDOCK_SETTLE_S - 1e-9 {
            let r = next(&mut servo, &rx);
            assert!(!r.live.inkwell);
            t = r.t;
            assert_eq!(prediction(&servo), before, "learnt at t = {t}");
        }
        for _ in 0..50 {
            next(&mut servo, &rx);
        }
        assert_ne!(prediction(&servo), before, "learning did not resume");
    }

    #[test]
    fn paced_runs_never_wait_for_the_writer() {
        // The realtime loop keeps going: 16 rows fit, the other 185 are dropped and counted.
        assert_eq!(run_with_slow_writer(true, 200), (185, 16));
    }

    /// A free-mode tick under CT: what it commanded beyond CT's compensation at zero
    /// acceleration, and M(q)·q̈ at its estimate (the inertia compensation is a fraction of it).
    fn beyond_compensation(
        ct: &mut crate::control::ComputedTorque,
        model: &Dynamics,
        r: &TickRecord,
    ) -> (Joint3, Joint3) {
        let est = Estimate {
            q: r.qf.into(),
            qd: r.qd.into(),
            qdd: r.qdd.into(),
        };
        let rest = crate::control::Controller::compensation(ct, &est, None);
        (Joint3::from(r.tau_cmd) - rest, model.mass(&est.q) * est.qdd)
    }

    #[test]
    fn free_mode_compensates_the_gated_fraction_of_the_inertia_and_none_near_the_inkwell() {
        // docs/HAPTICS.md §3. Under CT (its parametric model, no identifier in the way) with
        // no effects, the commanded torque is the compensation at the acceleration g·q̈: the
        // fraction g is read back from each tick's record. The simulated hand pulls the stylus
        // out of its inkwell and traces the path.
        let mut cfg = Config::default();
        cfg.sim.torque_noise_nm = 0.0;
        cfg.haptics.hand.pattern = crate::haptics::HandPattern::Path;
        cfg.haptics.inertia_compensation = 0.4;
        let (mut servo, rx) = sim_servo(&cfg, ControllerKind::Ct, Trajectory::Hold);
        servo.start_free();
        let mut ct = crate::control::ComputedTorque::from_config(&cfg);
        let model = Dynamics::new(cfg.model, cfg.geometry);
        let (mut docked_t, mut last_g, mut opened) = (None, 0.0, false);
        for _ in 0..3000 {
            let r = next(&mut servo, &rx);
            let (residual, mq) = beyond_compensation(&mut ct, &model, &r);
            if r.live.inkwell {
                docked_t = Some(r.t);
            }
            if docked_t.is_none_or(|t0| r.t - t0 < UNDOCK_SETTLE_S) {
                // In the inkwell and just out of it, q̈ is not believed: nothing of it.
                assert_eq!(residual, Joint3::zeros(), "at {} s", r.t);
                continue;
            }
            if mq.norm() < 1e-6 {
                continue;
            }
            let g = residual.dot(&mq) / mq.norm_squared();
            assert!(
                (residual - mq * g).norm() < 1e-12,
                "not along M·q̈ at {} s",
                r.t
            );
            // Never more than β, and it opens no faster than β per RETURN_S.
            assert!((-1e-9..=0.4 + 1e-9).contains(&g), "{g} at {} s", r.t);
            assert!(g - last_g <= 0.4 * 1e-3 / crate::haptics::inertia::RETURN_S + 1e-9);
            opened |= (g - 0.4).abs() < 1e-9;
            last_g = g;
        }
        assert!(
            docked_t.is_some_and(|t| t < 2.0),
            "the stylus never left the inkwell"
        );
        assert!(opened, "the gate never opened fully");
    }

    /// The simulator, its device time jumping by `gap_s` after `at` exchanges (a gap in the
    /// data, as a USB stall makes).
    struct Gappy {
        sim: SimOmni,
        exchanges: u64,
        at: u64,
        gap_s: f64,
    }

    impl Device for Gappy {
        fn kind(&self) -> &'static str {
            "sim"
        }

        fn exchange(
            &mut self,
            command: &[u8; crate::device::COMMAND_LEN],
        ) -> Result<crate::device::RawSample, DeviceError> {
            let mut raw = self.sim.exchange(command)?;
            self.exchanges += 1;
            if self.exchanges > self.at {
                raw.device_time_s += self.gap_s;
            }
            Ok(raw)
        }

        fn hand_force(&self) -> Option<[f64; 3]> {
            self.sim.hand_force()
        }
    }

    #[test]
    fn free_mode_compensates_no_inertia_just_after_the_estimator_restarted() {
        // As above, undocked at the centre; 0.1 s without data after 1.5 s restarts the
        // estimator, whose q̈ is then not believed for UNDOCK_SETTLE_S.
        let mut cfg = Config::default();
        cfg.sim.torque_noise_nm = 0.0;
        cfg.sim.start_pose = cfg.reference.center;
        cfg.sim.docked = false;
        cfg.haptics.hand.pattern = crate::haptics::HandPattern::Path;
        cfg.haptics.inertia_compensation = 0.4;
        let (tx, rx) = crossbeam_channel::unbounded();
        let device = Gappy {
            sim: SimOmni::new(&cfg, false),
            exchanges: 0,
            at: 1500,
            gap_s: 0.1,
        };
        let mut servo = Servo::new(
            &cfg,
            Box::new(device),
            ControllerSet::new(&cfg, ControllerKind::Ct, 0.0),
            Reference::new(Trajectory::Hold, &cfg.reference, 1),
            tx,
            Arc::new(AtomicBool::new(false)),
            None,
            false,
        );
        servo.start_free();
        let mut ct = crate::control::ComputedTorque::from_config(&cfg);
        let model = Dynamics::new(cfg.model, cfg.geometry);
        let (mut before, mut held, mut after) = (0.0_f64, 0, 0.0_f64);
        for k in 0..2000 {
            let r = next(&mut servo, &rx);
            let (residual, mq) = beyond_compensation(&mut ct, &model, &r);
            let g = residual.dot(&mq) / mq.norm_squared().max(1e-300);
            match k {
                1000..1500 => before = before.max(g),
                1500..1599 => {
                    assert_eq!(residual, Joint3::zeros(), "tick {k}, {} s", r.t);
                    held += 1;
                }
                1800.. => after = after.max(g),
                _ => {}
            }
        }
        assert_eq!(servo.kalman.restarts(), 1);
        assert_eq!(held, 99);
        assert!((before - 0.4).abs() < 1e-9, "before the gap: {before}");
        assert!((after - 0.4).abs() < 1e-9, "after the gap: {after}");
    }
}
