//! Control: reference trajectories and the controllers that turn (estimate, reference) into
//! joint torque. Every controller is behind one trait and chosen by flag.

pub mod ct;
pub mod nnidc;
pub mod pd;
pub mod reference;
pub mod set;

pub use ct::{ComputedTorque, OuterLoop};
pub use nnidc::Nnidc;
pub use pd::{Off, Pd};
pub use reference::{RefPoint, Reference, Trajectory};
pub use set::ControllerSet;

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

    /// The law's own model of what holds the arm up and drags on it (gravity, Coriolis and
    /// friction at zero commanded acceleration): what free mode sends, so the arm feels
    /// weightless. Laws without a model compensate nothing.
    fn compensation(&mut self, _estimate: &Estimate, _learned: Option<&mut Identifier>) -> Joint3 {
        Joint3::zeros()
    }
}

/// A fresh law of `kind` from the config.
pub fn make_controller(kind: ControllerKind, cfg: &crate::config::Config) -> Box<dyn Controller> {
    match kind {
        ControllerKind::Pd => Box::new(Pd::from_config(cfg)),
        ControllerKind::Off => Box::new(Off),
        ControllerKind::Ct => Box::new(ComputedTorque::from_config(cfg)),
        ControllerKind::Nnidc => Box::new(Nnidc::from_config(cfg)),
    }
}

/// Controllers selectable with `--controller`.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum ControllerKind {
    Pd,
    Nnidc,
    Ct,
    Off,
}

impl ControllerKind {
    pub const ALL: [ControllerKind; 4] = [
        ControllerKind::Pd,
        ControllerKind::Nnidc,
        ControllerKind::Ct,
        ControllerKind::Off,
    ];

    pub fn parse(s: &str) -> Option<ControllerKind> {
        ControllerKind::ALL.into_iter().find(|k| k.as_str() == s)
    }

    pub fn as_str(self) -> &'static str {
        match self {
            ControllerKind::Pd => "pd",
            ControllerKind::Nnidc => "nnidc",
            ControllerKind::Ct => "ct",
            ControllerKind::Off => "off",
        }
    }
}
