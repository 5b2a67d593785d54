//! Finding the bridge: enumerate, match ids and serial, check its endpoints, claim its
//! interface, and say what was looked for when nothing matches.

use super::*;
use crate::device::{Device, DeviceError};

/// Endpoint transfer kinds as the descriptors state them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum EndpointKind {
    Bulk,
    Interrupt,
    Other,
}

impl EndpointKind {
    fn name(self) -> &'static str {
        match self {
            EndpointKind::Bulk => "bulk",
            EndpointKind::Interrupt => "interrupt",
            EndpointKind::Other => "isochronous/control",
        }
    }
}

/// Check the configured endpoints against the interface's endpoint list
/// `(address, kind)`; the error says what the bridge has and which key to change.
pub(crate) fn check_endpoints(cfg: &UsbConfig, found: &[(u8, EndpointKind)]) -> Result<(), String> {
    let want = match cfg.transfer {
        UsbTransfer::Bulk => EndpointKind::Bulk,
        UsbTransfer::Interrupt => EndpointKind::Interrupt,
    };
    let list = || {
        let v: Vec<String> = found
            .iter()
            .map(|(a, k)| {
                let dir = if a & 0x80 != 0 { "in" } else { "out" };
                format!("{a:#04x} {} {dir}", k.name())
            })
            .collect();
        if v.is_empty() {
            "no endpoints".to_string()
        } else {
            v.join(", ")
        }
    };
    for (key, addr) in [
        ("usb.endpoint_out", cfg.endpoint_out),
        ("usb.endpoint_in", cfg.endpoint_in),
    ] {
        match found.iter().find(|(a, _)| *a == addr) {
            None => {
                return Err(format!(
                    "interface {} has no endpoint {addr:#04x} ({key}); it has: {}",
                    cfg.interface,
                    list()
                ))
            }
            Some((_, kind)) if *kind != want => {
                return Err(format!(
                    "endpoint {addr:#04x} is {} but usb.transfer = \"{}\"; it has: {}",
                    kind.name(),
                    cfg.transfer,
                    list()
                ))
            }
            Some(_) => {}
        }
    }
    Ok(())
}

/// Why libusb cannot start, with what to check.
pub(crate) fn no_usb_hint(e: rusb::Error) -> String {
    let usbfs = std::path::Path::new("/dev/bus/usb").exists();
    format!(
        "libusb cannot start here ({e}){}. Run on a machine with USB and the bridge plugged in \
         (in a container, pass the bus through, e.g. --device /dev/bus/usb).",
        if usbfs {
            ""
        } else {
            ": this machine has no USB subsystem (no /dev/bus/usb)"
        }
    )
}

/// One USB device whose ids match the configuration.
pub(crate) struct Matched {
    pub device: rusb::Device<rusb::Context>,
    pub descriptor: rusb::DeviceDescriptor,
    pub location: String,
}

/// USB Touches on the bus, as `2988:0302 at bus 001 device 004`.
pub(crate) fn touches(context: &rusb::Context) -> Vec<String> {
    use rusb::UsbContext;
    let Ok(list) = context.devices() else {
        return Vec::new();
    };
    list.iter()
        .filter_map(|device| {
            let d = device.device_descriptor().ok()?;
            is_usb_touch(d.vendor_id(), d.product_id()).then(|| {
                format!(
                    "{:04x}:{:04x} at bus {:03} device {:03}",
                    d.vendor_id(),
                    d.product_id(),
                    device.bus_number(),
                    device.address()
                )
            })
        })
        .collect()
}

/// The hint when no bridge is there but a USB Touch is.
pub(crate) fn touch_hint(touches: &[String]) -> String {
    if touches.is_empty() {
        String::new()
    } else {
        format!(
            " The USB device {} is {TOUCH_IS_NOT_A_BRIDGE}.",
            touches.join(", ")
        )
    }
}

/// All devices on the bus and those matching the configured ids.
pub(crate) fn enumerate(
    context: &rusb::Context,
    cfg: &UsbConfig,
) -> Result<(usize, Vec<Matched>), rusb::Error> {
    use rusb::UsbContext;
    let list = context.devices()?;
    let total = list.len();
    let mut matched = Vec::new();
    for device in list.iter() {
        let Ok(descriptor) = device.device_descriptor() else {
            continue;
        };
        if cfg.matches(descriptor.vendor_id(), descriptor.product_id()) {
            let location = format!(
                "bus {:03} device {:03} (/dev/bus/usb/{:03}/{:03})",
                device.bus_number(),
                device.address(),
                device.bus_number(),
                device.address()
            );
            matched.push(Matched {
                device,
                descriptor,
                location,
            });
        }
    }
    Ok((total, matched))
}

/// The hint when no device has the configured ids.
pub(crate) fn no_match_hint(cfg: &UsbConfig, total: usize) -> String {
    if total == 0 {
        "libusb sees no USB devices at all: is the bridge plugged in, and is /dev/bus/usb \
         visible here?"
            .to_string()
    } else {
        format!(
            "{total} USB device(s) present, none with id {}. Check that the bridge is plugged \
             in and powered, and that usb.vendor_id / usb.product_id match what `lsusb` shows.",
            cfg.ids()
        )
    }
}

/// Read the serial string of an opened device (None when it has none or it cannot be read).
pub(crate) fn read_serial(
    handle: &rusb::DeviceHandle<rusb::Context>,
    descriptor: &rusb::DeviceDescriptor,
) -> Option<String> {
    descriptor.serial_number_string_index()?;
    handle
        .read_serial_number_string_ascii(descriptor)
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
}

/// Endpoints of interface `cfg.interface` (alternate setting 0) in the active configuration.
pub(crate) fn interface_endpoints(
    device: &rusb::Device<rusb::Context>,
    cfg: &UsbConfig,
) -> Result<Vec<(u8, EndpointKind)>, String> {
    let config = device
        .active_config_descriptor()
        .map_err(|e| format!("cannot read the configuration descriptor: {e}"))?;
    let mut numbers = Vec::new();
    for interface in config.interfaces() {
        numbers.push(interface.number());
        if interface.number() != cfg.interface {
            continue;
        }
        if let Some(alt) = interface.descriptors().next() {
            return Ok(alt
                .endpoint_descriptors()
                .map(|ep| {
                    let kind = match ep.transfer_type() {
                        rusb::TransferType::Bulk => EndpointKind::Bulk,
                        rusb::TransferType::Interrupt => EndpointKind::Interrupt,
                        _ => EndpointKind::Other,
                    };
                    (ep.address(), kind)
                })
                .collect());
        }
    }
    Err(format!(
        "the bridge has no interface {} (usb.interface); it has {:?}",
        cfg.interface, numbers
    ))
}

/// Open the configured USB bridge; `rate_hz` is the device's packet rate (device time comes
/// from the packet counter). Fails fast with `NotFound` when there is no USB or no bridge,
/// and with `Permission` (and the udev fix) when the bridge cannot be opened.
pub(crate) fn open_usb_with_rate(
    cfg: &UsbConfig,
    rate_hz: f64,
) -> Result<Box<dyn Device>, DeviceError> {
    cfg.validate()
        .map_err(|e| DeviceError::Unsupported(e.to_string()))?;
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
        return Err(DeviceError::Unsupported(format!(
            "packet rate {rate_hz} Hz is out of range: allowed a finite rate > 0"
        )));
    }
    let (m, handle, serial) = find_bridge(cfg)?;
    check_bridge_endpoints(cfg, &m)?;
    let reattach = claim_interface(cfg, &handle, &m.location)?;
    let name = match &serial {
        Some(s) => format!("{} serial {s} at {}", cfg.ids(), m.location),
        None => format!("{} at {}", cfg.ids(), m.location),
    };
    let transport = RusbTransport {
        handle,
        interface: cfg.interface,
        endpoint_out: cfg.endpoint_out,
        endpoint_in: cfg.endpoint_in,
        transfer: cfg.transfer,
        reattach_kernel_driver: reattach,
        released: false,
    };
    Ok(Box::new(UsbOmni::new(
        transport, cfg, rate_hz, name, serial,
    )))
}

/// A bridge opened by [`open_matches`]: where it is, its handle, its serial.
type OpenedBridge = (Matched, rusb::DeviceHandle<rusb::Context>, Option<String>);

/// The one bridge with the configured ids (and serial, when set), opened. No USB, no match,
/// no permission, or several matches without a serial to choose: each its own error.
fn find_bridge(cfg: &UsbConfig) -> Result<OpenedBridge, DeviceError> {
    let not_found = |hint: String| DeviceError::NotFound {
        looked_for: cfg.looked_for(),
        hint,
    };
    let context = rusb::Context::new().map_err(|e| not_found(no_usb_hint(e)))?;
    let (total, matched) =
        enumerate(&context, cfg).map_err(|e| not_found(format!("cannot list USB devices: {e}")))?;
    if matched.is_empty() {
        return Err(not_found(format!(
            "{}{}",
            no_match_hint(cfg, total),
            touch_hint(&touches(&context))
        )));
    }
    let (mut opened, serials_seen) = open_matches(cfg, matched)?;
    if opened.len() > 1 {
        return Err(DeviceError::NotFound {
            looked_for: format!("exactly one USB bridge with id {}", cfg.ids()),
            hint: format!(
                "found {} (serials {}); set usb.serial to choose one.",
                opened.len(),
                serials_seen.join(", ")
            ),
        });
    }
    opened
        .pop()
        .ok_or_else(|| not_found(no_match_hint(cfg, total)))
}

/// Open every match (permission problems show here) and keep those with the wanted serial;
/// also every serial seen, for the message when none or several are kept. None kept: a
/// permission error when one was denied, else a hint naming the serials present.
fn open_matches(
    cfg: &UsbConfig,
    matched: Vec<Matched>,
) -> Result<(Vec<OpenedBridge>, Vec<String>), DeviceError> {
    let mut opened = Vec::new();
    let mut denied = None;
    let mut serials_seen = Vec::new();
    for m in matched {
        match m.device.open() {
            Ok(handle) => {
                let serial = read_serial(&handle, &m.descriptor);
                serials_seen.push(serial.clone().unwrap_or_else(|| "(none)".into()));
                if cfg.serial.is_empty() || serial.as_deref() == Some(cfg.serial.as_str()) {
                    opened.push((m, handle, serial));
                }
            }
            Err(rusb::Error::Access) => {
                denied.get_or_insert(m.location.clone());
            }
            Err(rusb::Error::NoDevice) => {}
            Err(e) => {
                return Err(DeviceError::Io(format!(
                    "opening the USB bridge at {}: {e}",
                    m.location
                )))
            }
        }
    }
    if opened.is_empty() {
        if let Some(location) = denied {
            return Err(DeviceError::Permission {
                what: format!("the USB bridge {} at {location}", cfg.ids()),
                hint: cfg.permission_hint(),
            });
        }
        return Err(DeviceError::NotFound {
            looked_for: cfg.looked_for(),
            hint: format!(
                "bridges with id {} have serials {}; set usb.serial to one of them.",
                cfg.ids(),
                serials_seen.join(", ")
            ),
        });
    }
    Ok((opened, serials_seen))
}

/// The bridge's interface must exist and have the configured endpoints and transfer type.
fn check_bridge_endpoints(cfg: &UsbConfig, m: &Matched) -> Result<(), DeviceError> {
    let endpoints = interface_endpoints(&m.device, cfg).map_err(|e| DeviceError::NotFound {
        looked_for: format!(
            "interface {} of the bridge at {}",
            cfg.interface, m.location
        ),
        hint: e,
    })?;
    check_endpoints(cfg, &endpoints).map_err(|e| DeviceError::NotFound {
        looked_for: format!(
            "endpoints {:#04x}/{:#04x} ({}) on the bridge at {}",
            cfg.endpoint_out, cfg.endpoint_in, cfg.transfer, m.location
        ),
        hint: e,
    })
}

/// Detach a kernel driver from the interface (if one holds it) and claim it; whether a
/// driver was detached (to reattach it on release). A failed claim reattaches it at once.
fn claim_interface(
    cfg: &UsbConfig,
    handle: &rusb::DeviceHandle<rusb::Context>,
    location: &str,
) -> Result<bool, DeviceError> {
    let iface = cfg.interface;
    let mut reattach = false;
    if let Ok(true) = handle.kernel_driver_active(iface) {
        handle.detach_kernel_driver(iface).map_err(|e| match e {
            rusb::Error::Access => DeviceError::Permission {
                what: format!("detaching the kernel driver from {location}"),
                hint: cfg.permission_hint(),
            },
            e => DeviceError::Io(format!(
                "detaching the kernel driver from interface {iface} at {location}: {e}"
            )),
        })?;
        reattach = true;
    }
    if let Err(e) = handle.claim_interface(iface) {
        if reattach {
            let _ = handle.attach_kernel_driver(iface);
        }
        return Err(match e {
            rusb::Error::Busy => DeviceError::Io(format!(
                "interface {iface} of the bridge at {location} is in use by another program (another omnid?)"
            )),
            rusb::Error::Access => DeviceError::Permission {
                what: format!("claiming interface {iface} of the bridge at {location}"),
                hint: cfg.permission_hint(),
            },
            rusb::Error::NoDevice => DeviceError::NotFound {
                looked_for: cfg.looked_for(),
                hint: "the bridge vanished while opening it".into(),
            },
            e => DeviceError::Io(format!("claiming interface {iface} at {location}: {e}")),
        });
    }
    Ok(reattach)
}
