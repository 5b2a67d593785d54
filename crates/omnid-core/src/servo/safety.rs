//! The safety layer every command passes through (docs/DESIGN.md §4.7, issue "Safety and faults"):
//! non-finite guard, joint velocity limit, soft joint-limit walls, start-up ramp, per-joint
//! clamp, torque-rate (kick) limit and a motor thermal model. It runs in the 1 kHz loop: fixed
//! state, no allocation. Each limit that acts sets a bit in the tick's `flags`.

use crate::config_check::{self as check, ConfigError};
use crate::omni::Joint3;
use crate::telemetry::record::flags;
use serde::{Deserialize, Serialize};

/// The `[safety]` section: the limits the safety layer enforces on every tick.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SafetyConfig {
    /// Per-joint torque clamp, N·m.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub max_torque_nm: [f64; 3],
    /// Consecutive missed or bad packets that make a device fault.
    pub max_missed_ticks: u32,
    /// Largest torque change per second (kick limit), N·m/s.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub max_torque_rate_nm_s: [f64; 3],
    /// Start-up ramp from zero to full authority, s.
    pub ramp_s: f64,
    /// Joint speed beyond which the run stops with a safety fault, rad/s.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub max_velocity_rad_s: [f64; 3],
    /// Soft wall: lower joint angles, rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub wall_lower: [f64; 3],
    /// Soft wall: upper joint angles, rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub wall_upper: [f64; 3],
    /// Soft wall stiffness, N·m/rad.
    pub wall_stiffness: f64,
    /// Soft wall damping, N·m·s/rad.
    pub wall_damping: f64,
    /// Continuous torque rating per motor, N·m: the thermal model's unit of heating.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub continuous_torque_nm: [f64; 3],
    /// Thermal time constant of the motor windings, s.
    pub thermal_time_constant_s: f64,
    /// Heat level that warns (1 = steady state at continuous torque).
    pub thermal_warn: f64,
    /// Heat level that clamps the motor to its continuous torque.
    pub thermal_limit: f64,
    /// Heat level below which the thermal clamp releases.
    pub thermal_release: f64,
    /// Carry motor heat over between runs (a small file in the user's state directory; one
    /// that cannot be believed means motors at the thermal limit, never cold ones).
    pub persist_heat: bool,
}

impl Default for SafetyConfig {
    fn default() -> Self {
        SafetyConfig {
            max_torque_nm: [0.45; 3],
            max_missed_ticks: 20,
            max_torque_rate_nm_s: [50.0; 3],
            ramp_s: 0.5,
            max_velocity_rad_s: [10.0; 3],
            wall_lower: [-0.95, -0.05, -0.55],
            wall_upper: [0.95, 1.7, 1.15],
            wall_stiffness: 2.0,
            wall_damping: 0.02,
            continuous_torque_nm: [0.13; 3],
            thermal_time_constant_s: 30.0,
            thermal_warn: 0.8,
            thermal_limit: 1.0,
            thermal_release: 0.9,
            persist_heat: true,
        }
    }
}

impl SafetyConfig {
    /// Check every value; the first problem names its field (`safety.…`). Long on purpose:
    /// one check per field in the fields' order.
    pub fn validate(&self) -> Result<(), ConfigError> {
        for j in 0..3 {
            let f = |name: &str| format!("safety.{name}[{j}]");
            check::in_range(
                &f("max_torque_nm"),
                self.max_torque_nm[j],
                f64::MIN_POSITIVE,
                2.0,
                "> 0 and ≤ 2 N·m",
            )?;
            check::in_range(
                &f("max_torque_rate_nm_s"),
                self.max_torque_rate_nm_s[j],
                1e-3,
                1e6,
                "1e-3 ..= 1e6 N·m/s",
            )?;
            check::in_range(
                &f("max_velocity_rad_s"),
                self.max_velocity_rad_s[j],
                0.1,
                1000.0,
                "0.1 ..= 1000 rad/s",
            )?;
            check::in_range(
                &f("wall_lower"),
                self.wall_lower[j],
                -3.2,
                self.wall_upper[j],
                "-3.2 rad ..= safety.wall_upper",
            )?;
            check::in_range(
                &f("wall_upper"),
                self.wall_upper[j],
                self.wall_lower[j],
                3.2,
                "safety.wall_lower ..= 3.2 rad",
            )?;
            check::in_range(
                &f("continuous_torque_nm"),
                self.continuous_torque_nm[j],
                f64::MIN_POSITIVE,
                self.max_torque_nm[j],
                "> 0 and ≤ safety.max_torque_nm",
            )?;
        }
        if !(1..=10_000).contains(&self.max_missed_ticks) {
            return Err(check::invalid(
                "safety.max_missed_ticks",
                self.max_missed_ticks.to_string(),
                "1 ..= 10000",
            ));
        }
        check::in_range("safety.ramp_s", self.ramp_s, 0.0, 60.0, "0 ..= 60 s")?;
        check::in_range(
            "safety.wall_stiffness",
            self.wall_stiffness,
            0.0,
            1e3,
            "0 ..= 1000 N·m/rad",
        )?;
        check::in_range(
            "safety.wall_damping",
            self.wall_damping,
            0.0,
            10.0,
            "0 ..= 10 N·m·s/rad",
        )?;
        check::in_range(
            "safety.thermal_time_constant_s",
            self.thermal_time_constant_s,
            0.1,
            1e5,
            "0.1 ..= 1e5 s",
        )?;
        check::in_range(
            "safety.thermal_limit",
            self.thermal_limit,
            0.1,
            100.0,
            "0.1 ..= 100",
        )?;
        check::in_range(
            "safety.thermal_warn",
            self.thermal_warn,
            0.0,
            self.thermal_limit,
            "0 ..= safety.thermal_limit",
        )?;
        check::in_range(
            "safety.thermal_release",
            self.thermal_release,
            0.0,
            self.thermal_limit,
            "0 ..= safety.thermal_limit",
        )?;
        Ok(())
    }
}

pub use crate::telemetry::record::SafetyTrip;

/// The torque the layer let through and which limits acted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Limited {
    pub tau: Joint3,
    pub flags: u32,
}

/// Measured samples the encoder speed is taken over (about 10 ms at 1 kHz: long enough that
/// one count of quantisation is a small margin, short enough to catch a runaway).
const MEASURED_WINDOW: usize = 11;

/// State of the safety layer for one run.
#[derive(Debug, Clone)]
pub struct SafetyLayer {
    cfg: SafetyConfig,
    dt: f64,
    last_tau: Joint3,
    /// Seconds of authority since start (or since the last recovery).
    ramp_elapsed: f64,
    /// Heat per motor, in units of the continuous-torque steady state.
    heat: [f64; 3],
    hot: [bool; 3],
    warned: [bool; 3],
    /// Recent (device time, measured angles), a ring; `seen` of them valid.
    measured: [(f64, Joint3); MEASURED_WINDOW],
    newest: usize,
    seen: usize,
    /// One encoder count, rad: the measured speed's quantisation margin.
    count_rad: f64,
}

impl SafetyLayer {
    /// `dt`: the servo period, s. `heat`: the motors' heat at start (0 = cold).
    pub fn new(cfg: &SafetyConfig, dt: f64, heat: [f64; 3]) -> Self {
        SafetyLayer {
            cfg: cfg.clone(),
            dt,
            last_tau: Joint3::zeros(),
            ramp_elapsed: 0.0,
            heat,
            hot: [false; 3],
            warned: [false; 3],
            measured: [(0.0, Joint3::zeros()); MEASURED_WINDOW],
            newest: 0,
            seen: 0,
            count_rad: 0.0,
        }
    }

    /// The limits also watch the encoders, `count_rad` radians a count (0: ideal).
    pub fn with_encoder_step(mut self, count_rad: f64) -> Self {
        self.count_rad = count_rad;
        self
    }

    /// What the encoders measured at device time `t` (every tick, amplifiers on or off): the
    /// walls and the speed limit act on it as well as on the estimate, so the limits hold
    /// whatever the estimator's tuning.
    pub fn observe(&mut self, t: f64, q: &Joint3) {
        self.newest = (self.newest + 1) % MEASURED_WINDOW;
        self.measured[self.newest] = (t, *q);
        self.seen = (self.seen + 1).min(MEASURED_WINDOW);
    }

    /// The fastest joint by the encoders over the window, beyond one count of quantisation at
    /// each end: (joint, speed) if any exceeds its limit.
    fn measured_overspeed(&self) -> Option<(usize, f64)> {
        if self.seen < MEASURED_WINDOW {
            return None;
        }
        let (t1, q1) = self.measured[self.newest];
        let (t0, q0) = self.measured[(self.newest + 1) % MEASURED_WINDOW];
        let span = t1 - t0;
        if span <= 0.0 {
            return None;
        }
        let margin = 2.0 * self.count_rad / span;
        (0..3).find_map(|j| {
            let speed = (q1[j] - q0[j]) / span;
            (speed.abs() > self.cfg.max_velocity_rad_s[j] + margin).then_some((j, speed))
        })
    }

    /// One tick with the amplifiers off: nothing is sent, the motors cool, and authority
    /// will ramp up again from zero.
    pub fn rest(&mut self) {
        self.last_tau = Joint3::zeros();
        self.ramp_elapsed = 0.0;
        let mut unused = 0;
        self.heat_up(&Joint3::zeros(), &mut unused);
    }

    /// Whether the start-up ramp is over: the commands pass at full authority.
    pub fn full_authority(&self) -> bool {
        self.ramp_elapsed >= self.cfg.ramp_s
    }

    /// Start the ramp again (after a recovery): authority returns gradually.
    pub fn restart_ramp(&mut self) {
        self.ramp_elapsed = 0.0;
    }

    pub fn set_heat(&mut self, heat: [f64; 3]) {
        self.heat = heat;
    }

    pub fn heat(&self) -> [f64; 3] {
        self.heat
    }

    /// Pass one command through every limit. `q`, `qd`: the estimated joint state. Long on
    /// purpose: the limits act in a fixed order (the order is part of the safety contract,
    /// docs/DESIGN.md §4.7), and reading them top to bottom in one function shows it.
    pub fn apply(
        &mut self,
        tau_cmd: &Joint3,
        q: &Joint3,
        qd: &Joint3,
    ) -> Result<Limited, SafetyTrip> {
        let c = &self.cfg;
        if let Some(joint) = tau_cmd.iter().position(|v| !v.is_finite()) {
            return Err(SafetyTrip::NonFinite { joint });
        }
        for j in 0..3 {
            if qd[j].abs() > c.max_velocity_rad_s[j] || !qd[j].is_finite() {
                return Err(SafetyTrip::Velocity {
                    joint: j,
                    speed: qd[j],
                });
            }
        }
        if let Some((joint, speed)) = self.measured_overspeed() {
            return Err(SafetyTrip::MeasuredVelocity { joint, speed });
        }
        let mut fl = 0;
        let mut tau = *tau_cmd;

        // Soft walls: a spring-damper pushing back into the workspace, from whichever of the
        // estimate and the encoders is further out, added to what the controller asks that
        // points back in (its push further out is dropped). Replacing the controller's torque
        // would leave only the weak wall spring to lift the arm against gravity, and the
        // controller would wind up beyond the wall.
        let measured = (self.seen > 0).then(|| self.measured[self.newest].1);
        for j in 0..3 {
            let beyond = |q: f64| {
                if q < c.wall_lower[j] {
                    q - c.wall_lower[j]
                } else if q > c.wall_upper[j] {
                    q - c.wall_upper[j]
                } else {
                    0.0
                }
            };
            let (by_estimate, by_encoders) = (beyond(q[j]), measured.map_or(0.0, |m| beyond(m[j])));
            let over = if by_encoders.abs() > by_estimate.abs() {
                by_encoders
            } else {
                by_estimate
            };
            if over == 0.0 {
                continue;
            }
            // Damp only motion that goes further out.
            let outward = if qd[j] * over > 0.0 { qd[j] } else { 0.0 };
            let inward = if tau[j] * over < 0.0 { tau[j] } else { 0.0 };
            tau[j] = inward - c.wall_stiffness * over - c.wall_damping * outward;
            fl |= flags::WALL;
        }

        // Start-up ramp: authority grows linearly from zero.
        if self.ramp_elapsed < c.ramp_s {
            self.ramp_elapsed += self.dt;
            tau *= (self.ramp_elapsed / c.ramp_s).min(1.0);
            fl |= flags::RAMP;
        }

        // Thermal model, then the clamp: a hot motor is held to its continuous torque.
        for j in 0..3 {
            let lim = if self.hot[j] {
                c.continuous_torque_nm[j]
            } else {
                c.max_torque_nm[j]
            };
            if tau[j].abs() > lim {
                tau[j] = tau[j].clamp(-lim, lim);
                fl |= if self.hot[j] {
                    flags::THERMAL
                } else {
                    flags::CLAMPED
                };
            }
        }

        // Kick limit: bounded change from the last command.
        for j in 0..3 {
            let step = c.max_torque_rate_nm_s[j] * self.dt;
            let d = tau[j] - self.last_tau[j];
            if d.abs() > step {
                tau[j] = self.last_tau[j] + step.copysign(d);
                fl |= flags::RATE;
            }
        }

        self.heat_up(&tau, &mut fl);
        self.last_tau = tau;
        Ok(Limited { tau, flags: fl })
    }

    /// First-order I²R heating: d(heat)/dt = ((τ/τ_cont)² − heat)/T_th.
    fn heat_up(&mut self, tau: &Joint3, fl: &mut u32) {
        let c = &self.cfg;
        let a = (-self.dt / c.thermal_time_constant_s).exp();
        for j in 0..3 {
            let load = (tau[j] / c.continuous_torque_nm[j]).powi(2);
            self.heat[j] = a * self.heat[j] + (1.0 - a) * load;
            if self.heat[j] >= c.thermal_limit {
                self.hot[j] = true;
            } else if self.heat[j] < c.thermal_release {
                self.hot[j] = false;
            }
            if self.heat[j] >= c.thermal_warn {
                self.warned[j] = true;
                *fl |= flags::THERMAL_WARN;
            }
        }
    }

    /// Joints that reached the warning level at some point in the run.
    pub fn thermal_warned(&self) -> [bool; 3] {
        self.warned
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn layer() -> SafetyLayer {
        SafetyLayer::new(&SafetyConfig::default(), 1e-3, [0.0; 3])
    }

    const Q: Joint3 = Joint3::new(0.0, 0.6, 0.3);

    #[test]
    fn defaults_are_valid() {
        SafetyConfig::default().validate().unwrap();
    }

    #[test]
    fn ramp_starts_at_zero_authority() {
        let mut s = layer();
        let first = s
            .apply(&Joint3::repeat(0.01), &Q, &Joint3::zeros())
            .unwrap();
        assert!(first.tau.amax() <= 0.01 * 1e-3 / 0.5 + 1e-15);
        assert!(first.flags & flags::RAMP != 0);
        for _ in 0..600 {
            s.apply(&Joint3::repeat(0.01), &Q, &Joint3::zeros())
                .unwrap();
        }
        let later = s
            .apply(&Joint3::repeat(0.01), &Q, &Joint3::zeros())
            .unwrap();
        assert_eq!(later.tau, Joint3::repeat(0.01));
        assert_eq!(later.flags, 0);
    }

    #[test]
    fn non_finite_and_overspeed_trip() {
        let mut s = layer();
        assert_eq!(
            s.apply(&Joint3::new(0.0, f64::NAN, 0.0), &Q, &Joint3::zeros()),
            Err(SafetyTrip::NonFinite { joint: 1 })
        );
        assert!(matches!(
            s.apply(&Joint3::zeros(), &Q, &Joint3::new(0.0, 0.0, -12.0)),
            Err(SafetyTrip::Velocity { joint: 2, .. })
        ));
    }

    #[test]
    fn walls_push_back_into_the_workspace() {
        let cfg = SafetyConfig {
            ramp_s: 0.0,
            ..Default::default()
        };
        let mut s = SafetyLayer::new(&cfg, 1e-3, [0.0; 3]);
        let q = Joint3::new(1.0, 0.6, -0.6); // beyond j1's upper and j3's lower wall
        let out = s.apply(&Joint3::zeros(), &q, &Joint3::zeros()).unwrap();
        assert!(out.tau[0] < 0.0 && out.tau[2] > 0.0 && out.tau[1] == 0.0);
        assert!(out.flags & flags::WALL != 0);
    }

    #[test]
    fn beyond_a_wall_the_controllers_pull_back_in_is_kept_and_its_push_out_dropped() {
        let cfg = SafetyConfig {
            ramp_s: 0.0,
            max_torque_rate_nm_s: [1e6; 3],
            ..Default::default()
        };
        let mut s = SafetyLayer::new(&cfg, 1e-3, [0.0; 3]);
        // 0.06 rad beyond joint 3's lower wall: the wall spring alone is 0.12 N·m.
        let q = Joint3::new(0.0, 0.6, -0.61);
        let spring = cfg.wall_stiffness * 0.06;
        // The controller lifts the arm back in with 0.3 N·m: both act (the wall used to
        // replace it, too weak alone to lift the arm against gravity).
        let out = s
            .apply(&Joint3::new(0.0, 0.0, 0.3), &q, &Joint3::zeros())
            .unwrap();
        assert!((out.tau[2] - (0.3 + spring)).abs() < 1e-9, "{}", out.tau[2]);
        // A push further out is dropped: only the wall acts.
        let mut s = SafetyLayer::new(&cfg, 1e-3, [0.0; 3]);
        let out = s
            .apply(&Joint3::new(0.0, 0.0, -0.3), &q, &Joint3::zeros())
            .unwrap();
        assert!((out.tau[2] - spring).abs() < 1e-9, "{}", out.tau[2]);
    }

    #[test]
    fn sustained_high_torque_heats_and_clamps_to_continuous() {
        let cfg = SafetyConfig {
            ramp_s: 0.0,
            thermal_time_constant_s: 2.0,
            ..Default::default()
        };
        let mut s = SafetyLayer::new(&cfg, 1e-3, [0.0; 3]);
        let demand = Joint3::new(0.4, 0.0, 0.0);
        let mut clamped_at = None;
        for k in 0..20_000 {
            let out = s.apply(&demand, &Q, &Joint3::zeros()).unwrap();
            if out.flags & flags::THERMAL != 0 {
                clamped_at.get_or_insert(k);
                assert!((out.tau[0] - 0.13).abs() < 1e-12 || out.flags & flags::RATE != 0);
            }
        }
        let k = clamped_at.expect("the thermal clamp must act");
        // Heating toward (0.4/0.13)² ≈ 9.5 reaches 1 after T·ln(9.5/8.5) ≈ 0.22 s.
        assert!((150..400).contains(&k), "clamped after {k} ticks");
        assert!(s.thermal_warned()[0] && !s.thermal_warned()[1]);
        // Held at the continuous torque, the heat settles at ≤ 1 and the clamp releases and
        // re-engages around the limit rather than running away.
        assert!(s.heat()[0] < 1.05);
    }

    #[test]
    fn limits_hold_on_the_encoders_whatever_the_estimate() {
        let count = std::f64::consts::TAU / 15000.0;
        let cfg = SafetyConfig {
            ramp_s: 0.0,
            ..Default::default()
        };
        let mut s = SafetyLayer::new(&cfg, 1e-3, [0.0; 3]).with_encoder_step(count);
        // At rest, one count of jitter every tick never trips.
        for k in 0..100 {
            let jitter = if k % 2 == 0 { count } else { 0.0 };
            s.observe(k as f64 * 1e-3, &(Q + Joint3::new(jitter, 0.0, 0.0)));
            s.apply(&Joint3::zeros(), &Q, &Joint3::zeros()).unwrap();
        }
        // The encoders say joint 2 runs at 12 rad/s; the estimate says it is at rest.
        let mut tripped = None;
        for k in 100..130 {
            let t = k as f64 * 1e-3;
            s.observe(t, &(Q + Joint3::new(0.0, 12.0 * (t - 0.1), 0.0)));
            if let Err(e) = s.apply(&Joint3::zeros(), &Q, &Joint3::zeros()) {
                tripped = Some((k, e));
                break;
            }
        }
        let (k, e) = tripped.expect("the encoders' speed trips");
        assert!(
            matches!(e, SafetyTrip::MeasuredVelocity { joint: 1, .. }),
            "{e}"
        );
        assert!(k <= 100 + 11, "tripped after {} ticks", k - 100);

        // The encoders beyond the upper wall of joint 1; the estimate inside: the wall acts.
        let mut w = SafetyLayer::new(&cfg, 1e-3, [0.0; 3]).with_encoder_step(count);
        w.observe(0.0, &Joint3::new(1.0, 0.6, 0.3));
        let out = w.apply(&Joint3::zeros(), &Q, &Joint3::zeros()).unwrap();
        assert!(out.tau[0] < 0.0 && out.flags & flags::WALL != 0);
    }

    #[test]
    fn motors_cool_while_resting_and_authority_ramps_up_again() {
        let cfg = SafetyConfig {
            ramp_s: 0.0,
            thermal_time_constant_s: 1.0,
            ..Default::default()
        };
        let mut s = SafetyLayer::new(&cfg, 1e-3, [0.0; 3]);
        for _ in 0..2000 {
            s.apply(&Joint3::new(0.3, 0.0, 0.0), &Q, &Joint3::zeros())
                .unwrap();
        }
        let hot = s.heat()[0];
        assert!(hot > 1.0);
        for _ in 0..1000 {
            s.rest();
        }
        // First-order cooling over one time constant: e⁻¹ of the heat is left.
        let left = s.heat()[0] / hot;
        assert!((left - (-1.0f64).exp()).abs() < 1e-3, "{left}");
        let cfg_ramp = SafetyConfig::default();
        let mut r = SafetyLayer::new(&cfg_ramp, 1e-3, [0.0; 3]);
        for _ in 0..1000 {
            r.apply(&Joint3::repeat(0.01), &Q, &Joint3::zeros())
                .unwrap();
        }
        r.rest();
        let first = r
            .apply(&Joint3::repeat(0.01), &Q, &Joint3::zeros())
            .unwrap();
        assert!(first.flags & flags::RAMP != 0 && first.tau.amax() < 0.001);
    }

    proptest! {
        #[test]
        fn never_exceeds_clamp_or_kick_limit(cmds in proptest::collection::vec(
            prop_oneof![
                (-5.0f64..5.0),
                Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY), Just(1e300)
            ], 3..300)) {
            let cfg = SafetyConfig::default();
            let mut s = SafetyLayer::new(&cfg, 1e-3, [0.0; 3]);
            let mut last = Joint3::zeros();
            for chunk in cmds.chunks(3) {
                let cmd = Joint3::from_fn(|j, _| chunk[j % chunk.len()]);
                match s.apply(&cmd, &Q, &Joint3::zeros()) {
                    Ok(out) => {
                        for j in 0..3 {
                            prop_assert!(out.tau[j].is_finite());
                            prop_assert!(out.tau[j].abs() <= cfg.max_torque_nm[j] + 1e-12);
                            prop_assert!((out.tau[j] - last[j]).abs() <= cfg.max_torque_rate_nm_s[j] * 1e-3 + 1e-12);
                        }
                        last = out.tau;
                    }
                    Err(SafetyTrip::NonFinite { .. }) => prop_assert!(cmd.iter().any(|v| !v.is_finite())),
                    Err(e) => prop_assert!(false, "unexpected trip {e}"),
                }
            }
        }
    }
}
