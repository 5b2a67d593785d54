//! Control: reference trajectories and the controllers that turn (estimate, reference) into
//! joint torque. Every controller is behind one trait and chosen by flag.

pub(crate) mod ct;
pub(crate) mod nan_after;
pub(crate) mod nnidc;
pub(crate) mod pd;
pub(crate) mod reference;
pub(crate) mod set;

pub(crate) use ct::ComputedTorque;
pub(crate) use nan_after::NanAfter;
pub(crate) use nnidc::Nnidc;
pub(crate) use pd::Off;
pub use pd::Pd;
pub use reference::{RefPoint, Reference, ReferenceConfig, Trajectory};
pub use set::ControllerSet;

use crate::config_check::{self as check, ConfigError};
use crate::estimate::kalman::Estimate;
use crate::identifier::Identifier;
use crate::omni::{Geometry, Joint3, ModelParams};
use serde::{Deserialize, Serialize};

/// `[control]`: the gains of the closed loop, shared by PD, CT and NNIDC.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ControlConfig {
    /// Closed-loop natural frequency, rad/s (K_p = ω², K_d = 2ζω, scaled by M₀ for PD).
    pub omega_n: f64,
    /// Closed-loop damping ratio.
    pub zeta: f64,
    /// Computed torque: its rigid-body model is the plant's parameters times this factor.
    pub ct_model_scale: f64,
    /// Computed torque: also compensate the model's viscous and Coulomb friction.
    pub ct_friction: bool,
}

impl Default for ControlConfig {
    fn default() -> Self {
        ControlConfig {
            omega_n: 25.0,
            zeta: 1.0,
            ct_model_scale: 1.0,
            ct_friction: false,
        }
    }
}

impl ControlConfig {
    /// Check every value; the first problem names its field (`control.…`).
    pub(crate) fn validate(&self) -> Result<(), ConfigError> {
        check::in_range(
            "control.omega_n",
            self.omega_n,
            0.1,
            200.0,
            "0.1 ..= 200 rad/s",
        )?;
        check::in_range("control.zeta", self.zeta, 0.05, 10.0, "0.05 ..= 10")?;
        check::in_range(
            "control.ct_model_scale",
            self.ct_model_scale,
            0.1,
            10.0,
            "0.1 ..= 10",
        )
    }
}

/// The sections of the configuration the control laws are built from (a `&Config` gives
/// them).
#[derive(Debug, Clone, Copy)]
pub struct ControlSetup<'a> {
    pub(crate) control: &'a ControlConfig,
    pub(crate) model: &'a ModelParams,
    pub(crate) geometry: &'a Geometry,
    /// PD's nominal inertia is taken at the reference's centre.
    pub(crate) reference: &'a ReferenceConfig,
}

/// What a controller sees each tick.
#[derive(Debug, Clone, Copy)]
pub struct ControlInput<'a> {
    /// Seconds since the run started.
    pub t: f64,
    /// The Kalman estimate of the joint state at this tick.
    pub estimate: &'a Estimate,
    /// Where the reference wants the joints at this tick.
    pub reference: &'a RefPoint,
}

/// A joint-torque control law. Called once per tick inside the 1 kHz loop: it must not
/// allocate, lock, log or block. `learned` is the online identifier (after this tick's
/// update), for the laws that use the learned model.
pub trait Controller: Send {
    /// The law's name as the log and the summary spell it (`pd`, `nnidc`, `ct`, `off`).
    fn name(&self) -> &'static str;
    /// The joint torque to command this tick, N·m.
    fn torque(&mut self, input: &ControlInput, learned: Option<&mut Identifier>) -> Joint3;

    /// The law's own model of what holds the arm up and drags on it (gravity, Coriolis and
    /// friction at zero commanded acceleration): what free mode sends, so the arm feels
    /// weightless. Laws without a model compensate nothing.
    fn compensation(&mut self, estimate: &Estimate, learned: Option<&mut Identifier>) -> Joint3 {
        self.compensation_at(estimate, &Joint3::zeros(), learned)
    }

    /// The law's model at the estimated state and the joint acceleration `accel`:
    /// M(q)·accel plus [`compensation`](Self::compensation). The haptic modes pass a gated
    /// fraction of the estimated q̈ (partial inertia compensation, docs/HAPTICS.md §3);
    /// laws without a model compensate nothing.
    fn compensation_at(
        &mut self,
        _estimate: &Estimate,
        _accel: &Joint3,
        _learned: Option<&mut Identifier>,
    ) -> Joint3 {
        Joint3::zeros()
    }

    /// What a teleoperation coupling's force is added to (docs/TELEOP.md §2): the law's
    /// compensation, unless the law says otherwise.
    fn coupling_compensation(
        &mut self,
        estimate: &Estimate,
        learned: Option<&mut Identifier>,
    ) -> Joint3 {
        self.compensation(estimate, learned)
    }
}

/// A fresh law of `kind` from the config.
pub fn make_controller<'a>(
    kind: ControllerKind,
    cfg: impl Into<ControlSetup<'a>>,
) -> Box<dyn Controller> {
    let cfg = cfg.into();
    match kind {
        ControllerKind::Pd => Box::new(Pd::from_config(cfg)),
        ControllerKind::Off => Box::new(Off),
        ControllerKind::Ct => Box::new(ComputedTorque::from_config(cfg)),
        ControllerKind::Nnidc => Box::new(Nnidc::from_config(cfg)),
    }
}

/// Controllers selectable with `--controller`: `Pd` the PD baseline ([`Pd`]), `Nnidc` inverse
/// dynamics with the identifier's learned model (PD while the identifier is stopped), `Ct`
/// computed torque with the parametric rigid-body model, `Off` no torque (the arm hangs free).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
// The variants are described in the enum's doc: a doc comment on each would become clap's
// help text for `--controller` and change `omnid run --help`.
#[allow(missing_docs)]
pub enum ControllerKind {
    Pd,
    Nnidc,
    Ct,
    Off,
}

impl ControllerKind {
    /// Every controller, in the order `--controller` lists them.
    pub const ALL: [ControllerKind; 4] = [
        ControllerKind::Pd,
        ControllerKind::Nnidc,
        ControllerKind::Ct,
        ControllerKind::Off,
    ];

    pub(crate) fn parse(s: &str) -> Option<ControllerKind> {
        ControllerKind::ALL.into_iter().find(|k| k.as_str() == s)
    }

    /// The name on the command line, in the log header and in the summary.
    pub fn as_str(self) -> &'static str {
        match self {
            ControllerKind::Pd => "pd",
            ControllerKind::Nnidc => "nnidc",
            ControllerKind::Ct => "ct",
            ControllerKind::Off => "off",
        }
    }
}
