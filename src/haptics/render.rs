//! The haptic step of the servo loop (docs/HAPTICS.md §2–§6): the tip's position and velocity
//! from the measured pose, the scene's effects plus a client's force, the passivity
//! controller, the peak clamp, and τ = Jᵀ F. Fixed-size state only: it runs every tick.

use super::effects::{Effect, Scene};
use super::passivity::Passivity;
use super::{limit_force, tip_force_torque, Force3, HapticsConfig};
use crate::omni::{jacobian, tip_position_mm, Geometry, Joint3};

#[derive(Debug, Clone, Copy)]
pub struct HapticLoop {
    geometry: Geometry,
    max_force_n: f64,
    scene: Scene,
    passivity: Passivity,
    /// The tip at the last tick, mm (OpenHaptics frame), and the force commanded there, N.
    pub tip_mm: [f64; 3],
    pub force: [f64; 3],
}

impl HapticLoop {
    pub fn new(cfg: &HapticsConfig, geometry: Geometry) -> HapticLoop {
        HapticLoop {
            geometry,
            max_force_n: cfg.max_force_n,
            scene: Scene::new(cfg.fade_s),
            passivity: Passivity::new(
                cfg.passivity,
                cfg.passivity_max_damping_n_s_per_m,
                cfg.passivity_reserve_j,
            ),
            tip_mm: [0.0; 3],
            force: [0.0; 3],
        }
    }

    /// Put `effect` in `slot` (None removes it), faded in from time `t`.
    pub fn set_effect(&mut self, slot: usize, effect: Option<Effect>, t: f64) {
        self.scene.set(slot, effect, t);
    }

    /// Turn the passivity controller on or off (the observer keeps observing).
    pub fn set_passivity(&mut self, on: bool) {
        self.passivity.enabled = on;
    }

    /// Observed energy of the effects, J, and the damping the controller added last, N·s/m.
    pub fn passivity_state(&self) -> (f64, f64) {
        (self.passivity.energy(), self.passivity.damping)
    }

    /// A tick without haptics (another mode): note where the tip is, for the log, and start
    /// the passivity observer afresh when haptics resume.
    pub fn observe(&mut self, q: &Joint3) {
        self.tip_mm = tip_position_mm(&self.geometry, q).into();
        self.force = [0.0; 3];
        self.passivity.reset();
    }

    /// The joint torque of this tick's tip force: the effects (`effects`: rendered in this
    /// mode) at the measured pose `q` with the estimated joint velocity `qd`, through the
    /// passivity controller, plus a client's force `stream`, clamped to the peak.
    pub fn torque(
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
            self.scene.split(t, &p, &v)
        } else {
            (Force3::zeros(), Force3::zeros())
        };
        let rendered = self.passivity.step(&p, &watched, dt) + constant;
        let f = limit_force(&(rendered + stream), self.max_force_n);
        self.tip_mm = (p * 1e3).into();
        self.force = f.into();
        tip_force_torque(&self.geometry, q, &f)
    }
}
