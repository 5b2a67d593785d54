//! Geometry and physics of the Phantom Omni: forward kinematics in the OpenHaptics convention
//! and the rigid-body model (Cavusoglu structure) used by the simulator and by computed torque.

pub(crate) mod dynamics;
pub mod kinematics;

pub use dynamics::{Dynamics, ModelParams};
pub use kinematics::{jacobian, tip_position_mm, Geometry};

/// Joint vector (three actuated joints, OpenHaptics convention, rad or N·m).
pub type Joint3 = nalgebra::Vector3<f64>;
/// 3×3 joint-space matrix.
pub(crate) type Mat3 = nalgebra::Matrix3<f64>;

/// Standard gravity, m/s².
pub(crate) const GRAVITY: f64 = 9.80665;
