//! The PD baseline (docs/DESIGN.md §3): gains K_p = M₀·ω², K_d = M₀·2ζω with M₀ the nominal
//! diagonal inertia at the workspace centre, so that it is comparable with CT and NNIDC. No gravity
//! compensation: that is what the model-based controllers add.

use super::ControlSetup;
use super::{ControlInput, Controller};
use crate::identifier::Identifier;
use crate::omni::{Dynamics, Joint3};

/// Independent joint PD, τ = K_p (q_r − q) + K_d (q̇_r − q̇), gains per joint.
pub struct Pd {
    kp: Joint3,
    kd: Joint3,
}

impl Pd {
    pub(crate) fn new(kp: Joint3, kd: Joint3) -> Self {
        Pd { kp, kd }
    }

    /// The baseline gains from the config.
    pub fn from_config<'a>(cfg: impl Into<ControlSetup<'a>>) -> Self {
        let cfg = cfg.into();
        let nominal = Dynamics::new(*cfg.model, *cfg.geometry);
        let m0 = nominal.mass(&Joint3::from(cfg.reference.center)).diagonal();
        let w = cfg.control.omega_n;
        Pd::new(m0 * (w * w), m0 * (2.0 * cfg.control.zeta * w))
    }

    /// (K_p, K_d) per joint.
    #[cfg(test)]
    fn gains(&self) -> (Joint3, Joint3) {
        (self.kp, self.kd)
    }
}

impl Controller for Pd {
    fn name(&self) -> &'static str {
        "pd"
    }

    fn torque(&mut self, input: &ControlInput, _learned: Option<&mut Identifier>) -> Joint3 {
        let e = input.reference.q - input.estimate.q;
        let ed = input.reference.qd - input.estimate.qd;
        self.kp.component_mul(&e) + self.kd.component_mul(&ed)
    }
}

/// No torque: the arm hangs free (identification passes, replays).
pub(crate) struct Off;

impl Controller for Off {
    fn name(&self) -> &'static str {
        "off"
    }

    fn torque(&mut self, _input: &ControlInput, _learned: Option<&mut Identifier>) -> Joint3 {
        Joint3::zeros()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::control::RefPoint;
    use crate::estimate::kalman::Estimate;

    #[test]
    fn pd_gains_follow_the_nominal_inertia() {
        let cfg = Config::default();
        let pd = Pd::from_config(&cfg);
        let (kp, kd) = pd.gains();
        let m0 = Dynamics::new(cfg.model, cfg.geometry)
            .mass(&Joint3::from(cfg.reference.center))
            .diagonal();
        for j in 0..3 {
            assert!((kp[j] / m0[j] - 625.0).abs() < 1e-9);
            assert!((kd[j] / m0[j] - 50.0).abs() < 1e-9);
        }
    }

    #[test]
    fn pd_pushes_toward_the_reference() {
        let mut pd = Pd::new(Joint3::repeat(2.0), Joint3::repeat(0.5));
        let est = Estimate {
            q: Joint3::new(0.1, 0.0, -0.1),
            qd: Joint3::new(0.0, 1.0, 0.0),
            qdd: Joint3::zeros(),
        };
        let r = RefPoint::default();
        let tau = pd.torque(
            &ControlInput {
                t: 0.0,
                estimate: &est,
                reference: &r,
            },
            None,
        );
        assert_eq!(tau, Joint3::new(-0.2, -0.5, 0.2));
    }
}
