//! One row of the log: a plain `Copy` struct, so sending it through the bounded channel never
//! allocates.

/// What the loop was doing at this tick (the log's `mode` column).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Blending from the start pose onto the reference.
    Blend,
    /// Following the reference (tracking statistics are taken here).
    Track,
    /// The final packet: zero torque, amplifiers off.
    Stop,
    /// `omnid serve` only: amplifiers off, state streaming.
    Idle,
    /// Holding the pose where the mode began.
    Hold,
    /// Compensation by the active controller's model only (the arm moves freely).
    Free,
    /// Following a client's joint setpoint stream.
    ServoJp,
    /// A client's joint torque stream on top of the compensation.
    ServoJf,
    /// A client's tip force stream (Jᵀ F) on top of the compensation.
    ServoCf,
    /// One side of a teleoperation pair: the coupling's tip force on top of the compensation
    /// (docs/TELEOP.md).
    Teleop,
}

impl Mode {
    /// Every mode, in the order of the enum.
    pub const ALL: [Mode; 10] = [
        Mode::Blend,
        Mode::Track,
        Mode::Stop,
        Mode::Idle,
        Mode::Hold,
        Mode::Free,
        Mode::ServoJp,
        Mode::ServoJf,
        Mode::ServoCf,
        Mode::Teleop,
    ];

    /// The name in the log's `mode` column (`servo_jp`, …).
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Blend => "blend",
            Mode::Track => "track",
            Mode::Stop => "stop",
            Mode::Idle => "idle",
            Mode::Hold => "hold",
            Mode::Free => "free",
            Mode::ServoJp => "servo_jp",
            Mode::ServoJf => "servo_jf",
            Mode::ServoCf => "servo_cf",
            Mode::Teleop => "teleop",
        }
    }

    /// The mode a `mode` column names, if any.
    pub fn parse(s: &str) -> Option<Mode> {
        Mode::ALL.into_iter().find(|m| m.as_str() == s)
    }
}

/// Bits of the `flags` column: which safety action touched this tick.
pub mod flags {
    /// The torque clamp limited at least one joint.
    pub const CLAMPED: u32 = 1 << 0;
    /// The controller's output was not finite; zero torque was sent instead. Kept for the
    /// log format (docs/DESIGN.md's `flags` row) but never set: a non-finite command trips
    /// the safety layer instead ([`SafetyTrip::NonFinite`](super::SafetyTrip::NonFinite)).
    pub const NON_FINITE: u32 = 1 << 1;
    /// The previous tick's packet was missed and its torque held.
    pub const HELD: u32 = 1 << 2;
    /// The kick (torque-rate) limit acted.
    pub const RATE: u32 = 1 << 3;
    /// The start-up ramp scaled the torque down.
    pub const RAMP: u32 = 1 << 4;
    /// A soft joint-limit wall acted.
    pub const WALL: u32 = 1 << 5;
    /// A hot motor was held to its continuous torque.
    pub const THERMAL: u32 = 1 << 6;
    /// A motor is near its thermal limit.
    pub const THERMAL_WARN: u32 = 1 << 7;
    /// The identifier has stopped on a non-finite value (NNIDC runs on PD).
    pub const IDENT_FAULT: u32 = 1 << 8;
    /// The tip force was held to `[haptics] max_force_n` (a client's `servo_cf`, the scene's
    /// effects, or both).
    pub const FORCE_LIMIT: u32 = 1 << 9;
    /// An effect whose force was not finite at this pose was left out of the sum (the other
    /// effects still act).
    pub const EFFECT_SKIPPED: u32 = 1 << 10;
    /// The safety layer tripped on a joint's speed this tick (`safety.max_velocity_rad_s`):
    /// the arm is now idle (`omnid serve`; a run ends instead).
    pub const SPEED_TRIP: u32 = 1 << 11;
    /// The servo loop stalled: this sample came more than 50 ms after the previous one
    /// (paced runs; `servo::STALL_NS`).
    pub const STALL: u32 = 1 << 12;
}

/// Everything the loop knows at one tick: one row of the log, what `omnid serve` streams and
/// what a fault dump keeps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TickRecord {
    /// Device time since start, s.
    pub t: f64,
    /// Measured joint angles (from the encoders), rad.
    pub q: [f64; 3],
    /// Torque actually commanded to the motors after limits and DAC quantisation, N·m (on a
    /// replay: the recorded torque, what the recorded plant got).
    pub tau: [f64; 3],
    /// Kalman estimates.
    pub qf: [f64; 3],
    /// Joint velocities, rad/s (the estimator's).
    pub qd: [f64; 3],
    /// Joint accelerations, rad/s² (the estimator's).
    pub qdd: [f64; 3],
    /// Reference position, rad.
    pub reference: [f64; 3],
    /// Controller output before the safety layer, N·m.
    pub tau_cmd: [f64; 3],
    /// The identifier's prediction of the torque that acted (NaN when it has none).
    pub tau_hat: [f64; 3],
    /// The plant's exact model on the estimated states (simulator only, else NaN).
    pub tau_model: [f64; 3],
    /// The outside's torque on each joint estimated from the motors and the model, N·m
    /// (τ̂_ext, docs/TELEOP.md §2; NaN when read from a log without it).
    pub tau_ext: [f64; 3],
    /// Continuous encoder counts.
    pub enc: [i64; 3],
    /// Whether the amplifiers were on.
    pub amps: bool,
    /// The servo's mode.
    pub mode: Mode,
    /// Event flags (`flags::*`).
    pub flags: u32,
    /// The tip and the forces there (docs/HAPTICS.md).
    pub haptic: HapticRecord,
    /// What the daemon's clients see beyond the log's columns (not written to the log).
    pub live: Live,
}

impl TickRecord {
    /// Device time since start, s.
    pub fn t(&self) -> f64 {
        self.t
    }

    /// The tip force commanded this tick (effects, a client's, or a teleoperation coupling's),
    /// N.
    pub fn haptic_force(&self) -> [f64; 3] {
        self.haptic.force
    }

    /// The stylus tip, mm.
    pub fn tip_mm(&self) -> [f64; 3] {
        self.haptic.tip_mm
    }

    /// The mode's name, as the log's `mode` column writes it.
    pub fn mode_name(&self) -> &'static str {
        self.mode.as_str()
    }
}

#[cfg(test)]
impl TickRecord {
    /// A record at tick `seq` in `mode`, every value zero (tests of what carries records).
    pub(crate) fn at(seq: u64, mode: Mode) -> TickRecord {
        let mut r = TickRecord {
            t: seq as f64 * 1e-3,
            q: [0.0; 3],
            tau: [0.0; 3],
            qf: [0.0; 3],
            qd: [0.0; 3],
            qdd: [0.0; 3],
            reference: [0.0; 3],
            tau_cmd: [0.0; 3],
            tau_hat: [0.0; 3],
            tau_model: [0.0; 3],
            tau_ext: [0.0; 3],
            enc: [0; 3],
            amps: true,
            mode,
            flags: 0,
            haptic: HapticRecord::default(),
            live: Default::default(),
        };
        r.live.seq = seq;
        r
    }
}

/// The log's haptic columns.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct HapticRecord {
    /// Stylus tip at the measured pose, mm, OpenHaptics frame (`tip1..3`).
    pub tip_mm: [f64; 3],
    /// The tip force commanded this tick (effects and a client's `servo_cf`, after the
    /// passivity controller and the peak clamp), N (`fcmd1..3`).
    pub force: [f64; 3],
    /// Simulator: the force the simulated hand put on the tip, N (`fhand1..3`; NaN elsewhere).
    pub hand: [f64; 3],
    /// The outside's force on the tip estimated from the motors and the model, N, OpenHaptics
    /// frame (`fext1..3`, the state stream's `fext`; docs/TELEOP.md §2; NaN when read from a
    /// log without it).
    pub fext: [f64; 3],
}

/// Per-tick facts for `omnid serve`'s clients: fixed-size, so the record stays `Copy`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Live {
    /// Tick number since the servo started (the state stream's sequence number).
    pub seq: u64,
    /// Stylus buttons pressed, and the stylus in its inkwell.
    pub buttons: [bool; 2],
    /// Whether the stylus sat in its inkwell.
    pub inkwell: bool,
    /// Gimbal potentiometer words as the device sent them (the hub converts them to angles,
    /// `serve::device_info`).
    pub gimbal: [u16; 3],
    /// The controller whose law is in effect (the new one during a bumpless switch).
    pub controller: Option<crate::control::ControllerKind>,
    /// Sequence number of the last stream command (`servo_jp`/`servo_jf`/`servo_cf`) applied.
    pub cmd_seq: u64,
    /// Something happened this tick that every client is told about.
    pub event: Option<ServoEvent>,
    /// Motor heat per joint from the safety layer's thermal model (1 = the steady state at the
    /// continuous torque; `[safety] thermal_limit` holds the motor to it).
    pub heat: [f64; 3],
    /// This arm's side of a teleoperation pair, if it has one: its state's name
    /// (`teleop::TeleopState::as_str`; a name, so telemetry does not depend on teleop).
    pub teleop: Option<&'static str>,
    /// The pair's round trip as this side measures it (its own packets' times echoed back),
    /// s; 0 without a pair.
    pub teleop_round_trip_s: f64,
}

/// Which optional column groups a log carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LogSchema {
    /// `tau_model1..3` and `fhand1..3` (simulator runs).
    pub(crate) model: bool,
    /// `tau_ext1..3` and `fext1..3`, the external-force estimate (every log this omnid
    /// writes; absent from logs written before it was logged).
    pub(crate) external: bool,
    /// `button1`, `button2` and `inkwell` (0 or 1): what the stylus reported, which the servo
    /// acts on (a docked stylus stops the identifier learning), so a replay re-runs it (every
    /// log this omnid writes; absent from older CSV logs, whose replays report neither).
    pub(crate) buttons: bool,
}

/// A group of log columns (and its MCAP channels) that a log may carry or not.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Group {
    /// In every log.
    Always,
    /// Simulator runs only ([`LogSchema::model`]).
    Model,
    /// The external-force estimate ([`LogSchema::external`]).
    External,
    /// The stylus's buttons and inkwell ([`LogSchema::buttons`]).
    Buttons,
}

/// The stylus's columns ([`LogSchema::buttons`]), after `enc1..3`.
pub(crate) const STYLUS_COLUMNS: [&str; 3] = ["button1", "button2", "inkwell"];

/// The seven columns every log starts with, and every replayable file must have.
pub const REQUIRED_COLUMNS: [&str; 7] = ["t", "q1", "q2", "q3", "tau1", "tau2", "tau3"];

impl LogSchema {
    /// What this omnid writes: with the simulator's columns when `model`.
    pub(crate) fn new(model: bool) -> LogSchema {
        LogSchema {
            model,
            external: true,
            buttons: true,
        }
    }

    /// Whether logs of this schema carry `group`.
    pub(crate) fn has(&self, group: Group) -> bool {
        match group {
            Group::Always => true,
            Group::Model => self.model,
            Group::External => self.external,
            Group::Buttons => self.buttons,
        }
    }

    pub(crate) fn columns(&self) -> Vec<String> {
        let mut c: Vec<String> = REQUIRED_COLUMNS.iter().map(|s| s.to_string()).collect();
        let three = |c: &mut Vec<String>, group: &str, on: bool| {
            if on {
                c.extend((1..=3).map(|j| format!("{group}{j}")));
            }
        };
        for group in ["qf", "qd", "qdd", "ref", "tau_cmd", "tau_hat"] {
            three(&mut c, group, true);
        }
        three(&mut c, "tau_model", self.model);
        three(&mut c, "tau_ext", self.external);
        three(&mut c, "tip", true);
        three(&mut c, "fcmd", true);
        three(&mut c, "fhand", self.model);
        three(&mut c, "fext", self.external);
        c.extend((1..=3).map(|j| format!("enc{j}")));
        if self.buttons {
            c.extend(STYLUS_COLUMNS.map(String::from));
        }
        c.extend(["amps", "mode", "flags"].map(String::from));
        c
    }
}
// What a tick can carry besides its numbers: the events the servo loop reports (in the log's
// `fault` column and to `omnid serve`'s clients).

/// Something every client is told about, carried by the tick it happened at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ServoEvent {
    /// No stream command arrived within its time to live; the loop fell back to `fallback`.
    StreamStale {
        /// The mode the loop is in now.
        fallback: Mode,
    },
    /// The stream's owner left; the loop fell back to `fallback`.
    StreamEnded {
        /// The mode the loop is in now.
        fallback: Mode,
    },
    /// A safety limit tripped: zero torque, amplifiers off, mode `idle`.
    SafetyTrip(SafetyTrip),
    /// A limit started holding the force or torque back (`flags` bits newly acting:
    /// `FORCE_LIMIT`, `THERMAL`, `EFFECT_SKIPPED`); said once per episode, not every tick.
    Limit {
        /// The bits that started acting.
        flags: u32,
    },
}

/// Why the safety layer stops a run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SafetyTrip {
    /// The controller's output was NaN or infinite on this joint.
    NonFinite {
        /// The joint, 0..=2.
        joint: usize,
    },
    /// A joint moved faster than its limit (by the estimate).
    Velocity {
        /// The joint, 0..=2.
        joint: usize,
        /// Its speed, rad/s.
        speed: f64,
    },
    /// A joint moved faster than its limit by its encoders (over the last few ticks, beyond
    /// the quantisation margin), whatever the estimate says.
    MeasuredVelocity {
        /// The joint, 0..=2.
        joint: usize,
        /// Its speed from the encoders, rad/s.
        speed: f64,
    },
}

impl std::fmt::Display for SafetyTrip {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SafetyTrip::NonFinite { joint } => {
                write!(f, "controller output on joint {} is not finite", joint + 1)
            }
            SafetyTrip::Velocity { joint, speed } => {
                write!(
                    f,
                    "joint {} speed {speed:.2} rad/s exceeds the limit",
                    joint + 1
                )
            }
            SafetyTrip::MeasuredVelocity { joint, speed } => {
                write!(
                    f,
                    "joint {} moved at {speed:.2} rad/s by its encoders, beyond the limit",
                    joint + 1
                )
            }
        }
    }
}
