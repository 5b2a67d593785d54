//! Kinematics the HD API needs beyond the daemon's state: velocity, stylus transform,
//! Jacobian and the joint torque of a tip force (docs/HDAPI.md, Units and frames). Omnid's
//! own forward kinematics and Jacobian with the nominal Omni geometry; the position itself
//! is the daemon's `tip_mm`.

use omnid_client::kinematics::Joint3;
use omnid_client::kinematics::{jacobian, Geometry};

/// The Omni's nominal peak force, N (docs/HDAPI.md, Device description): larger forces are
/// clamped here, silently (clients stop on any error).
pub const MAX_FORCE_N: f64 = 3.3;

/// Scale `f` down to at most [`MAX_FORCE_N`]; a non-finite force is no force.
pub fn clamp_force(f: [f64; 3]) -> [f64; 3] {
    if f.iter().any(|v| !v.is_finite()) {
        return [0.0; 3];
    }
    let n = (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt();
    if n > MAX_FORCE_N {
        f.map(|v| v * MAX_FORCE_N / n)
    } else {
        f
    }
}

/// Joint torque (N·m) that puts force `f` (N) at the tip at joint angles `q`: τ = Jᵀ F.
pub fn joint_torque(q: &[f64; 3], f: &[f64; 3]) -> [f64; 3] {
    let j = jacobian(&Geometry::default(), &Joint3::from(*q));
    (j.transpose() * Joint3::from(*f)).into()
}

/// Tip velocity, mm/s, from the joint velocity.
pub fn velocity_mm_s(q: &[f64; 3], qd: &[f64; 3]) -> [f64; 3] {
    let j = jacobian(&Geometry::default(), &Joint3::from(*q));
    (j * Joint3::from(*qd) * 1e3).into()
}

/// The 6×6 Jacobian, column-major, linear rows in mm/rad (upper left 3×3); the gimbal's
/// rotational part is not modelled (zeros).
pub fn jacobian6(q: &[f64; 3]) -> [f64; 36] {
    let j = jacobian(&Geometry::default(), &Joint3::from(*q));
    let mut out = [0.0; 36];
    for c in 0..3 {
        for r in 0..3 {
            out[c * 6 + r] = j[(r, c)] * 1e3;
        }
    }
    out
}

type M3 = [[f64; 3]; 3];

fn mul(a: &M3, b: &M3) -> M3 {
    std::array::from_fn(|r| std::array::from_fn(|c| (0..3).map(|k| a[r][k] * b[k][c]).sum()))
}

fn rot_x(a: f64) -> M3 {
    let (s, c) = a.sin_cos();
    [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]
}

fn rot_y(a: f64) -> M3 {
    let (s, c) = a.sin_cos();
    [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
}

fn rot_z(a: f64) -> M3 {
    let (s, c) = a.sin_cos();
    [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
}

/// The stylus transform: 16 doubles, column-major, translation (mm) at 12..14. Orientation:
/// base yaw −j1 about y, the lower arm's pitch j3 about x, then the gimbal's yaw, pitch and
/// roll (docs/HDAPI.md, Transform).
pub fn transform(q: &[f64; 3], gimbal: &[f64; 3], tip_mm: &[f64; 3]) -> [f64; 16] {
    let r = [
        rot_y(-q[0]),
        rot_x(q[2]),
        rot_y(-gimbal[0]),
        rot_x(gimbal[1]),
        rot_z(gimbal[2]),
    ]
    .iter()
    .fold(
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        |acc, m| mul(&acc, m),
    );
    let mut t = [0.0; 16];
    for c in 0..3 {
        for row in 0..3 {
            t[c * 4 + row] = r[row][c];
        }
    }
    t[12..15].copy_from_slice(tip_mm);
    t[15] = 1.0;
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn force_is_clamped_in_direction() {
        let f = clamp_force([10.0, 0.0, 0.0]);
        assert!((f[0] - MAX_FORCE_N).abs() < 1e-12 && f[1] == 0.0);
        assert_eq!(clamp_force([f64::NAN, 0.0, 0.0]), [0.0; 3]);
        assert_eq!(clamp_force([1.0, 1.0, 0.0]), [1.0, 1.0, 0.0]);
    }

    #[test]
    fn joint_torque_does_the_work_of_the_force() {
        // Virtual work: τ·q̇ = F·v for any joint velocity.
        let (q, f, qd) = ([0.2, 0.5, 0.1], [0.3, -1.0, 0.7], [0.4, -0.2, 0.9]);
        let tau = joint_torque(&q, &f);
        let v = velocity_mm_s(&q, &qd);
        let power_joint: f64 = (0..3).map(|j| tau[j] * qd[j]).sum();
        let power_tip: f64 = (0..3).map(|j| f[j] * v[j] * 1e-3).sum();
        assert!((power_joint - power_tip).abs() < 1e-12);
    }

    #[test]
    fn transform_is_a_rigid_motion_with_the_tip_as_translation() {
        let t = transform(&[0.3, 0.4, -0.2], &[0.1, 0.2, 0.3], &[1.0, 2.0, 3.0]);
        assert_eq!(&t[12..16], &[1.0, 2.0, 3.0, 1.0]);
        for a in 0..3 {
            for b in 0..3 {
                let dot: f64 = (0..3).map(|k| t[a * 4 + k] * t[b * 4 + k]).sum();
                assert!((dot - f64::from(u8::from(a == b))).abs() < 1e-12);
            }
        }
    }
}
