//! `[identifier]` configuration: every tunable of the adaptive identifier (docs/DESIGN.md §3), its
//! defaults, validation naming the field and the allowed range, and one line of documentation
//! per key for `omnid config --print-default`.

use crate::config_check::{self as check, ConfigError};
use serde::{Deserialize, Serialize};

/// `[identifier]`: the networks' sizes and the learning law's gains and guards.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct IdentifierConfig {
    /// Bandwidth of the modified error α·e + ė = ε (eq. 21), 1/s.
    pub alpha: f64,
    /// Modified-error filter with unit DC gain, e ← e^(−αT)e + (1 − e^(−αT))ε, so α only sets
    /// the bandwidth; false is eq. 21 as written (DC gain 1/α, so the effective rate is Γ/α).
    pub unit_gain_filter: bool,
    /// Hidden units of every network.
    pub hidden: usize,
    /// Adapt the weights online.
    pub adapt: bool,
    /// Fourth network for joint friction F̂(q̇); false gives the paper's three networks.
    pub friction_net: bool,
    /// WAE weight of e2 (diagonal of Ṁ̂ − 2Ĉ); 0 = off, paper: > 1.
    pub lambda1: f64,
    /// WAE weight of e3 (off-diagonal skew-symmetry); 0 = off, paper: > 1.
    pub lambda2: f64,
    /// WAE weight of e4 (eigenvalues of M̂ in [eig_min, eig_max]); 0 = off.
    pub lambda3: f64,
    /// Learning rates Γ of the M-net, [hidden layer, output layer].
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub rate_m: [f64; 2],
    /// Learning rates Γ of the C-net, [hidden layer, output layer].
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub rate_c: [f64; 2],
    /// Learning rates Γ of the G-net, [hidden layer, output layer].
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub rate_g: [f64; 2],
    /// Learning rates Γ of the F-net, [hidden layer, output layer].
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub rate_f: [f64; 2],
    /// Dead zone: no update while the modified error at the scale of ε (α·‖e‖, or ‖e‖ with
    /// `unit_gain_filter`), in N·m, is at or below this; 0 switches it off.
    pub dead_zone: f64,
    /// σ-modification: leakage −σΓ(θ − θ0) toward the pre-tuned (or loaded) weights; 0 switches
    /// it off. Fresh random weights are no anchor: it acts only once weights are pre-tuned or
    /// loaded. Without it (1e-4 before) NNIDC's weights drift and the arm goes unstable after
    /// ~50 s of the sine.
    pub sigma: f64,
    /// Velocity reversals (docs/IDENTIFIER.md, "fifth round"): while a joint's estimated speed
    /// is below this, and for `reversal_hold_s` after, its row of e1 does not drive the update
    /// (the Coulomb step the plant takes at the true velocity's zero, the filter's q̇ crosses
    /// some 10 ms later: no model of the filtered state explains it), rad/s; 0 switches it off.
    /// Only with the friction net (without it the update is what compensates the step).
    pub reversal_speed: f64,
    /// How long a joint's e1 stays out of the update after its speed rose above
    /// `reversal_speed`, s.
    pub reversal_hold_s: f64,
    /// Lag-matched e1 (docs/IDENTIFIER.md, "Lag-matched e1"): online, τ − Ĉq̇ − Ĝ − F̂ passes
    /// through the Kalman filter's own acceleration response before it meets M̂·q̈ (so the
    /// torque and the estimated q̈ carry the same lag); false is e1 = τ − τ̂ as the paper
    /// writes it.
    pub lag_match: bool,
    /// Projection: bound on each network's parameter norm ‖θ‖_F; 0 switches it off.
    pub w_max: f64,
    /// Lower bound on the eigenvalues of M̂ (e4), kg·m².
    pub eig_min: f64,
    /// Upper bound on the eigenvalues of M̂ (e4), kg·m².
    pub eig_max: f64,
    /// Joint angles are fed as (q − q_center)/q_scale, rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub q_center: [f64; 3],
    /// Joint-angle input scale, rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub q_scale: [f64; 3],
    /// Joint-velocity inputs of the C-net enter as q̇/qd_scale, rad/s.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub qd_scale: [f64; 3],
    /// Joint-velocity inputs of the F-net enter as q̇/friction_qd_scale, rad/s (smaller than
    /// qd_scale: Coulomb friction changes sign within a few 0.01 rad/s).
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub friction_qd_scale: [f64; 3],
    /// Output unit of the M-net and of e4, kg·m².
    pub inertia_scale: f64,
    /// Output unit of the C-net, kg·m².
    pub coriolis_scale: f64,
    /// Output unit of the G-net, N·m.
    pub gravity_scale: f64,
    /// Output unit of the F-net, N·m.
    pub friction_scale: f64,
    /// The errors are made dimensionless with this torque, N·m (e1, e2, e3; e4 with
    /// inertia_scale), so the rates are O(1)–O(100) instead of O(1e6).
    pub torque_scale: f64,
    /// Initial diagonal of M̂ (output biases of the M-net), kg·m²; zeros start from M̂ = 0.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub init_mass_diag: [f64; 3],
    /// Std of fresh hidden-layer weights (divided by √inputs).
    pub init_std_hidden: f64,
    /// Std of fresh output-layer weights.
    pub init_std_output: f64,
    /// Seed of the initial weights.
    pub seed: u64,
    /// `omnid serve`: keep what the arm learned (a file per arm in the state directory, beside
    /// its motor heat), saved when the daemon ends cleanly, and start the next daemon from it
    /// (docs/IDENTIFIER.md); false: every daemon starts from the shipped (or `--weights`) ones.
    pub persist: bool,
}

impl Default for IdentifierConfig {
    fn default() -> Self {
        IdentifierConfig {
            alpha: 50.0,
            unit_gain_filter: false,
            hidden: 16,
            adapt: true,
            friction_net: true,
            lambda1: 2.0,
            lambda2: 2.0,
            lambda3: 2.0,
            rate_m: [50.0, 50.0],
            rate_c: [50.0, 50.0],
            rate_g: [25.0, 25.0],
            rate_f: [25.0, 25.0],
            dead_zone: 1e-4,
            sigma: 3e-3,
            reversal_speed: 0.01,
            reversal_hold_s: 0.01,
            lag_match: true,
            w_max: 100.0,
            eig_min: 2e-4,
            eig_max: 1.5e-2,
            q_center: [0.0, 0.65, 0.3],
            q_scale: [0.5, 0.4, 0.4],
            qd_scale: [1.0; 3],
            friction_qd_scale: [0.05; 3],
            inertia_scale: 1e-3,
            coriolis_scale: 1e-3,
            gravity_scale: 3e-2,
            friction_scale: 1e-2,
            torque_scale: 1e-2,
            init_mass_diag: [3.5e-3, 2.6e-3, 1.1e-3],
            init_std_hidden: 1.0,
            init_std_output: 0.1,
            seed: 1,
            persist: true,
        }
    }
}

fn positive(field: &str, v: f64, hi: f64, allowed: &str) -> Result<(), ConfigError> {
    if v.is_finite() && v > 0.0 && v <= hi {
        Ok(())
    } else {
        Err(check::invalid(field, v, allowed))
    }
}

impl IdentifierConfig {
    /// Check every value; the first problem is returned naming its field (`identifier.…`).
    /// One helper per group of fields, called in the fields' order, so the first problem found
    /// is the same as one check per field in order would find.
    pub(crate) fn validate(&self) -> Result<(), ConfigError> {
        self.check_law()?;
        self.check_rates()?;
        self.check_guards()?;
        self.check_inertia_bounds()?;
        self.check_scalings()?;
        self.check_init()
    }

    /// The update law: α, the hidden layer's size, the error weights λ1..λ3.
    fn check_law(&self) -> Result<(), ConfigError> {
        positive(
            "identifier.alpha",
            self.alpha,
            1e6,
            "finite, > 0 and ≤ 1e6 1/s",
        )?;
        if !(1..=256).contains(&self.hidden) {
            return Err(check::invalid(
                "identifier.hidden",
                self.hidden,
                "1 ..= 256",
            ));
        }
        for (name, v) in [
            ("lambda1", self.lambda1),
            ("lambda2", self.lambda2),
            ("lambda3", self.lambda3),
        ] {
            if !(v == 0.0 || (v.is_finite() && (1.0..=1e6).contains(&v))) {
                return Err(check::invalid(
                    format!("identifier.{name}"),
                    v,
                    "0 (off) or 1 ..= 1e6 (the paper asks > 1)",
                ));
            }
        }
        Ok(())
    }

    /// The learning rates Γ of each network's two layers.
    fn check_rates(&self) -> Result<(), ConfigError> {
        for (name, rates) in [
            ("rate_m", self.rate_m),
            ("rate_c", self.rate_c),
            ("rate_g", self.rate_g),
            ("rate_f", self.rate_f),
        ] {
            for (i, v) in rates.iter().enumerate() {
                check::in_range(
                    &format!("identifier.{name}[{i}]"),
                    *v,
                    0.0,
                    1e9,
                    "0 ..= 1e9",
                )?;
            }
        }
        Ok(())
    }

    /// The robust modifications: dead zone, σ-modification, projection bound.
    fn check_guards(&self) -> Result<(), ConfigError> {
        check::in_range(
            "identifier.dead_zone",
            self.dead_zone,
            0.0,
            1.0,
            "0 (off) ..= 1 N·m",
        )?;
        check::in_range("identifier.sigma", self.sigma, 0.0, 1e3, "0 (off) ..= 1e3")?;
        check::in_range(
            "identifier.reversal_speed",
            self.reversal_speed,
            0.0,
            10.0,
            "0 (off) ..= 10 rad/s",
        )?;
        check::in_range(
            "identifier.reversal_hold_s",
            self.reversal_hold_s,
            0.0,
            10.0,
            "0 ..= 10 s",
        )?;
        check::in_range("identifier.w_max", self.w_max, 0.0, 1e6, "0 (off) ..= 1e6")?;
        Ok(())
    }

    /// The eigenvalue bounds on M̂ (e4): each in range, the lower below the upper.
    fn check_inertia_bounds(&self) -> Result<(), ConfigError> {
        check::in_range(
            "identifier.eig_min",
            self.eig_min,
            0.0,
            1.0,
            "0 ..= 1 kg·m², below identifier.eig_max",
        )?;
        check::in_range(
            "identifier.eig_max",
            self.eig_max,
            0.0,
            1.0,
            "0 ..= 1 kg·m², above identifier.eig_min",
        )?;
        if self.eig_min >= self.eig_max {
            return Err(check::invalid(
                "identifier.eig_min",
                self.eig_min,
                "below identifier.eig_max",
            ));
        }
        Ok(())
    }

    /// The networks' input centres and scales and their output scales.
    fn check_scalings(&self) -> Result<(), ConfigError> {
        for (i, v) in self.q_center.iter().enumerate() {
            check::in_range(
                &format!("identifier.q_center[{i}]"),
                *v,
                -3.2,
                3.2,
                "-3.2 ..= 3.2 rad",
            )?;
        }
        for (name, vals) in [
            ("q_scale", self.q_scale),
            ("qd_scale", self.qd_scale),
            ("friction_qd_scale", self.friction_qd_scale),
        ] {
            for (i, v) in vals.iter().enumerate() {
                positive(
                    &format!("identifier.{name}[{i}]"),
                    *v,
                    1e3,
                    "finite, > 0 and ≤ 1e3",
                )?;
            }
        }
        for (name, v) in [
            ("inertia_scale", self.inertia_scale),
            ("coriolis_scale", self.coriolis_scale),
            ("gravity_scale", self.gravity_scale),
            ("friction_scale", self.friction_scale),
            ("torque_scale", self.torque_scale),
        ] {
            positive(
                &format!("identifier.{name}"),
                v,
                10.0,
                "finite, > 0 and ≤ 10",
            )?;
        }
        Ok(())
    }

    /// Fresh networks' start: M̂'s diagonal, the weights' spreads.
    fn check_init(&self) -> Result<(), ConfigError> {
        for (i, v) in self.init_mass_diag.iter().enumerate() {
            check::in_range(
                &format!("identifier.init_mass_diag[{i}]"),
                *v,
                0.0,
                1.0,
                "0 ..= 1 kg·m²",
            )?;
        }
        check::in_range(
            "identifier.init_std_hidden",
            self.init_std_hidden,
            0.0,
            10.0,
            "0 ..= 10",
        )?;
        check::in_range(
            "identifier.init_std_output",
            self.init_std_output,
            0.0,
            10.0,
            "0 ..= 10",
        )?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Deserialize)]
    #[serde(deny_unknown_fields)]
    struct Wrapper {
        identifier: IdentifierConfig,
    }

    fn parse(text: &str) -> Result<IdentifierConfig, String> {
        let w: Wrapper = toml::from_str(text).map_err(|e| e.to_string())?;
        w.identifier.validate().map_err(|e| e.to_string())?;
        Ok(w.identifier)
    }

    #[test]
    fn defaults_are_valid_and_match_design() {
        let c = IdentifierConfig::default();
        c.validate().unwrap();
        assert_eq!((c.alpha, c.hidden, c.adapt), (50.0, 16, true));
        assert!(c.friction_net);
        assert_eq!(parse("[identifier]\n").unwrap(), c);
    }

    #[test]
    fn errors_name_the_field_and_the_range() {
        let e = parse("[identifier]\nalpha = -1.0\n").unwrap_err();
        assert!(e.contains("identifier.alpha") && e.contains("> 0"), "{e}");
        let e = parse("[identifier]\nlambda2 = 0.5\n").unwrap_err();
        assert!(
            e.contains("identifier.lambda2") && e.contains("0 (off)"),
            "{e}"
        );
        let e = parse("[identifier]\nhidden = 0\n").unwrap_err();
        assert!(
            e.contains("identifier.hidden") && e.contains("1 ..= 256"),
            "{e}"
        );
        let e = parse("[identifier]\nrate_c = [1.0, nan]\n").unwrap_err();
        assert!(e.contains("identifier.rate_c[1]"), "{e}");
        let e = parse("[identifier]\neig_min = 0.02\n").unwrap_err();
        assert!(e.contains("identifier.eig_min"), "{e}");
        let e = parse("[identifier]\nqd_scale = [1.0, 0.0, 1.0]\n").unwrap_err();
        assert!(e.contains("identifier.qd_scale[1]"), "{e}");
        let e = parse("[identifier]\nalhpa = 3.0\n").unwrap_err();
        assert!(e.contains("alhpa"), "{e}");
    }

    #[test]
    fn lambdas_may_be_switched_off() {
        let c = parse("[identifier]\nlambda1 = 0.0\nlambda2 = 0.0\n").unwrap();
        assert_eq!((c.lambda1, c.lambda2), (0.0, 0.0));
    }
}
