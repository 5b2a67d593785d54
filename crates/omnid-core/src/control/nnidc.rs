//! NNIDC (paper Fig. 7, docs/DESIGN.md §3): the inverse-dynamics law with the networks' model,
//! τ = M̂(q)·v + Ĉ(q, q̇)·q̇ + Ĝ(q) + F̂(q̇), v = q̈_d + K_d(q̇_d − q̇) + K_p(q_d − q),
//! while the identifier keeps learning. When the identifier has stopped on a non-finite value
//! (or there is none), it falls back to the PD baseline until the operator resets.

use super::ct::OuterLoop;
use super::pd::Pd;
use super::ControlSetup;
use super::{ControlInput, Controller};
use crate::identifier::Identifier;
use crate::omni::Joint3;

pub(crate) struct Nnidc {
    gains: OuterLoop,
    fallback: Pd,
    /// Set once the law has fallen back to PD (read by the tests only).
    #[cfg(test)]
    fell_back: bool,
}

impl Nnidc {
    pub(crate) fn from_config<'a>(cfg: impl Into<ControlSetup<'a>>) -> Self {
        let cfg = cfg.into();
        Nnidc {
            gains: OuterLoop::from_config(cfg),
            fallback: Pd::from_config(cfg),
            #[cfg(test)]
            fell_back: false,
        }
    }

    /// True once the law has had to fall back to PD in this run.
    #[cfg(test)]
    pub(crate) fn fell_back(&self) -> bool {
        self.fell_back
    }
}

impl Controller for Nnidc {
    fn name(&self) -> &'static str {
        "nnidc"
    }

    fn torque(&mut self, input: &ControlInput, learned: Option<&mut Identifier>) -> Joint3 {
        match learned {
            Some(id) if id.healthy() => {
                let x = input.estimate;
                let v = self.gains.acceleration(x, input.reference);
                id.inverse_dynamics(&x.q, &x.qd, &v)
            }
            _ => {
                #[cfg(test)]
                {
                    self.fell_back = true;
                }
                self.fallback.torque(input, None)
            }
        }
    }

    fn compensation_at(
        &mut self,
        x: &crate::estimate::kalman::Estimate,
        accel: &Joint3,
        learned: Option<&mut Identifier>,
    ) -> Joint3 {
        match learned {
            Some(id) if id.healthy() => id.inverse_dynamics(&x.q, &x.qd, accel),
            // The PD fallback has no model to compensate with.
            _ => Joint3::zeros(),
        }
    }

    /// Ĝ + Ĉ q̇ without the learned friction F̂ (docs/TELEOP.md §2): at the near-rest,
    /// noisy q̇ of a contact, F̂ (a learned Coulomb step) cancels the plant's own friction,
    /// the pair's damping, and a pf pair pressing 1 N into 1 N/mm vibrated at about 37 Hz.
    /// Computed torque compensates no friction either (`ct_friction` off by default).
    fn coupling_compensation(
        &mut self,
        x: &crate::estimate::kalman::Estimate,
        learned: Option<&mut Identifier>,
    ) -> Joint3 {
        match learned {
            Some(id) if id.healthy() => id.gravity_coriolis(&x.q, &x.qd),
            _ => Joint3::zeros(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::control::RefPoint;
    use crate::estimate::kalman::Estimate;

    fn input_parts() -> (Estimate, RefPoint) {
        let r = RefPoint {
            q: Joint3::new(0.1, 0.7, 0.2),
            qd: Joint3::new(0.3, -0.2, 0.1),
            qdd: Joint3::new(1.0, 0.5, -0.4),
        };
        let x = Estimate {
            q: r.q + Joint3::new(0.01, -0.02, 0.0),
            qd: r.qd,
            qdd: Joint3::zeros(),
        };
        (x, r)
    }

    #[test]
    fn uses_the_learned_inverse_dynamics() {
        let cfg = Config::default();
        let mut id = Identifier::new(&cfg.identifier).unwrap();
        let mut c = Nnidc::from_config(&cfg);
        let (x, r) = input_parts();
        let input = ControlInput {
            t: 0.0,
            estimate: &x,
            reference: &r,
        };
        let tau = c.torque(&input, Some(&mut id));
        let v = OuterLoop::from_config(&cfg).acceleration(&x, &r);
        assert_eq!(tau, id.inverse_dynamics(&x.q, &x.qd, &v));
        assert!(!c.fell_back());
    }

    #[test]
    fn a_couplings_compensation_is_the_learned_gravity_and_coriolis_without_friction() {
        // Shipped weights (a friction network that is not zero), the compensation against the
        // networks evaluated one by one.
        let cfg = Config::default();
        let (mut id, _) = crate::cmd::assembly::make_identifier(
            &cfg,
            crate::control::ControllerKind::Nnidc,
            None,
            false,
            None,
        )
        .unwrap();
        let mut c = Nnidc::from_config(&cfg);
        let (x, _) = input_parts();
        let coupled = c.coupling_compensation(&x, Some(&mut id));
        let free = c.compensation(&x, Some(&mut id));
        // The learned rest torque is Ĝ + F̂(0) (the G- and F-nets share a constant).
        let expected =
            id.gravity(&x.q) + id.coriolis(&x.q, &x.qd) * x.qd + id.friction(&Joint3::zeros());
        assert!(
            (coupled - expected).norm() < 1e-12,
            "{coupled} vs {expected}"
        );
        let friction = id.friction(&x.qd) - id.friction(&Joint3::zeros());
        assert!(
            friction.norm() > 1e-4,
            "the test needs a friction: {friction}"
        );
        assert!((free - coupled - friction).norm() < 1e-12);
    }

    #[test]
    fn falls_back_to_pd_without_a_healthy_identifier() {
        let cfg = Config::default();
        let mut id = Identifier::new(&cfg.identifier).unwrap();
        let (x, r) = input_parts();
        let input = ControlInput {
            t: 0.0,
            estimate: &x,
            reference: &r,
        };
        // A non-finite input trips the identifier's guard.
        let nan = Joint3::repeat(f64::NAN);
        id.update(&x.q, &x.qd, &nan, &Joint3::zeros(), 1e-3);
        assert!(!id.healthy());
        let mut c = Nnidc::from_config(&cfg);
        let tau = c.torque(&input, Some(&mut id));
        let pd = Pd::from_config(&cfg).torque(&input, None);
        assert_eq!(tau, pd);
        assert!(c.fell_back());
    }
}
