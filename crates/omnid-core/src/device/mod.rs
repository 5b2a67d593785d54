//! The device boundary: one packet exchange per tick (command out, state in, with the device's
//! own timestamp), behind one trait for the simulator, log replay, the USB bridge and FireWire.

pub(crate) mod calibration;
pub mod codec;
pub(crate) mod discovery;
pub(crate) mod firewire;
pub mod inject;
/// The guided first contact with a FireWire Omni (`omnid probe`), part of the FireWire backend.
pub use firewire::probe;
pub mod registry;
pub mod replay;
pub mod sim;
pub(crate) mod stream;
#[cfg(test)]
pub(crate) mod testkit;
pub(crate) mod usb;

pub use codec::{
    decode_state, encode_command, CodecError, DacScale, EncoderUnwrap, MotorCommand, StatePacket,
    COMMAND_LEN, STATE_LEN,
};
pub use discovery::{list_devices, DiscoveryReport};

use crate::config_check::{self as check, ConfigError};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Device-independent facts of the Omni's electronics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DeviceConfig {
    /// Encoder counts per joint revolution.
    pub counts_per_rev: f64,
    /// Motor torque per DAC count, N·m (12-bit offset binary, ±2047 counts).
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub nm_per_count: [f64; 3],
    /// Servo rate, Hz.
    pub rate_hz: f64,
}

impl Default for DeviceConfig {
    fn default() -> Self {
        DeviceConfig {
            counts_per_rev: 15000.0,
            nm_per_count: [2.2e-4; 3],
            rate_hz: 1000.0,
        }
    }
}

impl DeviceConfig {
    /// Joint angle of one encoder count, rad.
    pub fn rad_per_count(&self) -> f64 {
        std::f64::consts::TAU / self.counts_per_rev
    }
}

impl DeviceConfig {
    /// Check every value; the first problem names its field (`device.…`).
    pub fn validate(&self) -> Result<(), ConfigError> {
        check::in_range(
            "device.counts_per_rev",
            self.counts_per_rev,
            100.0,
            1e7,
            "100 ..= 1e7",
        )?;
        check::each("device.nm_per_count", &self.nm_per_count, check::positive)?;
        check::in_range(
            "device.rate_hz",
            self.rate_hz,
            100.0,
            10_000.0,
            "100 ..= 10000 Hz",
        )
    }
}

/// One state packet as it came off the wire, with the device's own timestamp.
#[derive(Debug, Clone, Copy)]
pub struct RawSample {
    /// Packet bytes; `len` of them are valid.
    pub bytes: [u8; STATE_LEN],
    /// Valid bytes in `bytes`.
    pub len: usize,
    /// Device time of this sample, seconds since the device started streaming.
    pub device_time_s: f64,
}

impl RawSample {
    /// A full-length packet taken at `device_time_s`.
    pub fn new(bytes: [u8; STATE_LEN], device_time_s: f64) -> Self {
        RawSample {
            bytes,
            len: STATE_LEN,
            device_time_s,
        }
    }

    /// The valid bytes.
    pub fn packet(&self) -> &[u8] {
        &self.bytes[..self.len]
    }
}

/// Why an exchange returned no sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MissReason {
    /// No packet arrived before the exchange timeout.
    ReadTimeout,
    /// The command could not be written before the timeout (or the transmit queue is stuck).
    WriteStalled,
    /// Data arrived but no complete fresh packet could be cut from it in time.
    NoFreshPacket,
    /// The command handed to the backend was malformed; the safe packet went instead.
    MalformedCommand,
    /// A FireWire bus reset: streaming was restarted, this tick has no sample.
    BusReset,
    /// A stall made on purpose (`--inject stall@T:MS`).
    InjectedStall,
}

impl std::fmt::Display for MissReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            MissReason::ReadTimeout => "no packet before the exchange timeout",
            MissReason::WriteStalled => "the command could not be written in time",
            MissReason::NoFreshPacket => "no complete fresh packet in time",
            MissReason::MalformedCommand => "malformed command (the safe packet went instead)",
            MissReason::BusReset => "bus reset (streaming restarted)",
            MissReason::InjectedStall => "injected stall",
        })
    }
}

/// Errors at the device boundary. `Missed` is survivable (the loop holds the last torque);
/// the others end the run.
#[derive(Debug, Error)]
pub enum DeviceError {
    /// No device matched. `looked_for` says what was searched, `hint` how to fix it.
    #[error("no device found: looked for {looked_for}. {hint}")]
    NotFound {
        /// What was searched.
        looked_for: String,
        /// How to fix it.
        hint: String,
    },
    /// The device node exists but may not be opened.
    #[error("permission denied opening {what}. {hint}")]
    Permission {
        /// The node or interface refused.
        what: String,
        /// How to get access (udev rules, group).
        hint: String,
    },
    /// The packet for this tick did not arrive in time or was corrupt: hold and go on. The
    /// reason is a `Copy` value, so a miss on the servo thread allocates nothing.
    #[error("missed packet: {0}")]
    Missed(MissReason),
    /// A packet that does not decode.
    #[error("malformed packet: {0}")]
    Malformed(#[from] CodecError),
    /// The device went away.
    #[error("device disconnected: {0}")]
    Disconnected(String),
    /// Any other I/O failure talking to the device.
    #[error("device I/O error: {0}")]
    Io(String),
    /// A recorded log has no more samples: the normal end of a replay.
    #[error("end of recorded data")]
    EndOfData,
    /// The backend cannot do what was asked (on this platform or with this device).
    #[error("{0}")]
    Unsupported(String),
    /// Another process drives this very unit (whatever arm name it gave it): refused before
    /// anything is written to the device.
    #[error("{what} is in use by {holder}; stop it first")]
    InUse {
        /// The unit (kind, serial, node).
        what: String,
        /// Who holds it (`omnid (pid N: COMMAND)`).
        holder: String,
    },
}

/// What the simulator's hand does with the stylus (`[sim] stylus`, the `stylus` op of
/// `omnid serve`): press or release a button (0 or 1: the stylus's buttons 1 and 2), click one
/// (pressed for [`sim::CLICK_S`]), put the stylus in its inkwell or take it out. Plain `Copy`
/// data: it reaches the servo thread through the mailbox and allocates nothing there.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StylusAction {
    /// Press button `0` (button 1) or `1` (button 2) and keep it pressed.
    Press(usize),
    /// Release the button.
    Release(usize),
    /// Press the button and release it [`sim::CLICK_S`] later.
    Click(usize),
    /// The hand carries the stylus into its inkwell and lets it rest there.
    Dock,
    /// The hand takes the stylus out of its inkwell and holds it lightly at the workspace
    /// centre.
    Undock,
}

impl StylusAction {
    /// The names `[sim] stylus` and the `stylus` op use.
    pub const NAMES: &'static str = "press, release, click, dock or undock";

    /// `action` (press, release, click: with `button` 1 or 2; dock, undock: without one). The
    /// error names the field at fault (`action` or `button`) and what it allows.
    pub fn parse(
        action: &str,
        button: Option<u64>,
    ) -> Result<StylusAction, (&'static str, &'static str)> {
        const BUTTONS: &str = "1 or 2 (the Omni's stylus has two buttons)";
        let which = |button: Option<u64>| match button {
            Some(b @ 1..=2) => Ok(b as usize - 1),
            _ => Err(("button", BUTTONS)),
        };
        match action {
            "press" => Ok(StylusAction::Press(which(button)?)),
            "release" => Ok(StylusAction::Release(which(button)?)),
            "click" => Ok(StylusAction::Click(which(button)?)),
            "dock" | "undock" if button.is_some() => {
                Err(("button", "none: dock and undock take no button"))
            }
            "dock" => Ok(StylusAction::Dock),
            "undock" => Ok(StylusAction::Undock),
            _ => Err(("action", Self::NAMES)),
        }
    }

    /// The action's name.
    pub fn name(self) -> &'static str {
        match self {
            StylusAction::Press(_) => "press",
            StylusAction::Release(_) => "release",
            StylusAction::Click(_) => "click",
            StylusAction::Dock => "dock",
            StylusAction::Undock => "undock",
        }
    }

    /// The button it presses or releases, 1 or 2 (none for dock and undock).
    pub fn button(self) -> Option<u8> {
        match self {
            StylusAction::Press(b) | StylusAction::Release(b) | StylusAction::Click(b) => {
                Some(b as u8 + 1)
            }
            StylusAction::Dock | StylusAction::Undock => None,
        }
    }
}

/// A Phantom Omni, real or mock, at the packet level.
pub trait Device: Send {
    /// Short name for logs and the summary (`sim`, `replay`, `usb`, `firewire`).
    fn kind(&self) -> &'static str;

    /// Send one command packet and return the next state packet. Blocks until the device's
    /// next sample (paced devices) or returns at once (`--fast`).
    fn exchange(&mut self, command: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError>;

    /// The device's serial number, when the backend knows one (real hardware): calibration
    /// is stored per serial.
    fn serial(&self) -> Option<&str> {
        None
    }

    /// Stop streaming and release the device. Called once, after the last (safe) exchange.
    fn close(&mut self) -> Result<(), DeviceError> {
        Ok(())
    }

    /// The recorded torque for the sample just returned, for replay devices (the identifier
    /// learns from what the recording applied, not from what this run computes).
    fn recorded_torque(&self) -> Option<[f64; 3]> {
        None
    }

    /// The plant's exact dynamics at this moment, for simulated devices (the oracle model).
    fn plant_model(&self) -> Option<&crate::omni::Dynamics> {
        None
    }

    /// The force the simulated hand puts on the stylus tip, N (OpenHaptics frame): the
    /// simulator only (docs/HAPTICS.md §7).
    fn hand_force(&self) -> Option<[f64; 3]> {
        None
    }

    /// The force the simulated world's wall (`[sim.wall]`) puts on the tip, N: the true
    /// contact force an estimate is checked against (simulator only).
    fn contact_force(&self) -> Option<[f64; 3]> {
        None
    }

    /// The simulated hand acts on the stylus (buttons, inkwell): the simulator only; false
    /// where nothing can (a real stylus is pressed by a real hand). Called on the servo thread
    /// between exchanges: it must not allocate or block.
    fn stylus(&mut self, action: StylusAction) -> bool {
        let _ = action;
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_miss_says_why_without_carrying_any_heap_data() {
        fn copy<T: Copy>(_: T) {}
        copy(MissReason::ReadTimeout);
        let text = DeviceError::Missed(MissReason::ReadTimeout).to_string();
        assert_eq!(text, "missed packet: no packet before the exchange timeout");
        assert!(DeviceError::Missed(MissReason::BusReset)
            .to_string()
            .contains("bus reset"));
    }
}
