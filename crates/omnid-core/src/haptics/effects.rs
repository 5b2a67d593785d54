//! Haptic effects rendered in the 1 kHz loop (docs/HAPTICS.md §5): each maps the tip's
//! position and velocity to a force. Plain `Copy` data in fixed slots, so a scene is set up
//! before the loop or changed by a command without allocating. A change of an effect's
//! parameters fades in over `fade_s`, so the force never jumps.

use super::Force3;
use serde::{Deserialize, Serialize};

/// Most effects in a scene at once.
pub(crate) const MAX_EFFECTS: usize = 8;

/// One effect. Positions in mm (OpenHaptics frame, as `tip_mm`), stiffness in N/mm (as the
/// vendor quotes it), damping in N·s/m, forces in N.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum Effect {
    /// Pulls the tip towards `center_mm`.
    Spring {
        /// Rest point, mm.
        center_mm: [f64; 3],
        /// Stiffness, N/mm.
        stiffness_n_per_mm: f64,
        /// Damping of the tip's velocity, N·s/m (0 if left out).
        #[serde(default)]
        damping_n_s_per_m: f64,
    },
    /// Resists the tip's velocity everywhere (viscous field).
    Damper {
        /// Damping, N·s/m.
        damping_n_s_per_m: f64,
    },
    /// A one-sided wall through `point_mm`; `normal` points out of the wall (where the tip is
    /// free). Pushes only, never pulls.
    Plane {
        /// A point of the wall's surface, mm.
        point_mm: [f64; 3],
        /// Outward normal (any non-zero length).
        normal: [f64; 3],
        /// Stiffness against penetration, N/mm.
        stiffness_n_per_mm: f64,
        /// Damping of the velocity into the wall while inside it, N·s/m (0 if left out).
        #[serde(default)]
        damping_n_s_per_m: f64,
    },
    /// Keeps the tip inside the box between `min_mm` and `max_mm` (six one-sided walls).
    Box {
        /// Lowest corner, mm.
        min_mm: [f64; 3],
        /// Highest corner, mm.
        max_mm: [f64; 3],
        /// Stiffness of each wall, N/mm.
        stiffness_n_per_mm: f64,
        /// Damping of the velocity into a wall while beyond it, N·s/m (0 if left out).
        #[serde(default)]
        damping_n_s_per_m: f64,
    },
    /// A constant force, N.
    Constant {
        /// The force, N (OpenHaptics frame).
        force_n: [f64; 3],
    },
}

/// A one-sided spring-damper along one direction: `depth` m into the wall (> 0 inside),
/// `speed` m/s into the wall. Never pulls the tip back in (no sticky walls).
fn wall(depth: f64, speed: f64, k: f64, b: f64) -> f64 {
    if depth <= 0.0 {
        0.0
    } else {
        (k * depth + b * speed).max(0.0)
    }
}

impl Effect {
    /// The force on the tip at `p` (m) moving at `v` (m/s).
    pub(crate) fn force(&self, p: &Force3, v: &Force3) -> Force3 {
        match *self {
            Effect::Spring {
                center_mm,
                stiffness_n_per_mm: k,
                damping_n_s_per_m: b,
            } => (Force3::from(center_mm) * 1e-3 - p) * (k * 1e3) - v * b,
            Effect::Damper {
                damping_n_s_per_m: b,
            } => -v * b,
            Effect::Plane {
                point_mm,
                normal,
                stiffness_n_per_mm: k,
                damping_n_s_per_m: b,
            } => {
                let n = Force3::from(normal).normalize();
                let depth = (Force3::from(point_mm) * 1e-3 - p).dot(&n);
                n * wall(depth, -v.dot(&n), k * 1e3, b)
            }
            Effect::Box {
                min_mm,
                max_mm,
                stiffness_n_per_mm: k,
                damping_n_s_per_m: b,
            } => Force3::from_fn(|i, _| {
                let (lo, hi) = (min_mm[i] * 1e-3, max_mm[i] * 1e-3);
                wall(lo - p[i], -v[i], k * 1e3, b) - wall(p[i] - hi, v[i], k * 1e3, b)
            }),
            Effect::Constant { force_n } => force_n.into(),
        }
    }

    /// Its `type` name, as in scene files and the protocol.
    pub fn kind(&self) -> &'static str {
        match self {
            Effect::Spring { .. } => "spring",
            Effect::Damper { .. } => "damper",
            Effect::Plane { .. } => "plane",
            Effect::Box { .. } => "box",
            Effect::Constant { .. } => "constant",
        }
    }

    /// How deep the tip at `p` (m) is into this effect's wall, m (0 outside); None for an
    /// effect without a wall (spring, damper, constant). A box holds the tip inside it: its
    /// depth is how far the tip is out past its farthest face.
    pub(crate) fn depth(&self, p: &Force3) -> Option<f64> {
        match *self {
            Effect::Plane {
                point_mm, normal, ..
            } => {
                let n = Force3::from(normal).normalize();
                Some((Force3::from(point_mm) * 1e-3 - p).dot(&n).max(0.0))
            }
            Effect::Box { min_mm, max_mm, .. } => Some((0..3).fold(0.0f64, |d, i| {
                d.max(min_mm[i] * 1e-3 - p[i]).max(p[i] - max_mm[i] * 1e-3)
            })),
            _ => None,
        }
    }

    /// Check every parameter; the error names the field (`prefix` says which effect).
    pub(crate) fn validate(&self, prefix: &str) -> Result<(), String> {
        let finite = |name: &str, v: &[f64]| -> Result<(), String> {
            match v.iter().find(|x| !x.is_finite()) {
                Some(x) => Err(format!("{prefix}{name} = {x}: must be a finite number")),
                None => Ok(()),
            }
        };
        let range = |name: &str, v: f64, hi: f64, unit: &str| -> Result<(), String> {
            finite(name, &[v])?;
            if (0.0..=hi).contains(&v) {
                Ok(())
            } else {
                Err(format!(
                    "{prefix}{name} = {v} is out of range: allowed 0 ..= {hi} {unit}"
                ))
            }
        };
        const K_MAX: f64 = 100.0;
        const B_MAX: f64 = 200.0;
        // A point of an effect within 10 m of the base: a spring or wall anywhere farther
        // (1e308 mm) would give a force that is not finite at any pose the arm can reach.
        const REACH_MM: f64 = 10_000.0;
        let place = |name: &str, v: &[f64; 3]| -> Result<(), String> {
            finite(name, v)?;
            match v.iter().find(|x| x.abs() > REACH_MM) {
                Some(x) => Err(format!(
                    "{prefix}{name} has {x} mm: allowed within ±{REACH_MM} mm of the base"
                )),
                None => Ok(()),
            }
        };
        match self {
            Effect::Spring {
                center_mm,
                stiffness_n_per_mm,
                damping_n_s_per_m,
            } => {
                place("center_mm", center_mm)?;
                range("stiffness_n_per_mm", *stiffness_n_per_mm, K_MAX, "N/mm")?;
                range("damping_n_s_per_m", *damping_n_s_per_m, B_MAX, "N·s/m")
            }
            Effect::Damper { damping_n_s_per_m } => {
                range("damping_n_s_per_m", *damping_n_s_per_m, B_MAX, "N·s/m")
            }
            Effect::Plane {
                point_mm,
                normal,
                stiffness_n_per_mm,
                damping_n_s_per_m,
            } => {
                place("point_mm", point_mm)?;
                finite("normal", normal)?;
                let n = Force3::from(*normal).norm();
                if !(n > 1e-9 && n.is_finite()) {
                    return Err(format!("{prefix}normal = {normal:?}: must not be zero"));
                }
                range("stiffness_n_per_mm", *stiffness_n_per_mm, K_MAX, "N/mm")?;
                range("damping_n_s_per_m", *damping_n_s_per_m, B_MAX, "N·s/m")
            }
            Effect::Box {
                min_mm,
                max_mm,
                stiffness_n_per_mm,
                damping_n_s_per_m,
            } => {
                place("min_mm", min_mm)?;
                place("max_mm", max_mm)?;
                if let Some(i) = (0..3).find(|&i| min_mm[i] >= max_mm[i]) {
                    return Err(format!(
                        "{prefix}min_mm[{i}] = {} must be below max_mm[{i}] = {}",
                        min_mm[i], max_mm[i]
                    ));
                }
                range("stiffness_n_per_mm", *stiffness_n_per_mm, K_MAX, "N/mm")?;
                range("damping_n_s_per_m", *damping_n_s_per_m, B_MAX, "N·s/m")
            }
            Effect::Constant { force_n } => {
                finite("force_n", force_n)?;
                let n = Force3::from(*force_n).norm();
                if n > 20.0 {
                    return Err(format!(
                        "{prefix}force_n has norm {n} N: allowed ≤ 20 N (the servo clamps to \
                         haptics.max_force_n)"
                    ));
                }
                Ok(())
            }
        }
    }
}

/// One slot: its effect and the fade from what the slot rendered before the last change.
#[derive(Debug, Clone, Copy, Default)]
struct Slot {
    effect: Option<Effect>,
    /// Old output minus new output at the change, faded out over `fade_s`.
    offset: Force3,
    since: f64,
    /// This slot's output at the last tick.
    last: Force3,
    /// Changed since the last tick: the fade starts from the tip where it is next.
    pending: bool,
}

/// The effects in force, in fixed slots.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Scene {
    slots: [Slot; MAX_EFFECTS],
    fade_s: f64,
    /// An effect's force was not finite at the last tick's pose and was left out.
    pub(crate) skipped: bool,
}

impl Scene {
    pub(crate) fn new(fade_s: f64) -> Scene {
        Scene {
            slots: [Slot::default(); MAX_EFFECTS],
            fade_s,
            skipped: false,
        }
    }

    /// Put `effect` in `slot` (None: remove it) at time `t`. The slot's force moves from what
    /// it was to the new effect's over `fade_s` instead of stepping. Slots beyond
    /// [`MAX_EFFECTS`] are ignored (the callers check).
    pub(crate) fn set(&mut self, slot: usize, effect: Option<Effect>, t: f64) {
        let Some(s) = self.slots.get_mut(slot) else {
            return;
        };
        s.since = t;
        s.effect = effect;
        s.pending = true;
    }

    /// The sum of every slot's force at `t` with the tip at `p` (m) moving at `v` (m/s). A
    /// slot whose force is not finite here is left out (and `skipped` set): one bad effect
    /// never takes the others with it.
    pub(crate) fn force(&mut self, t: f64, p: &Force3, v: &Force3) -> Force3 {
        let mut total = Force3::zeros();
        self.skipped = false;
        for s in &mut self.slots {
            let mut f = s.effect.map_or(Force3::zeros(), |e| e.force(p, v));
            if !f.iter().all(|x| x.is_finite()) {
                self.skipped = true;
                f = Force3::zeros();
            }
            if s.pending {
                // Start from what the slot rendered at the last tick.
                s.offset = s.last - f;
                s.pending = false;
            }
            if s.offset != Force3::zeros() {
                let w = if self.fade_s > 0.0 {
                    crate::control::reference::quintic((t - s.since) / self.fade_s).0
                } else {
                    1.0
                };
                if w >= 1.0 {
                    s.offset = Force3::zeros();
                } else {
                    f += s.offset * (1.0 - w);
                }
            }
            s.last = f;
            total += f;
        }
        total
    }

    /// Each slot's effect kind and how deep the tip at `p` (m) is into its wall, m (see
    /// [`Effect::depth`]).
    pub(crate) fn depths(&self, p: &Force3) -> [Option<(&'static str, Option<f64>)>; MAX_EFFECTS] {
        let mut out = [None; MAX_EFFECTS];
        for (o, s) in out.iter_mut().zip(&self.slots) {
            *o = s
                .effect
                .map(|e| (e.kind(), e.depth(p).filter(|d| d.is_finite())));
        }
        out
    }

    /// The scene's force split into what the passivity controller watches and the constant
    /// forces it leaves alone: a constant force is a potential field (what it gives as the tip
    /// moves along it, it takes back when the tip returns), and weakening it would only bend
    /// a force the client asked for (docs/HAPTICS.md §6). Fades stay with the watched part.
    pub(crate) fn split(&mut self, t: f64, p: &Force3, v: &Force3) -> (Force3, Force3) {
        let total = self.force(t, p, v);
        let constant: Force3 = self
            .slots
            .iter()
            .filter(|s| s.offset == Force3::zeros())
            .filter_map(|s| match s.effect {
                Some(Effect::Constant { force_n }) => Some(Force3::from(force_n)),
                _ => None,
            })
            .sum();
        (total - constant, constant)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn v3(x: f64, y: f64, z: f64) -> Force3 {
        Force3::new(x, y, z)
    }

    #[test]
    fn an_effect_whose_force_cannot_be_finite_is_refused_and_a_bad_one_never_removes_the_rest() {
        let far = Effect::Spring {
            center_mm: [1e308, 0.0, 0.0],
            stiffness_n_per_mm: 100.0,
            damping_n_s_per_m: 0.0,
        };
        let e = far.validate("effect.").unwrap_err();
        assert!(e.contains("effect.center_mm") && e.contains("10000"), "{e}");
        // Were one to get past the check, the scene leaves it out and keeps the others.
        let near = Effect::Spring {
            center_mm: [10.0, 0.0, 0.0],
            stiffness_n_per_mm: 0.5,
            damping_n_s_per_m: 0.0,
        };
        let mut scene = Scene::new(0.0);
        scene.set(0, Some(near), 0.0);
        scene.set(1, Some(far), 0.0);
        let f = scene.force(0.0, &v3(0.006, 0.0, 0.0), &Force3::zeros());
        assert!((f - v3(2.0, 0.0, 0.0)).norm() < 1e-12, "{f}");
        assert!(scene.skipped);
    }

    #[test]
    fn a_spring_pulls_to_its_centre_in_proportion() {
        let e = Effect::Spring {
            center_mm: [10.0, 0.0, 0.0],
            stiffness_n_per_mm: 0.5,
            damping_n_s_per_m: 0.0,
        };
        // 4 mm short of the centre along x at 0.5 N/mm: 2 N towards it.
        let f = e.force(&v3(0.006, 0.0, 0.0), &Force3::zeros());
        assert!((f - v3(2.0, 0.0, 0.0)).norm() < 1e-12, "{f}");
    }

    #[test]
    fn a_damper_opposes_the_velocity() {
        let e = Effect::Damper {
            damping_n_s_per_m: 3.0,
        };
        let f = e.force(&Force3::zeros(), &v3(0.1, -0.2, 0.0));
        assert!((f - v3(-0.3, 0.6, 0.0)).norm() < 1e-12, "{f}");
    }

    #[test]
    fn a_plane_pushes_out_only_when_penetrated_and_never_pulls() {
        // A floor at y = −20 mm, normal up (unnormalised on purpose).
        let e = Effect::Plane {
            point_mm: [0.0, -20.0, 0.0],
            normal: [0.0, 2.0, 0.0],
            stiffness_n_per_mm: 1.0,
            damping_n_s_per_m: 10.0,
        };
        let still = Force3::zeros();
        assert_eq!(e.force(&v3(0.0, -0.019, 0.0), &still), Force3::zeros());
        // 1.5 mm deep: 1.5 N up.
        let f = e.force(&v3(0.03, -0.0215, 0.0), &still);
        assert!((f - v3(0.0, 1.5, 0.0)).norm() < 1e-9, "{f}");
        // Moving in adds damping; moving out fast enough removes the push but never pulls.
        let f = e.force(&v3(0.0, -0.0215, 0.0), &v3(0.0, -0.1, 0.0));
        assert!((f[1] - 2.5).abs() < 1e-9, "{f}");
        let f = e.force(&v3(0.0, -0.0215, 0.0), &v3(0.0, 0.5, 0.0));
        assert_eq!(f, Force3::zeros());
    }

    #[test]
    fn a_box_pushes_back_from_each_face() {
        let e = Effect::Box {
            min_mm: [-50.0, -40.0, -30.0],
            max_mm: [50.0, 40.0, 30.0],
            stiffness_n_per_mm: 0.2,
            damping_n_s_per_m: 0.0,
        };
        let still = Force3::zeros();
        assert_eq!(e.force(&Force3::zeros(), &still), Force3::zeros());
        let f = e.force(&v3(0.055, -0.045, 0.0), &still);
        assert!((f - v3(-1.0, 1.0, 0.0)).norm() < 1e-9, "{f}");
        let f = e.force(&v3(0.0, 0.0, 0.035), &still);
        assert!((f - v3(0.0, 0.0, -1.0)).norm() < 1e-9, "{f}");
    }

    #[test]
    fn a_constant_force_is_constant() {
        let e = Effect::Constant {
            force_n: [0.1, 0.2, -0.3],
        };
        assert_eq!(
            e.force(&v3(1.0, 2.0, 3.0), &v3(4.0, 5.0, 6.0)),
            v3(0.1, 0.2, -0.3)
        );
    }

    #[test]
    fn several_effects_add_and_changes_fade_without_a_jump() {
        let mut scene = Scene::new(0.1);
        let p = v3(0.0, 0.0, 0.002);
        let still = Force3::zeros();
        scene.set(
            0,
            Some(Effect::Constant {
                force_n: [0.5, 0.0, 0.0],
            }),
            0.0,
        );
        let spring = |k: f64| Effect::Spring {
            center_mm: [0.0; 3],
            stiffness_n_per_mm: k,
            damping_n_s_per_m: 0.0,
        };
        scene.set(1, Some(spring(0.5)), 0.0);
        // Both fade in from nothing: no step at the change...
        assert!(scene.force(0.0, &p, &still).norm() < 1e-12);
        // ... and both are in full once the fade is over: the sum.
        let f = scene.force(0.2, &p, &still);
        assert!((f - v3(0.5, 0.0, -1.0)).norm() < 1e-12, "{f}");
        // A stiffness change mid-contact: the force moves from −1 N to −2 N in small steps.
        scene.set(1, Some(spring(1.0)), 0.2);
        let mut last = f;
        let mut biggest = 0.0f64;
        for k in 0..=150 {
            let f = scene.force(0.2 + k as f64 * 1e-3, &p, &still);
            biggest = biggest.max((f - last).norm());
            last = f;
        }
        assert!((last - v3(0.5, 0.0, -2.0)).norm() < 1e-12, "{last}");
        // A 1 N change over 100 ms with the quintic's steepest slope: under 20 mN a tick.
        assert!(biggest < 0.02, "largest step {biggest} N");
        // Removing fades out too.
        scene.set(0, None, 1.0);
        assert!((scene.force(1.0, &p, &still) - last).norm() < 1e-12);
        assert!((scene.force(1.2, &p, &still) - v3(0.0, 0.0, -2.0)).norm() < 1e-12);
    }

    #[test]
    fn bad_parameters_are_refused_by_name() {
        let e = Effect::Plane {
            point_mm: [0.0; 3],
            normal: [0.0; 3],
            stiffness_n_per_mm: 1.0,
            damping_n_s_per_m: 0.0,
        };
        assert!(e
            .validate("effect[0].")
            .unwrap_err()
            .contains("effect[0].normal"));
        let e = Effect::Damper {
            damping_n_s_per_m: f64::NAN,
        };
        assert!(e.validate("").unwrap_err().contains("damping_n_s_per_m"));
        let e = Effect::Box {
            min_mm: [0.0; 3],
            max_mm: [1.0, -1.0, 1.0],
            stiffness_n_per_mm: 1.0,
            damping_n_s_per_m: 0.0,
        };
        assert!(e.validate("").unwrap_err().contains("min_mm[1]"));
    }
}
