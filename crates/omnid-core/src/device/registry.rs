//! The device registry: every backend `--device` names, opened from one place for `run`,
//! `serve` and the tests (sim, replay, the USB bridge, FireWire), with the steps real
//! hardware needs before torque (calibration at the inkwell, measured DAC signs).

use crate::device::calibration::{self, CalibrationError};
use crate::device::firewire::{find_firewire, FireWireBus, FireWireOmni, FirewireConfig};
use crate::device::replay::{ReplayDevice, ReplayError};
use crate::device::sim::{SimOmni, SimSetup};
use crate::device::usb::open_usb_with_rate;
use crate::device::usb::UsbConfig;
use crate::device::DeviceConfig;
use crate::device::{Device, DeviceError};
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// `--device`: which Omni to talk to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DeviceSpec {
    /// The simulated Omni (`sim`).
    Sim,
    /// A recorded omnid log played back (`replay:PATH`).
    Replay(PathBuf),
    /// A real Omni through the USB bridge (`usb`).
    Usb,
    /// A real FireWire Omni on Linux firewire-cdev (`firewire`).
    Firewire,
}

impl FromStr for DeviceSpec {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "sim" => Ok(DeviceSpec::Sim),
            "usb" => Ok(DeviceSpec::Usb),
            "firewire" => Ok(DeviceSpec::Firewire),
            _ => match s.strip_prefix("replay:") {
                Some(p) if !p.is_empty() => Ok(DeviceSpec::Replay(PathBuf::from(p))),
                _ => Err(format!(
                    "unknown device `{s}`: expected sim, replay:PATH, usb or firewire"
                )),
            },
        }
    }
}

impl DeviceSpec {
    /// The backend's name: `sim`, `replay`, `usb` or `firewire`.
    pub fn name(&self) -> &'static str {
        match self {
            DeviceSpec::Sim => "sim",
            DeviceSpec::Replay(_) => "replay",
            DeviceSpec::Usb => "usb",
            DeviceSpec::Firewire => "firewire",
        }
    }
}

/// Why a device could not be opened.
#[derive(Debug, Error)]
pub enum OpenError {
    /// A configuration that cannot drive this device; the message says why.
    #[error("{0}")]
    BadInput(String),
    /// The device is missing or failed.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The log given to `--device replay:PATH` cannot be replayed.
    #[error(transparent)]
    Replay(#[from] ReplayError),
}

/// The configuration sections the devices are opened from (a `&Config` gives them).
#[derive(Debug, Clone, Copy)]
pub struct DeviceSetup<'a> {
    /// Encoder resolution, DAC scale, servo rate.
    pub device: &'a DeviceConfig,
    /// The simulated Omni.
    pub sim: SimSetup<'a>,
    /// The USB bridge.
    pub usb: &'a UsbConfig,
    /// The FireWire Omni.
    pub firewire: &'a FirewireConfig,
}

/// How a device is to be opened beyond the config.
#[derive(Debug, Clone, Copy)]
pub struct OpenOptions<'a> {
    /// Paced at the device's rate (not `--fast`).
    pub paced: bool,
    /// Replay: skip damaged rows.
    pub lenient: bool,
    /// Replay: stop after this much device time.
    pub duration_s: Option<f64>,
    /// The operator's stop (ends a wait on a replayed pipe).
    pub stop: &'a Arc<AtomicBool>,
}

/// Real hardware gets encoder zero at the inkwell from its stored calibration (in
/// `calibrations`, looked up by the unit's serial) before the loop starts; a device without
/// one is refused (the message says how to calibrate).
fn ready_for_torque(
    device: Box<dyn Device>,
    cfg: &DeviceSetup<'_>,
    calibrations: Option<&Path>,
) -> Result<Box<dyn Device>, OpenError> {
    calibration::prepare_for_torque(device, calibrations, cfg.device.rad_per_count()).map_err(|e| {
        match e {
            CalibrationError::Device(d) => OpenError::Device(d),
            e => OpenError::BadInput(e.to_string()),
        }
    })
}

/// A found FireWire Omni made ready for torque: identified first (reads only, so that a
/// machine without the Omni hears what was looked for), then no torque before the motors'
/// signs are known; started, its packet rate checked, and encoder zero set from its own
/// calibration.
pub(crate) fn bring_up_firewire<B: FireWireBus + 'static>(
    mut omni: FireWireOmni<B>,
    cfg: &DeviceSetup<'_>,
    calibrations: Option<&Path>,
) -> Result<Box<dyn Device>, OpenError> {
    if let Some(why) = unmeasured_dac_signs(cfg.firewire, omni.serial()) {
        return Err(OpenError::BadInput(why));
    }
    omni.start()?;
    omni.check_rate()?;
    ready_for_torque(Box::new(omni), cfg, calibrations)
}

/// The refusal when a motor's DAC sign has not been measured: the first torque on a new Omni
/// goes through `omnid probe --outputs`, never straight into a controller.
pub(crate) fn unmeasured_dac_signs(cfg: &FirewireConfig, serial: Option<&str>) -> Option<String> {
    let missing = cfg.unmeasured_dac_signs();
    if missing.is_empty() {
        return None;
    }
    let motors: Vec<String> = missing.iter().map(|j| (j + 1).to_string()).collect();
    Some(format!(
        "the DAC sign of motor(s) {} of FireWire Omni {} is not measured (firewire.dac_sign = \
         {:?}), so omnid applies no torque with it. Run `omnid probe --outputs`: it finds each \
         motor's sign with a few DAC counts, asking before every step, and prints the \
         `dac_sign` line to put under [firewire] (docs/BRINGUP.md).",
        motors.join(", "),
        serial.unwrap_or("?"),
        cfg.dac_sign
    ))
}

/// Open the device `spec` names (as `--device` gives it); notes for the operator (rows a
/// lenient replay skipped) go to `warnings`.
pub fn open<'a>(
    spec: &DeviceSpec,
    cfg: impl Into<DeviceSetup<'a>>,
    how: OpenOptions<'_>,
    warnings: &mut Vec<String>,
) -> Result<Box<dyn Device>, OpenError> {
    let cfg = cfg.into();
    match spec {
        DeviceSpec::Sim => Ok(Box::new(SimOmni::new(cfg.sim, how.paced))),
        DeviceSpec::Replay(path) => {
            let device = ReplayDevice::open(path, cfg.device, how.paced, how.lenient, how.stop)?
                .with_duration_limit(how.duration_s);
            if device.info().skipped.count > 0 {
                warnings.push(format!(
                    "--lenient: {}: {}",
                    path.display(),
                    device.info().skipped
                ));
            }
            Ok(Box::new(device))
        }
        DeviceSpec::Usb => ready_for_torque(
            open_usb_with_rate(cfg.usb, cfg.device.rate_hz)?,
            &cfg,
            calibration::default_dir().as_deref(),
        ),
        DeviceSpec::Firewire => bring_up_firewire(
            find_firewire(cfg.firewire, cfg.device.rate_hz)?,
            &cfg,
            calibration::default_dir().as_deref(),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cmd::assembly::{heat_path, RunOptions};
    use crate::config::Config;
    use crate::device::calibration::Calibration;
    use crate::device::codec::{decode_state, encode_command, MotorCommand};
    use crate::device::firewire::fake::{ArmState, FakeBus};
    use crate::device::firewire::{choose_by_serial, serial};
    use crate::servo::thermal_store;

    /// Two FireWire Omnis on one bus, served as two arms: each arm finds its own unit by
    /// serial, zeroes its encoders from that unit's calibration, and keeps its own heat file.
    #[test]
    fn two_firewire_arms_keep_their_own_unit_calibration_and_heat() {
        let cfg: Config = toml::from_str(
            r#"
            [firewire]
            dac_sign = [1, 1, 1]
            [[arm]]
            name = "left"
            device = "firewire"
            serial = "10203400567"
            [[arm]]
            name = "right"
            device = "firewire"
            serial = "20304500678"
            "#,
        )
        .unwrap();
        let arms = cfg.arms().unwrap();
        // The units, in the order the bus lists them (not the config's), each docked with
        // its own raw encoder counts.
        let unit = |label: &str, encoder: [u16; 3]| {
            FakeBus::with(|n| {
                n.serial = serial::parse(label).unwrap();
                n.arm = ArmState {
                    encoder,
                    docked: true,
                    ..ArmState::default()
                };
            })
        };
        let nodes = [
            ("/dev/fw2", unit("20304500678", [40_000, 1_000, 65_000])),
            ("/dev/fw1", unit("10203400567", [100, 30_000, 7])),
        ];
        let candidates: Vec<PathBuf> = nodes.iter().map(|(p, _)| PathBuf::from(p)).collect();
        let calibrations = tempfile::tempdir().unwrap();
        let docked = [
            ("10203400567", [0.1, 0.25, -0.3]),
            ("20304500678", [-0.2, 0.4, 0.05]),
        ];
        for (serial, pose) in docked {
            calibration::save(
                calibrations.path(),
                &Calibration {
                    serial: serial.into(),
                    docked_pose_rad: pose,
                },
            )
            .unwrap();
        }
        let state = tempfile::tempdir().unwrap();
        let mut heat_files = Vec::new();
        for (arm, (serial, pose)) in arms.iter().zip(docked) {
            let omni = choose_by_serial(
                &arm.config.firewire,
                arm.config.device.rate_hz,
                &candidates,
                |p| {
                    let (_, bus) = nodes.iter().find(|(n, _)| Path::new(n) == p).unwrap();
                    Ok(bus.clone())
                },
                || "no Omni".into(),
            )
            .unwrap();
            assert_eq!(omni.serial(), Some(serial), "arm {}", arm.name);
            let mut device =
                bring_up_firewire(omni, &(&arm.config).into(), Some(calibrations.path())).unwrap();
            let sample = device
                .exchange(&encode_command(&MotorCommand::safe(0)))
                .unwrap();
            let encoder = decode_state(sample.packet()).unwrap().encoder;
            // The unit's encoders read its own docked pose (the backend's encoder signs are
            // applied before calibration, so compare magnitudes of the signed counts).
            let rad_per_count = arm.config.device.rad_per_count();
            for j in 0..3 {
                let q = f64::from(encoder[j] as i16) * rad_per_count;
                assert!(
                    (q - pose[j]).abs() <= rad_per_count,
                    "arm {} joint {j}: reads {q} rad, its calibration says {}",
                    arm.name,
                    pose[j]
                );
            }
            device.close().unwrap();

            let opts = RunOptions {
                device: arm.device.clone(),
                arm: Some(arm.name.clone()),
                arm_configured: true,
                ..RunOptions::default()
            };
            heat_files.push(heat_path(&opts, &arm.config, Some(state.path().into())).unwrap());
        }
        assert_ne!(heat_files[0], heat_files[1]);
        // The left arm's motors are warm; the right arm's stay cold.
        thermal_store::save(&heat_files[0], [0.8, 0.5, 0.3]).unwrap();
        let safety = &arms[0].config.safety;
        let (left, _) = thermal_store::load(&heat_files[0], safety);
        let (right, _) = thermal_store::load(&heat_files[1], safety);
        assert!(left[0] > 0.7, "left heat {left:?}");
        assert_eq!(right, [0.0; 3]);
    }
}
