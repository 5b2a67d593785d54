//! `[firewire]`: which node, how long to wait, the start sequence's options, and the options
//! the protocol runs with.

use super::*;
use crate::config_check::{self as check, ConfigError};
use crate::device::stream::{Byte7, WireFormat};
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// `[firewire]`: which node, how long to wait, and the start sequence's options.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct FirewireConfig {
    /// Device node to use (`/dev/fw1`); empty = search every `/dev/fw*` for vendor 0x000B99.
    pub device: String,
    /// Serial number of the Omni to use when several are on the bus (the 11 digits of its
    /// label); empty = the only one.
    pub serial: String,
    /// How long one exchange may wait for the next state packet, ms.
    pub timeout_ms: u32,
    /// How long a register read or write, or a channel allocation, may take, ms.
    pub register_timeout_ms: u32,
    /// Write the vendor library's quadlet to 0x20010 before starting.
    pub vendor_init: bool,
    /// The vendor library's scratch test of register 0x1001 (write 0x40, read it back).
    pub scratch_test: bool,
    /// Retries of a register transaction the node answers busy.
    pub busy_retries: u32,
    /// Pause before each such retry, ms.
    pub busy_retry_ms: u32,
    /// Sign per joint that turns encoder counts into the OpenHaptics joint directions.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub encoder_sign: [i8; 3],
    /// Sign per motor of the DAC word; 0 = not measured yet (`omnid probe --outputs`): no
    /// torque on that motor, and `run`/`serve` refuse to start.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub dac_sign: [i8; 3],
    /// Byte 7 of every command: "0x53" (the open drivers) or another "0xNN", or "counter".
    pub command_byte7: String,
}

impl Default for FirewireConfig {
    fn default() -> Self {
        FirewireConfig {
            device: String::new(),
            serial: String::new(),
            timeout_ms: 10,
            register_timeout_ms: 100,
            vendor_init: true,
            scratch_test: true,
            busy_retries: 5,
            busy_retry_ms: 100,
            encoder_sign: OPENHAPTICS_ENCODER_SIGN,
            dac_sign: [0; 3],
            command_byte7: "0x53".into(),
        }
    }
}

/// Encoder count direction → OpenHaptics joint direction, per joint (docs/FIREWIRE.md §6).
pub(crate) const OPENHAPTICS_ENCODER_SIGN: [i8; 3] = [-1, -1, 1];

impl FirewireConfig {
    /// Check every value; the first problem names its field (`firewire.timeout_ms`, ...).
    pub(crate) fn validate(&self) -> Result<(), ConfigError> {
        let node_ok = self
            .device
            .strip_prefix("/dev/fw")
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        if !self.device.is_empty() && !node_ok {
            return Err(check::invalid(
                "firewire.device",
                format!("{:?}", self.device),
                "empty (search) or a node like \"/dev/fw1\"",
            ));
        }
        if !self.serial.is_empty() {
            if let Err(e) = serial::parse(&self.serial) {
                return Err(check::invalid(
                    "firewire.serial",
                    format!("{:?}", self.serial),
                    format!("empty, or {}", e.0),
                ));
            }
        }
        if !(1..=1000).contains(&self.timeout_ms) {
            return Err(check::invalid(
                "firewire.timeout_ms",
                self.timeout_ms.to_string(),
                "1 ..= 1000 ms",
            ));
        }
        if !(1..=5000).contains(&self.register_timeout_ms) {
            return Err(check::invalid(
                "firewire.register_timeout_ms",
                self.register_timeout_ms.to_string(),
                "1 ..= 5000 ms",
            ));
        }
        if self.busy_retries > 50 {
            return Err(check::invalid(
                "firewire.busy_retries",
                self.busy_retries.to_string(),
                "0 ..= 50",
            ));
        }
        if !(1..=1000).contains(&self.busy_retry_ms) {
            return Err(check::invalid(
                "firewire.busy_retry_ms",
                self.busy_retry_ms.to_string(),
                "1 ..= 1000 ms",
            ));
        }
        for (j, s) in self.encoder_sign.iter().enumerate() {
            if !matches!(s, -1 | 1) {
                return Err(check::invalid(
                    format!("firewire.encoder_sign[{j}]"),
                    s.to_string(),
                    "1 or -1",
                ));
            }
        }
        for (j, s) in self.dac_sign.iter().enumerate() {
            if !matches!(s, -1..=1) {
                return Err(check::invalid(
                    format!("firewire.dac_sign[{j}]"),
                    s.to_string(),
                    "1 or -1, or 0 (not measured yet)",
                ));
            }
        }
        if self.byte7().is_none() {
            return Err(check::invalid(
                "firewire.command_byte7",
                format!("{:?}", self.command_byte7),
                "\"0x53\" (the open drivers), another \"0xNN\", or \"counter\"",
            ));
        }
        Ok(())
    }

    /// `command_byte7` parsed (`None` when it is not valid).
    pub(crate) fn byte7(&self) -> Option<Byte7> {
        if self.command_byte7 == "counter" {
            return Some(Byte7::Counter);
        }
        let hex = self.command_byte7.strip_prefix("0x")?;
        (hex.len() == 2)
            .then(|| u8::from_str_radix(hex, 16).ok())
            .flatten()
            .map(Byte7::Constant)
    }

    /// Motors whose DAC sign has not been measured (0-based).
    pub(crate) fn unmeasured_dac_signs(&self) -> Vec<usize> {
        (0..3).filter(|&j| self.dac_sign[j] == 0).collect()
    }

    /// The protocol options of this configuration at packet rate `rate_hz`.
    pub(crate) fn options(&self, rate_hz: f64) -> FireWireOptions {
        FireWireOptions {
            timeout: Duration::from_millis(u64::from(self.timeout_ms)),
            rate_hz,
            vendor_init: self.vendor_init,
            scratch_test: self.scratch_test,
            busy_retries: self.busy_retries,
            busy_retry: Duration::from_millis(u64::from(self.busy_retry_ms)),
            encoder_sign: self.encoder_sign,
            format: WireFormat {
                byte7: self.byte7().unwrap_or(WireFormat::DRIVERS.byte7),
                dac_sign: self.dac_sign,
            },
        }
    }

    /// What [`find_firewire`] looks for, in words.
    pub(crate) fn looked_for(&self) -> String {
        let what = if self.device.is_empty() {
            "a FireWire Omni (config-ROM vendor 0x000B99) on /dev/fw*".to_string()
        } else {
            format!("a FireWire Omni (vendor 0x000B99) at {}", self.device)
        };
        if self.serial.is_empty() {
            what
        } else {
            format!("{what} with serial {}", self.serial)
        }
    }

    /// Whether the unit with serial quadlet `quadlet` is the configured one.
    pub(crate) fn wants_serial(&self, quadlet: u32) -> bool {
        self.serial.is_empty() || serial::parse(&self.serial) == Ok(quadlet)
    }
}

/// How [`FireWireOmni`] runs the protocol.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FireWireOptions {
    /// How long one exchange waits for the next packet.
    pub(crate) timeout: Duration,
    /// The configured packet rate (device time is counter / rate; checked at open).
    pub(crate) rate_hz: f64,
    pub(crate) vendor_init: bool,
    pub(crate) scratch_test: bool,
    pub(crate) busy_retries: u32,
    pub(crate) busy_retry: Duration,
    pub(crate) encoder_sign: [i8; 3],
    pub(crate) format: WireFormat,
}

impl FireWireOptions {
    /// The defaults of `[firewire]` at `rate_hz`, with `timeout`.
    pub(crate) fn new(timeout: Duration, rate_hz: f64) -> Self {
        FireWireOptions {
            timeout,
            ..FirewireConfig::default().options(rate_hz)
        }
    }
}
