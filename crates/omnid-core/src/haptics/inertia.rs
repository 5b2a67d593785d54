//! Partial inertia compensation in the haptic modes (docs/HAPTICS.md §3): free mode and a
//! client's force stream add β·M(q)·q̈ — a fraction of the law's own inertia times the
//! estimated acceleration — so the hand carries less of the arm's mass. The estimated q̈
//! lags, and a lagged acceleration fed back takes from the stability margin of a stiff
//! contact, so the fraction is gated: it falls to zero as the rendered tip force grows past
//! [`CONTACT_FORCE_N`], while the passivity controller is dissipating or a joint is at its soft
//! wall ([`near_walls`]), and wherever q̈ is not to be trusted; it comes back over
//! [`RETURN_S`]. Fixed-size state only: it runs every tick.

use crate::control::reference::quintic;
use crate::omni::Joint3;

/// The largest fraction of the inertia that may be compensated (`[haptics]
/// inertia_compensation`): beyond it the measurements showed walls that no longer hold, and
/// the free arm's own stability is at stake (docs/HAPTICS.md §9).
pub const MAX_INERTIA_COMPENSATION: f64 = 0.5;

/// At this rendered tip force (N) and above, the compensation is off: the tip is in contact
/// with something the scene or a client renders. Well above free mode's own forces (none)
/// and well below a wall's push (1 N).
pub(crate) const CONTACT_FORCE_N: f64 = 0.1;

/// After the gate closed (contact, dissipation, an untrusted q̈), the fraction returns to β
/// over this time at the fastest, s (a tip bouncing off a wall gets none of it between the
/// bounces).
pub(crate) const RETURN_S: f64 = 0.2;

/// Within this of a soft wall (rad, any joint) the gate is shut: the wall's spring is a
/// contact like a rendered wall's, and it engages from the estimate or the encoders, whichever
/// is further out (docs/HAPTICS.md §3). At 2.5 rad/s that is 20 ticks before the wall.
pub(crate) const WALL_MARGIN_RAD: f64 = 0.05;

/// Some joint is within [`WALL_MARGIN_RAD`] of its soft wall, or beyond it (or its angle is
/// not finite).
pub(crate) fn near_walls(q: &Joint3, lower: &[f64; 3], upper: &[f64; 3]) -> bool {
    (0..3).any(|j| !(q[j] > lower[j] + WALL_MARGIN_RAD && q[j] < upper[j] - WALL_MARGIN_RAD))
}

/// The static gate: `beta` with no force at the tip, falling smoothly (a quintic, continuous
/// with its first two derivatives) to 0 at [`CONTACT_FORCE_N`], 0 beyond it. A force that is
/// not finite closes it.
pub(crate) fn contact_gate(beta: f64, force_n: f64) -> f64 {
    if !force_n.is_finite() {
        return 0.0;
    }
    beta * (1.0 - quintic(force_n.abs() / CONTACT_FORCE_N).0)
}

/// The gate over time: it closes at once and reopens at a bounded rate.
#[derive(Debug, Clone, Copy)]
pub(crate) struct InertiaGate {
    beta: f64,
    level: f64,
}

impl InertiaGate {
    /// A closed gate that opens to `beta` (0: the feature is off and the gate stays shut).
    pub(crate) fn new(beta: f64) -> InertiaGate {
        InertiaGate {
            beta: if beta.is_finite() {
                beta.clamp(0.0, MAX_INERTIA_COMPENSATION)
            } else {
                0.0
            },
            level: 0.0,
        }
    }

    /// The fraction of the inertia to compensate this tick (`dt` s after the last), with
    /// `force_n` the norm of the tip force rendered this tick, `held_off` when something else
    /// shuts it (the passivity controller taking energy back, a joint at its soft wall),
    /// `trusted` when the estimated q̈ can be believed (not just after the estimator restarted
    /// or the inkwell let go).
    pub(crate) fn step(&mut self, dt: f64, force_n: f64, held_off: bool, trusted: bool) -> f64 {
        let target = if trusted && !held_off {
            contact_gate(self.beta, force_n)
        } else {
            0.0
        };
        self.level = if target <= self.level {
            target
        } else {
            let rise = if dt.is_finite() && dt > 0.0 {
                self.beta * dt / RETURN_S
            } else {
                0.0
            };
            (self.level + rise).min(target)
        };
        self.level
    }

    /// Shut the gate (the loop left the haptic modes): it opens again from zero.
    pub(crate) fn reset(&mut self) {
        self.level = 0.0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_gate_is_beta_without_force_zero_in_contact_and_continuous_between() {
        let beta = 0.3;
        assert_eq!(contact_gate(beta, 0.0), beta);
        assert_eq!(contact_gate(beta, CONTACT_FORCE_N), 0.0);
        for f in [
            1.0001 * CONTACT_FORCE_N,
            0.5,
            1.0,
            3.3,
            1e9,
            f64::INFINITY,
            f64::NAN,
        ] {
            assert_eq!(contact_gate(beta, f), 0.0, "at {f} N");
        }
        // Strictly between: below β, above 0, falling as the force grows; no step anywhere
        // (the quintic's steepest slope is 1.875 per unit of force / threshold).
        let n = 10_000;
        let h = 2.0 * CONTACT_FORCE_N / n as f64;
        let mut last = contact_gate(beta, 0.0);
        for k in 1..=n {
            let f = k as f64 * h;
            let g = contact_gate(beta, f);
            if f < CONTACT_FORCE_N {
                assert!(g > 0.0 && g < beta, "{g} at {f} N");
            }
            assert!(g <= last, "not falling at {f} N");
            assert!(
                last - g <= beta * 1.875 * h / CONTACT_FORCE_N + 1e-15,
                "a step at {f} N: {last} -> {g}"
            );
            last = g;
        }
        assert_eq!(contact_gate(0.0, 0.0), 0.0);
    }

    #[test]
    fn near_walls_is_within_the_margin_of_either_wall_on_any_joint() {
        let (lo, hi) = ([-1.0, 0.0, -0.5], [1.0, 1.5, 1.0]);
        let m = WALL_MARGIN_RAD;
        assert!(!near_walls(&Joint3::new(0.0, 0.75, 0.2), &lo, &hi));
        // Just inside the margin on one joint, at either wall, or beyond the wall.
        for j in 0..3 {
            for q in [lo[j] + 0.99 * m, hi[j] - 0.99 * m, lo[j] - 1.0, hi[j] + 1.0] {
                let mut x = Joint3::new(0.0, 0.75, 0.2);
                x[j] = q;
                assert!(near_walls(&x, &lo, &hi), "joint {j} at {q}");
            }
            let mut x = Joint3::new(0.0, 0.75, 0.2);
            x[j] = lo[j] + 1.01 * m;
            assert!(
                !near_walls(&x, &lo, &hi),
                "joint {j} just outside the margin"
            );
        }
        assert!(near_walls(&Joint3::new(f64::NAN, 0.75, 0.2), &lo, &hi));
    }

    #[test]
    fn the_gate_closes_at_once_and_reopens_over_the_return_time() {
        let dt = 1e-3;
        let mut g = InertiaGate::new(0.4);
        // It starts shut and opens over RETURN_S.
        assert_eq!(g.step(dt, 0.0, false, true), 0.4 * dt / RETURN_S);
        let mut ticks = 1;
        while g.step(dt, 0.0, false, true) < 0.4 {
            ticks += 1;
            assert!(ticks < 1000, "never opened");
        }
        assert!((ticks as f64 * dt - RETURN_S).abs() <= 2.0 * dt, "{ticks}");
        // Contact, dissipation, an untrusted q̈: shut within the tick.
        assert_eq!(g.step(dt, 1.0, false, true), 0.0);
        g.step(1.0, 0.0, false, true);
        assert_eq!(g.step(dt, 0.0, true, true), 0.0);
        g.step(1.0, 0.0, false, true);
        assert_eq!(g.step(dt, 0.0, false, false), 0.0);
        // A light force partly closes it, at once.
        g.step(1.0, 0.0, false, true);
        let partial = g.step(dt, 0.5 * CONTACT_FORCE_N, false, true);
        assert_eq!(partial, contact_gate(0.4, 0.5 * CONTACT_FORCE_N));
        // Reset: shut until it reopens.
        g.reset();
        assert!(g.step(dt, 0.0, false, true) < 0.01);
        // Out-of-range fractions are held to the bound; a zero fraction never opens.
        let mut big = InertiaGate::new(5.0);
        assert_eq!(big.step(10.0, 0.0, false, true), MAX_INERTIA_COMPENSATION);
        let mut off = InertiaGate::new(0.0);
        assert_eq!(off.step(10.0, 0.0, false, true), 0.0);
        let mut nan = InertiaGate::new(f64::NAN);
        assert_eq!(nan.step(10.0, 0.0, false, true), 0.0);
    }
}
