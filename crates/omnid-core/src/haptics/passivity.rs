//! Passivity observer and controller (Hannaford & Ryu; docs/HAPTICS.md §6). The observer sums
//! the energy the rendered force has taken from the hand, E = Σ −F_{k−1}·(p_k − p_{k−1}), from
//! the measured tip displacement over each tick and the force that acted over it. A passive
//! environment keeps E ≥ 0; when E < 0 it has given out energy it never took in (the sampled
//! wall's excess), and the controller adds a damper along the tip's velocity sized to
//! dissipate exactly that excess over the next tick. The energy in hand is capped (a reserve),
//! so what a damper absorbed long ago cannot license an active wall later.

use super::Force3;

#[derive(Debug, Clone, Copy)]
pub(crate) struct Passivity {
    /// The controller acts (the observer always observes).
    pub(crate) enabled: bool,
    /// Largest damping the controller adds, N·s/m.
    max_damping: f64,
    /// Most energy the observer keeps in hand, J.
    reserve_j: f64,
    /// Observed energy, J.
    energy: f64,
    /// The force that acted over the last tick and where the tip was then.
    last_force: Force3,
    last_p: Option<Force3>,
    /// The damping the controller added at the last tick, N·s/m.
    pub(crate) damping: f64,
}

impl Passivity {
    pub(crate) fn new(enabled: bool, max_damping: f64, reserve_j: f64) -> Passivity {
        Passivity {
            enabled,
            max_damping,
            reserve_j,
            energy: 0.0,
            last_force: Force3::zeros(),
            last_p: None,
            damping: 0.0,
        }
    }

    /// Observed energy, J (≥ 0 while the rendering has been passive).
    #[cfg(test)]
    pub(crate) fn energy(&self) -> f64 {
        self.energy
    }

    /// Observe the tick that ended with the tip at `p` (m), then return the force to render
    /// this tick: `f` (N) with the controller's damping when the observer shows a deficit.
    /// The damping acts on the velocity the observer saw over that tick (the same flow it
    /// integrates), and never removes more than the effects' own force: the controller only
    /// weakens a rendering, it never pushes by itself.
    pub(crate) fn step(&mut self, p: &Force3, f: &Force3, dt: f64) -> Force3 {
        let mut v = Force3::zeros();
        if let Some(before) = self.last_p {
            let dp = p - before;
            let taken = -self.last_force.dot(&dp);
            self.energy = (self.energy + taken).clamp(-self.reserve_j, self.reserve_j);
            if dt > 0.0 {
                v = dp / dt;
            }
        }
        self.last_p = Some(*p);
        let speed2 = v.norm_squared();
        self.damping = 0.0;
        let mut out = *f;
        if self.enabled && self.energy < 0.0 && speed2 > 0.0 && dt > 0.0 {
            // α·|v|²·T dissipates −E over the next tick.
            self.damping = (-self.energy / (speed2 * dt)).min(self.max_damping);
            let correction = v * self.damping;
            let n = correction.norm();
            let cap = f.norm();
            out -= if n > cap {
                correction * (cap / n)
            } else {
                correction
            };
        }
        self.last_force = out;
        out
    }

    /// Forget the history (a new contact, a mode change).
    pub(crate) fn reset(&mut self) {
        self.energy = 0.0;
        self.last_p = None;
        self.last_force = Force3::zeros();
        self.damping = 0.0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sampled stiff spring (zero-order hold, one tick late) against a bouncing mass: the
    /// textbook active case. Returns (observer's lowest energy, energy the mass gained, J).
    fn bounce(enabled: bool) -> (f64, f64) {
        let (m, k, dt) = (0.05, 3000.0, 1e-3);
        let mut pc = Passivity::new(enabled, 50.0, 1e-3);
        let (mut x, mut v) = (0.001, -0.05);
        let e0 = 0.5 * m * v * v;
        let mut lowest = 0.0f64;
        let mut f = Force3::zeros();
        for _ in 0..2000 {
            let p = Force3::new(0.0, x, 0.0);
            let wall = if x < 0.0 { -k * x } else { 0.0 };
            f = pc.step(&p, &Force3::new(0.0, wall, 0.0), dt);
            lowest = lowest.min(pc.energy());
            // The mass under the held force over the tick (exactly integrated, fine steps).
            for _ in 0..100 {
                let a = f[1] / m;
                v += a * dt / 100.0;
                x += v * dt / 100.0;
            }
        }
        let _ = f;
        let spring = if x < 0.0 { 0.5 * k * x * x } else { 0.0 };
        (lowest, 0.5 * m * v * v + spring - e0)
    }

    #[test]
    fn the_observer_catches_a_sampled_wall_giving_out_energy() {
        let (lowest, gained) = bounce(false);
        // The held spring returns more than it took: the mass leaves faster than it came,
        // and the observer's energy goes negative.
        assert!(gained > 1e-5, "gained {gained} J");
        assert!(lowest < -1e-5, "observer low {lowest} J");
    }

    #[test]
    fn the_controller_dissipates_the_excess() {
        let (lowest, gained) = bounce(true);
        let (_, gained_open) = bounce(false);
        // It cannot take back what the wall gave on the last tick of contact (outside the
        // wall there is no force to weaken), but much of the excess is gone, and the deficit
        // stays within the reserve.
        assert!(
            gained < 0.6 * gained_open,
            "gained {gained} J vs {gained_open} J open"
        );
        assert!(lowest >= -1e-3, "observer low {lowest} J");
    }

    #[test]
    fn a_passive_damper_is_left_alone() {
        let mut pc = Passivity::new(true, 50.0, 1.0);
        let mut x = 0.0;
        let v = 0.05;
        for _ in 0..1000 {
            let p = Force3::new(x, 0.0, 0.0);
            let vel = Force3::new(v, 0.0, 0.0);
            let f = pc.step(&p, &(-vel * 2.0), 1e-3);
            assert_eq!(pc.damping, 0.0);
            assert_eq!(f, -vel * 2.0);
            x += v * 1e-3;
        }
        // It took in energy: 2 N·s/m · (0.05 m/s)² · 1 s = 5 mJ (less the first tick).
        assert!((pc.energy() - 5e-3).abs() < 1e-5, "{}", pc.energy());
    }
}
