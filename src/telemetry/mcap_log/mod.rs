//! MCAP logs (docs/MCAP.md): every value of the CSV log, bit for bit, as ROS 2 standard
//! messages in CDR on channels named for what they carry, plus what a viewer needs (tip pose,
//! transforms for the arm's URDF, buttons, events). Profile `ros2`, zstd chunks, statistics and
//! indexes, so `ros2 bag play`, Foxglove, Lichtblick and Rerun open the file.
//!
//! Each tick's messages are written in [`Topic`] order and `/joint_states` comes last: a reader
//! has a whole row when it reads a `/joint_states`. Chunks close only between rows, so a file cut
//! short (a killed run) reads back as whole rows.

pub(crate) mod arm3d;
pub mod read;
pub mod write;

use crate::ros2::msgs::{self, MsgType};

/// A channel of an omnid MCAP log.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Topic {
    pub(crate) name: &'static str,
    pub(crate) ty: MsgType,
    /// Only in logs of the simulator's schema (`tau_model`, `fhand`).
    pub(crate) model_only: bool,
}

const fn topic(name: &'static str, ty: MsgType) -> Topic {
    Topic {
        name,
        ty,
        model_only: false,
    }
}

pub(crate) const ROBOT_DESCRIPTION: Topic = topic("/robot_description", msgs::STRING);
pub(crate) const TIME: Topic = topic("/omnid/time", msgs::FLOAT64);
pub(crate) const ESTIMATE_POSITION: Topic =
    topic("/omnid/estimate/position", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const ESTIMATE_ACCELERATION: Topic =
    topic("/omnid/estimate/acceleration", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const REFERENCE: Topic = topic("/omnid/reference/position", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TORQUE_CONTROLLER: Topic =
    topic("/omnid/torque/controller", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TORQUE_PREDICTED: Topic =
    topic("/omnid/torque/predicted", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TORQUE_MODEL: Topic = Topic {
    model_only: true,
    ..topic("/omnid/torque/model", msgs::FLOAT64_MULTI_ARRAY)
};
pub(crate) const TIP_MM: Topic = topic("/omnid/tip/position_mm", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TIP_POSE: Topic = topic("/omnid/tip/pose", msgs::POSE_STAMPED);
pub(crate) const TIP_FORCE: Topic = topic("/omnid/tip/force", msgs::WRENCH_STAMPED);
pub(crate) const HAND_FORCE: Topic = Topic {
    model_only: true,
    ..topic("/omnid/hand/force", msgs::WRENCH_STAMPED)
};
pub(crate) const ENCODERS: Topic = topic("/omnid/encoders", msgs::INT64_MULTI_ARRAY);
pub(crate) const FLAGS: Topic = topic("/omnid/safety/flags", msgs::UINT32);
pub(crate) const MODE: Topic = topic("/omnid/mode", msgs::STRING);
pub(crate) const AMPLIFIERS: Topic = topic("/omnid/amplifiers", msgs::BOOL);
pub(crate) const BUTTONS: Topic = topic("/omnid/buttons", msgs::JOY);
pub(crate) const CONTROLLER: Topic = topic("/omnid/controller", msgs::STRING);
pub(crate) const EVENTS: Topic = topic("/omnid/events", msgs::STRING);
pub(crate) const HEAT: Topic = topic("/omnid/motor/heat", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TF: Topic = topic("/tf", msgs::TF_MESSAGE);
pub(crate) const JOINT_STATES: Topic = topic("/joint_states", msgs::JOINT_STATE);

/// Every channel, in the order a tick writes them (`/joint_states` last).
pub(crate) const TOPICS: [Topic; 22] = [
    ROBOT_DESCRIPTION,
    TIME,
    ESTIMATE_POSITION,
    ESTIMATE_ACCELERATION,
    REFERENCE,
    TORQUE_CONTROLLER,
    TORQUE_PREDICTED,
    TORQUE_MODEL,
    TIP_MM,
    TIP_POSE,
    TIP_FORCE,
    HAND_FORCE,
    ENCODERS,
    FLAGS,
    MODE,
    AMPLIFIERS,
    BUTTONS,
    CONTROLLER,
    EVENTS,
    HEAT,
    TF,
    JOINT_STATES,
];

/// The joint names of `/joint_states`: omnid's joints in the OpenHaptics convention (the
/// URDF's joints follow the ROS driver's; see [`arm3d`]).
pub(crate) const JOINT_NAMES: [&str; 3] = ["joint1", "joint2", "joint3"];

/// The file's first bytes.
pub const MAGIC: &[u8; 8] = b"\x89MCAP0\r\n";

/// A log format by name, for config keys (`[serve] log_format`).
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "lowercase")]
pub enum LogKind {
    /// CSV (docs/DESIGN.md §2.2).
    #[default]
    Csv,
    /// MCAP (docs/MCAP.md).
    Mcap,
}

impl LogKind {
    /// The format, with the arm's geometry for an MCAP's URDF.
    pub fn format(self, geometry: crate::omni::kinematics::Geometry) -> LogFormat {
        match self {
            LogKind::Csv => LogFormat::Csv,
            LogKind::Mcap => LogFormat::Mcap { geometry },
        }
    }
}

/// Which format a log path asks for: `.mcap` is MCAP, anything else CSV.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum LogFormat {
    /// CSV (docs/DESIGN.md §2.2).
    Csv,
    /// MCAP, with the arm's geometry for its URDF.
    Mcap {
        /// Link lengths of the arm drawn.
        geometry: crate::omni::kinematics::Geometry,
    },
}

impl LogFormat {
    /// The format `path`'s extension names (`geometry`: the arm's, for an MCAP's URDF).
    pub fn for_path(path: &std::path::Path, geometry: crate::omni::kinematics::Geometry) -> Self {
        if path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("mcap"))
        {
            LogFormat::Mcap { geometry }
        } else {
            LogFormat::Csv
        }
    }

    /// The file extension, without the dot.
    pub fn extension(&self) -> &'static str {
        match self {
            LogFormat::Csv => "csv",
            LogFormat::Mcap { .. } => "mcap",
        }
    }
}
