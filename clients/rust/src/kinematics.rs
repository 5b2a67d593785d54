//! Forward kinematics of the Omni arm (docs/DESIGN.md §4.1), OpenHaptics joint convention:
//! j1 base yaw, j2 upper arm up from horizontal, j3 lower arm angle (absolute, through the
//! parallelogram). Tip in the OpenHaptics frame: +x right, +y up, +z toward the user.
//! Clients need it too (libHD maps forces to joint torques with the Jacobian).

use serde::{Deserialize, Serialize};

/// Joint vector (three actuated joints, OpenHaptics convention, rad or N·m), or a point or
/// force in the OpenHaptics frame.
pub type Joint3 = nalgebra::Vector3<f64>;
/// 3×3 matrix (a Jacobian).
pub type Mat3 = nalgebra::Matrix3<f64>;

/// Link lengths and the offsets of the OpenHaptics origin, in millimetres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "schema", derive(schemars::JsonSchema))]
#[serde(deny_unknown_fields, default)]
pub struct Geometry {
    /// Upper arm length, mm.
    pub l1_mm: f64,
    /// Lower arm length, mm.
    pub l2_mm: f64,
    /// Offset added to y, mm.
    pub y_offset_mm: f64,
    /// Offset subtracted from z, mm.
    pub z_offset_mm: f64,
}

impl Default for Geometry {
    fn default() -> Self {
        Geometry {
            l1_mm: 133.35,
            l2_mm: 133.35,
            y_offset_mm: 23.35,
            z_offset_mm: 168.35,
        }
    }
}

/// Tip position in mm for OpenHaptics joint angles `q` (rad).
#[inline]
pub fn tip_position_mm(g: &Geometry, q: &Joint3) -> Joint3 {
    let (s1, c1) = q[0].sin_cos();
    let (s2, c2) = q[1].sin_cos();
    let (s3, c3) = q[2].sin_cos();
    let r = g.l1_mm * c2 + g.l2_mm * s3;
    Joint3::new(
        -s1 * r,
        g.l1_mm * s2 - g.l2_mm * c3 + g.y_offset_mm,
        c1 * r - g.z_offset_mm,
    )
}

/// Jacobian ∂tip/∂q in metres per radian (rows x, y, z; columns joints).
#[inline]
pub fn jacobian(g: &Geometry, q: &Joint3) -> Mat3 {
    let (l1, l2) = (g.l1_mm * 1e-3, g.l2_mm * 1e-3);
    let (s1, c1) = q[0].sin_cos();
    let (s2, c2) = q[1].sin_cos();
    let (s3, c3) = q[2].sin_cos();
    let r = l1 * c2 + l2 * s3;
    Mat3::new(
        -c1 * r,
        s1 * l1 * s2,
        -s1 * l2 * c3,
        0.0,
        l1 * c2,
        l2 * s3,
        -s1 * r,
        -c1 * l1 * s2,
        c1 * l2 * c3,
    )
}

/// Time derivative of the Jacobian along the joint velocity `qd`, m/(rad·s).
#[inline]
pub fn jacobian_dot(g: &Geometry, q: &Joint3, qd: &Joint3) -> Mat3 {
    let (l1, l2) = (g.l1_mm * 1e-3, g.l2_mm * 1e-3);
    let (s1, c1) = q[0].sin_cos();
    let (s2, c2) = q[1].sin_cos();
    let (s3, c3) = q[2].sin_cos();
    let (w1, w2, w3) = (qd[0], qd[1], qd[2]);
    let r = l1 * c2 + l2 * s3;
    let rd = -l1 * s2 * w2 + l2 * c3 * w3;
    Mat3::new(
        s1 * w1 * r - c1 * rd,
        c1 * w1 * l1 * s2 + s1 * l1 * c2 * w2,
        -c1 * w1 * l2 * c3 + s1 * l2 * s3 * w3,
        0.0,
        -l1 * s2 * w2,
        l2 * c3 * w3,
        -c1 * w1 * r - s1 * rd,
        s1 * w1 * l1 * s2 - c1 * l1 * c2 * w2,
        -s1 * w1 * l2 * c3 - c1 * l2 * s3 * w3,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fd_jacobian(g: &Geometry, q: &Joint3) -> Mat3 {
        let h = 1e-6;
        let mut j = Mat3::zeros();
        for k in 0..3 {
            let mut qp = *q;
            let mut qm = *q;
            qp[k] += h;
            qm[k] -= h;
            let d = (tip_position_mm(g, &qp) - tip_position_mm(g, &qm)) * (1e-3 / (2.0 * h));
            j.set_column(k, &d);
        }
        j
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let g = Geometry::default();
        for q in [
            Joint3::new(0.1, 0.5, 0.2),
            Joint3::new(-0.7, 1.0, -0.3),
            Joint3::new(0.4, 0.3, 0.9),
        ] {
            let err = (jacobian(&g, &q) - fd_jacobian(&g, &q)).abs().max();
            assert!(err < 1e-8, "jacobian error {err} at {q:?}");
        }
    }

    #[test]
    fn jacobian_dot_matches_finite_differences() {
        let g = Geometry::default();
        let q = Joint3::new(0.3, 0.6, 0.1);
        let qd = Joint3::new(0.7, -1.1, 0.5);
        let h = 1e-6;
        let fd = (jacobian(&g, &(q + qd * h)) - jacobian(&g, &(q - qd * h))) / (2.0 * h);
        let err = (jacobian_dot(&g, &q, &qd) - fd).abs().max();
        assert!(err < 1e-8, "jacobian_dot error {err}");
    }

    #[test]
    fn home_pose_is_where_the_formula_puts_it() {
        // j = 0: upper arm horizontal, lower arm hanging straight down.
        let p = tip_position_mm(&Geometry::default(), &Joint3::zeros());
        assert!((p - Joint3::new(0.0, -133.35 + 23.35, 133.35 - 168.35)).norm() < 1e-12);
    }
}
