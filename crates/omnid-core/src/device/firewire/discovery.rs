//! Finding the Omni among `/dev/fw*`, and what to say (the udev rule) when it cannot be
//! opened.

use super::*;
use crate::device::DeviceError;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The udev rule of docs/FIREWIRE.md §7.
pub(crate) const FIREWIRE_UDEV_RULE: &str =
    "SUBSYSTEM==\"firewire\", ATTR{vendor}==\"0x000b99\", MODE=\"0660\", GROUP=\"plugdev\"";

/// How to fix "permission denied" on `/dev/fwN`.
pub(crate) fn firewire_permission_hint() -> String {
    format!(
        "Install the udev rule (udev/99-omnid-firewire.rules, or put this line in \
         /etc/udev/rules.d/99-omnid-firewire.rules: {FIREWIRE_UDEV_RULE}), run `sudo udevadm \
         control --reload-rules && sudo udevadm trigger`, add yourself to plugdev (`sudo usermod \
         -aG plugdev $USER`), log in again and replug the Omni. See udev/README.md."
    )
}

/// A `/dev/fw*` node as found on this machine.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeInfo {
    /// `/dev/fw1`.
    pub(crate) path: PathBuf,
    /// Config-ROM vendor id (from sysfs, else from the ROM through the node), when known.
    pub(crate) vendor: Option<u32>,
    /// GUID from sysfs, when known.
    pub(crate) guid: Option<String>,
    /// Vendor and model names from sysfs, when known.
    pub(crate) vendor_name: Option<String>,
    pub(crate) model_name: Option<String>,
    /// Whether this user may open the node.
    pub(crate) access: NodeAccess,
}

/// Whether a node can be opened read-write.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum NodeAccess {
    /// It opens read-write.
    Ok,
    /// Permission denied (the udev rule is missing or the user is not in its group).
    Denied,
    /// Another error, its message.
    Error(String),
}

impl NodeInfo {
    pub(crate) fn is_omni(&self) -> bool {
        self.vendor == Some(SENSABLE_VENDOR_ID)
    }
}

/// The hint when there is no Omni among `nodes`.
pub(crate) fn no_omni_hint(nodes: &[NodeInfo]) -> String {
    if nodes.is_empty() {
        return "There are no /dev/fw* nodes at all: this machine has no IEEE-1394 (FireWire) \
                controller, or its driver is not loaded (`sudo modprobe firewire-ohci`). Check \
                the controller, the cable and the Omni's power."
            .to_string();
    }
    let seen: Vec<String> = nodes
        .iter()
        .map(|n| match (n.vendor, &n.access) {
            (Some(v), _) => format!("{} vendor {v:#08x}", n.path.display()),
            (None, NodeAccess::Denied) => {
                format!("{} (vendor unknown: permission denied)", n.path.display())
            }
            (None, _) => format!("{} (vendor unknown)", n.path.display()),
        })
        .collect();
    format!(
        "found {}; none has vendor 0x000b99. The Omni shows up as its own node beside the \
         controller's: check the cable and the Omni's power (the inkwell lamp).",
        seen.join(", ")
    )
}

/// Nodes to try, in order, for this configuration; errors say what was found instead.
pub(crate) fn candidate_nodes(
    nodes: &[NodeInfo],
    cfg: &FirewireConfig,
) -> Result<Vec<PathBuf>, DeviceError> {
    let not_found = |hint: String| DeviceError::NotFound {
        looked_for: cfg.looked_for(),
        hint,
    };
    if !cfg.device.is_empty() {
        let Some(node) = nodes.iter().find(|n| n.path == Path::new(&cfg.device)) else {
            return Err(not_found(format!(
                "{} does not exist. {}",
                cfg.device,
                if nodes.is_empty() {
                    no_omni_hint(nodes)
                } else {
                    "Leave firewire.device empty to search.".to_string()
                }
            )));
        };
        if node.access == NodeAccess::Denied {
            return Err(DeviceError::Permission {
                what: cfg.device.clone(),
                hint: firewire_permission_hint(),
            });
        }
        // The vendor register check after opening refuses anything that is not an Omni.
        return Ok(vec![node.path.clone()]);
    }
    let omnis: Vec<&NodeInfo> = nodes.iter().filter(|n| n.is_omni()).collect();
    let openable: Vec<PathBuf> = omnis
        .iter()
        .filter(|n| n.access != NodeAccess::Denied)
        .map(|n| n.path.clone())
        .collect();
    if openable.is_empty() {
        if let Some(n) = omnis.first() {
            return Err(DeviceError::Permission {
                what: format!("the FireWire Omni at {}", n.path.display()),
                hint: firewire_permission_hint(),
            });
        }
        // Nodes whose vendor could not be read because of permissions may hide the Omni.
        if let Some(n) = nodes
            .iter()
            .find(|n| n.vendor.is_none() && n.access == NodeAccess::Denied)
        {
            return Err(DeviceError::Permission {
                what: format!("{} (to read its vendor id)", n.path.display()),
                hint: firewire_permission_hint(),
            });
        }
        return Err(not_found(no_omni_hint(nodes)));
    }
    Ok(openable)
}

/// Find and identify the configured Omni (reads only: nothing is written to it yet).
pub(crate) fn find_firewire(
    cfg: &FirewireConfig,
    rate_hz: f64,
) -> Result<FireWireOmni<cdev::CdevBus>, DeviceError> {
    cfg.validate()
        .map_err(|e| DeviceError::Unsupported(e.to_string()))?;
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
        return Err(DeviceError::Unsupported(format!(
            "packet rate {rate_hz} Hz is out of range: allowed a finite rate > 0"
        )));
    }
    let nodes = cdev::scan_nodes(Path::new("/dev"), Path::new(cdev::SYSFS_FIREWIRE_DEVICES));
    let candidates = candidate_nodes(&nodes, cfg)?;
    let register_timeout = Duration::from_millis(u64::from(cfg.register_timeout_ms));
    choose_by_serial(
        cfg,
        rate_hz,
        &candidates,
        |path| cdev::CdevBus::open(path, register_timeout),
        || no_omni_hint(&nodes),
    )
}

/// Identify the Omni on each candidate node (opened by `open`) and keep the one whose serial
/// the configuration wants: with several Omnis on the bus, each arm finds its own unit by
/// `firewire.serial`. `nothing_found` says what to do when no node answers as an Omni.
pub(crate) fn choose_by_serial<B: FireWireBus>(
    cfg: &FirewireConfig,
    rate_hz: f64,
    candidates: &[PathBuf],
    mut open: impl FnMut(&Path) -> Result<B, BusError>,
    nothing_found: impl FnOnce() -> String,
) -> Result<FireWireOmni<B>, DeviceError> {
    let mut serials = Vec::new();
    let mut chosen = Vec::new();
    for path in candidates {
        let bus = match open(path) {
            Ok(b) => b,
            Err(BusError::Permission) => {
                return Err(DeviceError::Permission {
                    what: path.display().to_string(),
                    hint: firewire_permission_hint(),
                })
            }
            Err(BusError::Gone) => continue,
            Err(e) => return Err(DeviceError::Io(format!("opening {}: {e}", path.display()))),
        };
        let mut omni =
            FireWireOmni::with_options(bus, path.display().to_string(), cfg.options(rate_hz));
        let serial = omni.identify()?;
        serials.push(format!("{serial} at {}", path.display()));
        if omni.serial_quadlet().is_some_and(|q| cfg.wants_serial(q)) {
            chosen.push(omni);
        }
    }
    if chosen.len() > 1 {
        return Err(DeviceError::NotFound {
            looked_for: "exactly one FireWire Omni".into(),
            hint: format!(
                "found {} ({}); set firewire.serial to choose one.",
                chosen.len(),
                serials.join(", ")
            ),
        });
    }
    chosen.pop().ok_or_else(|| DeviceError::NotFound {
        looked_for: cfg.looked_for(),
        hint: if serials.is_empty() {
            nothing_found()
        } else {
            format!(
                "Omnis found: {}; set firewire.serial to one of them.",
                serials.join(", ")
            )
        },
    })
}
