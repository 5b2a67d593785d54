//! A simulated hand on the stylus (docs/HAPTICS.md §7): a spring-damper between the tip and
//! where the hand is, the hand moving along a pattern. The force in that spring acts on the
//! simulated tip (through Jᵀ) and is what a user would feel, so transparency and walls become
//! numbers. Plain data, no allocation: it runs inside the simulator's integration.

use super::Force3;
use crate::control::reference::quintic;
use serde::{Deserialize, Serialize};

/// What the hand does.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(try_from = "String", into = "String")]
pub enum HandPattern {
    /// No hand on the stylus.
    None,
    /// Hold the stylus still where it was grasped.
    Hold,
    /// Free motion along a closed 3-D path around the workspace centre at `speed_m_s`.
    Path,
    /// Move from the centre along `dir` (an axis, ±) at `speed_m_s` until pushing with
    /// `push_force_n`, then keep pushing with that force.
    Push {
        /// The axis, 0..=2 for x, y, z.
        axis: usize,
        /// Its direction, +1.0 or −1.0.
        sign: f64,
    },
    /// Tap along `dir` from the centre: out to `path_radius_m` and back, `TAP_HZ` times a
    /// second (a teleoperation follower tapping a surface).
    Tap {
        /// The axis, 0..=2 for x, y, z.
        axis: usize,
        /// Its direction, +1.0 or −1.0.
        sign: f64,
    },
}

/// How often the tapping hand taps, Hz.
pub const TAP_HZ: f64 = 1.5;

impl HandPattern {
    pub(crate) const NAMES: &'static str =
        "none, hold, path, push+x, push-x, push+y, push-y, push+z, push-z, tap+x, tap-x, tap+y, \
         tap-y, tap+z, tap-z";

    pub(crate) fn parse(s: &str) -> Option<HandPattern> {
        Some(match s {
            "none" => HandPattern::None,
            "hold" => HandPattern::Hold,
            "path" => HandPattern::Path,
            _ => {
                let (tap, rest) = match s.strip_prefix("push") {
                    Some(rest) => (false, rest),
                    None => (true, s.strip_prefix("tap")?),
                };
                let sign = match rest.as_bytes().first()? {
                    b'+' => 1.0,
                    b'-' => -1.0,
                    _ => return None,
                };
                let axis = match &rest[1..] {
                    "x" => 0,
                    "y" => 1,
                    "z" => 2,
                    _ => return None,
                };
                if tap {
                    HandPattern::Tap { axis, sign }
                } else {
                    HandPattern::Push { axis, sign }
                }
            }
        })
    }

    pub(crate) fn name(self) -> String {
        match self {
            HandPattern::None => "none".into(),
            HandPattern::Hold => "hold".into(),
            HandPattern::Path => "path".into(),
            HandPattern::Push { axis, sign } => format!(
                "push{}{}",
                if sign > 0.0 { '+' } else { '-' },
                ["x", "y", "z"][axis]
            ),
            HandPattern::Tap { axis, sign } => format!(
                "tap{}{}",
                if sign > 0.0 { '+' } else { '-' },
                ["x", "y", "z"][axis]
            ),
        }
    }
}

impl TryFrom<String> for HandPattern {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        HandPattern::parse(&s)
            .ok_or_else(|| format!("unknown hand pattern `{s}`: expected {}", Self::NAMES))
    }
}

impl From<HandPattern> for String {
    fn from(p: HandPattern) -> String {
        p.name()
    }
}

/// `[haptics.hand]`: the simulated hand (simulator only).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct HandConfig {
    /// None, hold, path (a 3-D path at speed_m_s), push+x .. push-z (push a wall with
    /// push_force_n).
    pub pattern: HandPattern,
    /// Grip stiffness between the hand and the tip, N/m (a grip: 200–1000).
    pub stiffness_n_per_m: f64,
    /// Grip damping, N·s/m (a grip: 2–10).
    pub damping_n_s_per_m: f64,
    /// Hand speed along the path and towards a wall, m/s.
    pub speed_m_s: f64,
    /// Force the pushing hand settles at, N.
    pub push_force_n: f64,
    /// The hand lets go at this time, s (0: never).
    pub release_s: f64,
    /// Time to move from where it grasped the stylus to the workspace centre, s.
    pub approach_s: f64,
    /// Size of the path (its half-width along x), m.
    pub path_radius_m: f64,
}

impl Default for HandConfig {
    fn default() -> Self {
        HandConfig {
            pattern: HandPattern::None,
            stiffness_n_per_m: 500.0,
            damping_n_s_per_m: 5.0,
            speed_m_s: 0.1,
            push_force_n: 1.0,
            release_s: 0.0,
            approach_s: 1.0,
            path_radius_m: 0.04,
        }
    }
}

/// Time constant of the pushing hand's force regulation, s (a deliberate, slow push).
const PUSH_TAU_S: f64 = 0.1;

/// The hand as it moves: where it is (m, OpenHaptics frame) and how fast.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Hand {
    cfg: HandParams,
    /// Where it grasped the stylus and the workspace centre, m.
    grasp: Force3,
    centre: Force3,
    /// The hand's own position and velocity now.
    pub(crate) pos: Force3,
    pub(crate) vel: Force3,
    /// Pushing: the hand's offset along its direction beyond the centre, m.
    push_depth: f64,
    /// Path: the phase travelled, rad.
    phase: f64,
}

/// The numbers of [`HandConfig`] the hand needs (`Copy`, so the simulator stays plain data).
#[derive(Debug, Clone, Copy)]
struct HandParams {
    pattern: HandPattern,
    k: f64,
    b: f64,
    speed: f64,
    push: f64,
    release_s: f64,
    approach_s: f64,
    radius: f64,
}

impl Hand {
    /// A hand that grasps the stylus at `grasp` (m) and works around `centre` (m).
    pub(crate) fn new(cfg: &HandConfig, grasp: Force3, centre: Force3) -> Hand {
        Hand {
            cfg: HandParams {
                pattern: cfg.pattern,
                k: cfg.stiffness_n_per_m,
                b: cfg.damping_n_s_per_m,
                speed: cfg.speed_m_s,
                push: cfg.push_force_n,
                release_s: cfg.release_s,
                approach_s: cfg.approach_s,
                radius: cfg.path_radius_m,
            },
            grasp,
            centre,
            pos: grasp,
            vel: Force3::zeros(),
            push_depth: 0.0,
            phase: 0.0,
        }
    }

    /// On the stylus at time `t`.
    pub(crate) fn holding(&self, t: f64) -> bool {
        self.cfg.pattern != HandPattern::None
            && (self.cfg.release_s <= 0.0 || t < self.cfg.release_s)
    }

    /// The force the hand puts on the tip at `tip` (m) moving at `tip_vel` (m/s), `tau` s
    /// after the hand's state was last advanced (it moves on at its velocity meanwhile).
    pub(crate) fn force(&self, t: f64, tip: &Force3, tip_vel: &Force3, tau: f64) -> Force3 {
        if !self.holding(t) {
            return Force3::zeros();
        }
        let at = self.pos + self.vel * tau;
        (at - tip) * self.cfg.k + (self.vel - tip_vel) * self.cfg.b
    }

    /// The path's point at phase θ (rad): a closed 3-D curve through the centre, about
    /// `radius` wide in x, half that in y and z.
    fn path_point(&self, theta: f64) -> Force3 {
        let r = self.cfg.radius;
        let (s, c) = theta.sin_cos();
        self.centre + Force3::new(r * s, 0.5 * r * (2.0 * theta).sin(), 0.5 * r * (1.0 - c))
    }

    /// Move the hand on to time `t + dt`; `felt` is the force the hand put on the tip last.
    pub(crate) fn advance(&mut self, t: f64, dt: f64, felt: &Force3) {
        let before = self.pos;
        let t1 = t + dt;
        // First the approach to the centre, then the pattern.
        let a = self.cfg.approach_s;
        let to_centre = |t: f64| {
            let s = if a > 0.0 { (t / a).min(1.0) } else { 1.0 };
            self.grasp + (self.centre - self.grasp) * quintic(s).0
        };
        self.pos = match self.cfg.pattern {
            HandPattern::None => before,
            HandPattern::Hold => self.grasp,
            _ if t1 <= a => to_centre(t1),
            HandPattern::Path => {
                // Speed ramps up over the first second so the hand starts smoothly.
                let ramp = ((t1 - a) / 1.0).min(1.0);
                let h = 1e-4;
                let ds = (self.path_point(self.phase + h) - self.path_point(self.phase)).norm() / h;
                self.phase += self.cfg.speed * ramp * dt / ds.max(1e-9);
                self.path_point(self.phase)
            }
            HandPattern::Push { axis, sign } => {
                // The hand regulates the force it pushes with along its direction: it moves
                // on while the force is short of the target and backs off when over, never
                // faster than its speed.
                let along = felt[axis] * sign;
                let rate = ((self.cfg.push - along) / (self.cfg.k * PUSH_TAU_S))
                    .clamp(-self.cfg.speed, self.cfg.speed);
                self.push_depth += rate * dt;
                let mut p = self.centre;
                p[axis] += sign * self.push_depth;
                p
            }
            HandPattern::Tap { axis, sign } => {
                let phase = std::f64::consts::TAU * TAP_HZ * (t1 - a);
                let mut p = self.centre;
                p[axis] += sign * self.cfg.radius * 0.5 * (1.0 - phase.cos());
                p
            }
        };
        self.vel = if dt > 0.0 {
            (self.pos - before) / dt
        } else {
            Force3::zeros()
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_parse_and_print_back() {
        for name in [
            "none", "hold", "path", "push+x", "push-y", "push+z", "tap-y", "tap+x",
        ] {
            assert_eq!(HandPattern::parse(name).unwrap().name(), name);
        }
        for bad in ["push", "push*x", "push+w", "walk", "tap", "tapy"] {
            assert!(HandPattern::parse(bad).is_none(), "{bad}");
        }
    }

    #[test]
    fn the_path_is_traced_at_the_hand_speed() {
        let cfg = HandConfig {
            pattern: HandPattern::Path,
            ..HandConfig::default()
        };
        let mut hand = Hand::new(&cfg, Force3::zeros(), Force3::new(0.0, 0.01, 0.0));
        let dt = 1e-3;
        let mut travelled = 0.0;
        let mut t = 0.0;
        while t < 6.0 {
            let before = hand.pos;
            hand.advance(t, dt, &Force3::zeros());
            if t > 2.5 {
                travelled += (hand.pos - before).norm();
            }
            t += dt;
        }
        // From 2.5 s (approach and ramp over) to 6 s at 0.1 m/s: 0.35 m.
        assert!((travelled - 0.35).abs() < 0.01, "{travelled}");
        // It moves in all three directions.
        let cfg_r = cfg.path_radius_m;
        assert!((hand.pos - hand.centre).amax() < 1.2 * cfg_r);
    }

    #[test]
    fn a_pushing_hand_settles_at_its_force_against_a_rigid_tip() {
        let cfg = HandConfig {
            pattern: HandPattern::Push {
                axis: 1,
                sign: -1.0,
            },
            approach_s: 0.0,
            ..HandConfig::default()
        };
        let centre = Force3::zeros();
        let mut hand = Hand::new(&cfg, centre, centre);
        let tip = Force3::zeros();
        let mut felt = Force3::zeros();
        for k in 0..3000 {
            let t = k as f64 * 1e-3;
            hand.advance(t, 1e-3, &felt);
            felt = hand.force(t, &tip, &Force3::zeros(), 0.0);
        }
        // Pushing down (−y) with 1 N: the spring holds the hand 2 mm past the tip.
        assert!((felt[1] + 1.0).abs() < 1e-3, "{felt}");
        assert!((hand.pos[1] + 0.002).abs() < 1e-5, "{}", hand.pos);
    }

    #[test]
    fn a_released_hand_puts_no_force() {
        let cfg = HandConfig {
            pattern: HandPattern::Hold,
            release_s: 1.0,
            ..HandConfig::default()
        };
        let hand = Hand::new(&cfg, Force3::zeros(), Force3::zeros());
        let tip = Force3::new(0.01, 0.0, 0.0);
        assert!(hand.force(0.5, &tip, &Force3::zeros(), 0.0).norm() > 1.0);
        assert_eq!(
            hand.force(1.5, &tip, &Force3::zeros(), 0.0),
            Force3::zeros()
        );
    }
}
