//! The state of an arm as its clients see it at one tick: the record's values with what a
//! client needs computed once here (the tip, the gimbal angles), for every transport.

use super::device_info::gimbal_angles;
use crate::omni::kinematics::{tip_position_mm, Geometry};
use crate::telemetry::record::TickRecord;
use serde::{Deserialize, Serialize};

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
}

impl ArmState {
    /// The view of `r` on an arm of `geometry`.
    pub fn of(r: &TickRecord, geometry: &Geometry) -> ArmState {
        ArmState {
            seq: r.live.seq,
            t: r.t,
            q: r.q,
            qd: r.qd,
            tip_mm: tip_position_mm(geometry, &r.q.into()).into(),
            buttons: r.live.buttons,
            inkwell: r.live.inkwell,
            gimbal: gimbal_angles(r.live.gimbal),
            tau: r.tau,
            tau_hat: r.tau_hat,
            controller: r.live.controller.map_or("none", |k| k.as_str()).to_string(),
            mode: r.mode.as_str().to_string(),
            amps: r.amps,
            flags: r.flags,
            cmd_seq: r.live.cmd_seq,
            heat: r.live.heat,
        }
    }
}
