//! `[usb]`: which bridge, which endpoints, how long to wait, and the udev rule that lets a
//! user open it.

use crate::config_check::{self as check, ConfigError};
use serde::{Deserialize, Serialize};
use std::fmt;

/// USB transfer type of the bridge's endpoints.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum UsbTransfer {
    /// Bulk endpoints (most bridges).
    Bulk,
    /// Interrupt endpoints (polled by the host every frame).
    Interrupt,
}

impl fmt::Display for UsbTransfer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            UsbTransfer::Bulk => "bulk",
            UsbTransfer::Interrupt => "interrupt",
        })
    }
}

/// `[usb]`: which bridge and how to talk to it. Nothing public fixes these, so the defaults
/// are placeholders (the pid.codes test id 1209:0001) to be set for the bridge at hand.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct UsbConfig {
    /// USB vendor id of the bridge.
    pub vendor_id: u16,
    /// USB product id of the bridge.
    pub product_id: u16,
    /// Interface number carrying the two endpoints.
    pub interface: u8,
    /// OUT endpoint address for commands (0x01..=0x0F).
    pub endpoint_out: u8,
    /// IN endpoint address for state packets (0x81..=0x8F).
    pub endpoint_in: u8,
    /// Transfer type of both endpoints.
    pub transfer: UsbTransfer,
    /// How long one exchange may wait for the next state packet, ms (≥ 1: libusb takes 0 as
    /// "wait forever").
    pub timeout_ms: u32,
    /// Serial number of the bridge to use; empty = the only one present.
    pub serial: String,
}

impl Default for UsbConfig {
    fn default() -> Self {
        UsbConfig {
            vendor_id: 0x1209,
            product_id: 0x0001,
            interface: 0,
            endpoint_out: 0x01,
            endpoint_in: 0x81,
            transfer: UsbTransfer::Bulk,
            timeout_ms: 10,
            serial: String::new(),
        }
    }
}

/// USB vendor id of 3D Systems, maker of the USB Geomagic/3D Systems Touch.
pub(crate) const TOUCH_VENDOR_ID: u16 = 0x2988;

/// Whether these ids are a USB Touch: vendor 0x2988 (the Touch reports 2988:0302), or
/// 0301:2988, the pair 3D Systems' own instructions give (both seen in
/// bharatm11/Geomagic_Touch_ROS_Drivers issue #2). docs/FIREWIRE.md §8.
pub(crate) fn is_usb_touch(vendor_id: u16, product_id: u16) -> bool {
    vendor_id == TOUCH_VENDOR_ID || (vendor_id == 0x0301 && product_id == TOUCH_VENDOR_ID)
}

/// What a USB Touch is, for refusals.
pub(crate) const TOUCH_IS_NOT_A_BRIDGE: &str =
    "a 3D Systems (Geomagic) Touch: a USB CDC-ACM serial \
     device with an undocumented protocol, not a bridge forwarding a FireWire Omni's packets; \
     omnid cannot drive it (docs/FIREWIRE.md §8)";

impl UsbConfig {
    /// Check every value; the first problem names its field (`usb.timeout_ms`, ...).
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.vendor_id == 0 {
            return Err(check::invalid(
                "usb.vendor_id",
                "0x0000",
                "0x0001 ..= 0xFFFF",
            ));
        }
        if is_usb_touch(self.vendor_id, self.product_id) {
            return Err(check::invalid(
                "usb.vendor_id",
                format!(
                    "{:#06x} (with usb.product_id {:#06x})",
                    self.vendor_id, self.product_id
                ),
                format!(
                    "the ids of a USB bridge to an Omni; {} is {TOUCH_IS_NOT_A_BRIDGE}",
                    self.ids()
                ),
            ));
        }
        let ep_ok = |ep: u8, dir: u8| ep & 0xF0 == dir && (1..=15).contains(&(ep & 0x0F));
        if !ep_ok(self.endpoint_out, 0x00) {
            return Err(check::invalid(
                "usb.endpoint_out",
                format!("{:#04x}", self.endpoint_out),
                "an OUT endpoint address, 0x01 ..= 0x0F",
            ));
        }
        if !ep_ok(self.endpoint_in, 0x80) {
            return Err(check::invalid(
                "usb.endpoint_in",
                format!("{:#04x}", self.endpoint_in),
                "an IN endpoint address, 0x81 ..= 0x8F",
            ));
        }
        if !(1..=1000).contains(&self.timeout_ms) {
            return Err(check::invalid(
                "usb.timeout_ms",
                self.timeout_ms.to_string(),
                "1 ..= 1000 ms (0 would mean \"wait forever\" to libusb)",
            ));
        }
        if self.serial.len() > 126 || !self.serial.chars().all(|c| c.is_ascii_graphic()) {
            return Err(check::invalid(
                "usb.serial",
                format!("{:?}", self.serial),
                "empty, or up to 126 printable ASCII characters without spaces",
            ));
        }
        Ok(())
    }

    /// Whether a device with these ids is the configured bridge.
    pub(crate) fn matches(&self, vendor_id: u16, product_id: u16) -> bool {
        vendor_id == self.vendor_id && product_id == self.product_id
    }

    /// `1209:0001` style.
    pub(crate) fn ids(&self) -> String {
        format!("{:04x}:{:04x}", self.vendor_id, self.product_id)
    }

    /// What `open_usb_with_rate` looks for, in words.
    pub(crate) fn looked_for(&self) -> String {
        if self.serial.is_empty() {
            format!("a USB bridge with id {}", self.ids())
        } else {
            format!(
                "a USB bridge with id {} and serial {:?}",
                self.ids(),
                self.serial
            )
        }
    }

    /// The udev rule that lets the plugdev group open this bridge.
    pub(crate) fn udev_rule(&self) -> String {
        format!(
            "SUBSYSTEM==\"usb\", ATTRS{{idVendor}}==\"{:04x}\", ATTRS{{idProduct}}==\"{:04x}\", MODE=\"0660\", GROUP=\"plugdev\"",
            self.vendor_id, self.product_id
        )
    }

    /// How to fix "permission denied" on the bridge.
    pub(crate) fn permission_hint(&self) -> String {
        format!(
            "Install the udev rule (udev/99-omnid-usb.rules, or put this line in \
             /etc/udev/rules.d/99-omnid-usb.rules: {}), run `sudo udevadm control --reload-rules \
             && sudo udevadm trigger`, add yourself to plugdev (`sudo usermod -aG plugdev $USER`), \
             log in again and replug the bridge. See udev/README.md.",
            self.udev_rule()
        )
    }
}
