//! The force something outside puts on the tip, estimated from the motors and the model
//! (docs/TELEOP.md §2): the arm obeys M q̈ + C q̇ + G + F(q̇) = τ_motor + Jᵀ F_ext, so what the
//! model says the free arm needed for the estimated motion, minus what the motors gave, is the
//! outside's share τ_ext = τ_model − τ_motor, and F_ext solves Jᵀ F_ext = τ_ext. No force
//! sensor: a teleoperation follower's contact, or a hand on the stylus, from the torques alone.
//! Plain data, fixed size: it runs on the servo thread every tick.

use super::Force3;
use crate::omni::{jacobian, Geometry, Joint3};
use serde::{Deserialize, Serialize};

/// Which model says what the free arm needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum ExternalModel {
    /// The active controller's: the identifier's learned model under nnidc, the parametric
    /// rigid-body model under every other law.
    Active,
    /// The parametric rigid-body model (`[model]`).
    Parametric,
    /// The identifier's learned model (the paper's networks for M, C, G and friction).
    Learned,
}

/// Below this |det J| (m³) the tip force cannot be told from the joint torques (the arm is
/// stretched straight or folded onto its base): the estimate holds its last value.
const SINGULAR_DET: f64 = 1e-7;

/// A low-passed estimate of the external tip force and joint torque.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ExternalForce {
    /// The filter's weight on each new value (first order, from the cut-off and the period).
    alpha: f64,
    /// Filtered τ_ext, N·m.
    pub(crate) tau: Joint3,
    /// F_ext at the tip from the filtered τ_ext, N, OpenHaptics frame.
    pub(crate) force: Force3,
    primed: bool,
}

impl ExternalForce {
    /// A first-order low-pass at `cutoff_hz` sampled every `dt` s.
    pub(crate) fn new(cutoff_hz: f64, dt: f64) -> Self {
        let rc = 1.0 / (std::f64::consts::TAU * cutoff_hz);
        ExternalForce {
            alpha: dt / (rc + dt),
            tau: Joint3::zeros(),
            force: Force3::zeros(),
            primed: false,
        }
    }

    /// One sample: `needed` the model's torque for the estimated (q, q̇, q̈), `acting` the
    /// motors' torque over the interval that ended at it, `q` where the tip is.
    pub(crate) fn update(&mut self, g: &Geometry, q: &Joint3, needed: &Joint3, acting: &Joint3) {
        let raw = needed - acting;
        if !raw.iter().all(|v| v.is_finite()) {
            return;
        }
        if self.primed {
            self.tau += (raw - self.tau) * self.alpha;
        } else {
            self.tau = raw;
            self.primed = true;
        }
        let jt = jacobian(g, q).transpose();
        if jt.determinant().abs() > SINGULAR_DET {
            if let Some(f) = jt.lu().solve(&self.tau) {
                self.force = f;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::haptics::tip_force_torque;

    #[test]
    fn a_known_tip_force_is_recovered_from_the_torques_it_leaves_unexplained() {
        // The outside pushes with F; the motors give what the model needs minus Jᵀ F. The
        // estimate must return F (and τ_ext = Jᵀ F) once the filter has settled.
        let g = Geometry::default();
        let q = Joint3::new(0.2, 0.5, -0.1);
        let f = Force3::new(0.4, -1.0, 0.7);
        let needed = Joint3::new(0.01, 0.12, -0.05);
        let acting = needed - tip_force_torque(&g, &q, &f);
        let mut e = ExternalForce::new(20.0, 1e-3);
        for _ in 0..500 {
            e.update(&g, &q, &needed, &acting);
        }
        assert!((e.force - f).norm() < 1e-9, "{:?}", e.force);
        assert!((e.tau - tip_force_torque(&g, &q, &f)).norm() < 1e-9);
    }

    #[test]
    fn the_filter_is_a_first_order_low_pass_at_its_cut_off() {
        // A step reaches 1 − e^(−1) of its size after one time constant 1/(2π f_c).
        let g = Geometry::default();
        let q = Joint3::new(0.0, 0.6, 0.2);
        let mut e = ExternalForce::new(10.0, 1e-4);
        e.update(&g, &q, &Joint3::zeros(), &Joint3::zeros());
        let step = Joint3::new(0.0, 0.1, 0.0);
        let n = (1.0 / (std::f64::consts::TAU * 10.0) / 1e-4).round() as usize;
        for _ in 0..n {
            e.update(&g, &q, &step, &Joint3::zeros());
        }
        let reached = e.tau[1] / 0.1;
        assert!(
            (reached - (1.0 - (-1.0f64).exp())).abs() < 0.01,
            "{reached}"
        );
    }

    #[test]
    fn non_finite_torques_are_ignored_and_a_singular_pose_holds_the_last_force() {
        let g = Geometry::default();
        let q = Joint3::new(0.1, 0.5, 0.3);
        let mut e = ExternalForce::new(20.0, 1e-3);
        let tau = Joint3::new(0.0, 0.05, 0.02);
        e.update(&g, &q, &tau, &Joint3::zeros());
        let before = e.force;
        e.update(&g, &q, &Joint3::new(f64::NAN, 0.0, 0.0), &Joint3::zeros());
        assert_eq!(e.force, before);
        // The tip on the base's vertical axis (l1 cos q2 + l2 sin q3 = 0): turning the base
        // moves it nowhere, J loses rank and no tip force explains a base torque.
        let mut on_axis = q;
        on_axis[2] = (-g.l1_mm * q[1].cos() / g.l2_mm).asin();
        assert!(jacobian(&g, &on_axis).determinant().abs() <= SINGULAR_DET);
        e.update(&g, &on_axis, &Joint3::new(0.05, 0.0, 0.0), &Joint3::zeros());
        assert_eq!(e.force, before);
        assert!(e.force.iter().all(|v| v.is_finite()));
    }
}
