//! Run configuration: TOML, every field optional with the defaults of docs/DESIGN.md §2.4,
//! unknown keys refused, every value validated with an error that names the field and the
//! allowed range.
//! Each section is defined and validated beside the component it configures; this module only
//! gathers them into the file's layout and hands each component the sections it needs.

mod arms;
pub mod serve;
pub mod zenoh;

pub use crate::config_check::ConfigError;
pub use crate::control::reference::ReferenceConfig;
pub use crate::control::ControlConfig;
pub(crate) use crate::control::ControlSetup;
pub use crate::device::firewire::FirewireConfig;
pub use crate::device::inject::InjectConfig;
pub(crate) use crate::device::probe::ProbeSetup;
pub use crate::device::sim::SimConfig;
pub(crate) use crate::device::sim::SimSetup;
pub use crate::device::usb::UsbConfig;
pub use crate::device::DeviceConfig;
pub use crate::estimate::kalman::KalmanConfig;
pub use crate::haptics::HapticsConfig;
pub use crate::identifier::IdentifierConfig;
use crate::omni::{Geometry, ModelParams};
pub use crate::servo::realtime::RealtimeConfig;
pub use crate::servo::safety::SafetyConfig;
pub(crate) use crate::servo::ServoSetup;
pub use crate::telemetry::TelemetryConfig;
pub use arms::ArmSpec;
use serde::{Deserialize, Serialize};
pub use serve::ServeConfig;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// How `[[arm]]` reads, at the end of the default configuration (commented out: a file
/// without arms is one arm named after its device).
const ARMS_EXAMPLE: &str = "
# Several arms in one daemon: one [[arm]] each (name, device, serial, aliases, cpu, socket),
# with any of [arm.sim], [arm.model], [arm.geometry], [arm.kalman], [arm.control],
# [arm.reference], [arm.safety], [arm.identifier], [arm.usb], [arm.firewire], [arm.inject],
# [arm.haptics] laid over the sections above key by key. `omnid serve` serves them all, each
# on <runtime dir>/<name>.sock; `omnid run --arm NAME` runs one.
# [[arm]]
# name = \"left\"
# device = \"firewire\"
# serial = \"10203400567\"
# aliases = [\"PHANToM 1\"]
# cpu = 2
# [arm.safety]
# max_torque_nm = [0.3, 0.3, 0.3]
";

/// The largest config file read (the full default config is about 12 kB).
pub(crate) const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// The whole configuration file.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Electronics of the Omni, shared by every backend.
    pub device: DeviceConfig,
    /// The simulated Omni.
    pub sim: SimConfig,
    /// Rigid-body model (docs/DESIGN.md §4.2): the simulator's plant and CT's model.
    pub model: ModelParams,
    /// Arm geometry (docs/DESIGN.md §4.1), mm.
    pub geometry: Geometry,
    /// Per-joint Kalman filter (docs/DESIGN.md §4.3).
    pub kalman: KalmanConfig,
    /// Controller gains, shared by PD, CT and NNIDC.
    pub control: ControlConfig,
    /// Reference trajectories.
    pub reference: ReferenceConfig,
    /// Limits every command passes through (in this order: non-finite guard, velocity fault, walls, ramp, thermal, clamp, kick).
    pub safety: SafetyConfig,
    /// Telemetry from the servo loop to the log writer.
    pub telemetry: TelemetryConfig,
    /// Adaptive NN identifier (docs/DESIGN.md §3): M-, C-, G- (and F-) networks learning online.
    pub identifier: IdentifierConfig,
    /// Realtime set-up of the servo thread (paced runs only; see udev/omnid-limits.conf).
    pub realtime: RealtimeConfig,
    /// USB bridge (docs/DESIGN.md §4.6): ids and endpoints of the bridge at hand (TOML takes hex: 0x1209).
    pub usb: UsbConfig,
    /// FireWire Omni on Linux firewire-cdev (/dev/fw*); facts and sources in docs/FIREWIRE.md.
    pub firewire: FirewireConfig,
    /// Fault injection for tests of the safety layer (also --inject).
    pub inject: InjectConfig,
    /// `omnid serve`: the client interface (docs/PROTOCOL.md).
    pub serve: ServeConfig,
    /// Haptics: tip force limits, the passivity controller, and the simulated hand (docs/HAPTICS.md).
    pub haptics: HapticsConfig,
    /// zenoh: the arms past this PC, ROS 2 (rmw_zenoh) and remote clients (docs/ZENOH.md).
    pub zenoh: zenoh::ZenohConfig,
    /// Teleoperation between a leader and a follower arm (docs/TELEOP.md).
    pub teleop: crate::teleop::TeleopConfig,
    /// Several arms in one daemon (`[[arm]]`, see `omnid config --print-default`'s end); none:
    /// one arm, named after its device.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub arm: Vec<crate::arm::config::ArmEntry>,
}

impl Config {
    /// Parse TOML text; `origin` names the source in messages.
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let cfg: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: origin.to_string(),
            message: crate::toml_place::describe(text, &e),
        })?;
        cfg.validate().map_err(|e| e.in_file(origin, text))?;
        cfg.arms().map_err(|e| e.in_file(origin, text))?;
        Ok(cfg)
    }

    /// Read and validate a config file (at most 1 MiB, `MAX_CONFIG_BYTES`; `stop`, the operator's,
    /// ends a wait on a pipe, without it only a regular file is read: see
    /// [`crate::input::open`]).
    pub fn load(path: &Path, stop: Option<&Arc<AtomicBool>>) -> Result<Self, ConfigError> {
        let text = crate::input::read_capped(path, MAX_CONFIG_BYTES, stop).map_err(|source| {
            ConfigError::Read {
                path: path.display().to_string(),
                source,
            }
        })?;
        Self::from_toml(&text, &path.display().to_string())
    }

    /// What the simulated Omni needs beyond `validate` (checked when the simulator is the
    /// device, so a hardware configuration at another servo rate is not refused for it).
    pub(crate) fn check_sim(&self) -> Result<(), ConfigError> {
        let hand = (self.haptics.hand.pattern != crate::haptics::HandPattern::None)
            .then_some(&self.haptics.hand);
        self.sim
            .check_plant(&self.device, &self.model, self.geometry, hand)
    }

    /// Check every section; the first problem is returned naming its field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.device.validate()?;
        self.sim.validate()?;
        self.model.validate(self.geometry)?;
        crate::omni::kinematics::check_geometry(&self.geometry)?;
        self.kalman.validate(self.device.rate_hz)?;
        self.control.validate()?;
        self.reference
            .validate(&self.model.limit_lower, &self.model.limit_upper)?;
        self.safety.validate()?;
        self.identifier.validate()?;
        self.realtime.validate()?;
        // The hub must stay below the servo: blame whichever of the two moved from its default.
        let (hub, servo) = (self.serve.hub_fifo_priority, self.realtime.fifo_priority);
        if hub > 0
            && servo > 0
            && hub >= servo
            && hub == ServeConfig::default().hub_fifo_priority
            && servo != RealtimeConfig::default().fifo_priority
        {
            return Err(crate::config_check::invalid(
                "realtime.fifo_priority",
                servo.to_string(),
                format!(
                    "above serve.hub_fifo_priority ({hub}), so the client hub never delays a tick"
                ),
            ));
        }
        self.serve.validate(self.realtime.fifo_priority)?;
        self.usb.validate()?;
        self.firewire.validate()?;
        self.inject.validate()?;
        self.haptics.validate()?;
        self.zenoh.validate()?;
        self.teleop.validate()?;
        self.telemetry.validate()
    }

    /// The default configuration as commented TOML. Every comment is the doc comment of its
    /// section or field, read from the derived schema: the code's docs are the one source.
    pub fn default_toml() -> String {
        let text = toml::to_string(&Config::default()).expect("default config serialises");
        let docs = FieldDocs::of::<Config>();
        let mut out =
            String::from("# omnid configuration: every key is optional; these are the defaults.\n");
        let mut section = String::new();
        for line in text.lines() {
            let trimmed = line.trim();
            if let Some(name) = trimmed.strip_prefix('[').and_then(|s| s.strip_suffix(']')) {
                section = name.to_string();
                out.push('\n');
                if let Some(doc) = docs.section(&section) {
                    out.push_str(&format!("# {doc}\n"));
                }
                out.push_str(line);
                out.push('\n');
            } else if let Some((key, _)) = trimmed.split_once(" = ") {
                match docs.field(&format!("{section}.{key}")) {
                    Some(doc) => out.push_str(&format!("{line}  # {doc}\n")),
                    None => out.push_str(&format!("{line}\n")),
                }
            } else if !trimmed.is_empty() {
                out.push_str(line);
                out.push('\n');
            }
        }
        out.push_str(ARMS_EXAMPLE);
        out
    }
}

/// The doc comments of a configuration type's sections and fields, from its JSON schema.
struct FieldDocs {
    schema: serde_json::Value,
}

impl FieldDocs {
    fn of<T: schemars::JsonSchema>() -> Self {
        FieldDocs {
            schema: schemars::schema_for!(T).to_value(),
        }
    }

    /// The schema a `$ref` points at (or the schema itself).
    fn resolve<'s>(&'s self, node: &'s serde_json::Value) -> &'s serde_json::Value {
        node.get("$ref")
            .and_then(|r| r.as_str())
            .and_then(|r| r.strip_prefix("#/$defs/"))
            .and_then(|name| self.schema.get("$defs")?.get(name))
            .unwrap_or(node)
    }

    /// The doc of the property at the dotted `path`: its field's doc comment, else its type's.
    fn doc(&self, path: &str) -> Option<String> {
        let mut entry = &self.schema;
        for key in path.split('.') {
            entry = self.resolve(entry).get("properties")?.get(key)?;
        }
        let doc = entry
            .get("description")
            .or(self.resolve(entry).get("description"))?;
        // A doc comment on one line: its lines and paragraphs joined by single spaces.
        Some(
            doc.as_str()?
                .split_whitespace()
                .collect::<Vec<_>>()
                .join(" "),
        )
    }

    /// A table's doc, as the sentence above it.
    fn section(&self, path: &str) -> Option<String> {
        self.doc(path)
    }

    /// A key's doc, as a phrase after its value: "Upper arm length, mm." reads "upper arm
    /// length, mm"; an initialism ("RK4 substeps", "USB vendor id") keeps its capitals.
    fn field(&self, path: &str) -> Option<String> {
        let doc = self.doc(path)?;
        let doc = match doc.strip_suffix('.') {
            Some(rest) if !rest.ends_with("..") => rest,
            _ => &doc,
        };
        let first_word = doc.split(' ').next()?;
        let initialism = first_word.len() > 1
            && first_word
                .chars()
                .all(|c| !c.is_alphabetic() || c.is_uppercase());
        let first = doc.chars().next()?;
        Some(if initialism {
            doc.to_string()
        } else {
            first.to_lowercase().collect::<String>() + &doc[first.len_utf8()..]
        })
    }
}

impl<'a> From<&'a Config> for SimSetup<'a> {
    fn from(cfg: &'a Config) -> Self {
        SimSetup {
            device: &cfg.device,
            sim: &cfg.sim,
            model: &cfg.model,
            geometry: &cfg.geometry,
            hand: &cfg.haptics.hand,
            center: cfg.reference.center,
        }
    }
}

impl<'a> From<&'a Config> for crate::device::registry::DeviceSetup<'a> {
    fn from(cfg: &'a Config) -> Self {
        crate::device::registry::DeviceSetup {
            device: &cfg.device,
            sim: cfg.into(),
            usb: &cfg.usb,
            firewire: &cfg.firewire,
        }
    }
}

impl<'a> From<&'a Config> for ControlSetup<'a> {
    fn from(cfg: &'a Config) -> Self {
        ControlSetup {
            control: &cfg.control,
            model: &cfg.model,
            geometry: &cfg.geometry,
            reference: &cfg.reference,
        }
    }
}

impl<'a> From<&'a Config> for ServoSetup<'a> {
    fn from(cfg: &'a Config) -> Self {
        ServoSetup {
            device: &cfg.device,
            identifier: &cfg.identifier,
            reference: &cfg.reference,
            safety: &cfg.safety,
            kalman: &cfg.kalman,
            seed: cfg.sim.seed,
            haptics: &cfg.haptics,
            geometry: &cfg.geometry,
            model: &cfg.model,
        }
    }
}

impl<'a> From<&'a Config> for ProbeSetup<'a> {
    fn from(cfg: &'a Config) -> Self {
        ProbeSetup {
            device: &cfg.device,
            firewire: &cfg.firewire,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(text: &str) -> String {
        Config::from_toml(text, "test.toml")
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn empty_file_is_the_defaults() {
        assert_eq!(Config::from_toml("", "x").unwrap(), Config::default());
        Config::default().validate().unwrap();
    }

    #[test]
    fn too_few_substeps_for_a_stiff_friction_curve_are_refused() {
        let err = |text: &str| {
            let cfg = Config::from_toml(text, "test.toml").unwrap();
            cfg.check_sim().unwrap_err().to_string()
        };
        Config::default().check_sim().unwrap();
        // Ten times steeper Coulomb smoothing needs ten times the substeps.
        let e = err("[model]\ncoulomb_velocity = 0.001\n");
        assert!(
            e.contains("`model.coulomb_velocity` = 0.001") && e.contains("sim.substeps ≥ 11"),
            "{e}"
        );
        Config::from_toml(
            "[model]\ncoulomb_velocity = 0.001\n[sim]\nsubsteps = 11\n",
            "x",
        )
        .unwrap()
        .check_sim()
        .unwrap();
        // The defaults sit at the bound: one substep is too few for them.
        let e = err("[sim]\nsubsteps = 1\n");
        assert!(
            e.contains("`sim.substeps` = 1") && e.contains("sim.substeps ≥ 2"),
            "{e}"
        );
        // A slower servo rate means longer ticks.
        let e = err("[device]\nrate_hz = 200\n");
        assert!(e.contains("`device.rate_hz` = 200"), "{e}");
    }

    #[test]
    fn default_toml_round_trips_and_documents_every_key() {
        let text = Config::default_toml();
        assert_eq!(
            Config::from_toml(&text, "default").unwrap(),
            Config::default()
        );
        for line in text
            .lines()
            .filter(|l| !l.starts_with('#') && l.contains(" = "))
        {
            assert!(line.contains("  # "), "undocumented key: {line}");
        }
    }

    #[test]
    fn unknown_key_names_the_key_and_line() {
        let e = err("[kalman]\njerk_psd = 10.0\njerk_pds = 3.0\n");
        assert!(e.contains("jerk_pds") && e.contains("line 3"), "{e}");
        assert!(!e.contains('\n'));
        let e = err("[kalmann]\n");
        assert!(e.contains("kalmann"), "{e}");
    }

    #[test]
    fn wrong_type_names_the_line() {
        let e = err("[sim]\nseed = \"one\"\n");
        assert!(e.contains("line 2") && e.contains("seed"), "{e}");
    }

    #[test]
    fn negative_gain_names_field_and_range() {
        let e = err("[control]\nomega_n = -5.0\n");
        assert!(
            e.contains("control.omega_n") && e.contains("0.1 ..= 200"),
            "{e}"
        );
    }

    #[test]
    fn non_finite_values_are_refused() {
        let e = err("[kalman]\njerk_psd = nan\n");
        assert!(e.contains("kalman.jerk_psd") && e.contains("finite"), "{e}");
        let e = err("[control]\nzeta = inf\n");
        assert!(e.contains("control.zeta"), "{e}");
    }

    #[test]
    fn arrays_of_the_wrong_length_are_refused() {
        // serde alone read the first three of four and dropped the 99 without a word.
        for (text, got) in [
            ("[safety]\nmax_torque_nm = [0.4, 0.4, 0.4, 99]\n", "4"),
            ("[safety]\nmax_torque_nm = [0.4, 0.4]\n", "2"),
            ("[reference]\nmultisine_band_hz = [0.1, 1.5, 3.0]\n", "3"),
        ] {
            let e = err(text);
            let key = text.lines().nth(1).unwrap().split(" = ").next().unwrap();
            assert!(
                e.contains("line 2") && e.contains(key) && e.contains(&format!("length {got}")),
                "{e}"
            );
        }
        let e = err("[safety]\nmax_torque_nm = [0.4, 0.4, 0.4, 99]\n");
        assert!(e.contains("exactly 3 values"), "{e}");
        let e = err("[reference]\nmultisine_band_hz = [0.1, 1.5, 3.0]\n");
        assert!(e.contains("exactly 2 values"), "{e}");
    }

    #[test]
    fn torque_limit_must_be_positive() {
        for bad in ["0.0", "-0.1"] {
            let e = err(&format!("[safety]\nmax_torque_nm = [0.4, {bad}, 0.4]\n"));
            assert!(
                e.contains("safety.max_torque_nm[1]") && e.contains("> 0"),
                "{e}"
            );
        }
    }

    #[test]
    fn non_positive_definite_inertia_is_refused() {
        let e = err("[model]\nk1 = 1e-6\nk2 = 0.5\n");
        assert!(
            e.contains("positive definite") || e.contains("model."),
            "{e}"
        );
    }
}
