//! Geometry and physics of the Phantom Omni: forward kinematics in the OpenHaptics convention
//! and the rigid-body model (Cavusoglu structure) used by the simulator and by computed torque.

pub(crate) mod dynamics;
pub mod kinematics;

pub use dynamics::{Dynamics, ModelParams};
pub use kinematics::{jacobian, tip_position_mm, Geometry};

pub use omnid_client::kinematics::Joint3;
pub(crate) use omnid_client::kinematics::Mat3;

/// Standard gravity, m/s².
pub(crate) const GRAVITY: f64 = 9.80665;
