//! The force something outside puts on the tip, estimated from the motors and the model
//! (docs/TELEOP.md §2): the arm obeys M q̈ + C q̇ + G + F(q̇) = τ_motor + τ_ext and the tip force
//! F_ext solves Jᵀ F_ext = τ_ext. No force sensor: a teleoperation follower's contact, or a hand
//! on the stylus, from the torques alone. Plain data, fixed size: it runs on the servo thread.
//!
//! With the parametric model it is a generalized-momentum observer: p = M(q) q̇ changes by
//! ṗ = τ_motor + τ_ext − n(q, q̇) + Ṁ q̇ (n = C q̇ + G + F), so the residual
//! r = K (p − p₀ − ∫ (τ_motor − n + Ṁ q̇ + r) dt) follows τ_ext as a first-order lag of
//! bandwidth K, from q and q̇ alone: no differentiated acceleration, whose noise and lag against
//! the motor torque would otherwise be felt as force. With the learned model (whose networks
//! give the torque for a motion, not M alone) it is τ_ext = τ̂(q, q̇, q̈) − τ_motor through a
//! first-order low-pass at the same cut-off.

use super::Force3;
use crate::omni::{jacobian, Dynamics, Geometry, Joint3, Mat3};
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

/// The external torque and tip force, estimated every tick.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ExternalForce {
    /// Bandwidth, 1/s (2π × the cut-off).
    gain: f64,
    dt: f64,
    /// The filter's weight on each new value (learned model).
    alpha: f64,
    /// Momentum observer: p₀, the integral, the last M.
    p0: Joint3,
    integral: Joint3,
    last_m: Option<Mat3>,
    /// τ_ext, N·m.
    pub(crate) tau: Joint3,
    /// F_ext at the tip, N, OpenHaptics frame.
    pub(crate) force: Force3,
    primed: bool,
}

impl ExternalForce {
    /// An estimate of bandwidth `cutoff_hz` sampled every `dt` s.
    pub(crate) fn new(cutoff_hz: f64, dt: f64) -> Self {
        let gain = std::f64::consts::TAU * cutoff_hz;
        ExternalForce {
            gain,
            dt,
            alpha: dt / (1.0 / gain + dt),
            p0: Joint3::zeros(),
            integral: Joint3::zeros(),
            last_m: None,
            tau: Joint3::zeros(),
            force: Force3::zeros(),
            primed: false,
        }
    }

    /// One sample with the parametric model `m`: the estimated (q, q̇) and the motors' torque
    /// over the interval that ended at it.
    pub(crate) fn observe(&mut self, m: &Dynamics, q: &Joint3, qd: &Joint3, acting: &Joint3) {
        if !(q
            .iter()
            .chain(qd.iter())
            .chain(acting.iter())
            .all(|v| v.is_finite()))
        {
            return;
        }
        let mass = m.mass(q);
        let p = mass * qd;
        let Some(last_m) = self.last_m.replace(mass) else {
            self.p0 = p;
            self.integral = Joint3::zeros();
            self.tau = Joint3::zeros();
            return;
        };
        let m_dot_qd = (mass - last_m) * qd / self.dt;
        let n = m.inverse_dynamics(q, qd, &Joint3::zeros());
        self.integral += (acting - n + m_dot_qd + self.tau) * self.dt;
        self.tau = (p - self.p0 - self.integral) * self.gain;
        let g = m.geometry;
        self.map(&g, q);
    }

    /// One sample with a model's torque `needed` for the estimated (q, q̇, q̈) and the motors'
    /// torque `acting` over the interval that ended at it (the learned model).
    pub(crate) fn update(&mut self, g: &Geometry, q: &Joint3, needed: &Joint3, acting: &Joint3) {
        let raw = needed - acting;
        if !raw.iter().all(|v| v.is_finite()) {
            return;
        }
        // The momentum observer starts afresh should the model change back.
        self.last_m = None;
        if self.primed {
            self.tau += (raw - self.tau) * self.alpha;
        } else {
            self.tau = raw;
            self.primed = true;
        }
        self.map(g, q);
    }

    /// F_ext from τ_ext at `q` (held where J is singular).
    fn map(&mut self, g: &Geometry, q: &Joint3) {
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
        let mut e = ExternalForce::new(10.0, 1e-5);
        e.update(&g, &q, &Joint3::zeros(), &Joint3::zeros());
        let step = Joint3::new(0.0, 0.1, 0.0);
        let n = (1.0 / (std::f64::consts::TAU * 10.0) / 1e-5).round() as usize;
        for _ in 0..n {
            e.update(&g, &q, &step, &Joint3::zeros());
        }
        let reached = e.tau[1] / 0.1;
        assert!(
            (reached - (1.0 - (-1.0f64).exp())).abs() < 0.002,
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

    #[test]
    fn the_momentum_observer_finds_a_push_on_a_moving_arm_simulated_independently() {
        // The plant (RK4 on the model's forward dynamics) swings under a torque of its own and
        // a constant external tip force; the observer sees only (q, q̇) and the motor torque.
        // After a few time constants its estimate must match the push, while the arm moves.
        let g = Geometry::default();
        let mut plant = Dynamics::new(crate::omni::ModelParams::default(), g);
        plant.friction = true;
        let push = Force3::new(0.3, -0.8, 0.5);
        let dt = 1e-3;
        let (mut q, mut qd) = (Joint3::new(0.1, 0.6, 0.2), Joint3::zeros());
        let mut e = ExternalForce::new(20.0, dt);
        let mut worst_late = 0.0f64;
        for k in 0..3000 {
            let t = k as f64 * dt;
            // The motors: gravity held, the push resisted, a swing about the start kept
            // inside the joint limits by a spring (whose torque the observer is told).
            let ext = tip_force_torque(&g, &q, &push);
            let swing = Joint3::new(0.2 * (3.0 * t).sin(), 0.6 + 0.2 * (2.0 * t).cos(), 0.2);
            let motor = plant.gravity(&q) - ext + (swing - q) * 0.5 - qd * 0.01;
            let f = |q: &Joint3, qd: &Joint3| plant.forward_dynamics(q, qd, &(motor + ext));
            let h = dt / 10.0;
            for _ in 0..10 {
                let a1 = f(&q, &qd);
                let a2 = f(&(q + qd * (h / 2.0)), &(qd + a1 * (h / 2.0)));
                let a3 = f(
                    &(q + (qd + a1 * (h / 2.0)) * (h / 2.0)),
                    &(qd + a2 * (h / 2.0)),
                );
                let a4 = f(&(q + (qd + a2 * (h / 2.0)) * h), &(qd + a3 * h));
                q += (qd
                    + (qd + a1 * (h / 2.0)) * 2.0
                    + (qd + a2 * (h / 2.0)) * 2.0
                    + (qd + a3 * h))
                    * (h / 6.0);
                qd += (a1 + a2 * 2.0 + a3 * 2.0 + a4) * (h / 6.0);
            }
            e.observe(&plant, &q, &qd, &motor);
            if t > 0.5 {
                worst_late = worst_late.max((e.force - push).norm());
            }
        }
        assert!(qd.norm() > 0.01, "the arm should be moving: {qd}");
        assert!(worst_late < 0.02, "estimate off by {worst_late} N");
    }
}
