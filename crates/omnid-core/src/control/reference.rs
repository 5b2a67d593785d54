//! Reference trajectories (sine, multisine, hold) and the quintic blend from the pose at start
//! onto them, so that start-up never kicks.

use crate::config_check::{self as check, ConfigError};
use crate::omni::Joint3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;

/// `[reference]`: where the trajectories are centred and how they move.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ReferenceConfig {
    /// Mid-workspace pose the trajectories move about, rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub center: [f64; 3],
    /// Sine amplitudes, rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub amplitude: [f64; 3],
    /// Sine frequency, Hz.
    pub frequency_hz: f64,
    /// Duration of the quintic blend from the start pose onto the reference, s.
    pub blend_s: f64,
    /// Tracking statistics start here (after the blend and its transient), s.
    pub settle_s: f64,
    /// Fastest a setpoint target moves (a `hold` start, a `servo_jp` step), rad/s.
    pub slew_rad_s: f64,
    /// Multisine: amplitude per joint (sum over components), rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub multisine_amplitude: [f64; 3],
    /// Multisine: lowest and highest component frequency, Hz.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub multisine_band_hz: [f64; 2],
    /// Multisine: number of components per joint.
    pub multisine_components: u32,
}

impl Default for ReferenceConfig {
    fn default() -> Self {
        ReferenceConfig {
            center: [0.0, 0.65, 0.3],
            amplitude: [0.4, 0.3, 0.3],
            frequency_hz: 0.5,
            blend_s: 1.0,
            settle_s: 2.0,
            slew_rad_s: 2.0,
            multisine_amplitude: [0.45, 0.32, 0.32],
            multisine_band_hz: [0.1, 1.5],
            multisine_components: 6,
        }
    }
}

impl ReferenceConfig {
    /// Check every value; the centre must lie inside the joint limits `lower ..= upper`.
    pub(crate) fn validate(&self, lower: &[f64; 3], upper: &[f64; 3]) -> Result<(), ConfigError> {
        for i in 0..3 {
            check::in_range(
                &format!("reference.center[{i}]"),
                self.center[i],
                lower[i],
                upper[i],
                "inside model.limit_lower ..= model.limit_upper",
            )?;
        }
        check::in_range(
            "reference.slew_rad_s",
            self.slew_rad_s,
            0.01,
            100.0,
            "0.01 ..= 100 rad/s",
        )?;
        check::each("reference.amplitude", &self.amplitude, |f, v| {
            check::in_range(f, v, 0.0, 1.0, "0 ..= 1 rad")
        })?;
        check::in_range(
            "reference.frequency_hz",
            self.frequency_hz,
            0.0,
            10.0,
            "0 ..= 10 Hz",
        )?;
        check::in_range(
            "reference.blend_s",
            self.blend_s,
            0.05,
            60.0,
            "0.05 ..= 60 s",
        )?;
        check::in_range("reference.settle_s", self.settle_s, 0.0, 1e6, "0 ..= 1e6 s")?;
        check::each(
            "reference.multisine_amplitude",
            &self.multisine_amplitude,
            |f, v| check::in_range(f, v, 0.0, 1.0, "0 ..= 1 rad"),
        )?;
        let [lo, hi] = self.multisine_band_hz;
        check::in_range(
            "reference.multisine_band_hz[0]",
            lo,
            0.01,
            hi,
            "0.01 Hz ..= multisine_band_hz[1]",
        )?;
        check::in_range(
            "reference.multisine_band_hz[1]",
            hi,
            lo,
            10.0,
            "multisine_band_hz[0] ..= 10 Hz",
        )?;
        check::int_in(
            "reference.multisine_components",
            self.multisine_components,
            1,
            32,
            "1 ..= 32",
        )
    }
}

/// Desired position, velocity and acceleration.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RefPoint {
    pub(crate) q: Joint3,
    pub(crate) qd: Joint3,
    pub(crate) qdd: Joint3,
}

/// Trajectories selectable with `--trajectory`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Trajectory {
    /// 0.5 Hz sines about the workspace centre (amplitudes 0.4 / 0.3 / 0.3 rad).
    Sine,
    /// Sum of sines with random phases: rich excitation for identification.
    Multisine,
    /// Hold the workspace centre.
    Hold,
}

/// Most multisine components per joint (fixed storage, no allocation).
pub(crate) const MAX_COMPONENTS: usize = 32;

#[derive(Debug, Clone, Copy)]
struct Sines {
    n: usize,
    amp: [[f64; MAX_COMPONENTS]; 3],
    omega: [[f64; MAX_COMPONENTS]; 3],
    phase: [[f64; MAX_COMPONENTS]; 3],
}

impl Sines {
    fn eval(&self, center: &Joint3, t: f64) -> RefPoint {
        let mut r = RefPoint {
            q: *center,
            ..RefPoint::default()
        };
        for j in 0..3 {
            for i in 0..self.n {
                let (a, w) = (self.amp[j][i], self.omega[j][i]);
                let (s, c) = (w * t + self.phase[j][i]).sin_cos();
                r.q[j] += a * s;
                r.qd[j] += a * w * c;
                r.qdd[j] -= a * w * w * s;
            }
        }
        r
    }
}

/// A trajectory blended in from the start pose over `blend_s` seconds.
#[derive(Debug, Clone, Copy)]
pub struct Reference {
    center: Joint3,
    sines: Sines,
    blend_s: f64,
    start: Option<Joint3>,
}

/// Quintic smoothstep s(τ) = 10τ³ − 15τ⁴ + 6τ⁵ and its first two derivatives in τ.
pub(crate) fn quintic(tau: f64) -> (f64, f64, f64) {
    let t = tau.clamp(0.0, 1.0);
    let (t2, t3) = (t * t, t * t * t);
    (
        t3 * (10.0 - 15.0 * t + 6.0 * t2),
        30.0 * t2 * (1.0 - t) * (1.0 - t),
        60.0 * t * (1.0 - t) * (1.0 - 2.0 * t),
    )
}

impl Reference {
    /// Build a trajectory; `seed` draws the multisine phases.
    pub fn new(kind: Trajectory, cfg: &ReferenceConfig, seed: u64) -> Self {
        let mut sines = Sines {
            n: 0,
            amp: [[0.0; MAX_COMPONENTS]; 3],
            omega: [[0.0; MAX_COMPONENTS]; 3],
            phase: [[0.0; MAX_COMPONENTS]; 3],
        };
        match kind {
            Trajectory::Hold => {}
            Trajectory::Sine => {
                sines.n = 1;
                for j in 0..3 {
                    sines.amp[j][0] = cfg.amplitude[j];
                    sines.omega[j][0] = TAU * cfg.frequency_hz;
                }
            }
            Trajectory::Multisine => {
                let n = (cfg.multisine_components as usize).min(MAX_COMPONENTS);
                let mut rng = ChaCha8Rng::seed_from_u64(seed);
                let [lo, hi] = cfg.multisine_band_hz;
                sines.n = n;
                for j in 0..3 {
                    for i in 0..n {
                        // Log-spaced, interleaved between joints so no two share a frequency.
                        let x = (i as f64 + j as f64 / 3.0) / (n as f64 - 1.0 + 2.0 / 3.0).max(1.0);
                        sines.omega[j][i] = TAU * lo * (hi / lo).powf(x);
                        // Equal amplitudes: the sum can never exceed the configured peak.
                        sines.amp[j][i] = cfg.multisine_amplitude[j] / n as f64;
                        sines.phase[j][i] = TAU * rng.random::<f64>();
                    }
                }
            }
        }
        Reference {
            center: Joint3::from(cfg.center),
            sines,
            blend_s: cfg.blend_s,
            start: None,
        }
    }

    /// The unblended trajectory at time `t` since start.
    pub fn target(&self, t: f64) -> RefPoint {
        self.sines.eval(&self.center, t)
    }

    /// Reference at `t` seconds since start; `q_now` fixes the start pose on the first call.
    pub fn at(&mut self, t: f64, q_now: &Joint3) -> RefPoint {
        let start = *self.start.get_or_insert(*q_now);
        let target = self.target(t);
        if t >= self.blend_s {
            return target;
        }
        let (s, ds, dds) = quintic(t / self.blend_s);
        let (ds, dds) = (ds / self.blend_s, dds / (self.blend_s * self.blend_s));
        let gap = target.q - start;
        RefPoint {
            q: start + gap * s,
            qd: gap * ds + target.qd * s,
            qdd: gap * dds + target.qd * (2.0 * ds) + target.qdd * s,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fd_check(r: &mut Reference, q0: &Joint3, t: f64) {
        let h = 1e-5;
        let (p, m, c) = (r.at(t + h, q0), r.at(t - h, q0), r.at(t, q0));
        let vel = (p.q - m.q) / (2.0 * h);
        let acc = (p.qd - m.qd) / (2.0 * h);
        assert!((vel - c.qd).amax() < 1e-5, "velocity at {t}");
        assert!((acc - c.qdd).amax() < 1e-4, "acceleration at {t}");
    }

    #[test]
    fn blend_starts_at_rest_at_the_start_pose_and_is_smooth() {
        let cfg = ReferenceConfig::default();
        for kind in [Trajectory::Sine, Trajectory::Multisine, Trajectory::Hold] {
            let mut r = Reference::new(kind, &cfg, 3);
            let q0 = Joint3::new(0.0, 0.27, -0.37);
            let p0 = r.at(0.0, &q0);
            assert!((p0.q - q0).norm() < 1e-15);
            assert!(p0.qd.norm() < 1e-15 && p0.qdd.norm() < 1e-12);
            for t in [0.1, 0.5, 0.9, 1.5, 3.3] {
                fd_check(&mut r, &q0, t);
            }
            // After the blend it is the trajectory itself.
            assert_eq!(r.at(2.0, &q0), r.target(2.0));
        }
    }

    #[test]
    fn sine_matches_the_configured_amplitudes() {
        let cfg = ReferenceConfig::default();
        let r = Reference::new(Trajectory::Sine, &cfg, 0);
        let p = r.target(0.5); // quarter period of 0.5 Hz
        for j in 0..3 {
            assert!((p.q[j] - cfg.center[j] - cfg.amplitude[j]).abs() < 1e-12);
        }
    }

    #[test]
    fn multisine_stays_within_amplitude_and_depends_on_seed() {
        let cfg = ReferenceConfig::default();
        let a = Reference::new(Trajectory::Multisine, &cfg, 1);
        let b = Reference::new(Trajectory::Multisine, &cfg, 2);
        let mut differs = false;
        for k in 0..2000 {
            let t = k as f64 * 0.05;
            let (pa, pb) = (a.target(t), b.target(t));
            for j in 0..3 {
                assert!((pa.q[j] - cfg.center[j]).abs() <= cfg.multisine_amplitude[j] + 1e-12);
            }
            differs |= (pa.q - pb.q).norm() > 1e-3;
        }
        assert!(differs);
    }
}
