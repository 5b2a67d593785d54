//! `[[arm]]` resolved: each configured arm's whole configuration, the file's sections with the
//! arm's own laid over them key by key, checked as a whole file is (the entries themselves are
//! defined in `arm::config`).

use super::{Config, ConfigError};
use crate::arm::config::ArmEntry;
use crate::device::registry::DeviceSpec;
use std::collections::BTreeMap;
use std::path::PathBuf;

/// An arm ready to assemble: who it is and its whole configuration.
#[derive(Debug, Clone, PartialEq)]
pub struct ArmSpec {
    /// Its name.
    pub name: String,
    /// Its device.
    pub device: DeviceSpec,
    /// The serial it must have (`None`: any).
    pub serial: Option<String>,
    /// Other names.
    pub aliases: Vec<String>,
    /// Its socket (`None`: the default for its name).
    pub socket: Option<PathBuf>,
    /// The file's configuration with this arm's sections laid over it.
    pub config: Config,
}

impl ArmSpec {
    /// The one arm of a configuration without `[[arm]]`: named after its device kind.
    pub fn single(device: DeviceSpec, cfg: &Config) -> ArmSpec {
        ArmSpec {
            name: device.name().to_string(),
            device,
            serial: None,
            aliases: Vec::new(),
            socket: None,
            config: cfg.clone(),
        }
    }

    /// Arms for devices given on the command line (`serve --device sim --device sim`): named
    /// after their kind, the second of a kind `<kind>-2`, and so on.
    pub fn from_devices(devices: &[DeviceSpec], cfg: &Config) -> Vec<ArmSpec> {
        let mut arms: Vec<ArmSpec> = Vec::new();
        for d in devices {
            let same = arms.iter().filter(|a| a.device.name() == d.name()).count();
            let mut arm = ArmSpec::single(d.clone(), cfg);
            if same > 0 {
                arm.name = format!("{}-{}", d.name(), same + 1);
            }
            arms.push(arm);
        }
        arms
    }
}

/// Lay `over` onto `base` key by key (tables merge, anything else replaces).
fn lay_over(base: &mut toml::Table, over: &BTreeMap<String, toml::Value>) {
    for (k, v) in over {
        match (base.get_mut(k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => {
                let o: BTreeMap<String, toml::Value> =
                    o.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
                lay_over(b, &o);
            }
            _ => {
                base.insert(k.clone(), v.clone());
            }
        }
    }
}

impl ArmEntry {
    /// This arm's spec from the file's configuration `global` (without arms): checked, the
    /// problem named with the arm (`arm[1] \`right\`: …`).
    pub(crate) fn resolve(&self, index: usize, global: &Config) -> Result<ArmSpec, ConfigError> {
        let at = |message: String| ConfigError::Parse {
            path: format!("arm[{index}] `{}`", crate::text::cut(&self.name)),
            message,
        };
        crate::arm::check_name(&self.name).map_err(at)?;
        let device: DeviceSpec = self.device.parse().map_err(at)?;
        for alias in &self.aliases {
            // An alias is what a program opens the arm by ("PHANToM 1", spaces allowed), never
            // a path: no separator, no control character, no leading dot, no edge spaces.
            let printable = alias.chars().all(|c| !c.is_control());
            if alias.is_empty()
                || alias.len() > 64
                || !printable
                || alias.contains('/')
                || alias.starts_with('.')
                || alias.trim() != alias
            {
                return Err(at(format!(
                    "alias `{}`: allowed 1 to 64 printable characters, without `/`, a leading \
                     `.` or spaces at either end (an alias names the arm to programs, not a file)",
                    crate::text::printable(&crate::text::cut(alias))
                )));
            }
        }
        let mut table = toml::Table::try_from(global)
            .map_err(|e| at(format!("cannot lay its sections over the file's: {e}")))?;
        table.remove("arm");
        // `[zenoh]` is the daemon's, not an arm's, and its secrets do not survive being
        // written out (they serialise as `(hidden)`): it is copied over as it is, below.
        table.remove("zenoh");
        for (name, section) in [
            ("sim", &self.sim),
            ("model", &self.model),
            ("geometry", &self.geometry),
            ("kalman", &self.kalman),
            ("control", &self.control),
            ("reference", &self.reference),
            ("safety", &self.safety),
            ("identifier", &self.identifier),
            ("usb", &self.usb),
            ("firewire", &self.firewire),
            ("inject", &self.inject),
            ("haptics", &self.haptics),
        ] {
            if let Some(over) = section {
                let mut wrapped = BTreeMap::new();
                wrapped.insert(
                    name.to_string(),
                    toml::Value::Table(over.clone().into_iter().collect()),
                );
                lay_over(&mut table, &wrapped);
            }
        }
        let mut config: Config = table
            .try_into()
            .map_err(|e: toml::de::Error| at(e.message().trim().replace('\n', " ")))?;
        if !self.serial.is_empty() {
            config.firewire.serial = self.serial.clone();
        }
        if self.cpu >= 0 {
            config.realtime.cpu = self.cpu;
        }
        config.arm.clear();
        config.zenoh = global.zenoh.clone();
        config.validate().map_err(|e| {
            let e = e.to_string();
            at(e.strip_prefix("config: ").unwrap_or(&e).to_string())
        })?;
        Ok(ArmSpec {
            name: self.name.clone(),
            device,
            serial: (!self.serial.is_empty()).then(|| self.serial.clone()),
            aliases: self.aliases.clone(),
            socket: (!self.socket.is_empty()).then(|| PathBuf::from(&self.socket)),
            config,
        })
    }
}

impl Config {
    /// The configured arms, each with its whole configuration; empty when the file lists
    /// none. Names and aliases must be distinct.
    pub fn arms(&self) -> Result<Vec<ArmSpec>, ConfigError> {
        let mut global = self.clone();
        global.arm.clear();
        let mut arms: Vec<ArmSpec> = Vec::new();
        for (i, entry) in self.arm.iter().enumerate() {
            let arm = entry.resolve(i, &global)?;
            let taken = arms.iter().any(|a| {
                a.name == arm.name
                    || a.aliases.contains(&arm.name)
                    || arm
                        .aliases
                        .iter()
                        .any(|x| a.name == *x || a.aliases.contains(x))
            });
            if taken {
                return Err(ConfigError::Parse {
                    path: format!("arm[{i}] `{}`", arm.name),
                    message: "its name or an alias is another arm's".into(),
                });
            }
            // Two arms on one socket would each find the other serving it.
            if let Some(other) = arms
                .iter()
                .find(|a| a.socket.is_some() && a.socket == arm.socket)
            {
                return Err(ConfigError::Parse {
                    path: format!("arm[{i}] `{}`", arm.name),
                    message: format!(
                        "socket = \"{}\" is also arm `{}`'s; give each arm its own (or leave \
                         `socket` out: `<runtime dir>/<name>.sock`)",
                        arm.socket
                            .as_deref()
                            .unwrap_or(std::path::Path::new(""))
                            .display(),
                        other.name
                    ),
                });
            }
            arms.push(arm);
        }
        Ok(arms)
    }

    /// The arm named `name` (or answering to it as an alias).
    pub fn arm_named(&self, name: &str) -> Result<ArmSpec, String> {
        let arms = self.arms().map_err(|e| e.to_string())?;
        let names: Vec<&str> = arms.iter().map(|a| a.name.as_str()).collect();
        let listed = if names.is_empty() {
            "the config lists no [[arm]]".to_string()
        } else {
            format!("configured: {}", names.join(", "))
        };
        arms.iter()
            .find(|a| a.name == name || a.aliases.iter().any(|x| x == name))
            .cloned()
            .ok_or_else(|| format!("no arm named `{}` ({listed})", crate::text::cut(name)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn arms_of(toml: &str) -> Result<Vec<ArmSpec>, String> {
        let c: Config = toml::from_str(toml).map_err(|e| e.to_string())?;
        c.arms().map_err(|e| e.to_string())
    }

    #[test]
    fn two_arms_on_one_socket_are_refused_naming_both() {
        let e = arms_of(
            "[[arm]]\nname = \"a\"\nsocket = \"/tmp/x.sock\"\n\
             [[arm]]\nname = \"b\"\nsocket = \"/tmp/x.sock\"\n",
        )
        .unwrap_err();
        assert!(
            e.contains("arm[1] `b`") && e.contains("also arm `a`'s"),
            "{e}"
        );
        assert!(arms_of(
            "[[arm]]\nname = \"a\"\nsocket = \"/tmp/x.sock\"\n\
             [[arm]]\nname = \"b\"\nsocket = \"/tmp/y.sock\"\n",
        )
        .is_ok());
    }

    #[test]
    fn aliases_are_names_for_programs_not_paths() {
        for bad in ["../../x", "a/b", ".hidden", " PHANToM", "bell\u{7}", ""] {
            let toml = format!("[[arm]]\nname = \"a\"\naliases = [{bad:?}]\n");
            let e = arms_of(&toml).unwrap_err();
            assert!(e.contains("alias"), "{bad:?}: {e}");
        }
        assert!(
            arms_of("[[arm]]\nname = \"a\"\naliases = [\"PHANToM 1\", \"Default PHANToM\"]\n")
                .is_ok()
        );
    }

    const TWO: &str = r#"
[safety]
ramp_s = 0.7

[[arm]]
name = "left"
aliases = ["PHANToM 1"]

[[arm]]
name = "right"
device = "firewire"
serial = "10203400567"
cpu = 1
[arm.safety]
max_torque_nm = [0.3, 0.3, 0.3]
"#;

    #[test]
    fn an_arm_keeps_the_daemons_zenoh_secrets() {
        let toml = "[zenoh]\nuser = \"omnid\"\npassword = \"pw-1234\"\n\
                    teleop_keys = { \"a/b\" = \"2dEoOzyuZk8W2mWRzN0kqxUJ1NQ3gHc6kBzYw3h0n3U=\" }\n\
                    [[arm]]\nname = \"a\"\n";
        let cfg = Config::from_toml(toml, "z.toml").unwrap();
        let arms = cfg.arms().unwrap();
        let z = &arms[0].config.zenoh;
        assert_eq!(z.password.expose(), "pw-1234");
        assert!(matches!(z.teleop_key("a", "b"), Some(Ok(_))));
    }

    #[test]
    fn an_arm_lays_its_sections_over_the_file_key_by_key() {
        let cfg = Config::from_toml(TWO, "two.toml").unwrap();
        let arms = cfg.arms().unwrap();
        assert_eq!(arms.len(), 2);
        let (l, r) = (&arms[0], &arms[1]);
        assert_eq!(
            (l.name.as_str(), l.device.clone()),
            ("left", DeviceSpec::Sim)
        );
        assert_eq!(l.aliases, ["PHANToM 1"]);
        assert_eq!(l.config.safety.max_torque_nm, [0.45; 3]);
        assert_eq!(r.device, DeviceSpec::Firewire);
        assert_eq!(r.config.safety.max_torque_nm, [0.3; 3]);
        // The file's own keys stay where the arm says nothing.
        assert_eq!((l.config.safety.ramp_s, r.config.safety.ramp_s), (0.7, 0.7));
        assert_eq!(r.config.firewire.serial, "10203400567");
        assert_eq!(r.config.realtime.cpu, 1);
    }

    #[test]
    fn bad_arms_are_refused_naming_the_arm() {
        let e = |text: &str| Config::from_toml(text, "a.toml").unwrap_err().to_string();
        let bad_range = e("[[arm]]\nname = \"x\"\n[arm.safety]\nramp_s = -1.0\n");
        assert!(
            bad_range.contains("arm[0] `x`") && bad_range.contains("safety.ramp_s"),
            "{bad_range}"
        );
        let dup = e("[[arm]]\nname = \"x\"\n[[arm]]\nname = \"y\"\naliases = [\"x\"]\n");
        assert!(
            dup.contains("arm[1] `y`") && dup.contains("another arm"),
            "{dup}"
        );
        let name = e("[[arm]]\nname = \"../etc\"\n");
        assert!(name.contains("arm name"), "{name}");
        let device = e("[[arm]]\nname = \"x\"\ndevice = \"serial\"\n");
        assert!(device.contains("unknown device"), "{device}");
        let key = e("[[arm]]\nname = \"x\"\n[arm.safety]\nramp = 1.0\n");
        assert!(key.contains("arm[0] `x`") && key.contains("ramp"), "{key}");
        let section = e("[[arm]]\nname = \"x\"\n[arm.serve]\nsocket = \"/x\"\n");
        assert!(section.contains("serve"), "{section}");
    }

    #[test]
    fn devices_on_the_command_line_get_distinct_names() {
        let cfg = Config::default();
        let arms =
            ArmSpec::from_devices(&[DeviceSpec::Sim, DeviceSpec::Sim, DeviceSpec::Usb], &cfg);
        let names: Vec<&str> = arms.iter().map(|a| a.name.as_str()).collect();
        assert_eq!(names, ["sim", "sim-2", "usb"]);
    }
}
