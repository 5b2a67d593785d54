//! Time-domain passivity on the teleoperation channel (docs/TELEOP.md §5), one port per side:
//! the observer integrates the power through the port (the coupling's force on this arm times
//! the arm's velocity), split into energy in (the arm pushed into the channel) and out (the
//! channel pushed the arm); each side sends its energy in, and the controller lets its own port
//! put out no more than what the other side's port has put in (the energy-transmitting scheme
//! for delayed channels): any surplus is taken back by a damping along the arm's velocity,
//! capped. Energy that entered but was never let out beyond `reserve_j` counts as dissipated,
//! so a long quiet stretch cannot bank a burst.

use nalgebra::Vector3;

/// Velocities below this (m/s, squared) carry no power worth damping.
const MIN_SPEED_SQ: f64 = 1e-8;

/// One side's port.
#[derive(Debug, Clone, Copy)]
pub struct Port {
    /// Energy the arm pushed into the channel here, J.
    pub energy_in: f64,
    /// Energy the channel put out into the arm here, J (including what counts as dissipated).
    pub energy_out: f64,
    /// Energy the controller took back by damping, J.
    pub dissipated: f64,
    /// The damping it used on the last tick, N·s/m.
    pub damping: f64,
    /// Most energy kept in hand from the far side, J.
    reserve_j: f64,
    /// Largest damping the controller adds, N·s/m (0: only the force's own bound).
    max_damping: f64,
    /// The controller acts (else the port only observes).
    enforce: bool,
}

impl Port {
    /// A port keeping at most `reserve_j` J in hand, damping with at most `max_damping`
    /// N·s/m (0: no cap but the force's own, see [`Port::pass`]); with `enforce` false it only
    /// observes.
    pub fn new(reserve_j: f64, max_damping: f64, enforce: bool) -> Port {
        Port {
            energy_in: 0.0,
            energy_out: 0.0,
            dissipated: 0.0,
            damping: 0.0,
            reserve_j,
            max_damping,
            enforce,
        }
    }

    /// Change the largest damping the controller adds from the next tick, N·s/m (0: no cap
    /// but the force's own). The coupling sets it every tick from the measured round trip
    /// (docs/TELEOP.md §5).
    pub fn set_max_damping(&mut self, max_damping: f64) {
        if max_damping.is_finite() && max_damping >= 0.0 {
            self.max_damping = max_damping;
        }
    }

    /// The largest damping the controller adds now, N·s/m (0: no cap).
    pub fn max_damping(&self) -> f64 {
        self.max_damping
    }

    /// The force to apply this tick: `force` (N) from the coupling, on an arm moving at `v`
    /// (m/s) for `dt` s, allowed at most what the far side has put in (`remote_in`, J); the
    /// energies are observed either way.
    pub fn pass(
        &mut self,
        force: Vector3<f64>,
        v: &Vector3<f64>,
        dt: f64,
        remote_in: f64,
    ) -> Vector3<f64> {
        let (reserve_j, max_damping, enforce) = (self.reserve_j, self.max_damping, self.enforce);
        // A budget that has grown past the reserve was dissipated somewhere: forget it.
        self.energy_out = self.energy_out.max(remote_in - reserve_j);
        let mut f = force;
        let power = f.dot(v);
        self.damping = 0.0;
        if enforce && power > 0.0 {
            let allowed = (remote_in - self.energy_out).max(0.0);
            let excess = power * dt - allowed;
            let speed_sq = v.norm_squared();
            if excess > 0.0 && speed_sq > MIN_SPEED_SQ {
                // The damping takes back at most the force's own work this tick (the allowance
                // is never negative, so excess ≤ power·dt): the force it removes along the
                // velocity is at most the coupling force's component along it — it never
                // pushes back, so it needs no cap to stay bounded on a noisy velocity. A cap
                // (`max_damping` > 0) lets a demand beyond it pass, and the port is then not
                // passive (docs/TELEOP.md §5).
                let mut alpha = excess / (dt * speed_sq);
                if max_damping > 0.0 {
                    alpha = alpha.min(max_damping);
                }
                f -= v * alpha;
                self.damping = alpha;
                self.dissipated += alpha * speed_sq * dt;
            }
        }
        let power = f.dot(v) * dt;
        if power >= 0.0 {
            self.energy_out += power;
        } else {
            self.energy_in -= power;
        }
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn with_no_energy_from_the_far_side_the_port_puts_out_nothing() {
        // A force along the velocity would push energy into the arm; the far side has put in
        // nothing, so the controller damps it to zero power (the cap is large enough).
        let mut p = Port::new(1.0, 1e6, true);
        let v = Vector3::new(0.05, 0.0, 0.0);
        let f = p.pass(Vector3::new(1.0, 0.5, 0.0), &v, 1e-3, 0.0);
        assert!(f.dot(&v).abs() < 1e-12, "{f:?}");
        assert!(p.energy_out.abs() < 1e-15);
        // The component across the velocity is untouched (it does no work).
        assert!((f[1] - 0.5).abs() < 1e-12);
    }

    #[test]
    fn output_is_bounded_by_what_the_far_side_put_in_over_a_long_run() {
        // Random forces and velocities; the far side's energy grows slowly. At every tick the
        // port's total output stays within what arrived (the passivity condition), checked
        // against energies summed independently here.
        let mut p = Port::new(10.0, 1e9, true);
        let mut out = 0.0;
        let mut remote = 0.0;
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut rnd = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        for _ in 0..20_000 {
            remote += 1e-5 * (rnd() + 1.0);
            let f = Vector3::new(rnd(), rnd(), rnd()) * 2.0;
            let v = Vector3::new(rnd(), rnd(), rnd()) * 0.1;
            let applied = p.pass(f, &v, 1e-3, remote);
            let w = applied.dot(&v) * 1e-3;
            if w > 0.0 {
                out += w;
            }
            assert!(out <= remote + 1e-12, "out {out} > in {remote}");
        }
        assert!(p.dissipated > 0.0);
    }

    #[test]
    fn off_it_observes_but_never_changes_the_force() {
        let mut p = Port::new(1.0, 1e3, false);
        let v = Vector3::new(0.0, 0.1, 0.0);
        let f = Vector3::new(0.0, 2.0, 0.0);
        assert_eq!(p.pass(f, &v, 1e-3, 0.0), f);
        assert!((p.energy_out - 2e-4).abs() < 1e-15);
        let f = p.pass(-f, &v, 1e-3, 0.0);
        assert!((p.energy_in - 2e-4).abs() < 1e-15 && f[1] == -2.0);
    }
}
