//! Rigid-body model of the Omni (docs/DESIGN.md §4.2): M(q), C(q, q̇), G(q) of the Cavusoglu
//! structure in the OpenHaptics joint angles, plus reflected rotor inertia, viscous and smoothed
//! Coulomb friction, joint-limit springs and an optional point-mass payload at the tip.

use super::kinematics::{jacobian, jacobian_dot, tip_position_mm, Geometry};
use super::{Joint3, Mat3, GRAVITY};
use crate::config_check::{self as check, ConfigError};
use crate::fast_tanh::tanh;
use serde::{Deserialize, Serialize};
use wide::f64x2;

/// Every constant of the plant model. Units: kg·m², N·m, N·m·s/rad, rad, rad/s.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ModelParams {
    /// Inertia parameter, kg·m².
    pub k1: f64,
    /// Inertia parameter, kg·m².
    pub k2: f64,
    /// Inertia parameter, kg·m².
    pub k3: f64,
    /// Inertia parameter, kg·m².
    pub k4: f64,
    /// Inertia parameter, kg·m².
    pub k5: f64,
    /// Inertia parameter, kg·m².
    pub k7: f64,
    /// Gravity parameter, N·m.
    pub k8: f64,
    /// Gravity parameter, N·m.
    pub k9: f64,
    /// Reflected rotor inertia added to the diagonal, kg·m².
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub rotor_inertia: [f64; 3],
    /// Viscous friction, N·m·s/rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub viscous: [f64; 3],
    /// Level of the Coulomb friction, N·m.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub coulomb: [f64; 3],
    /// Velocity scale of the tanh that smooths Coulomb friction, rad/s.
    pub coulomb_velocity: f64,
    /// Lower joint limits, rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub limit_lower: [f64; 3],
    /// Upper joint limits, rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub limit_upper: [f64; 3],
    /// Joint-limit spring stiffness, N·m/rad.
    pub limit_stiffness: f64,
    /// Joint-limit spring damping, N·m·s/rad.
    pub limit_damping: f64,
}

impl Default for ModelParams {
    fn default() -> Self {
        ModelParams {
            k1: 2.833e-3,
            k2: 1.132e-3,
            k3: -3.912e-4,
            k4: 9.123e-4,
            k5: 2.426e-3,
            k7: 9.319e-4,
            k8: -1.630e-2,
            k9: -7.376e-2,
            rotor_inertia: [1.9e-4, 1.35e-4, 1.35e-4],
            viscous: [5e-4; 3],
            coulomb: [0.01; 3],
            coulomb_velocity: 0.01,
            limit_lower: [-0.98, 0.0, -0.6],
            limit_upper: [0.98, 1.75, 1.2],
            limit_stiffness: 5.0,
            limit_damping: 0.02,
        }
    }
}

impl ModelParams {
    /// M(q) of this model on a 5×5 grid of (q2, q3) spanning the joint limits (M does not
    /// depend on q1), with the grid point.
    pub(crate) fn mass_over_joint_range(
        &self,
        geometry: Geometry,
    ) -> impl Iterator<Item = ((f64, f64), Mat3)> {
        let (m, dynamics) = (*self, Dynamics::new(*self, geometry));
        let across = move |i: usize, k: usize| {
            m.limit_lower[i] + (m.limit_upper[i] - m.limit_lower[i]) * k as f64 / 4.0
        };
        (0..=4)
            .flat_map(move |a| (0..=4).map(move |b| (across(1, a), across(2, b))))
            .map(move |(q2, q3)| {
                let q = Joint3::new(0.0, q2, q3);
                ((q2, q3), dynamics.mass(&q))
            })
    }

    /// Check every value, and that the inertia is positive definite over the whole joint
    /// range of this arm (`geometry`); the first problem names its field (`model.…`).
    pub(crate) fn validate(&self, geometry: Geometry) -> Result<(), ConfigError> {
        for (name, v) in [("k1", self.k1), ("k5", self.k5), ("k7", self.k7)] {
            check::positive(&format!("model.{name}"), v)?;
        }
        for (name, v) in [
            ("k2", self.k2),
            ("k3", self.k3),
            ("k4", self.k4),
            ("k8", self.k8),
            ("k9", self.k9),
        ] {
            check::in_range(&format!("model.{name}"), v, -1.0, 1.0, "-1 ..= 1")?;
        }
        check::each("model.rotor_inertia", &self.rotor_inertia, |f, v| {
            check::in_range(f, v, 0.0, 1.0, "0 ..= 1 kg·m²")
        })?;
        check::each("model.viscous", &self.viscous, |f, v| {
            check::in_range(f, v, 0.0, 1.0, "0 ..= 1 N·m·s/rad")
        })?;
        check::each("model.coulomb", &self.coulomb, |f, v| {
            check::in_range(f, v, 0.0, 1.0, "0 ..= 1 N·m")
        })?;
        check::positive("model.coulomb_velocity", self.coulomb_velocity)?;
        for i in 0..3 {
            let (lower, upper) = (self.limit_lower[i], self.limit_upper[i]);
            check::in_range(
                &format!("model.limit_lower[{i}]"),
                lower,
                -3.2,
                upper,
                "-3.2 rad ..= model.limit_upper",
            )?;
            check::in_range(
                &format!("model.limit_upper[{i}]"),
                upper,
                lower,
                3.2,
                "model.limit_lower ..= 3.2 rad",
            )?;
        }
        check::in_range(
            "model.limit_stiffness",
            self.limit_stiffness,
            0.0,
            1e4,
            "0 ..= 1e4 N·m/rad",
        )?;
        check::in_range(
            "model.limit_damping",
            self.limit_damping,
            0.0,
            100.0,
            "0 ..= 100 N·m·s/rad",
        )?;
        for ((q2, q3), mass) in self.mass_over_joint_range(geometry) {
            if mass.cholesky().is_none() {
                return Err(check::invalid(
                    "model.k1..k7",
                    format!("M(q) not positive definite at q = [0, {q2:.2}, {q3:.2}]"),
                    "parameters that give a positive definite inertia",
                ));
            }
        }
        Ok(())
    }
}

impl ModelParams {
    /// The same plant with every inertial and gravity parameter scaled by `factor` (a model
    /// error for computed torque experiments).
    pub(crate) fn scaled(&self, factor: f64) -> Self {
        let mut p = *self;
        for k in [
            &mut p.k1, &mut p.k2, &mut p.k3, &mut p.k4, &mut p.k5, &mut p.k7, &mut p.k8, &mut p.k9,
        ] {
            *k *= factor;
        }
        for r in &mut p.rotor_inertia {
            *r *= factor;
        }
        p
    }
}

/// Sines and cosines of q2 and q3, computed once per model evaluation, both angles in one
/// two-lane `wide` call (the simulator evaluates the model 16 times a tick; two libm `sin_cos`
/// calls were a tenth of the servo thread's time). Agrees with libm to a few 1e-16.
struct Trig {
    s2: f64,
    c2: f64,
    s3: f64,
    c3: f64,
}

impl Trig {
    fn new(q: &Joint3) -> Self {
        let (s, c) = f64x2::new([q[1], q[2]]).sin_cos();
        let ([s2, s3], [c2, c3]) = (s.to_array(), c.to_array());
        Trig { s2, c2, s3, c3 }
    }
}

/// The model evaluated on joint states. `payload_kg` is a point mass at the tip.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dynamics {
    pub(crate) params: ModelParams,
    pub(crate) geometry: Geometry,
    pub(crate) payload_kg: f64,
    /// Include viscous and Coulomb friction.
    pub(crate) friction: bool,
}

impl Dynamics {
    /// The model with these parameters and this geometry: no payload, friction included.
    pub fn new(params: ModelParams, geometry: Geometry) -> Self {
        Dynamics {
            params,
            geometry,
            payload_kg: 0.0,
            friction: true,
        }
    }

    /// Joint-space inertia M(q), kg·m² (symmetric positive definite).
    pub fn mass(&self, q: &Joint3) -> Mat3 {
        self.mass_with(q, &Trig::new(q))
    }

    /// Coriolis/centrifugal matrix C(q, q̇) with Ṁ − 2C skew-symmetric.
    pub fn coriolis(&self, q: &Joint3, qd: &Joint3) -> Mat3 {
        self.coriolis_with(q, qd, &Trig::new(q))
    }

    /// Gravity torque G(q) = ∂V/∂q, N·m.
    pub fn gravity(&self, q: &Joint3) -> Joint3 {
        self.gravity_with(q, &Trig::new(q))
    }

    fn mass_with(&self, q: &Joint3, t: &Trig) -> Mat3 {
        let p = &self.params;
        let cos_2q2 = t.c2 * t.c2 - t.s2 * t.s2;
        let cos_2q3 = t.c3 * t.c3 - t.s3 * t.s3;
        let m11 = p.k1 + p.k2 * cos_2q2 + p.k3 * cos_2q3 + p.k4 * t.c2 * t.s3;
        // sin(q2 − q3)
        let m23 = -0.5 * p.k4 * (t.s2 * t.c3 - t.c2 * t.s3);
        let mut m = Mat3::new(
            m11 + p.rotor_inertia[0],
            0.0,
            0.0,
            0.0,
            p.k5 + p.rotor_inertia[1],
            m23,
            0.0,
            m23,
            p.k7 + p.rotor_inertia[2],
        );
        if self.payload_kg != 0.0 {
            let j = jacobian(&self.geometry, q);
            m += self.payload_kg * j.transpose() * j;
        }
        m
    }

    fn coriolis_with(&self, q: &Joint3, qd: &Joint3, t: &Trig) -> Mat3 {
        let p = &self.params;
        let (s2, c2, s3, c3) = (t.s2, t.c2, t.s3, t.c3);
        let a = -(p.k2 * 2.0 * s2 * c2 + 0.5 * p.k4 * s2 * s3);
        let b = 0.5 * p.k4 * c2 * c3 - p.k3 * 2.0 * s3 * c3;
        // cos(q2 − q3)
        let h = 0.5 * p.k4 * (c2 * c3 + s2 * s3);
        let (w1, w2, w3) = (qd[0], qd[1], qd[2]);
        let mut c = Mat3::new(
            a * w2 + b * w3,
            a * w1,
            b * w1,
            -a * w1,
            0.0,
            h * w3,
            -b * w1,
            -h * w2,
            0.0,
        );
        if self.payload_kg != 0.0 {
            let j = jacobian(&self.geometry, q);
            let jd = jacobian_dot(&self.geometry, q, qd);
            c += self.payload_kg * j.transpose() * jd;
        }
        c
    }

    fn gravity_with(&self, q: &Joint3, t: &Trig) -> Joint3 {
        let p = &self.params;
        let mut g = Joint3::new(0.0, p.k8 * t.c2, p.k9 * t.s3);
        if self.payload_kg != 0.0 {
            // V = m·g·y with y the tip height: G = m·g·(∂y/∂q).
            let j = jacobian(&self.geometry, q);
            g += self.payload_kg * GRAVITY * j.row(1).transpose();
        }
        g
    }

    /// Potential energy V(q), J (up to a constant).
    pub(crate) fn potential(&self, q: &Joint3) -> f64 {
        let p = &self.params;
        let mut v = p.k8 * q[1].sin() - p.k9 * q[2].cos();
        if self.payload_kg != 0.0 {
            v += self.payload_kg * GRAVITY * tip_position_mm(&self.geometry, q)[1] * 1e-3;
        }
        v
    }

    /// Kinetic energy ½ q̇ᵀ M q̇, J.
    pub(crate) fn kinetic(&self, q: &Joint3, qd: &Joint3) -> f64 {
        0.5 * qd.dot(&(self.mass(q) * qd))
    }

    /// Friction torque (opposing motion), N·m: viscous plus tanh-smoothed Coulomb.
    pub(crate) fn friction_torque(&self, qd: &Joint3) -> Joint3 {
        if !self.friction {
            return Joint3::zeros();
        }
        let p = &self.params;
        Joint3::from_fn(|i, _| {
            p.viscous[i] * qd[i] + p.coulomb[i] * tanh(qd[i] / p.coulomb_velocity)
        })
    }

    /// Torque the joint-limit springs apply (zero inside the limits), N·m.
    pub(crate) fn limit_torque(&self, q: &Joint3, qd: &Joint3) -> Joint3 {
        let p = &self.params;
        Joint3::from_fn(|i, _| {
            let over = if q[i] < p.limit_lower[i] {
                q[i] - p.limit_lower[i]
            } else if q[i] > p.limit_upper[i] {
                q[i] - p.limit_upper[i]
            } else {
                return 0.0;
            };
            -p.limit_stiffness * over - p.limit_damping * qd[i]
        })
    }

    /// Torque needed for acceleration `qdd`: M q̈ + C q̇ + G (+ friction).
    pub(crate) fn inverse_dynamics(&self, q: &Joint3, qd: &Joint3, qdd: &Joint3) -> Joint3 {
        let t = Trig::new(q);
        self.mass_with(q, &t) * qdd
            + self.coriolis_with(q, qd, &t) * qd
            + self.gravity_with(q, &t)
            + self.friction_torque(qd)
    }

    /// Acceleration under applied torque `tau`, including joint-limit springs.
    pub(crate) fn forward_dynamics(&self, q: &Joint3, qd: &Joint3, tau: &Joint3) -> Joint3 {
        let t = Trig::new(q);
        let rhs = tau + self.limit_torque(q, qd)
            - self.coriolis_with(q, qd, &t) * qd
            - self.gravity_with(q, &t)
            - self.friction_torque(qd);
        let m = self.mass_with(q, &t);
        if self.payload_kg == 0.0 {
            return solve_base_decoupled(&m, &rhs);
        }
        // M is SPD by construction; Cholesky cannot fail for valid parameters, and a config
        // that made it fail is rejected by validation. Fall back to zero acceleration anyway.
        match m.cholesky() {
            Some(ch) => ch.solve(&rhs),
            None => Joint3::zeros(),
        }
    }
}

/// Solve M·x = r for the Omni's own inertia, in which the base joint is decoupled:
/// M = [[m11, 0, 0], [0, m22, m23], [0, m23, m33]]. One division and a 2×2 block (the simulator
/// solves this 16 times a tick). Zero, like the Cholesky path, if M is not positive definite.
fn solve_base_decoupled(m: &Mat3, r: &Joint3) -> Joint3 {
    let (m11, m22, m23, m33) = (m[(0, 0)], m[(1, 1)], m[(1, 2)], m[(2, 2)]);
    let det = m22 * m33 - m23 * m23;
    if !(m11 > 0.0 && m22 > 0.0 && det > 0.0) {
        return Joint3::zeros();
    }
    Joint3::new(
        r[0] / m11,
        (m33 * r[1] - m23 * r[2]) / det,
        (m22 * r[2] - m23 * r[1]) / det,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> Dynamics {
        Dynamics::new(ModelParams::default(), Geometry::default())
    }

    fn workspace_grid() -> Vec<Joint3> {
        let mut v = Vec::new();
        for i in 0..7 {
            for j in 0..7 {
                for k in 0..7 {
                    v.push(Joint3::new(
                        -0.98 + 1.96 * i as f64 / 6.0,
                        0.0 + 1.75 * j as f64 / 6.0,
                        -0.6 + 1.8 * k as f64 / 6.0,
                    ));
                }
            }
        }
        v
    }

    #[test]
    fn mass_is_symmetric_positive_definite_over_the_workspace() {
        for payload in [0.0, 0.05] {
            let mut d = model();
            d.payload_kg = payload;
            for q in workspace_grid() {
                let m = d.mass(&q);
                assert!((m - m.transpose()).abs().max() < 1e-15);
                let eig = m.symmetric_eigenvalues();
                assert!(eig.min() > 5e-4, "min eigenvalue {} at {q:?}", eig.min());
            }
        }
    }

    #[test]
    fn mdot_minus_two_c_is_skew_symmetric() {
        for payload in [0.0, 0.02] {
            let mut d = model();
            d.payload_kg = payload;
            let qd = Joint3::new(0.9, -1.3, 0.7);
            for q in workspace_grid().into_iter().step_by(17) {
                let h = 1e-6;
                let mdot = (d.mass(&(q + qd * h)) - d.mass(&(q - qd * h))) / (2.0 * h);
                let n = mdot - 2.0 * d.coriolis(&q, &qd);
                let asym = (n + n.transpose()).abs().max();
                assert!(asym < 1e-9, "Ṁ−2C not skew: {asym} at {q:?}");
            }
        }
    }

    #[test]
    fn gravity_is_the_gradient_of_the_potential() {
        for payload in [0.0, 0.02] {
            let mut d = model();
            d.payload_kg = payload;
            for q in workspace_grid().into_iter().step_by(11) {
                let h = 1e-6;
                let fd = Joint3::from_fn(|i, _| {
                    let mut qp = q;
                    let mut qm = q;
                    qp[i] += h;
                    qm[i] -= h;
                    (d.potential(&qp) - d.potential(&qm)) / (2.0 * h)
                });
                assert!((fd - d.gravity(&q)).abs().max() < 1e-9);
            }
        }
    }

    #[test]
    fn decoupled_solve_agrees_with_cholesky_over_the_workspace() {
        let d = model();
        let r = Joint3::new(0.03, -0.05, 0.02);
        for q in workspace_grid() {
            let m = d.mass(&q);
            assert_eq!(
                (m[(0, 1)], m[(0, 2)]),
                (0.0, 0.0),
                "base joint coupled at {q:?}"
            );
            let want = m.cholesky().unwrap().solve(&r);
            let got = solve_base_decoupled(&m, &r);
            assert!((got - want).norm() <= 1e-12 * want.norm(), "at {q:?}");
        }
        assert_eq!(solve_base_decoupled(&Mat3::zeros(), &r), Joint3::zeros());
    }

    #[test]
    fn forward_dynamics_inverts_inverse_dynamics_with_a_payload() {
        let mut d = model();
        d.payload_kg = 0.02;
        let q = Joint3::new(0.2, 0.6, 0.3);
        let qd = Joint3::new(0.4, -0.2, 0.8);
        let qdd = Joint3::new(3.0, -2.0, 1.0);
        let tau = d.inverse_dynamics(&q, &qd, &qdd);
        assert!((d.forward_dynamics(&q, &qd, &tau) - qdd).norm() < 1e-9);
    }

    #[test]
    fn trig_agrees_with_libm() {
        // Over the joints' range and well beyond it (a joint pushed through its limit spring).
        let mut worst: f64 = 0.0;
        for i in -100_000..=100_000 {
            let a = i as f64 * 1e-4; // −10 … 10 rad
            let t = Trig::new(&Joint3::new(0.0, a, -0.5 * a));
            for (got, want) in [
                (t.s2, a.sin()),
                (t.c2, a.cos()),
                (t.s3, (-0.5 * a).sin()),
                (t.c3, (-0.5 * a).cos()),
            ] {
                worst = worst.max((got - want).abs());
            }
        }
        assert!(worst < 5e-16, "worst absolute error {worst:e}");
    }

    #[test]
    fn forward_dynamics_inverts_inverse_dynamics() {
        let d = model();
        let q = Joint3::new(0.2, 0.6, 0.3);
        let qd = Joint3::new(0.4, -0.2, 0.8);
        let qdd = Joint3::new(3.0, -2.0, 1.0);
        let tau = d.inverse_dynamics(&q, &qd, &qdd);
        assert!((d.forward_dynamics(&q, &qd, &tau) - qdd).norm() < 1e-9);
    }
}
