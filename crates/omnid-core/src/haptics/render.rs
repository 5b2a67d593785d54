//! The haptic step of the servo loop (docs/HAPTICS.md §2–§6): the tip's position and velocity
//! from the measured pose, the scene's effects plus a client's force, the passivity
//! controller, the peak clamp, and τ = Jᵀ F. Fixed-size state only: it runs every tick.

use super::effects::{Effect, Scene};
use super::passivity::Passivity;
use super::{limit_force, tip_force_torque, Force3, HapticsConfig};
use crate::omni::{jacobian, tip_position_mm, Geometry, Joint3};

/// The continuous-force limit (docs/HAPTICS.md §2): the mean square of the tip force over
/// `time_s`, in units of the continuous force squared; at 1 the force is held to the
/// continuous force until the level falls to 0.9 (a hand pressing hard for long gets the
/// continuous force, never a cut).
#[derive(Debug, Clone, Copy)]
struct Continuous {
    force_n: f64,
    time_s: f64,
    level: f64,
    holding: bool,
}

impl Continuous {
    /// `f`, held to the continuous force while the mean square is over it.
    fn limit(&mut self, f: &Force3, dt: f64) -> Force3 {
        let out = if self.holding {
            limit_force(f, self.force_n)
        } else {
            *f
        };
        if self.force_n > 0.0 {
            let ratio = out.norm_squared() / (self.force_n * self.force_n);
            self.level += (ratio - self.level) * (dt / self.time_s).min(1.0);
        }
        if self.level >= 1.0 {
            self.holding = true;
        } else if self.level < 0.9 {
            self.holding = false;
        }
        out
    }
}

#[derive(Debug, Clone, Copy)]
pub(crate) struct HapticLoop {
    geometry: Geometry,
    max_force_n: f64,
    scene: Scene,
    passivity: Passivity,
    continuous: Continuous,
    /// The tip at the last tick, mm (OpenHaptics frame), and the force commanded there, N.
    pub(crate) tip_mm: [f64; 3],
    pub(crate) force: [f64; 3],
    /// What acted on this tick's force: `flags::FORCE_LIMIT` (held to the peak or the
    /// continuous force), `flags::EFFECT_SKIPPED`.
    pub(crate) flags: u32,
    /// Each slot's effect kind and the tip's depth into its wall this tick, m (None: no effect
    /// in the slot, or effects not rendered this tick), for the run's summary.
    pub(crate) depths: [Option<(&'static str, Option<f64>)>; super::effects::MAX_EFFECTS],
}

impl HapticLoop {
    pub(crate) fn new(cfg: &HapticsConfig, geometry: Geometry) -> HapticLoop {
        HapticLoop {
            geometry,
            max_force_n: cfg.max_force_n,
            scene: Scene::new(cfg.fade_s),
            passivity: Passivity::new(
                cfg.passivity,
                cfg.passivity_max_damping_n_s_per_m,
                cfg.passivity_reserve_j,
            ),
            continuous: Continuous {
                force_n: cfg.continuous_force_n,
                time_s: cfg.continuous_time_s,
                level: 0.0,
                holding: false,
            },
            tip_mm: [0.0; 3],
            force: [0.0; 3],
            flags: 0,
            depths: [None; super::effects::MAX_EFFECTS],
        }
    }

    /// Put `effect` in `slot` (None removes it), faded in from time `t`.
    pub(crate) fn set_effect(&mut self, slot: usize, effect: Option<Effect>, t: f64) {
        self.scene.set(slot, effect, t);
    }

    /// Turn the passivity controller on or off (the observer keeps observing).
    pub(crate) fn set_passivity(&mut self, on: bool) {
        self.passivity.enabled = on;
    }

    /// The passivity controller added damping at this tick (it is taking energy back).
    pub(crate) fn dissipating(&self) -> bool {
        self.passivity.damping > 0.0
    }

    /// A tick without haptics (another mode): note where the tip is, for the log, and start
    /// the passivity observer afresh when haptics resume.
    pub(crate) fn observe(&mut self, q: &Joint3) {
        self.tip_mm = tip_position_mm(&self.geometry, q).into();
        self.force = [0.0; 3];
        self.depths = [None; super::effects::MAX_EFFECTS];
        self.passivity.reset();
    }

    /// The joint torque of this tick's tip force: the effects (`effects`: rendered in this
    /// mode) at the measured pose `q` with the estimated joint velocity `qd`, through the
    /// passivity controller, plus a client's force `stream`, clamped to the peak.
    pub(crate) fn torque(
        &mut self,
        t: f64,
        dt: f64,
        q: &Joint3,
        qd: &Joint3,
        stream: &Force3,
        effects: bool,
    ) -> Joint3 {
        let p = tip_position_mm(&self.geometry, q) * 1e-3;
        let v = jacobian(&self.geometry, q) * qd;
        let (watched, constant) = if effects {
            self.depths = self.scene.depths(&p);
            self.scene.split(t, &p, &v)
        } else {
            self.depths = [None; super::effects::MAX_EFFECTS];
            (Force3::zeros(), Force3::zeros())
        };
        let rendered = self.passivity.step(&p, &watched, dt) + constant;
        let asked = rendered + stream;
        let f = limit_force(&asked, self.max_force_n);
        let f = self.continuous.limit(&f, dt);
        // Visible when it acts: the log's flags, and an event at its start (the servo).
        use crate::telemetry::record::flags;
        self.flags = 0;
        if super::held_back(&asked, &f) {
            self.flags |= flags::FORCE_LIMIT;
        }
        if self.scene.skipped {
            self.flags |= flags::EFFECT_SKIPPED;
        }
        self.tip_mm = (p * 1e3).into();
        self.force = f.into();
        tip_force_torque(&self.geometry, q, &f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_hard_push_is_held_to_the_continuous_force() {
        let cfg = HapticsConfig::default();
        let g = Geometry::default();
        let mut h = HapticLoop::new(&cfg, g);
        let q = Joint3::new(0.0, 0.65, 0.3);
        let push = Force3::new(0.0, -2.0, 0.0);
        let mut first_held = None;
        for k in 0..20_000 {
            h.torque(k as f64 * 1e-3, 1e-3, &q, &Joint3::zeros(), &push, false);
            let f = Force3::from(h.force).norm();
            if f < 1.99 && first_held.is_none() {
                first_held = Some(k);
                // Held to the continuous force, not cut.
                assert!((f - 0.88).abs() < 1e-9, "{f}");
            }
        }
        // 2 N against 0.88 N continuous with a 10 s mean square: held after about
        // −10 s · ln(1 − 0.88²/2²) ≈ 2.1 s, and still held after 20 s (the level stays up).
        let k = first_held.expect("the force was held");
        assert!((1_900..2_400).contains(&k), "held after {k} ticks");
        assert!((Force3::from(h.force).norm() - 0.88).abs() < 1e-9);
        // A brief peak passes untouched.
        let mut fresh = HapticLoop::new(&cfg, g);
        for k in 0..500 {
            fresh.torque(k as f64 * 1e-3, 1e-3, &q, &Joint3::zeros(), &push, false);
        }
        assert!((Force3::from(fresh.force).norm() - 2.0).abs() < 1e-9);
    }
}
