//! A control law that turns faulty on purpose (`--inject nan@T`), to test that the safety layer
//! catches a non-finite output.

use super::{ControlInput, Controller};
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
}
