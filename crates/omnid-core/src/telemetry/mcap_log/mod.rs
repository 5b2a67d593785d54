//! MCAP logs (docs/MCAP.md): every value of the CSV log, bit for bit, as ROS 2 standard
//! messages in CDR on channels named for what they carry, plus what a viewer needs (tip pose,
//! transforms for the arm's URDF, buttons, events). Profile `ros2`, zstd chunks, statistics and
//! indexes, so `ros2 bag play`, Foxglove, Lichtblick and Rerun open the file.
//!
//! Each tick's messages are written in `Topic` order and `/joint_states` comes last: a reader
//! has a whole row when it reads a `/joint_states`. Chunks close only between rows, so a file cut
//! short (a killed run) reads back as whole rows.

pub(crate) mod arm3d;
pub mod read;
pub mod write;

use crate::ros2::msgs::{self, MsgType};
use crate::telemetry::record::Group;

/// A channel of an omnid MCAP log.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Topic {
    /// Its place in [`TOPICS`] (per-channel tables are indexed by it).
    pub id: usize,
    /// The topic's name in the file.
    pub name: &'static str,
    /// The message type its records carry.
    pub ty: MsgType,
    /// The column group it carries: only in logs whose schema has it.
    pub(crate) group: Group,
}

const fn topic(id: usize, name: &'static str, ty: MsgType) -> Topic {
    Topic {
        id,
        name,
        ty,
        group: Group::Always,
    }
}

pub(crate) const ROBOT_DESCRIPTION: Topic = topic(0, "/robot_description", msgs::STRING);
pub(crate) const TIME: Topic = topic(1, "/omnid/time", msgs::FLOAT64);
pub(crate) const ESTIMATE_POSITION: Topic =
    topic(2, "/omnid/estimate/position", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const ESTIMATE_ACCELERATION: Topic =
    topic(3, "/omnid/estimate/acceleration", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const REFERENCE: Topic =
    topic(4, "/omnid/reference/position", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TORQUE_CONTROLLER: Topic =
    topic(5, "/omnid/torque/controller", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TORQUE_PREDICTED: Topic =
    topic(6, "/omnid/torque/predicted", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TORQUE_MODEL: Topic = Topic {
    group: Group::Model,
    ..topic(7, "/omnid/torque/model", msgs::FLOAT64_MULTI_ARRAY)
};
pub(crate) const TORQUE_EXTERNAL: Topic = Topic {
    group: Group::External,
    ..topic(8, "/omnid/torque/external", msgs::FLOAT64_MULTI_ARRAY)
};
pub(crate) const TIP_MM: Topic = topic(9, "/omnid/tip/position_mm", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TIP_POSE: Topic = topic(10, "/omnid/tip/pose", msgs::POSE_STAMPED);
pub(crate) const TIP_FORCE: Topic = topic(11, "/omnid/tip/force", msgs::WRENCH_STAMPED);
pub(crate) const HAND_FORCE: Topic = Topic {
    group: Group::Model,
    ..topic(12, "/omnid/hand/force", msgs::WRENCH_STAMPED)
};
pub(crate) const EXTERNAL_FORCE: Topic = Topic {
    group: Group::External,
    ..topic(13, "/omnid/external/force", msgs::WRENCH_STAMPED)
};
pub(crate) const ENCODERS: Topic = topic(14, "/omnid/encoders", msgs::INT64_MULTI_ARRAY);
pub(crate) const FLAGS: Topic = topic(15, "/omnid/safety/flags", msgs::UINT32);
pub(crate) const MODE: Topic = topic(16, "/omnid/mode", msgs::STRING);
pub(crate) const AMPLIFIERS: Topic = topic(17, "/omnid/amplifiers", msgs::BOOL);
pub(crate) const BUTTONS: Topic = Topic {
    group: Group::Buttons,
    ..topic(18, "/omnid/buttons", msgs::JOY)
};
pub(crate) const CONTROLLER: Topic = topic(19, "/omnid/controller", msgs::STRING);
pub(crate) const EVENTS: Topic = topic(20, "/omnid/events", msgs::STRING);
pub(crate) const HEAT: Topic = topic(21, "/omnid/motor/heat", msgs::FLOAT64_MULTI_ARRAY);
pub(crate) const TF: Topic = topic(22, "/tf", msgs::TF_MESSAGE);
pub(crate) const JOINT_STATES: Topic = topic(23, "/joint_states", msgs::JOINT_STATE);

/// Every channel, in the order a tick writes them (`/joint_states` last).
pub const TOPICS: [Topic; 24] = [
    ROBOT_DESCRIPTION,
    TIME,
    ESTIMATE_POSITION,
    ESTIMATE_ACCELERATION,
    REFERENCE,
    TORQUE_CONTROLLER,
    TORQUE_PREDICTED,
    TORQUE_MODEL,
    TORQUE_EXTERNAL,
    TIP_MM,
    TIP_POSE,
    TIP_FORCE,
    HAND_FORCE,
    EXTERNAL_FORCE,
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

#[cfg(test)]
#[test]
fn every_topic_knows_its_place() {
    for (i, t) in TOPICS.iter().enumerate() {
        assert_eq!(t.id, i, "{}", t.name);
    }
}

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
