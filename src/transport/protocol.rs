//! The client protocol of `omnid serve` (docs/PROTOCOL.md): one JSON object per
//! SOCK_SEQPACKET message. Clients send requests tagged by `op`; the daemon sends messages
//! tagged by `type`. serde does every encoding and decoding.

pub use omnid_client::protocol::{Hello, State, MAX_MESSAGE, PROTOCOL_VERSION};
use serde::{Deserialize, Serialize};

/// A request from a client. `id` (any JSON value) is echoed in the reply.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(tag = "op", rename_all = "snake_case", deny_unknown_fields)]
pub(crate) enum Request {
    /// Must be the first message: the protocol version the client speaks.
    Hello {
        protocol: u32,
        #[serde(default)]
        name: Option<String>,
        #[serde(default)]
        id: Option<serde_json::Value>,
        /// Over zenoh: the client's X25519 public key, base64 (docs/PROTOCOL.md); the socket
        /// ignores it.
        #[serde(default)]
        key: Option<String>,
    },
    /// Start (rate_hz > 0, up to the device's rate) or stop (0) the state stream.
    Stream {
        rate_hz: f64,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// The run summary so far, the mode, the controller, the lease, the clients.
    Status {
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Take the command lease (also taken by any command while it is free).
    Lease {
        /// Where this holder's stream falls back when it goes stale or the holder leaves:
        /// "hold", "idle" or "free" (default: the config's `serve.stale_fallback`). Haptic
        /// programs ask for "idle" or "free", so a crash leaves no force of theirs.
        #[serde(default)]
        fallback: Option<String>,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Give the command lease back (a stream mode then falls back as if the stream ended).
    Release {
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Change mode: idle, hold, track (with `trajectory`), free.
    Mode {
        mode: String,
        #[serde(default)]
        trajectory: Option<String>,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// CRTK `hold`: the same as mode hold.
    Hold {
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// CRTK `free`: the same as mode free.
    Free {
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Joint position setpoint stream (rad). No reply unless refused.
    ServoJp {
        seq: u64,
        q: [f64; 3],
        #[serde(default)]
        ttl_ms: Option<f64>,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Joint torque stream (N·m) on top of the compensation. No reply unless refused.
    ServoJf {
        seq: u64,
        tau: [f64; 3],
        #[serde(default)]
        ttl_ms: Option<f64>,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Tip force stream (N, OpenHaptics frame) on top of the compensation, as τ = Jᵀ F; its
    /// norm is clamped to `[haptics] max_force_n`. No reply unless refused.
    ServoCf {
        seq: u64,
        force: [f64; 3],
        #[serde(default)]
        ttl_ms: Option<f64>,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Put a haptic effect in a slot of the scene (`effect: null` removes it); rendered in
    /// free and servo_cf, faded in (docs/HAPTICS.md).
    Effect {
        slot: usize,
        effect: Option<crate::haptics::Effect>,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Turn the passivity controller on the effects on or off.
    Passivity {
        on: bool,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Switch the control law (bumpless): pd, ct, nnidc, off.
    Controller {
        controller: String,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Resume (`on: true`) or freeze (`on: false`) the identifier's online adaptation.
    Adapt {
        on: bool,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Save the identifier's current weights to a file (JSON, as `omnid identify` writes).
    WeightsSave {
        path: String,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Load weights from a file into the running identifier.
    WeightsLoad {
        path: String,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Put the shipped weights back into the running identifier and forget what the arm
    /// learned (its saved weights file is removed).
    WeightsReset {
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Start writing every tick to a log file (today's CSV format).
    RecordStart {
        #[serde(default)]
        path: Option<String>,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    RecordStop {
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// The simulator's hand on the stylus: `action` press, release or click `button` (1 or
    /// 2), or dock or undock the stylus. Control access; not the lease.
    Stylus {
        action: String,
        #[serde(default)]
        button: Option<u64>,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Couple this arm as one side of a teleoperation pair with `peer`, another arm of this
    /// daemon (docs/TELEOP.md §8): `role` leader or follower. The pair's settings are
    /// `[teleop]`'s, changed by those given; both sides must be started with the same.
    Teleop {
        role: String,
        peer: String,
        #[serde(default)]
        architecture: Option<String>,
        #[serde(default)]
        motion_scale: Option<f64>,
        #[serde(default)]
        force_scale: Option<f64>,
        #[serde(default)]
        operator: Option<String>,
        #[serde(default)]
        passivity: Option<bool>,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Uncouple this arm: it holds where it is.
    TeleopStop {
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// The leader's motion scale, changed live without a jump.
    TeleopScale {
        motion_scale: f64,
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
    /// Stop the daemon: zero torque, amplifiers off, socket removed.
    Shutdown {
        #[serde(default)]
        id: Option<serde_json::Value>,
    },
}

impl Request {
    pub fn op(&self) -> &'static str {
        match self {
            Request::Hello { .. } => "hello",
            Request::Stream { .. } => "stream",
            Request::Status { .. } => "status",
            Request::Lease { .. } => "lease",
            Request::Release { .. } => "release",
            Request::Mode { .. } => "mode",
            Request::Hold { .. } => "hold",
            Request::Free { .. } => "free",
            Request::ServoJp { .. } => "servo_jp",
            Request::ServoJf { .. } => "servo_jf",
            Request::ServoCf { .. } => "servo_cf",
            Request::Effect { .. } => "effect",
            Request::Passivity { .. } => "passivity",
            Request::Controller { .. } => "controller",
            Request::Adapt { .. } => "adapt",
            Request::WeightsSave { .. } => "weights_save",
            Request::WeightsLoad { .. } => "weights_load",
            Request::WeightsReset { .. } => "weights_reset",
            Request::RecordStart { .. } => "record_start",
            Request::RecordStop { .. } => "record_stop",
            Request::Stylus { .. } => "stylus",
            Request::Teleop { .. } => "teleop",
            Request::TeleopStop { .. } => "teleop_stop",
            Request::TeleopScale { .. } => "teleop_scale",
            Request::Shutdown { .. } => "shutdown",
        }
    }

    pub fn id(&self) -> Option<&serde_json::Value> {
        match self {
            Request::Hello { id, .. }
            | Request::Stream { id, .. }
            | Request::Status { id }
            | Request::Lease { id, .. }
            | Request::Release { id }
            | Request::Mode { id, .. }
            | Request::Hold { id }
            | Request::Free { id }
            | Request::ServoJp { id, .. }
            | Request::ServoJf { id, .. }
            | Request::ServoCf { id, .. }
            | Request::Effect { id, .. }
            | Request::Passivity { id, .. }
            | Request::Controller { id, .. }
            | Request::Adapt { id, .. }
            | Request::WeightsSave { id, .. }
            | Request::WeightsLoad { id, .. }
            | Request::WeightsReset { id }
            | Request::RecordStart { id, .. }
            | Request::RecordStop { id }
            | Request::Stylus { id, .. }
            | Request::Teleop { id, .. }
            | Request::TeleopStop { id }
            | Request::TeleopScale { id, .. }
            | Request::Shutdown { id } => id.as_ref(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_decode_from_plain_json() {
        let r: Request = serde_json::from_str(
            r#"{"op":"servo_jp","seq":7,"q":[0.1,0.2,0.3],"ttl_ms":15,"id":"a"}"#,
        )
        .unwrap();
        assert_eq!(
            r,
            Request::ServoJp {
                seq: 7,
                q: [0.1, 0.2, 0.3],
                ttl_ms: Some(15.0),
                id: Some(serde_json::json!("a"))
            }
        );
        assert!(super::super::json::to_op(r.clone()).unwrap().commands());
        let r: Request =
            serde_json::from_str(r#"{"op":"servo_cf","seq":8,"force":[1.5,0,-0.5],"ttl_ms":20}"#)
                .unwrap();
        assert_eq!(
            r,
            Request::ServoCf {
                seq: 8,
                force: [1.5, 0.0, -0.5],
                ttl_ms: Some(20.0),
                id: None
            }
        );
        assert!(super::super::json::to_op(r.clone()).unwrap().commands());
        assert_eq!(r.op(), "servo_cf");
        let r: Request =
            serde_json::from_str(r#"{"op":"stylus","action":"click","button":2}"#).unwrap();
        assert_eq!(r.op(), "stylus");
        let op = super::super::json::to_op(r).unwrap();
        assert_eq!(
            op,
            crate::station::Op::Stylus(crate::device::StylusAction::Click(1))
        );
        assert!(op.commands() && op.is_hand() && !op.is_stop());
        let r: Request = serde_json::from_str(r#"{"op":"stylus","action":"dock"}"#).unwrap();
        assert!(super::super::json::to_op(r).unwrap().is_hand());
        let r: Request =
            serde_json::from_str(r#"{"op":"stylus","action":"undock","button":1}"#).unwrap();
        let e = super::super::json::to_op(r).unwrap_err().to_string();
        assert!(e.contains("no button"), "{e}");
        let r: Request = serde_json::from_str(r#"{"op":"status"}"#).unwrap();
        assert!(!super::super::json::to_op(r.clone()).unwrap().commands());
        assert_eq!(r.op(), "status");
    }

    #[test]
    fn unknown_ops_and_fields_are_refused_by_name() {
        let e = serde_json::from_str::<Request>(r#"{"op":"fly"}"#).unwrap_err();
        assert!(e.to_string().contains("fly"), "{e}");
        let e = serde_json::from_str::<Request>(r#"{"op":"status","colour":1}"#).unwrap_err();
        assert!(e.to_string().contains("colour"), "{e}");
        let e =
            serde_json::from_str::<Request>(r#"{"op":"servo_jp","seq":1,"q":[1,2]}"#).unwrap_err();
        assert!(
            e.to_string().contains("length 3") || e.to_string().contains("3 elements"),
            "{e}"
        );
    }
}
