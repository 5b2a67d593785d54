//! `[haptics]`: the limits on forces rendered at the stylus tip (docs/HAPTICS.md).

use crate::config::ConfigError;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct HapticsConfig {
    /// Largest tip force the servo passes on, N (the norm of a commanded force is clamped to
    /// it; the vendor's peak figure by default).
    pub max_force_n: f64,
}

impl Default for HapticsConfig {
    fn default() -> Self {
        HapticsConfig { max_force_n: 3.3 }
    }
}

pub const HAPTICS_FIELD_DOCS: &[(&str, &str)] = &[
    (
        "haptics",
        "Forces at the stylus tip (servo_cf, effects): docs/HAPTICS.md.",
    ),
    (
        "haptics.max_force_n",
        "largest tip force passed on, N (a commanded force's norm is clamped to it; vendor peak 3.3 N)",
    ),
];

fn finite_in(field: &str, v: f64, lo: f64, hi: f64, allowed: &str) -> Result<(), ConfigError> {
    if v.is_finite() && (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(ConfigError::Invalid {
            field: field.to_string(),
            value: v.to_string(),
            allowed: allowed.to_string(),
        })
    }
}

impl HapticsConfig {
    pub fn validate(&self) -> Result<(), ConfigError> {
        finite_in(
            "haptics.max_force_n",
            self.max_force_n,
            0.0,
            20.0,
            "0 ..= 20 N",
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_values_name_the_field() {
        HapticsConfig::default().validate().unwrap();
        for bad in [-1.0, f64::NAN, 100.0] {
            let e = HapticsConfig { max_force_n: bad }.validate().unwrap_err();
            assert!(e.to_string().contains("haptics.max_force_n"), "{e}");
        }
    }
}
