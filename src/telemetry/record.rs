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
}

impl Mode {
    pub const ALL: [Mode; 8] = [
        Mode::Blend,
        Mode::Track,
        Mode::Stop,
        Mode::Idle,
        Mode::Hold,
        Mode::Free,
        Mode::ServoJp,
        Mode::ServoJf,
    ];

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
        }
    }

    pub fn parse(s: &str) -> Option<Mode> {
        Mode::ALL.into_iter().find(|m| m.as_str() == s)
    }
}

/// Bits of the `flags` column: which safety action touched this tick.
pub mod flags {
    /// The torque clamp limited at least one joint.
    pub const CLAMPED: u32 = 1 << 0;
    /// The controller's output was not finite; zero torque was sent instead.
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
}

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
    pub qd: [f64; 3],
    pub qdd: [f64; 3],
    /// Reference position, rad.
    pub reference: [f64; 3],
    /// Controller output before the safety layer, N·m.
    pub tau_cmd: [f64; 3],
    /// The identifier's prediction of the torque that acted (NaN when it has none).
    pub tau_hat: [f64; 3],
    /// The plant's exact model on the estimated states (simulator only, else NaN).
    pub tau_model: [f64; 3],
    /// Continuous encoder counts.
    pub enc: [i64; 3],
    pub amps: bool,
    pub mode: Mode,
    pub flags: u32,
    /// What the daemon's clients see beyond the log's columns (not written to the log).
    pub live: Live,
}

/// Per-tick facts for `omnid serve`'s clients: fixed-size, so the record stays `Copy`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Live {
    /// Tick number since the servo started (the state stream's sequence number).
    pub seq: u64,
    /// Stylus buttons pressed, and the stylus in its inkwell.
    pub buttons: [bool; 2],
    pub inkwell: bool,
    /// Gimbal potentiometer words as the device sent them (the hub converts them to angles,
    /// `serve::device_info`).
    pub gimbal: [u16; 3],
    /// The controller whose law is in effect (the new one during a bumpless switch).
    pub controller: Option<crate::control::ControllerKind>,
    /// Sequence number of the last stream command (`servo_jp`/`servo_jf`) applied.
    pub cmd_seq: u64,
    /// Something happened this tick that every client is told about.
    pub event: Option<crate::servo::ServoEvent>,
}

/// Which optional column groups a log carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LogSchema {
    /// `tau_model1..3` (simulator runs).
    pub model: bool,
}

/// The seven columns every log starts with, and every replayable file must have.
pub const REQUIRED_COLUMNS: [&str; 7] = ["t", "q1", "q2", "q3", "tau1", "tau2", "tau3"];

impl LogSchema {
    pub fn columns(&self) -> Vec<String> {
        let mut c: Vec<String> = REQUIRED_COLUMNS.iter().map(|s| s.to_string()).collect();
        for group in ["qf", "qd", "qdd", "ref", "tau_cmd", "tau_hat"] {
            c.extend((1..=3).map(|j| format!("{group}{j}")));
        }
        if self.model {
            c.extend((1..=3).map(|j| format!("tau_model{j}")));
        }
        c.extend((1..=3).map(|j| format!("enc{j}")));
        c.extend(["amps", "mode", "flags"].map(String::from));
        c
    }
}
