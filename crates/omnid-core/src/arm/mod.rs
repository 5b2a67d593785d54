//! The arm as the unit: a name (configured; by default the backend kind, so a one-arm set-up
//! keeps its socket, heat file and service name), the device it runs on, its serial where the
//! device reports one, and what is keyed by its name — the device lock, the socket, the
//! motor-heat file, recordings and fault dumps. `[[arm]]` in the config lists several
//! (docs/DESIGN.md §2.4, Arms).

pub mod config;
pub mod lock;

pub use lock::ArmLock;

/// Who an arm is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ArmIdentity {
    /// Its name (letters, digits, `-`, `_`; at most 32 characters).
    pub name: String,
    /// The backend: `sim`, `replay`, `usb` or `firewire`.
    pub kind: &'static str,
    /// The device's serial number, when its backend knows one.
    pub serial: Option<String>,
    /// Other names clients may open it by (OpenHaptics programs' "PHANToM 1", …).
    pub aliases: Vec<String>,
}

impl ArmIdentity {
    /// The name as it goes into file names (already restricted to safe characters).
    pub fn file_stem(&self) -> &str {
        &self.name
    }

    /// Whether a client asking for `name` means this arm (its name or an alias).
    pub fn answers_to(&self, name: &str) -> bool {
        self.name == name || self.aliases.iter().any(|a| a == name)
    }
}

pub use omnid_client::find::check_arm_name as check_name;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_that_could_escape_a_directory_or_a_unit_name_are_refused() {
        for ok in ["sim", "left", "PHANToM_1", "arm-2"] {
            assert!(check_name(ok).is_ok(), "{ok}");
        }
        for bad in ["", "../x", "a b", "a/b", "x.sock", &"a".repeat(33), "é"] {
            assert!(check_name(bad).is_err(), "{bad}");
        }
    }
}
