//! Forward kinematics of the Omni arm (docs/DESIGN.md §4.1), shared with clients through
//! `omnid_client::kinematics`; here what only the daemon needs: the config check and the ROS
//! driver's joint convention.

use super::Joint3;
use crate::config_check::{self as check, ConfigError};
pub use omnid_client::kinematics::{jacobian, jacobian_dot, tip_position_mm, Geometry};

/// Check every value of `[geometry]`; the first problem names its field (`geometry.…`).
pub(crate) fn check_geometry(g: &Geometry) -> Result<(), ConfigError> {
    check::in_range("geometry.l1_mm", g.l1_mm, 1.0, 1000.0, "1 ..= 1000 mm")?;
    check::in_range("geometry.l2_mm", g.l2_mm, 1.0, 1000.0, "1 ..= 1000 mm")?;
    for (field, v) in [
        ("geometry.y_offset_mm", g.y_offset_mm),
        ("geometry.z_offset_mm", g.z_offset_mm),
    ] {
        check::in_range(field, v, -1000.0, 1000.0, "-1000 ..= 1000 mm")?;
    }
    Ok(())
}

/// Map the ROS driver's published angles (waist, shoulder, elbow) to OpenHaptics joints:
/// waist = −j1, shoulder = j2, elbow = j3 − j2.
pub fn from_ros(waist: f64, shoulder: f64, elbow: f64) -> Joint3 {
    Joint3::new(-waist, shoulder, elbow + shoulder)
}
