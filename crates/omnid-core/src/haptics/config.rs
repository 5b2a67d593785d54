//! `[haptics]`: the limits on forces rendered at the stylus tip (docs/HAPTICS.md).

use super::hand::HandConfig;
use crate::config_check::{self as check, ConfigError};
use serde::{Deserialize, Serialize};

/// `[haptics]`: the force limits, the passivity controller and the simulated hand.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct HapticsConfig {
    /// Largest tip force the servo passes on, N (the norm of a commanded force is clamped to
    /// it; the vendor's peak figure by default).
    pub max_force_n: f64,
    /// Continuous tip force, N: when the force's mean square over `continuous_time_s` has
    /// reached this squared, the force is held to it until that falls to 90 % (the vendor's
    /// continuous figure by default).
    pub continuous_force_n: f64,
    /// Time constant of that mean square, s.
    pub continuous_time_s: f64,
    /// A change of an effect's parameters fades in over this time, s (no force step).
    pub fade_s: f64,
    /// The passivity controller acts on the effects (docs/HAPTICS.md §6).
    pub passivity: bool,
    /// Largest damping the passivity controller adds, N·s/m.
    pub passivity_max_damping_n_s_per_m: f64,
    /// Most energy the passivity observer keeps in hand, J.
    pub passivity_reserve_j: f64,
    /// Free mode and `servo_cf`: compensate this fraction β of the law's inertia, β·M(q)·q̈, so
    /// the hand carries less of the arm's mass; off in contact (docs/HAPTICS.md §3), 0 ..= 0.5.
    pub inertia_compensation: f64,
    /// The simulated hand on the stylus (simulator only; `omnid run --hand`).
    pub hand: HandConfig,
    /// Which model the external-force estimate subtracts (active, parametric or learned;
    /// docs/TELEOP.md §2).
    pub external_model: super::ExternalModel,
    /// Bandwidth of the external-force estimate (its momentum observer's first-order lag), Hz.
    pub external_cutoff_hz: f64,
}

impl Default for HapticsConfig {
    fn default() -> Self {
        HapticsConfig {
            max_force_n: 3.3,
            continuous_force_n: 0.88,
            continuous_time_s: 10.0,
            fade_s: 0.1,
            passivity: true,
            passivity_max_damping_n_s_per_m: 20.0,
            passivity_reserve_j: 1e-3,
            inertia_compensation: 0.3,
            hand: HandConfig::default(),
            external_model: super::ExternalModel::Active,
            external_cutoff_hz: 15.0,
        }
    }
}

impl HapticsConfig {
    pub(crate) fn validate(&self) -> Result<(), ConfigError> {
        check::in_range(
            "haptics.max_force_n",
            self.max_force_n,
            0.0,
            20.0,
            "0 ..= 20 N",
        )?;
        check::in_range(
            "haptics.continuous_force_n",
            self.continuous_force_n,
            0.0,
            self.max_force_n,
            "0 ..= haptics.max_force_n",
        )?;
        check::in_range(
            "haptics.continuous_time_s",
            self.continuous_time_s,
            0.01,
            1e4,
            "0.01 ..= 1e4 s",
        )?;
        check::in_range("haptics.fade_s", self.fade_s, 0.0, 10.0, "0 ..= 10 s")?;
        check::in_range(
            "haptics.passivity_max_damping_n_s_per_m",
            self.passivity_max_damping_n_s_per_m,
            0.0,
            1000.0,
            "0 ..= 1000 N·s/m",
        )?;
        check::in_range(
            "haptics.passivity_reserve_j",
            self.passivity_reserve_j,
            0.0,
            1.0,
            "0 ..= 1 J",
        )?;
        check::in_range(
            "haptics.inertia_compensation",
            self.inertia_compensation,
            0.0,
            super::MAX_INERTIA_COMPENSATION,
            "0 ..= 0.5",
        )?;
        check::in_range(
            "haptics.external_cutoff_hz",
            self.external_cutoff_hz,
            0.1,
            200.0,
            "0.1 ..= 200 Hz",
        )?;
        validate_hand(&self.hand)
    }
}

/// `[haptics.hand]` (the pattern was checked when it was read).
fn validate_hand(h: &HandConfig) -> Result<(), ConfigError> {
    check::in_range(
        "haptics.hand.stiffness_n_per_m",
        h.stiffness_n_per_m,
        1.0,
        1e5,
        "1 ..= 1e5 N/m",
    )?;
    check::in_range(
        "haptics.hand.damping_n_s_per_m",
        h.damping_n_s_per_m,
        0.0,
        1e3,
        "0 ..= 1000 N·s/m",
    )?;
    check::in_range(
        "haptics.hand.speed_m_s",
        h.speed_m_s,
        0.001,
        1.0,
        "0.001 ..= 1 m/s",
    )?;
    check::in_range(
        "haptics.hand.push_force_n",
        h.push_force_n,
        0.0,
        10.0,
        "0 ..= 10 N",
    )?;
    check::in_range(
        "haptics.hand.release_s",
        h.release_s,
        0.0,
        1e6,
        "0 ..= 1e6 s",
    )?;
    check::in_range(
        "haptics.hand.approach_s",
        h.approach_s,
        0.0,
        60.0,
        "0 ..= 60 s",
    )?;
    check::in_range(
        "haptics.hand.path_radius_m",
        h.path_radius_m,
        0.001,
        0.1,
        "0.001 ..= 0.1 m",
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::haptics::HandPattern;

    #[test]
    fn defaults_are_valid_and_bad_values_name_the_field() {
        HapticsConfig::default().validate().unwrap();
        for bad in [-1.0, f64::NAN, 100.0] {
            let e = HapticsConfig {
                max_force_n: bad,
                ..Default::default()
            }
            .validate()
            .unwrap_err();
            assert!(e.to_string().contains("haptics.max_force_n"), "{e}");
        }
        for bad in [-0.1, 0.51, f64::NAN, f64::INFINITY] {
            let e = HapticsConfig {
                inertia_compensation: bad,
                ..Default::default()
            }
            .validate()
            .unwrap_err();
            assert!(
                e.to_string().contains("haptics.inertia_compensation"),
                "{e}"
            );
        }
        for good in [0.0, 0.25, super::super::MAX_INERTIA_COMPENSATION] {
            HapticsConfig {
                inertia_compensation: good,
                ..Default::default()
            }
            .validate()
            .unwrap();
        }
        let mut bad = HapticsConfig::default();
        bad.hand.stiffness_n_per_m = 0.0;
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains("haptics.hand.stiffness_n_per_m"), "{e}");
    }

    #[test]
    fn a_hand_pattern_is_read_by_name_and_a_bad_one_named() {
        let cfg: HapticsConfig = toml::from_str("[hand]\npattern = \"push-y\"\n").unwrap();
        assert_eq!(
            cfg.hand.pattern,
            HandPattern::Push {
                axis: 1,
                sign: -1.0
            }
        );
        let e = toml::from_str::<HapticsConfig>("[hand]\npattern = \"walk\"\n").unwrap_err();
        assert!(
            e.to_string().contains("walk") && e.to_string().contains("push+x"),
            "{e}"
        );
    }
}
