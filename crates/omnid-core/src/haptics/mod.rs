//! Haptics: forces at the stylus tip (docs/HAPTICS.md). A Cartesian force F in newtons, in the
//! OpenHaptics frame (+x right, +y up, +z toward the user), becomes the joint torque τ = Jᵀ(q) F
//! with J the Jacobian of the tip position in metres; that torque then goes through the safety
//! layer like every other.

pub(crate) mod config;
pub(crate) mod effects;
pub(crate) mod external;
pub(crate) mod hand;
pub(crate) mod inertia;
pub(crate) mod passivity;
pub(crate) mod render;
pub mod scene;

pub use config::HapticsConfig;
pub use effects::Effect;
pub(crate) use effects::MAX_EFFECTS;
pub use external::ExternalModel;
pub(crate) use hand::Hand;
pub use hand::{HandConfig, HandPattern};
pub use inertia::MAX_INERTIA_COMPENSATION;
pub(crate) use inertia::{near_walls, InertiaGate};
pub(crate) use render::HapticLoop;

use crate::omni::{jacobian, Geometry, Joint3};

/// What `omnid run` renders: free mode instead of tracking, and the scene's effects.
#[derive(Debug, Clone, Default)]
pub struct HapticRun {
    /// Free mode: only the controller's compensation and the effects (no trajectory).
    pub free: bool,
    /// The scene's effects, from `--scene`.
    pub effects: Vec<Effect>,
}

/// A tip force, N, OpenHaptics frame.
pub(crate) type Force3 = nalgebra::Vector3<f64>;

/// Joint torque (N·m) that puts the force `f` (N) on the tip at pose `q` (τ = Jᵀ F: the
/// virtual work of F along a tip displacement J δq is τ·δq).
pub(crate) fn tip_force_torque(g: &Geometry, q: &Joint3, f: &Force3) -> Joint3 {
    jacobian(g, q).transpose() * f
}

/// `f` with its norm clamped to `max` N, direction kept. Any finite input, however large,
/// gives a finite result (the norm is taken on the scaled vector so it cannot overflow); a
/// non-finite input gives zero (callers refuse those earlier; this is the last line).
pub(crate) fn limit_force(f: &Force3, max: f64) -> Force3 {
    if !f.iter().all(|v| v.is_finite()) {
        return Force3::zeros();
    }
    let scale = f.amax();
    if scale == 0.0 {
        return *f;
    }
    let unit = f / scale;
    let norm = unit.norm() * scale;
    if norm <= max {
        *f
    } else {
        unit * (max / unit.norm())
    }
}

/// Whether a limit held `asked` back to `given`: by more than rounding, so a force a client
/// already scaled to the limit itself (its norm a last bit above it) is not said to be held.
pub(crate) fn held_back(asked: &Force3, given: &Force3) -> bool {
    (given - asked).norm() > 1e-9 * (1.0 + asked.norm())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::omni::tip_position_mm;

    #[test]
    fn jt_f_does_the_virtual_work_of_the_force() {
        // Independent of the analytic Jacobian: τ_j must equal F · ∂p/∂q_j with the partial
        // taken by central differences of the forward kinematics (metres).
        let g = Geometry::default();
        let f = Force3::new(0.7, -1.3, 2.1);
        for q in [
            Joint3::new(0.0, 0.6, 0.3),
            Joint3::new(-0.8, 1.2, -0.2),
            Joint3::new(0.5, 0.1, 0.9),
        ] {
            let tau = tip_force_torque(&g, &q, &f);
            for j in 0..3 {
                let h = 1e-6;
                let (mut qp, mut qm) = (q, q);
                qp[j] += h;
                qm[j] -= h;
                let dp = (tip_position_mm(&g, &qp) - tip_position_mm(&g, &qm)) * 1e-3 / (2.0 * h);
                let expected = f.dot(&dp);
                assert!(
                    (tau[j] - expected).abs() < 1e-9,
                    "joint {j} at {q:?}: {} vs {expected}",
                    tau[j]
                );
            }
        }
    }

    #[test]
    fn forces_beyond_the_peak_are_clamped_in_norm_keeping_direction() {
        let f = Force3::new(3.0, 4.0, 0.0);
        assert_eq!(limit_force(&f, 10.0), f);
        let c = limit_force(&f, 2.5);
        assert!((c - Force3::new(1.5, 2.0, 0.0)).norm() < 1e-12, "{c}");
        // Finite but huge: no overflow to inf or NaN.
        let huge = limit_force(&Force3::new(1e308, -1e308, 1e308), 3.3);
        assert!((huge.norm() - 3.3).abs() < 1e-12, "{huge}");
        assert!((huge[0] + huge[1]).abs() < 1e-12);
        // Not finite: nothing passes.
        assert_eq!(
            limit_force(&Force3::new(f64::NAN, 0.0, 0.0), 3.3),
            Force3::zeros()
        );
        assert_eq!(
            limit_force(&Force3::new(f64::INFINITY, 0.0, 0.0), 3.3),
            Force3::zeros()
        );
        assert_eq!(limit_force(&Force3::zeros(), 3.3), Force3::zeros());
    }
}
