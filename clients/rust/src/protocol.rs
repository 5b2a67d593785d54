//! What both sides of `omnid serve`'s socket agree on (docs/PROTOCOL.md): the protocol
//! version, the largest message, the daemon's greeting and the state of an arm at one tick.
//! One JSON object per SOCK_SEQPACKET message; serde does every encoding and decoding.

use serde::{Deserialize, Serialize};

/// The protocol version this daemon speaks; a client's hello must name it.
pub const PROTOCOL_VERSION: u32 = 1;

/// Largest message either side may send, bytes (a longer one is refused and its sender
/// dropped).
pub const MAX_MESSAGE: usize = 64 * 1024;

/// One tick as clients see it (`type: "state"`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArmState {
    /// Tick number since the daemon started: consecutive for a client that keeps up.
    pub seq: u64,
    /// Device time since the daemon started, s.
    pub t: f64,
    /// Joint angles from the encoders, rad (OpenHaptics convention).
    pub q: [f64; 3],
    /// Kalman estimate of the joint velocity, rad/s.
    pub qd: [f64; 3],
    /// Stylus tip, mm, OpenHaptics frame (+x right, +y up, +z toward the user).
    pub tip_mm: [f64; 3],
    /// Stylus buttons pressed (dark grey, light grey).
    pub buttons: [bool; 2],
    /// Whether the stylus sits in its inkwell.
    pub inkwell: bool,
    /// Gimbal angles, rad (nominal, uncalibrated: `station::device_info`; 0 at mid-scale).
    #[serde(default)]
    pub gimbal: [f64; 3],
    /// Torque sent to the motors, N·m.
    pub tau: [f64; 3],
    /// The identifier's prediction of the torque that acted, N·m.
    pub tau_hat: [f64; 3],
    /// The active controller (`pd`, `nnidc`, `ct`, `off`).
    pub controller: String,
    /// idle, hold, blend, track, free, servo_jp, servo_jf, servo_cf, stop.
    pub mode: String,
    /// Whether the motor amplifiers are on.
    pub amps: bool,
    /// Safety and status bits (README, Logs: `flags`).
    pub flags: u32,
    /// Sequence number of the last servo_jp/servo_jf/servo_cf command applied.
    pub cmd_seq: u64,
    /// Motor heat per joint from the thermal model (1 = steady state at the continuous
    /// torque; the limit is `[safety] thermal_limit`).
    #[serde(default)]
    pub heat: [f64; 3],
    /// The outside's force on the tip (a hand, a contact) estimated from the motor torques
    /// and the arm's model, N, OpenHaptics frame.
    #[serde(default)]
    pub fext: [f64; 3],
    /// This arm's side of a teleoperation pair, when it has one: waiting, engaged,
    /// clutched, link_lost or down (docs/TELEOP.md §3–§4).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub teleop: Option<String>,
}

/// The state stream's message (`type: "state"`), as the protocol names it.
pub type State = ArmState;

/// The daemon's greeting (`type: "hello"`), the first message on every admitted connection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Hello {
    /// The protocol version the daemon speaks ([`PROTOCOL_VERSION`]).
    pub protocol: u32,
    /// The daemon's name and version, e.g. `omnid 0.1.0`.
    pub server: String,
    /// The device backend: `sim`, `usb`, `firewire` or `replay`.
    pub device: String,
    /// The arm's name (a daemon serves each arm on its own socket, `<name>.sock`).
    #[serde(default)]
    pub arm: String,
    /// Other names the arm answers to (`[[arm]] aliases`: OpenHaptics' "PHANToM 1", …).
    #[serde(default)]
    pub aliases: Vec<String>,
    /// The servo rate, Hz (the fastest a state stream can run).
    pub rate_hz: f64,
    /// What this client may do: "read" or "control".
    pub access: String,
    /// This connection's number (named in lease messages).
    pub client: u64,
    /// How long a streamed command stays in effect without a newer one, ms of device time
    /// (the default `ttl_ms`).
    pub stream_ttl_ms: f64,
    /// Controllers a `controller` request may choose.
    pub controllers: Vec<String>,
    /// Modes a `mode` request may choose.
    pub modes: Vec<String>,
    /// The device's model name.
    #[serde(default)]
    pub model: String,
    /// The device's vendor.
    #[serde(default)]
    pub vendor: String,
    /// The device's serial number (`null` when the backend does not know it).
    #[serde(default)]
    pub serial: Option<String>,
    /// The device's firmware version (`null` when the backend does not know it).
    #[serde(default)]
    pub firmware: Option<String>,
}
