//! A control law that turns faulty on purpose (`--inject nan@T`), to test that the safety layer
//! catches a non-finite output.

use super::{ControlInput, Controller};
use crate::estimate::kalman::Estimate;
use crate::identifier::Identifier;
use crate::omni::Joint3;

/// A controller whose output turns non-finite from time T on (`nan@T`).
pub(crate) struct NanAfter {
    pub(crate) inner: Box<dyn Controller>,
    pub(crate) at_s: f64,
}

impl Controller for NanAfter {
    fn name(&self) -> &'static str {
        self.inner.name()
    }

    fn torque(&mut self, input: &ControlInput, learned: Option<&mut Identifier>) -> Joint3 {
        let tau = self.inner.torque(input, learned);
        if input.t >= self.at_s {
            Joint3::new(tau[0], f64::NAN, tau[2])
        } else {
            tau
        }
    }

    // The wrapped law's model stays its own: free mode and a coupling under the injection
    // compensate as the law would (the fault is in its tracking output only).
    fn compensation_at(
        &mut self,
        estimate: &Estimate,
        accel: &Joint3,
        learned: Option<&mut Identifier>,
    ) -> Joint3 {
        self.inner.compensation_at(estimate, accel, learned)
    }

    fn coupling_compensation(
        &mut self,
        estimate: &Estimate,
        learned: Option<&mut Identifier>,
    ) -> Joint3 {
        self.inner.coupling_compensation(estimate, learned)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::control::{make_controller, ControllerKind};

    #[test]
    fn the_wrapped_laws_compensation_passes_through_unchanged() {
        let cfg = Config::default();
        let x = Estimate {
            q: Joint3::new(0.2, 0.4, -0.3),
            qd: Joint3::new(0.5, -0.2, 0.1),
            qdd: Joint3::zeros(),
        };
        let mut ct = make_controller(ControllerKind::Ct, &cfg);
        let want = ct.compensation(&x, None);
        let want_coupling = ct.coupling_compensation(&x, None);
        assert!(want.norm() > 1e-3, "CT compensates gravity: {want}");
        let mut faulty = NanAfter {
            inner: make_controller(ControllerKind::Ct, &cfg),
            at_s: 0.0,
        };
        assert_eq!(faulty.compensation(&x, None), want);
        assert_eq!(faulty.coupling_compensation(&x, None), want_coupling);
    }
}
