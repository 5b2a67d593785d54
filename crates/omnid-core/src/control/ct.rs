//! Computed torque (docs/DESIGN.md §3): the inverse-dynamics law with the rigid-body parametric
//! model, τ = M(q)·v + C(q, q̇)·q̇ + G(q) (+ friction), v = q̈_d + K_d(q̇_d − q̇) + K_p(q_d − q).
//! What a lab with an identified parametric model would run; the oracle NNIDC is measured
//! against on the simulator.

use super::ControlSetup;
use super::{ControlInput, Controller, RefPoint};
use crate::estimate::kalman::Estimate;
use crate::identifier::Identifier;
use crate::omni::{Dynamics, Joint3};

/// Outer-loop gains of the inverse-dynamics laws: K_p = ω², K_d = 2ζω (per unit inertia).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct OuterLoop {
    pub(crate) kp: f64,
    pub(crate) kd: f64,
}

impl OuterLoop {
    pub(crate) fn from_config<'a>(cfg: impl Into<ControlSetup<'a>>) -> Self {
        let cfg = cfg.into();
        let w = cfg.control.omega_n;
        OuterLoop {
            kp: w * w,
            kd: 2.0 * cfg.control.zeta * w,
        }
    }

    /// The commanded acceleration v = q̈_d + K_d(q̇_d − q̇) + K_p(q_d − q).
    pub(crate) fn acceleration(&self, x: &Estimate, r: &RefPoint) -> Joint3 {
        r.qdd + (r.qd - x.qd) * self.kd + (r.q - x.q) * self.kp
    }
}

pub(crate) struct ComputedTorque {
    model: Dynamics,
    gains: OuterLoop,
}

impl ComputedTorque {
    pub(crate) fn new(model: Dynamics, gains: OuterLoop) -> Self {
        ComputedTorque { model, gains }
    }

    /// CT with the configured model: the plant's parameters scaled by `ct_model_scale`,
    /// friction compensation as configured.
    pub(crate) fn from_config<'a>(cfg: impl Into<ControlSetup<'a>>) -> Self {
        let cfg = cfg.into();
        let mut model = Dynamics::new(cfg.model.scaled(cfg.control.ct_model_scale), *cfg.geometry);
        model.friction = cfg.control.ct_friction;
        ComputedTorque::new(model, OuterLoop::from_config(cfg))
    }
}

impl Controller for ComputedTorque {
    fn name(&self) -> &'static str {
        "ct"
    }

    fn torque(&mut self, input: &ControlInput, _learned: Option<&mut Identifier>) -> Joint3 {
        let x = input.estimate;
        let v = self.gains.acceleration(x, input.reference);
        self.model.inverse_dynamics(&x.q, &x.qd, &v)
    }

    fn compensation_at(
        &mut self,
        x: &Estimate,
        accel: &Joint3,
        _learned: Option<&mut Identifier>,
    ) -> Joint3 {
        self.model.inverse_dynamics(&x.q, &x.qd, accel)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;

    #[test]
    fn on_the_reference_ct_is_the_model_inverse_dynamics() {
        let cfg = Config::default();
        let mut ct = ComputedTorque::from_config(&cfg);
        let r = RefPoint {
            q: Joint3::new(0.1, 0.7, 0.2),
            qd: Joint3::new(0.3, -0.2, 0.1),
            qdd: Joint3::new(1.0, 0.5, -0.4),
        };
        let x = Estimate {
            q: r.q,
            qd: r.qd,
            qdd: Joint3::zeros(),
        };
        let tau = ct.torque(
            &ControlInput {
                t: 0.0,
                estimate: &x,
                reference: &r,
            },
            None,
        );
        let mut plant = Dynamics::new(cfg.model, cfg.geometry);
        plant.friction = false;
        assert!((tau - plant.inverse_dynamics(&r.q, &r.qd, &r.qdd)).norm() < 1e-15);
    }

    #[test]
    fn error_feedback_is_scaled_by_the_inertia() {
        let cfg = Config::default();
        let mut ct = ComputedTorque::from_config(&cfg);
        let r = RefPoint {
            q: Joint3::new(0.0, 0.7, 0.3),
            ..Default::default()
        };
        let x = Estimate {
            q: r.q - Joint3::new(0.01, 0.0, 0.0),
            ..Default::default()
        };
        let tau = ct.torque(
            &ControlInput {
                t: 0.0,
                estimate: &x,
                reference: &r,
            },
            None,
        );
        let plant = Dynamics::new(cfg.model, cfg.geometry);
        let m = plant.mass(&x.q);
        let g = plant.gravity(&x.q);
        let expected = m * Joint3::new(0.01 * 625.0, 0.0, 0.0) + g;
        assert!((tau - expected).norm() < 1e-12, "{tau} vs {expected}");
    }
}
