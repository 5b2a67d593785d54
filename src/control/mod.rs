//! Control: reference trajectories and the controllers that turn (estimate, reference) into
//! joint torque. Every controller is behind one trait and chosen by flag.

pub mod ct;
pub mod nnidc;
pub mod pd;
pub mod reference;

pub use ct::{ComputedTorque, OuterLoop};
pub use nnidc::Nnidc;
pub use pd::{Off, Pd};
pub use reference::{RefPoint, Reference, Trajectory};

use crate::estimate::kalman::Estimate;
use crate::ident::Identifier;
use crate::omni::Joint3;

/// What a controller sees each tick.
#[derive(Debug, Clone, Copy)]
pub struct ControlInput<'a> {
    /// Seconds since the run started.
    pub t: f64,
    pub estimate: &'a Estimate,
    pub reference: &'a RefPoint,
}

/// A joint-torque control law. Called once per tick inside the 1 kHz loop: it must not
/// allocate, lock, log or block. `learned` is the online identifier (after this tick's
/// update), for the laws that use the learned model.
pub trait Controller: Send {
    fn name(&self) -> &'static str;
    fn torque(&mut self, input: &ControlInput, learned: Option<&mut Identifier>) -> Joint3;
}

/// Controllers selectable with `--controller`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ControllerKind {
    Pd,
    Nnidc,
    Ct,
    Off,
}

impl ControllerKind {
    pub fn as_str(self) -> &'static str {
        match self {
            ControllerKind::Pd => "pd",
            ControllerKind::Nnidc => "nnidc",
            ControllerKind::Ct => "ct",
            ControllerKind::Off => "off",
        }
    }
}
