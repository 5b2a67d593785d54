//! The state of an arm as its clients see it at one tick: the record's values with what a
//! client needs computed once here (the tip, the gimbal angles), for every transport.

use super::device_info::gimbal_angles;
use crate::omni::kinematics::{tip_position_mm, Geometry};
use crate::telemetry::record::TickRecord;
pub use omnid_client::protocol::ArmState;

/// The view of `r` on an arm of `geometry`.
pub fn arm_state(r: &TickRecord, geometry: &Geometry) -> ArmState {
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
        fext: r.haptic.fext,
        teleop: r.live.teleop.map(str::to_string),
    }
}
