//! The typed operations a session may ask of an arm's station, what they answer, and why one
//! is refused. Transports turn their own messages into these (the Unix socket's JSON in
//! `transport::hub`); the names and the messages are the same whichever transport a client uses.

use crate::control::{ControllerKind, Trajectory};
use crate::haptics::Effect;
use crate::servo::summary::RunSummary;
use serde::Serialize;
use std::path::PathBuf;
use thiserror::Error;

/// A session's number on its station (named in lease messages; a transport's client id).
pub type SessionId = u64;

/// A mode a client may ask for by name.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ModeRequest {
    /// Amplifiers off (also the emergency stop: no lease refuses it).
    Idle,
    /// Hold the pose where the mode began.
    Hold,
    /// Follow a built-in trajectory.
    Track(Trajectory),
    /// Compensation and the scene's effects only.
    Free,
}

impl ModeRequest {
    /// `mode` (`idle`/`disable`, `hold`, `track`, `free`) with `trajectory` for track (default
    /// `sine`); the refusal names what is accepted.
    pub fn parse(mode: &str, trajectory: Option<&str>) -> Result<ModeRequest, OpError> {
        match mode {
            "idle" | "disable" => Ok(ModeRequest::Idle),
            "hold" => Ok(ModeRequest::Hold),
            "free" => Ok(ModeRequest::Free),
            "track" => match trajectory.unwrap_or("sine") {
                "sine" => Ok(ModeRequest::Track(Trajectory::Sine)),
                "multisine" => Ok(ModeRequest::Track(Trajectory::Multisine)),
                "hold" => Ok(ModeRequest::Track(Trajectory::Hold)),
                other => Err(OpError::Invalid(format!(
                    "unknown trajectory `{}`: expected sine, multisine or hold",
                    crate::text::cut(other)
                ))),
            },
            "servo_jp" | "servo_jf" | "servo_cf" => Err(OpError::Invalid(format!(
                "{mode} starts with its first `{mode}` command (a stream)"
            ))),
            other => Err(OpError::Invalid(format!(
                "unknown mode `{}`: expected idle, hold, track or free",
                crate::text::cut(other)
            ))),
        }
    }

    /// The name a reply echoes.
    pub fn as_str(self) -> &'static str {
        match self {
            ModeRequest::Idle => "idle",
            ModeRequest::Hold => "hold",
            ModeRequest::Track(_) => "track",
            ModeRequest::Free => "free",
        }
    }
}

/// Where a lease holder's stream falls back to.
pub fn parse_fallback(name: &str) -> Result<crate::servo::Activity, OpError> {
    use crate::servo::Activity;
    match name {
        "hold" => Ok(Activity::Hold),
        "idle" => Ok(Activity::Idle),
        "free" => Ok(Activity::Free),
        other => Err(OpError::Invalid(format!(
            "fallback `{}`: expected hold, idle or free",
            crate::text::cut(other)
        ))),
    }
}

/// A controller by name.
pub fn parse_controller(name: &str) -> Result<ControllerKind, OpError> {
    ControllerKind::parse(name).ok_or_else(|| {
        OpError::Invalid(format!(
            "unknown controller `{}`: expected pd, ct, nnidc or off",
            crate::text::cut(name)
        ))
    })
}

/// What a session asks of the arm.
#[derive(Debug, Clone, PartialEq)]
pub enum Op {
    /// Stream every `rate / rate_hz`-th tick's state to this session (0 stops).
    Stream {
        /// Samples per second (0 stops).
        rate_hz: f64,
    },
    /// The run summary so far, the mode, the lease, the sessions.
    Status,
    /// Take the command lease, optionally with this holder's stream fallback.
    Lease {
        /// Where its streams fall back (hold, idle or free; `None`: the config's).
        fallback: Option<crate::servo::Activity>,
    },
    /// Give the lease back.
    Release,
    /// Change mode.
    Mode(ModeRequest),
    /// Joint position setpoint stream, rad.
    ServoJp {
        /// The client's sequence number (echoed as `cmd_seq`).
        seq: u64,
        /// Joint angles, rad.
        q: [f64; 3],
        /// How long it stays in effect, ms (`None`: `serve.stream_ttl_ms`).
        ttl_ms: Option<f64>,
    },
    /// Joint torque stream on top of the compensation, N·m.
    ServoJf {
        /// The client's sequence number (echoed as `cmd_seq`).
        seq: u64,
        /// Joint torques, N·m.
        tau: [f64; 3],
        /// How long it stays in effect, ms (`None`: `serve.stream_ttl_ms`).
        ttl_ms: Option<f64>,
    },
    /// Tip force stream on top of the compensation, N.
    ServoCf {
        /// The client's sequence number (echoed as `cmd_seq`).
        seq: u64,
        /// Tip force, N.
        force: [f64; 3],
        /// How long it stays in effect, ms (`None`: `serve.stream_ttl_ms`).
        ttl_ms: Option<f64>,
    },
    /// Put an effect in a slot of the scene (None clears it).
    Effect {
        /// The slot.
        slot: usize,
        /// The effect (`None` clears the slot).
        effect: Option<Effect>,
    },
    /// The passivity controller on or off.
    Passivity(bool),
    /// Switch the control law.
    Controller(ControllerKind),
    /// Resume or freeze online adaptation.
    Adapt(bool),
    /// Save the identifier's weights.
    WeightsSave(PathBuf),
    /// Load weights into the running identifier.
    WeightsLoad(PathBuf),
    /// The shipped weights back into the running identifier; the arm's saved weights removed.
    WeightsReset,
    /// Start recording every tick (a default name in the state directory when `None`).
    RecordStart(Option<PathBuf>),
    /// End the recording.
    RecordStop,
    /// Stop the daemon (zero torque, amplifiers off).
    Shutdown,
    /// The simulator's hand acts on the stylus: a button, the inkwell (simulator only).
    Stylus(crate::device::StylusAction),
    /// Couple this arm as one side of a teleoperation pair.
    Teleop(TeleopRequest),
    /// Uncouple this arm (it holds).
    TeleopStop,
    /// The leader's motion scale, live.
    TeleopScale(f64),
}

/// This arm's side of a pair, as started (the reply to `teleop`, and in `status`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TeleopReply {
    /// Leader or follower.
    pub role: crate::teleop::Role,
    /// The other arm.
    pub peer: String,
    /// pp or pf.
    pub architecture: &'static str,
    /// Follower mm per leader mm.
    pub motion_scale: f64,
    /// Leader's force per coupling force.
    pub force_scale: f64,
    /// When the operator counts as present.
    pub operator: crate::teleop::Operator,
    /// Time-domain passivity on.
    pub passivity: bool,
    /// What keeps the pair stable under delay on this channel: `gains` or `wave` (`[teleop]
    /// delay_control = "auto"` resolved: docs/TELEOP.md §5).
    pub delay_control: &'static str,
    /// In `status`: the side's state at the last tick (`down` once the arm has left
    /// `teleop`: a trip, another mode).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub state: Option<&'static str>,
    /// In `status`: the round trip this side measures, ms (in one daemon the channel adds
    /// at most a tick each way: about 2 ms).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub round_trip_ms: Option<f64>,
    /// The channel: `in_process` (both arms in this daemon) or `zenoh` (the peer is another
    /// daemon's arm).
    pub channel: &'static str,
    /// In `status`, over zenoh: what the network channel has carried.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub network: Option<Box<crate::teleop::LineStats>>,
}

/// This arm's side of a pair, as asked: `[teleop]` with the changes given.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct TeleopRequest {
    /// Leader or follower.
    pub role: Option<crate::teleop::Role>,
    /// The other arm, by name.
    pub peer: String,
    /// `[teleop] architecture`, if changed.
    pub architecture: Option<crate::teleop::Architecture>,
    /// `[teleop] motion_scale`, if changed.
    pub motion_scale: Option<f64>,
    /// `[teleop] force_scale`, if changed.
    pub force_scale: Option<f64>,
    /// `[teleop] operator`, if changed.
    pub operator: Option<crate::teleop::Operator>,
    /// `[teleop] passivity`, if changed.
    pub passivity: Option<bool>,
}

impl TeleopRequest {
    /// `base` with this request's changes, checked as the config is.
    pub fn settings(
        &self,
        base: &crate::teleop::TeleopConfig,
    ) -> Result<crate::teleop::TeleopConfig, OpError> {
        let mut cfg = base.clone();
        if let Some(a) = self.architecture {
            cfg.architecture = a;
        }
        if let Some(s) = self.motion_scale {
            cfg.motion_scale = s;
        }
        if let Some(s) = self.force_scale {
            cfg.force_scale = s;
        }
        if let Some(o) = self.operator {
            cfg.operator = o;
        }
        if let Some(p) = self.passivity {
            cfg.passivity = p;
        }
        // The config's wording, naming the request's field rather than the file's key (a
        // refusal is the op's own: no prefix, the client names the op it asked for).
        cfg.validate().map_err(|e| {
            OpError::Invalid(
                e.to_string()
                    .replacen("config: ", "", 1)
                    .replace("teleop.", ""),
            )
        })?;
        Ok(cfg)
    }
}

/// A teleop request's names parsed.
pub fn parse_teleop(
    role: &str,
    peer: String,
    architecture: Option<&str>,
    operator: Option<&str>,
) -> Result<TeleopRequest, OpError> {
    let role = match role {
        "leader" => crate::teleop::Role::Leader,
        "follower" => crate::teleop::Role::Follower,
        other => {
            return Err(OpError::Invalid(format!(
                "teleop role `{}`: expected leader or follower",
                crate::text::cut(other)
            )))
        }
    };
    let architecture = architecture
        .map(|a| {
            crate::teleop::Architecture::parse(a).ok_or_else(|| {
                OpError::Invalid(format!(
                    "teleop architecture `{}`: expected pp or pf",
                    crate::text::cut(a)
                ))
            })
        })
        .transpose()?;
    let operator = operator
        .map(|o| match o {
            "button1" => Ok(crate::teleop::Operator::Button1),
            "always" => Ok(crate::teleop::Operator::Always),
            other => Err(OpError::Invalid(format!(
                "teleop operator `{}`: expected button1 or always",
                crate::text::cut(other)
            ))),
        })
        .transpose()?;
    Ok(TeleopRequest {
        role: Some(role),
        peer,
        architecture,
        operator,
        ..TeleopRequest::default()
    })
}

impl Op {
    /// Ops that change the device or write files: they need control access and the lease
    /// (but for the emergency stop, [`Op::is_stop`]).
    pub fn commands(&self) -> bool {
        !matches!(self, Op::Stream { .. } | Op::Status)
    }

    /// The simulator's hand (`stylus`): it needs control access but not the lease. It stands
    /// for the user's hand on the stylus, not for a program commanding the motors, and the
    /// program that holds the lease (a libHD scheduler) is the one waiting for the button.
    pub fn is_hand(&self) -> bool {
        matches!(self, Op::Stylus(_))
    }

    /// `mode idle` and `shutdown`: the stop nobody can refuse. No lease refuses them to a
    /// session with control access; the holder is told who stopped the arm.
    pub fn is_stop(&self) -> bool {
        matches!(self, Op::Mode(ModeRequest::Idle) | Op::Shutdown)
    }

    /// Stream commands (servo_jp, servo_jf, servo_cf): no reply, a time to live.
    pub fn is_stream(&self) -> bool {
        matches!(
            self,
            Op::ServoJp { .. } | Op::ServoJf { .. } | Op::ServoCf { .. }
        )
    }
}

/// What a session is and may do, as its transport established it.
#[derive(Debug, Clone, PartialEq)]
pub struct SessionInfo {
    /// The name the client gave (cut to 64 characters).
    pub name: String,
    /// The peer's process and user, where the transport knows them.
    pub pid: i32,
    /// User id (`u32::MAX` where the transport cannot tell).
    pub uid: u32,
    /// Whether it may command.
    pub control: bool,
    /// Root or the daemon's own user: never refused a stop, kept a connection slot.
    pub privileged: bool,
    /// Why it may not command (the read-only reason), when it may not.
    pub read_only_reason: String,
    /// Whose rights open the files it names.
    pub files: super::FileRights,
}

/// A successful answer.
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum Reply {
    /// Stream commands: nothing goes back.
    #[serde(skip)]
    Silent,
    /// No fields.
    Done {},
    /// The stream's actual rate and interval.
    Stream {
        /// The rate granted.
        rate_hz: f64,
        /// Every `every`-th tick.
        every: u64,
    },
    /// The lease and the fallback in force.
    Lease {
        /// The holder.
        holder: SessionId,
        /// The fallback in force.
        fallback: &'static str,
    },
    /// The mode asked for.
    Mode {
        /// The mode.
        mode: &'static str,
    },
    /// The effect put in its slot.
    Effect {
        /// The slot.
        slot: usize,
        /// The effect now in it.
        effect: Option<Effect>,
    },
    /// The passivity controller's state.
    Passivity {
        /// On or off.
        passivity: bool,
    },
    /// The law now in effect.
    Controller {
        /// The law.
        controller: &'static str,
    },
    /// Adaptation on or off.
    Adapt {
        /// On or off.
        adapt: bool,
    },
    /// A file written or read.
    Path {
        /// The file.
        path: PathBuf,
    },
    /// The identifier is back on the shipped weights.
    WeightsReset {
        /// The shipped weights' name.
        weights: &'static str,
        /// The arm's saved weights file, removed (`None`: there was none).
        removed: Option<PathBuf>,
    },
    /// The recording ended.
    RecordStop {
        /// The file.
        path: PathBuf,
        /// Rows written.
        rows: u64,
        /// Why it is incomplete, if it is.
        error: Option<String>,
    },
    /// What the simulator's hand did.
    Stylus {
        /// The action (press, release, click, dock, undock).
        stylus: &'static str,
        /// The button it acted on, 1 or 2.
        #[serde(skip_serializing_if = "Option::is_none")]
        button: Option<u8>,
    },
    /// This arm's side of a pair, as started.
    Teleop {
        /// The side.
        teleop: TeleopReply,
    },
    /// The leader's motion scale now.
    TeleopScale {
        /// The scale.
        motion_scale: f64,
    },
    /// The daemon's status.
    Status {
        /// The status.
        status: Box<Status>,
    },
}

/// Who holds the lease.
#[derive(Debug, Clone, Serialize)]
pub struct LeaseHolder {
    /// The session.
    pub client: SessionId,
    /// The name it gave.
    pub name: String,
    /// Its process.
    pub pid: i32,
    /// Its user.
    pub uid: u32,
}

/// A recording in progress.
#[derive(Debug, Clone, Serialize)]
pub struct RecordingStatus {
    /// The file.
    pub path: PathBuf,
    /// Rows dropped so far because the disk fell behind.
    pub dropped: u64,
}

/// `status`: the run summary so far and the station's own state.
#[derive(Debug, Clone, Serialize)]
pub struct Status {
    /// As `omnid run`'s summary.
    #[serde(flatten)]
    pub summary: RunSummary,
    /// The arm's name.
    pub arm: String,
    /// The mode of the last tick.
    pub mode: Option<&'static str>,
    /// The lease holder.
    pub lease: Option<LeaseHolder>,
    /// Sessions connected.
    pub clients: usize,
    /// The recording in progress.
    pub recording: Option<RecordingStatus>,
    /// Motor heat per joint.
    pub heat: [f64; 3],
    /// This arm's side of a teleoperation pair, as started (`null`: none).
    pub teleop: Option<TeleopReply>,
}

/// Why an op was refused.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum OpError {
    /// A value out of range or a name not known.
    #[error("{0}")]
    Invalid(String),
    /// The session may only read.
    #[error("{0}")]
    ReadOnly(String),
    /// Another session holds the lease.
    #[error("{0}")]
    LeaseHeld(String),
    /// The arm was stopped by someone else or tripped: a stream does not re-arm it.
    #[error("{0}")]
    Stopped(String),
    /// The servo's mailbox is full or closed.
    #[error("the servo is not taking commands (queue full or stopped)")]
    ServoBusy,
    /// The op is valid but cannot be done now (recording already running, …).
    #[error("{0}")]
    Failed(String),
}
