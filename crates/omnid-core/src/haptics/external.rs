//! The force something outside puts on the tip, estimated from the motors and the model
//! (docs/TELEOP.md §2): the arm obeys M q̈ + C q̇ + G + F(q̇) = τ_motor + τ_ext and the tip force
//! F_ext solves Jᵀ F_ext = τ_ext. No force sensor: a teleoperation follower's contact, or a hand
//! on the stylus, from the torques alone. Plain data, fixed size: it runs on the servo thread.
//!
//! It is a generalized-momentum observer, on either model: p = M(q) q̇ changes by
//! ṗ = τ_motor + τ_ext − n(q, q̇) + Ṁ q̇ (n = C q̇ + G + F), so the residual
//! r = K (p − p₀ − ∫ (τ_motor − n + Ṁ q̇ + r) dt) follows τ_ext as a first-order lag of
//! bandwidth K, from q and q̇ alone: no differentiated acceleration, whose noise and lag against
//! the motor torque would otherwise be felt as force. The parametric model gives M and n
//! directly; the learned one gives M̂(q) (the M-net's six entries) and n̂ = Ĉ(q, q̇) q̇ + Ĝ(q) +
//! F̂(q̇) from its other networks.

use super::Force3;
use crate::identifier::Identifier;
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

/// The model the observer integrated last: a change starts it afresh (p₀ from the new M).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Source {
    Parametric,
    Learned,
}

/// The external torque and tip force, estimated every tick.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ExternalForce {
    /// Bandwidth, 1/s (2π × the cut-off).
    gain: f64,
    dt: f64,
    /// Momentum observer: p₀, the integral, the last M and the model it came from.
    p0: Joint3,
    integral: Joint3,
    last_m: Option<(Mat3, Source)>,
    /// τ_ext, N·m.
    pub(crate) tau: Joint3,
    /// F_ext at the tip, N, OpenHaptics frame.
    pub(crate) force: Force3,
}

fn finite(v: &Joint3) -> bool {
    v.iter().all(|x| x.is_finite())
}

impl ExternalForce {
    /// An estimate of bandwidth `cutoff_hz` sampled every `dt` s.
    pub(crate) fn new(cutoff_hz: f64, dt: f64) -> Self {
        ExternalForce {
            gain: std::f64::consts::TAU * cutoff_hz,
            dt,
            p0: Joint3::zeros(),
            integral: Joint3::zeros(),
            last_m: None,
            tau: Joint3::zeros(),
            force: Force3::zeros(),
        }
    }

    /// One sample with the parametric model `m`: the estimated (q, q̇) and the motors' torque
    /// over the interval that ended at it.
    pub(crate) fn observe(&mut self, m: &Dynamics, q: &Joint3, qd: &Joint3, acting: &Joint3) {
        if !(finite(q) && finite(qd) && finite(acting)) {
            return;
        }
        let mass = m.mass(q);
        let n = m.inverse_dynamics(q, qd, &Joint3::zeros());
        self.step(Source::Parametric, &m.geometry, q, qd, mass, n, acting);
    }

    /// One sample with the identifier's learned model (M̂, and Ĉ q̇ + Ĝ + F̂ from its other
    /// networks, as they were when this tick's sample was seen); `g` maps τ_ext to the tip.
    pub(crate) fn observe_learned(
        &mut self,
        id: &mut Identifier,
        g: &Geometry,
        q: &Joint3,
        qd: &Joint3,
        acting: &Joint3,
    ) {
        if !(finite(q) && finite(qd) && finite(acting)) {
            return;
        }
        let (mass, n) = id.momentum_model(q, qd);
        self.step(Source::Learned, g, q, qd, mass, n, acting);
    }

    /// The observer's step with the model's M(q) and n(q, q̇). A non-finite model holds the
    /// estimate; the first sample starts it at zero, a change of model from where it is.
    #[allow(clippy::too_many_arguments)]
    fn step(
        &mut self,
        source: Source,
        g: &Geometry,
        q: &Joint3,
        qd: &Joint3,
        mass: Mat3,
        n: Joint3,
        acting: &Joint3,
    ) {
        if !(mass.iter().all(|v| v.is_finite()) && finite(&n)) {
            return;
        }
        let p = mass * qd;
        let last_m = match self.last_m.replace((mass, source)) {
            Some((m, s)) if s == source => m,
            // Another model (a controller switch): its momentum starts where the estimate
            // stands, so the force goes on without a step and converges on the new model's.
            Some(_) => {
                self.integral = Joint3::zeros();
                self.p0 = p - self.tau / self.gain;
                return;
            }
            None => {
                self.p0 = p;
                self.integral = Joint3::zeros();
                self.tau = Joint3::zeros();
                return;
            }
        };
        let m_dot_qd = (mass - last_m) * qd / self.dt;
        self.integral += (acting - n + m_dot_qd + self.tau) * self.dt;
        self.tau = (p - self.p0 - self.integral) * self.gain;
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
    use nalgebra::Vector3;

    fn plant() -> Dynamics {
        let mut m = Dynamics::new(crate::omni::ModelParams::default(), Geometry::default());
        m.friction = true;
        m
    }

    fn shipped() -> Identifier {
        let cfg = crate::config::Config::default();
        let mut id = Identifier::new(&cfg.identifier).unwrap();
        let w = crate::identifier::WeightsFile::from_json(
            crate::cmd::assembly::SHIPPED_WEIGHTS,
            "shipped",
        )
        .unwrap();
        id.apply_weights(&w, "shipped").unwrap();
        id
    }

    /// RK4 over one tick of `dt` in ten substeps of q̈ = `f`(q, q̇).
    fn rk4(
        q: &mut Joint3,
        qd: &mut Joint3,
        dt: f64,
        mut f: impl FnMut(&Joint3, &Joint3) -> Joint3,
    ) {
        let h = dt / 10.0;
        for _ in 0..10 {
            let (q0, v0) = (*q, *qd);
            let a1 = f(&q0, &v0);
            let (q2, v2) = (q0 + v0 * (h / 2.0), v0 + a1 * (h / 2.0));
            let a2 = f(&q2, &v2);
            let (q3, v3) = (q0 + v2 * (h / 2.0), v0 + a2 * (h / 2.0));
            let a3 = f(&q3, &v3);
            let (q4, v4) = (q0 + v3 * h, v0 + a3 * h);
            let a4 = f(&q4, &v4);
            *q = q0 + (v0 + v2 * 2.0 + v3 * 2.0 + v4) * (h / 6.0);
            *qd = v0 + (a1 + a2 * 2.0 + a3 * 2.0 + a4) * (h / 6.0);
        }
    }

    #[test]
    fn a_known_tip_force_on_a_resting_arm_is_recovered() {
        // At rest the motors give the model's gravity less Jᵀ F: the estimate must return F
        // (and τ_ext = Jᵀ F) once it has settled.
        let m = plant();
        let q = Joint3::new(0.2, 0.5, -0.1);
        let f = Force3::new(0.4, -1.0, 0.7);
        let acting = m.gravity(&q) - tip_force_torque(&m.geometry, &q, &f);
        let mut e = ExternalForce::new(20.0, 1e-3);
        for _ in 0..500 {
            e.observe(&m, &q, &Joint3::zeros(), &acting);
        }
        assert!((e.force - f).norm() < 1e-9, "{:?}", e.force);
        assert!((e.tau - tip_force_torque(&m.geometry, &q, &f)).norm() < 1e-9);
    }

    #[test]
    fn the_observer_is_a_first_order_lag_at_its_cut_off() {
        // A step of external torque reaches 1 − e^(−1) of its size after one time constant
        // 1/(2π f_c).
        let m = plant();
        let q = Joint3::new(0.0, 0.6, 0.2);
        let mut e = ExternalForce::new(10.0, 1e-5);
        let hold = m.gravity(&q);
        e.observe(&m, &q, &Joint3::zeros(), &hold);
        let step = Joint3::new(0.0, 0.1, 0.0);
        let n = (1.0 / (std::f64::consts::TAU * 10.0) / 1e-5).round() as usize;
        for _ in 0..n {
            e.observe(&m, &q, &Joint3::zeros(), &(hold - step));
        }
        let reached = e.tau[1] / 0.1;
        assert!(
            (reached - (1.0 - (-1.0f64).exp())).abs() < 0.002,
            "{reached}"
        );
    }

    #[test]
    fn non_finite_inputs_are_ignored_and_a_singular_pose_holds_the_last_force() {
        let m = plant();
        let g = m.geometry;
        let q = Joint3::new(0.1, 0.5, 0.3);
        let mut e = ExternalForce::new(20.0, 1e-3);
        let push = m.gravity(&q) - Joint3::new(0.0, 0.05, 0.02);
        for _ in 0..200 {
            e.observe(&m, &q, &Joint3::zeros(), &push);
        }
        let before = e.force;
        assert!(before.norm() > 0.1, "{before:?}");
        e.observe(&m, &q, &Joint3::zeros(), &Joint3::new(f64::NAN, 0.0, 0.0));
        e.observe(
            &m,
            &Joint3::new(0.1, f64::INFINITY, 0.3),
            &Joint3::zeros(),
            &push,
        );
        assert_eq!(e.force, before);
        // The tip on the base's vertical axis (l1 cos q2 + l2 sin q3 = 0): turning the base
        // moves it nowhere, J loses rank and no tip force explains a base torque.
        let mut on_axis = q;
        on_axis[2] = (-g.l1_mm * q[1].cos() / g.l2_mm).asin();
        assert!(jacobian(&g, &on_axis).determinant().abs() <= SINGULAR_DET);
        let base = m.gravity(&on_axis) - Joint3::new(0.05, 0.0, 0.0);
        e.observe(&m, &on_axis, &Joint3::zeros(), &base);
        assert_eq!(e.force, before);
        assert!(e.force.iter().all(|v| v.is_finite()));
    }

    #[test]
    fn the_momentum_observer_finds_a_push_on_a_moving_arm_simulated_independently() {
        // The plant (RK4 on the model's forward dynamics) swings under a torque of its own and
        // a constant external tip force; the observer sees only (q, q̇) and the motor torque.
        // After a few time constants its estimate must match the push, while the arm moves.
        let plant = plant();
        let g = plant.geometry;
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
            rk4(&mut q, &mut qd, dt, |q, qd| {
                plant.forward_dynamics(q, qd, &(motor + ext))
            });
            e.observe(&plant, &q, &qd, &motor);
            if t > 0.5 {
                worst_late = worst_late.max((e.force - push).norm());
            }
        }
        assert!(qd.norm() > 0.01, "the arm should be moving: {qd}");
        assert!(worst_late < 0.02, "estimate off by {worst_late} N");
    }

    #[test]
    fn the_learned_observer_finds_a_push_on_an_arm_that_moves_as_the_networks_say() {
        // A plant whose dynamics are the shipped networks' own without friction (what the
        // learned observer models, as the parametric one does): q̈ = M̂⁻¹(τ − Ĉ q̇ − Ĝ − F̂(0)),
        // integrated by RK4 through the networks' single-net accessors. The observer sees
        // only (q, q̇) and the motor torque (no q̈); once settled it must find the push while
        // the arm swings. Nothing adapts: the model is the plant.
        let mut plant_id = shipped();
        let mut id = shipped();
        let g = Geometry::default();
        let push = Force3::new(0.3, -0.8, 0.5);
        let dt = 1e-3;
        let (mut q, mut qd) = (Joint3::new(0.1, 0.6, 0.2), Joint3::zeros());
        let mut e = ExternalForce::new(20.0, dt);
        let mut worst_late = 0.0f64;
        let mut moved = 0.0f64;
        for k in 0..3000 {
            let t = k as f64 * dt;
            let ext = tip_force_torque(&g, &q, &push);
            let swing = Joint3::new(0.2 * (3.0 * t).sin(), 0.6 + 0.2 * (2.0 * t).cos(), 0.2);
            let hold = plant_id.gravity(&q) + plant_id.friction(&Vector3::zeros());
            let motor = hold - ext + (swing - q) * 0.5 - qd * 0.05;
            rk4(&mut q, &mut qd, dt, |q, qd| {
                let m = plant_id.mass(q);
                let rhs = motor + ext
                    - plant_id.coriolis(q, qd) * qd
                    - plant_id.gravity(q)
                    - plant_id.friction(&Vector3::zeros());
                m.lu().solve(&rhs).unwrap_or_else(Joint3::zeros)
            });
            // The servo's order: the identifier evaluates this sample, then the observer.
            id.predict(&q, &qd, &Joint3::zeros());
            e.observe_learned(&mut id, &g, &q, &qd, &motor);
            moved = moved.max(qd.norm());
            if t > 0.5 {
                worst_late = worst_late.max((e.force - push).norm());
            }
        }
        assert!(moved > 0.1, "the arm should have moved: {moved}");
        assert!(worst_late < 0.02, "estimate off by {worst_late} N");
    }

    #[test]
    fn a_change_of_model_continues_the_estimate_without_a_step() {
        // Parametric, then learned at the same resting pose: the force goes on from where it
        // stood and converges on what the learned model explains. The parametric model is the
        // plant's parameters 20 % off (a lab's nominal model), so the two models differ here
        // (the learned one is within a fraction of a mN·m of the plant).
        let mut m = Dynamics::new(
            crate::omni::ModelParams::default().scaled(1.2),
            Geometry::default(),
        );
        m.friction = true;
        let mut id = shipped();
        let g = m.geometry;
        let q = Joint3::new(0.1, 0.6, 0.2);
        let f = Force3::new(0.0, -1.0, 0.0);
        let acting = m.gravity(&q) - tip_force_torque(&g, &q, &f);
        let mut e = ExternalForce::new(15.0, 1e-3);
        for _ in 0..500 {
            e.observe(&m, &q, &Joint3::zeros(), &acting);
        }
        let before = e.force;
        // What the learned model explains, computed on its own: n̂(q, 0) − τ_motor = Jᵀ F̂.
        let n = id.gravity(&q) + id.friction(&Vector3::zeros());
        let jt = jacobian(&g, &q).transpose();
        let expected = jt.lu().solve(&(n - acting)).unwrap();
        assert!(
            (expected - before).norm() > 0.01,
            "the models should differ here"
        );
        // Two samples on the new model: the first takes it up, the second moves the force by
        // one step of the lag (K·dt ≈ 0.09 of the way), not back to zero.
        for _ in 0..2 {
            e.observe_learned(&mut id, &g, &q, &Joint3::zeros(), &acting);
        }
        let moved = (e.force - before).norm();
        assert!(
            moved <= 0.1 * (expected - before).norm() && moved > 0.0,
            "{before:?} → {:?}",
            e.force
        );
        for _ in 0..500 {
            e.observe_learned(&mut id, &g, &q, &Joint3::zeros(), &acting);
        }
        assert!(
            (e.force - expected).norm() < 1e-6,
            "{:?} vs {expected:?}",
            e.force
        );
    }
}
