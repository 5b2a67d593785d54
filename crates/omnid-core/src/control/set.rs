//! Every control law built before the loop starts, one of them active. A switch at run time is
//! bumpless: for `fade_s` seconds the output crossfades (quintic weight) from the old law to
//! the new one, both evaluated each tick, so the torque moves smoothly instead of stepping and
//! leaning on the safety layer's kick limit.

use super::reference::quintic;
use super::ControlSetup;
use super::{ControlInput, Controller, ControllerKind};
use crate::estimate::kalman::Estimate;
use crate::identifier::Identifier;
use crate::omni::Joint3;

/// The four control laws, all built before the first tick, one of them active; a switch
/// crossfades from the old law to the new one.
pub struct ControllerSet {
    /// Indexed by `slot(kind)`.
    laws: [Box<dyn Controller>; 4],
    active: ControllerKind,
    /// The law being faded out and the time the switch began.
    fading: Option<(ControllerKind, f64)>,
    fade_s: f64,
}

fn slot(kind: ControllerKind) -> usize {
    match kind {
        ControllerKind::Pd => 0,
        ControllerKind::Nnidc => 1,
        ControllerKind::Ct => 2,
        ControllerKind::Off => 3,
    }
}

impl ControllerSet {
    /// All four laws from the config, `active` in effect. `fade_s`: crossfade length of a
    /// switch (0: switch at once).
    pub fn new<'a>(cfg: impl Into<ControlSetup<'a>>, active: ControllerKind, fade_s: f64) -> Self {
        ControllerSet {
            laws: ControllerKind::ALL.map(|_| Box::new(super::Off) as Box<dyn Controller>),
            active,
            fading: None,
            fade_s,
        }
        .with_laws(cfg.into())
    }

    fn with_laws(mut self, cfg: ControlSetup) -> Self {
        for kind in ControllerKind::ALL {
            self.laws[slot(kind)] = super::make_controller(kind, cfg);
        }
        self
    }

    /// Put `law` in `kind`'s place (fault injection wraps a law this way).
    pub(crate) fn replace(&mut self, kind: ControllerKind, law: Box<dyn Controller>) {
        self.laws[slot(kind)] = law;
    }

    /// Take `kind`'s law out, leaving `Off` in its place.
    pub(crate) fn take(&mut self, kind: ControllerKind) -> Box<dyn Controller> {
        std::mem::replace(&mut self.laws[slot(kind)], Box::new(super::Off))
    }

    pub(crate) fn active(&self) -> ControllerKind {
        self.active
    }

    /// True while a switch is still crossfading.
    #[cfg(test)]
    pub(crate) fn switching(&self) -> bool {
        self.fading.is_some()
    }

    /// Make `kind` the active law from time `t` on (s, the loop's clock).
    pub(crate) fn switch(&mut self, kind: ControllerKind, t: f64) {
        if kind == self.active {
            return;
        }
        // A switch during a crossfade restarts it from the law that was fading in: the output
        // then moves from (close to) where it is.
        self.fading = (self.fade_s > 0.0).then_some((self.active, t));
        self.active = kind;
    }

    /// Weight of the new law at `t`, or `None` once the crossfade is over.
    fn weight(&mut self, t: f64) -> Option<(ControllerKind, f64)> {
        let (old, t0) = self.fading?;
        let s = (t - t0) / self.fade_s;
        if s >= 1.0 {
            self.fading = None;
            return None;
        }
        Some((old, quintic(s).0))
    }

    /// The active law's torque (crossfaded during a switch).
    pub(crate) fn torque(
        &mut self,
        input: &ControlInput,
        mut learned: Option<&mut Identifier>,
    ) -> Joint3 {
        let new = self.laws[slot(self.active)].torque(input, learned.as_deref_mut());
        match self.weight(input.t) {
            None => new,
            Some((old, w)) => {
                let before = self.laws[slot(old)].torque(input, learned);
                before * (1.0 - w) + new * w
            }
        }
    }

    /// The active law's compensation (the haptic modes) at the joint acceleration `accel`
    /// (zero, or the gated fraction of q̈ of partial inertia compensation), crossfaded like
    /// [`torque`](Self::torque).
    pub(crate) fn compensation(
        &mut self,
        t: f64,
        estimate: &Estimate,
        accel: &Joint3,
        mut learned: Option<&mut Identifier>,
    ) -> Joint3 {
        let new =
            self.laws[slot(self.active)].compensation_at(estimate, accel, learned.as_deref_mut());
        match self.weight(t) {
            None => new,
            Some((old, w)) => {
                let before = self.laws[slot(old)].compensation_at(estimate, accel, learned);
                before * (1.0 - w) + new * w
            }
        }
    }

    /// The active law's compensation under a teleoperation coupling, crossfaded alike.
    pub(crate) fn coupling_compensation(
        &mut self,
        t: f64,
        estimate: &Estimate,
        mut learned: Option<&mut Identifier>,
    ) -> Joint3 {
        let new =
            self.laws[slot(self.active)].coupling_compensation(estimate, learned.as_deref_mut());
        match self.weight(t) {
            None => new,
            Some((old, w)) => {
                let before = self.laws[slot(old)].coupling_compensation(estimate, learned);
                before * (1.0 - w) + new * w
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::control::RefPoint;

    #[test]
    fn a_switch_crossfades_from_the_old_law_to_the_new() {
        let cfg = Config::default();
        let mut set = ControllerSet::new(&cfg, ControllerKind::Pd, 0.1);
        let x = Estimate {
            q: Joint3::new(0.0, 0.3, 0.1),
            qd: Joint3::zeros(),
            qdd: Joint3::zeros(),
        };
        let r = RefPoint {
            q: Joint3::new(0.05, 0.35, 0.15),
            ..RefPoint::default()
        };
        let at = |set: &mut ControllerSet, t: f64| {
            set.torque(
                &ControlInput {
                    t,
                    estimate: &x,
                    reference: &r,
                },
                None,
            )
        };
        let pd = at(&mut set, 0.0);
        assert!(pd.norm() > 0.0);
        set.switch(ControllerKind::Off, 1.0);
        assert!(set.switching());
        // At the switch the output is still the old law's; halfway it is half of it (the
        // quintic is symmetric); after the fade it is the new law's.
        assert!((at(&mut set, 1.0) - pd).norm() < 1e-15);
        assert!((at(&mut set, 1.05) - pd * 0.5).norm() < 1e-12);
        let mut last = pd;
        for k in 0..100 {
            let now = at(&mut set, 1.0 + k as f64 * 1e-3);
            // Never a step larger than the quintic's steepest slope allows (1.875/fade per s).
            assert!((now - last).amax() <= pd.amax() * 1.875 / 0.1 * 1e-3 + 1e-12);
            last = now;
        }
        assert_eq!(at(&mut set, 1.2), Joint3::zeros());
        assert!(!set.switching());
    }

    #[test]
    fn switching_to_the_active_law_does_nothing() {
        let cfg = Config::default();
        let mut set = ControllerSet::new(&cfg, ControllerKind::Ct, 0.1);
        set.switch(ControllerKind::Ct, 0.0);
        assert!(!set.switching());
        assert_eq!(set.active(), ControllerKind::Ct);
    }
}
