//! `omnid devices`: list the candidate devices (USB bridges with the configured ids, FireWire
//! nodes of vendor 0x000b99) with serial, calibration state and any permission problem, with
//! the fix spelled out.

use super::calibration;
use super::firewire::cdev::{self, SYSFS_FIREWIRE_DEVICES};
use super::firewire::{firewire_permission_hint, FireWireOmni, NodeAccess, NodeInfo};
use super::usb::{self, UsbConfig};
use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Calibration state of one device.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CalibrationState {
    /// A calibration file exists for this serial.
    Calibrated(PathBuf),
    /// None yet: this file would hold it.
    Missing(PathBuf),
    /// Cannot tell (no serial, no config directory, unreadable file).
    Unknown(String),
}

impl CalibrationState {
    pub fn of(dir: Option<&Path>, serial: Option<&str>) -> Self {
        let Some(serial) = serial else {
            return CalibrationState::Unknown("no serial number".into());
        };
        let Some(dir) = dir else {
            return CalibrationState::Unknown("no configuration directory (HOME unset)".into());
        };
        match (
            calibration::load(dir, serial),
            calibration::path_for(dir, serial),
        ) {
            (Ok(Some(_)), Ok(path)) => CalibrationState::Calibrated(path),
            (Ok(None), Ok(path)) => CalibrationState::Missing(path),
            (Err(e), _) | (_, Err(e)) => CalibrationState::Unknown(e.to_string()),
        }
    }
}

impl fmt::Display for CalibrationState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CalibrationState::Calibrated(p) => write!(f, "calibrated ({})", p.display()),
            CalibrationState::Missing(p) => write!(
                f,
                "not calibrated: torque stays off until {} exists (the error of `omnid run` shows its contents)",
                p.display()
            ),
            CalibrationState::Unknown(why) => write!(f, "calibration unknown: {why}"),
        }
    }
}

/// Whether a device can be used.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Access {
    Ready,
    /// Permission denied; `fix` says what to do.
    Denied {
        fix: String,
    },
    Problem(String),
}

/// One USB device with the configured ids.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BridgeEntry {
    pub location: String,
    pub serial: Option<String>,
    pub access: Access,
    pub calibration: CalibrationState,
}

/// The USB side of the report.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum UsbSection {
    /// libusb cannot start: no USB here.
    Unavailable { reason: String },
    /// Devices on the bus, and those with the configured ids.
    Scanned {
        ids: String,
        total: usize,
        bridges: Vec<BridgeEntry>,
    },
}

/// One `/dev/fw*` node; `serial` and `calibration` only for Omnis.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FirewireEntry {
    pub node: NodeInfo,
    pub serial: Option<String>,
    pub access: Access,
    pub calibration: Option<CalibrationState>,
}

/// Everything `omnid devices` prints.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiscoveryReport {
    pub(crate) usb: UsbSection,
    pub(crate) firewire: Vec<FirewireEntry>,
}

impl DiscoveryReport {
    /// Omnis (and bridges) that can be used now.
    pub fn ready(&self) -> usize {
        let usb = match &self.usb {
            UsbSection::Scanned { bridges, .. } => {
                bridges.iter().filter(|b| b.access == Access::Ready).count()
            }
            UsbSection::Unavailable { .. } => 0,
        };
        usb + self
            .firewire
            .iter()
            .filter(|e| e.node.is_omni() && e.access == Access::Ready)
            .count()
    }
}

/// List USB bridges with the configured ids and FireWire nodes, looking calibrations up in the
/// default directory.
pub fn list_devices(usb_cfg: &UsbConfig) -> DiscoveryReport {
    let dir = calibration::default_dir();
    DiscoveryReport {
        usb: scan_usb(usb_cfg, dir.as_deref()),
        firewire: scan_firewire(
            Path::new("/dev"),
            Path::new(SYSFS_FIREWIRE_DEVICES),
            dir.as_deref(),
            &|p| read_firewire_serial(p),
        ),
    }
}

/// The USB side: every device with the configured ids, opened to read its serial (which is
/// also where permission problems show).
pub fn scan_usb(cfg: &UsbConfig, calibration_dir: Option<&Path>) -> UsbSection {
    let context = match rusb::Context::new() {
        Ok(c) => c,
        Err(e) => {
            return UsbSection::Unavailable {
                reason: usb::no_usb_hint(e),
            }
        }
    };
    let (total, matched) = match usb::enumerate(&context, cfg) {
        Ok(x) => x,
        Err(e) => {
            return UsbSection::Unavailable {
                reason: format!("cannot list USB devices: {e}"),
            }
        }
    };
    let bridges = matched
        .into_iter()
        .map(|m| {
            let (serial, access) = match m.device.open() {
                Ok(handle) => {
                    let serial = usb::read_serial(&handle, &m.descriptor);
                    let access = match usb::interface_endpoints(&m.device, cfg)
                        .and_then(|eps| usb::check_endpoints(cfg, &eps))
                    {
                        Ok(()) => Access::Ready,
                        Err(e) => Access::Problem(e),
                    };
                    (serial, access)
                }
                Err(rusb::Error::Access) => (
                    None,
                    Access::Denied {
                        fix: cfg.permission_hint(),
                    },
                ),
                Err(e) => (None, Access::Problem(format!("cannot open: {e}"))),
            };
            let calibration = CalibrationState::of(calibration_dir, serial.as_deref());
            BridgeEntry {
                location: m.location,
                serial,
                access,
                calibration,
            }
        })
        .collect();
    UsbSection::Scanned {
        ids: cfg.ids(),
        total,
        bridges,
    }
}

/// Read an Omni's serial register through its node.
pub fn read_firewire_serial(path: &Path) -> Result<String, String> {
    let bus = cdev::CdevBus::open(path, Duration::from_millis(100)).map_err(|e| e.to_string())?;
    let mut omni = FireWireOmni::new(
        bus,
        path.display().to_string(),
        Duration::from_millis(10),
        1e3,
    );
    omni.identify().map_err(|e| e.to_string())
}

/// The FireWire side, from `dev_dir`/`sysfs_dir` (tests use a fake tree); `read_serial` reads
/// an accessible Omni's serial.
pub fn scan_firewire(
    dev_dir: &Path,
    sysfs_dir: &Path,
    calibration_dir: Option<&Path>,
    read_serial: &dyn Fn(&Path) -> Result<String, String>,
) -> Vec<FirewireEntry> {
    entries_from(
        cdev::scan_nodes(dev_dir, sysfs_dir),
        calibration_dir,
        read_serial,
    )
}

/// Turn scanned nodes into report entries.
pub fn entries_from(
    nodes: Vec<NodeInfo>,
    calibration_dir: Option<&Path>,
    read_serial: &dyn Fn(&Path) -> Result<String, String>,
) -> Vec<FirewireEntry> {
    nodes
        .into_iter()
        .map(|node| {
            let mut access = match &node.access {
                NodeAccess::Ok => Access::Ready,
                NodeAccess::Denied => Access::Denied {
                    fix: firewire_permission_hint(),
                },
                NodeAccess::Error(e) => Access::Problem(e.clone()),
            };
            let (serial, calibration) = if node.is_omni() {
                let serial = if access == Access::Ready {
                    match read_serial(&node.path) {
                        Ok(s) => Some(s),
                        Err(e) => {
                            access = Access::Problem(format!("cannot read the serial: {e}"));
                            None
                        }
                    }
                } else {
                    None
                };
                let cal = CalibrationState::of(calibration_dir, serial.as_deref());
                (serial, Some(cal))
            } else {
                (None, None)
            };
            FirewireEntry {
                node,
                serial,
                access,
                calibration,
            }
        })
        .collect()
}

impl fmt::Display for DiscoveryReport {
    /// The `omnid devices` listing. Long on purpose: one block per bus and per device, in the
    /// order printed.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let no_usb = matches!(self.usb, UsbSection::Unavailable { .. });
        if no_usb && self.firewire.is_empty() {
            writeln!(
                f,
                "No USB and no FireWire on this machine: there is nothing an Omni could be \
                 connected to."
            )?;
        }
        writeln!(f, "USB bridge:")?;
        match &self.usb {
            UsbSection::Unavailable { reason } => writeln!(f, "  USB not available: {reason}")?,
            UsbSection::Scanned {
                ids,
                total,
                bridges,
            } => {
                if bridges.is_empty() {
                    writeln!(
                        f,
                        "  none with id {ids} among {total} USB device(s) (set usb.vendor_id / \
                         usb.product_id to your bridge's ids as `lsusb` shows them)"
                    )?;
                }
                for b in bridges {
                    let serial = b.serial.as_deref().unwrap_or("(serial unknown)");
                    write!(f, "  {ids} at {}, serial {serial}: ", b.location)?;
                    write_access(f, &b.access)?;
                    writeln!(f, "    {}", b.calibration)?;
                }
            }
        }
        writeln!(f, "FireWire (vendor 0x000b99):")?;
        if self.firewire.is_empty() {
            writeln!(
                f,
                "  no /dev/fw* nodes: no FireWire controller here, or its driver is not loaded \
                 (`sudo modprobe firewire-ohci`)"
            )?;
        }
        for e in &self.firewire {
            let n = &e.node;
            let vendor = match n.vendor {
                Some(v) => format!("vendor {v:#08x}"),
                None => "vendor unknown".to_string(),
            };
            let names = [n.vendor_name.as_deref(), n.model_name.as_deref()]
                .into_iter()
                .flatten()
                .collect::<Vec<_>>()
                .join(" ");
            let names = if names.is_empty() {
                String::new()
            } else {
                format!(" ({names})")
            };
            if !n.is_omni() {
                write!(f, "  {}: {vendor}{names}, not an Omni", n.path.display())?;
                if matches!(e.access, Access::Denied { .. }) && n.vendor.is_none() {
                    write!(f, " as far as can be told (permission denied)")?;
                }
                writeln!(f)?;
                continue;
            }
            let serial = e.serial.as_deref().unwrap_or("(serial unknown)");
            write!(f, "  {}: Omni{names}, serial {serial}", n.path.display())?;
            if let Some(guid) = &n.guid {
                write!(f, ", GUID {guid}")?;
            }
            write!(f, ": ")?;
            write_access(f, &e.access)?;
            if let Some(cal) = &e.calibration {
                writeln!(f, "    {cal}")?;
            }
        }
        let ready = self.ready();
        if ready == 0 {
            writeln!(f, "No usable Omni found.")
        } else {
            writeln!(f, "{ready} usable device(s).")
        }
    }
}

fn write_access(f: &mut fmt::Formatter<'_>, a: &Access) -> fmt::Result {
    match a {
        Access::Ready => writeln!(f, "ready"),
        Access::Denied { fix } => writeln!(f, "permission denied.\n    Fix: {fix}"),
        Access::Problem(p) => writeln!(f, "problem: {p}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fake_tree(nodes: &[(&str, Option<&str>)]) -> tempfile::TempDir {
        let root = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(root.path().join("dev")).unwrap();
        for (name, vendor) in nodes {
            std::fs::write(root.path().join("dev").join(name), "").unwrap();
            let sys = root.path().join("sys").join(name);
            std::fs::create_dir_all(&sys).unwrap();
            if let Some(v) = vendor {
                std::fs::write(sys.join("vendor"), format!("{v}\n")).unwrap();
            }
        }
        root
    }

    #[test]
    fn firewire_omni_listed_with_serial_and_calibration() {
        let root = fake_tree(&[("fw0", Some("0x00601d")), ("fw1", Some("0x000b99"))]);
        std::fs::write(root.path().join("sys/fw1/model_name"), "PHANToM Omni\n").unwrap();
        let cal = tempfile::tempdir().unwrap();
        let entries = scan_firewire(
            &root.path().join("dev"),
            &root.path().join("sys"),
            Some(cal.path()),
            &|_| Ok("31337".into()),
        );
        assert_eq!(entries.len(), 2);
        assert_eq!(entries[1].serial.as_deref(), Some("31337"));
        assert_eq!(
            entries[1].calibration,
            Some(CalibrationState::Missing(cal.path().join("31337.toml")))
        );
        calibration::save(cal.path(), &calibration::Calibration::nominal("31337")).unwrap();
        let entries = scan_firewire(
            &root.path().join("dev"),
            &root.path().join("sys"),
            Some(cal.path()),
            &|_| Ok("31337".into()),
        );
        let report = DiscoveryReport {
            usb: UsbSection::Unavailable {
                reason: "no USB here".into(),
            },
            firewire: entries,
        };
        let text = report.to_string();
        assert!(text.contains("fw0: vendor 0x00601d, not an Omni"), "{text}");
        assert!(
            text.contains("fw1: Omni (PHANToM Omni), serial 31337: ready"),
            "{text}"
        );
        assert!(text.contains("calibrated ("), "{text}");
        assert!(text.contains("1 usable device(s)."), "{text}");
    }

    #[test]
    fn permission_problem_spells_out_the_fix() {
        let nodes = vec![NodeInfo {
            path: PathBuf::from("/dev/fw1"),
            vendor: Some(0x000B99),
            guid: Some("0x000b990000000001".into()),
            vendor_name: None,
            model_name: None,
            access: NodeAccess::Denied,
        }];
        let entries = entries_from(nodes, None, &|_| panic!("no serial read without access"));
        let report = DiscoveryReport {
            usb: UsbSection::Scanned {
                ids: "1209:0001".into(),
                total: 3,
                bridges: vec![BridgeEntry {
                    location: "bus 001 device 004 (/dev/bus/usb/001/004)".into(),
                    serial: None,
                    access: Access::Denied {
                        fix: UsbConfig::default().permission_hint(),
                    },
                    calibration: CalibrationState::of(None, None),
                }],
            },
            firewire: entries,
        };
        let text = report.to_string();
        assert!(
            text.contains("permission denied.\n    Fix: Install the udev rule"),
            "{text}"
        );
        assert!(text.contains("ATTR{vendor}==\"0x000b99\""), "{text}");
        assert!(text.contains("ATTRS{idVendor}==\"1209\""), "{text}");
        assert!(text.contains("usermod -aG plugdev"), "{text}");
        assert!(text.contains("No usable Omni found."), "{text}");
    }

    #[test]
    fn nothing_at_all_is_said_plainly() {
        let report = DiscoveryReport {
            usb: UsbSection::Unavailable {
                reason: "libusb cannot start here".into(),
            },
            firewire: vec![],
        };
        let text = report.to_string();
        assert!(
            text.starts_with("No USB and no FireWire on this machine"),
            "{text}"
        );
        assert!(text.contains("no /dev/fw* nodes"), "{text}");
    }

    #[test]
    fn this_machine_is_listed_without_error() {
        // Whatever is attached here (usually nothing), listing must work and say something
        // about both buses.
        let text = list_devices(&UsbConfig::default()).to_string();
        assert!(text.contains("USB bridge:") && text.contains("FireWire (vendor 0x000b99):"));
    }
}
