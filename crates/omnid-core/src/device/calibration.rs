//! Inkwell calibration (docs/FIREWIRE.md §4, §6). The Omni's encoders are incremental: their counts start
//! wherever the arm was at power-on. The inkwell is a known pose: when the switch says the
//! stylus is docked, encoder zero is set so that the counts read that pose's joint angles.
//! The docked pose of each unit is stored per serial number in
//! `$XDG_CONFIG_HOME/omnid/calibration/<serial>.toml` (or `~/.config/omnid/calibration/`).
//!
//! A run on real hardware calls [`prepare_for_torque`] before the servo loop starts: it
//! refuses a device without a stored calibration (saying how to make one), waits with the
//! amplifiers off until the stylus is docked, and hands back the device wrapped in
//! [`Calibrated`], which rewrites the encoder words of every packet. None of this runs in
//! the 1 kHz loop except that rewrite (two subtractions per joint, no allocation).

use super::codec::{decode_state, encode_command, MotorCommand, STATE_LAYOUT};
use super::{Device, DeviceError, RawSample, COMMAND_LEN};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use thiserror::Error;

/// Nominal joint angles with the stylus in the inkwell, rad (the simulator's start pose).
pub const NOMINAL_DOCKED_POSE_RAD: [f64; 3] = [0.0, 0.27, -0.37];

/// Packets to wait for the stylus to be docked at start-up (2 s at 1 kHz).
pub const INKWELL_WAIT_PACKETS: u32 = 2000;

/// One unit's calibration, as stored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// Serial number of the device this belongs to.
    pub serial: String,
    /// Joint angles (OpenHaptics convention) with the stylus in the inkwell, rad.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub docked_pose_rad: [f64; 3],
}

impl Calibration {
    /// The nominal inkwell pose for `serial` (a starting point; measure and correct per unit).
    #[cfg(test)]
    pub fn nominal(serial: &str) -> Self {
        Calibration {
            serial: serial.to_string(),
            docked_pose_rad: NOMINAL_DOCKED_POSE_RAD,
        }
    }

    fn validate(&self, path: &Path) -> Result<(), CalibrationError> {
        for (j, v) in self.docked_pose_rad.iter().enumerate() {
            if !(v.is_finite() && v.abs() <= 3.2) {
                return Err(CalibrationError::Invalid {
                    path: path.to_path_buf(),
                    message: format!(
                        "docked_pose_rad[{j}] = {v} is out of range: allowed -3.2 ..= 3.2 rad"
                    ),
                });
            }
        }
        Ok(())
    }

    /// Encoder offsets (raw counts to subtract) that make `raw` read the docked pose.
    pub fn offsets(&self, raw: [u16; 3], rad_per_count: f64) -> [u16; 3] {
        let mut off = [0u16; 3];
        for j in 0..3 {
            let docked = (self.docked_pose_rad[j] / rad_per_count).round() as i64;
            off[j] = raw[j].wrapping_sub(docked as u16);
        }
        off
    }
}

#[derive(Debug, Error)]
pub enum CalibrationError {
    #[error("the {kind} device reports no serial number, so its calibration cannot be looked up")]
    NoSerial { kind: &'static str },
    #[error(
        "serial {serial:?} cannot name a calibration file (allowed: letters, digits, '.', '_', '-')"
    )]
    BadSerial { serial: String },
    #[error("no configuration directory: set XDG_CONFIG_HOME or HOME")]
    NoConfigDir,
    #[error("{}", missing_message(.serial, .path))]
    Missing { serial: String, path: PathBuf },
    #[error("cannot read calibration {}: {source}", .path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("calibration {}: {message}", .path.display())]
    Invalid { path: PathBuf, message: String },
    #[error("calibration: {0}")]
    Write(#[from] crate::output::OutputError),
    #[error(
        "the stylus was not in the inkwell during the first {packets} packets: put the stylus \
         in the inkwell and start again (encoder zero is set there)"
    )]
    NotDocked { packets: u32 },
    #[error(transparent)]
    Device(#[from] DeviceError),
}

fn missing_message(serial: &str, path: &Path) -> String {
    let [a, b, c] = NOMINAL_DOCKED_POSE_RAD;
    format!(
        "device {serial} has no inkwell calibration ({} does not exist), so torque stays off. \
         To calibrate, write that file with this unit's joint angles when the stylus is in the \
         inkwell, for example the nominal pose:\n  serial = \"{serial}\"\n  \
         docked_pose_rad = [{a:.2}, {b:.2}, {c:.2}]\nthen start again with the stylus in the \
         inkwell.",
        path.display()
    )
}

/// `$XDG_CONFIG_HOME/omnid/calibration`, else `$HOME/.config/omnid/calibration`.
pub fn default_dir() -> Option<PathBuf> {
    let xdg = std::env::var_os("XDG_CONFIG_HOME")
        .map(PathBuf::from)
        .filter(|p| p.is_absolute());
    let base = xdg.or_else(|| {
        std::env::var_os("HOME")
            .map(PathBuf::from)
            .filter(|p| p.is_absolute())
            .map(|h| h.join(".config"))
    })?;
    Some(base.join("omnid").join("calibration"))
}

/// The calibration file of `serial` in `dir`.
pub fn path_for(dir: &Path, serial: &str) -> Result<PathBuf, CalibrationError> {
    let ok = !serial.is_empty()
        && serial.len() <= 64
        && !serial.starts_with('.')
        && serial
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
    if !ok {
        return Err(CalibrationError::BadSerial {
            serial: serial.to_string(),
        });
    }
    Ok(dir.join(format!("{serial}.toml")))
}

/// The stored calibration of `serial`, or `None` when there is none.
pub fn load(dir: &Path, serial: &str) -> Result<Option<Calibration>, CalibrationError> {
    let path = path_for(dir, serial)?;
    // A regular file of at most 64 KiB (it is two lines): never a wait, never a big read.
    let text = match crate::input::read_capped(&path, 64 << 10, None) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(source) => return Err(CalibrationError::Read { path, source }),
    };
    let cal: Calibration = toml::from_str(&text).map_err(|e| CalibrationError::Invalid {
        path: path.clone(),
        message: e.message().trim().replace('\n', " "),
    })?;
    if cal.serial != serial {
        return Err(CalibrationError::Invalid {
            path,
            message: format!("it is for serial {:?}, not {serial:?}", cal.serial),
        });
    }
    cal.validate(&path)?;
    Ok(Some(cal))
}

/// Store a calibration (atomically: a temporary file renamed into place).
#[cfg(test)]
pub fn save(dir: &Path, cal: &Calibration) -> Result<PathBuf, CalibrationError> {
    let path = path_for(dir, &cal.serial)?;
    cal.validate(&path)?;
    let text = toml::to_string(cal).map_err(|e| CalibrationError::Invalid {
        path: path.clone(),
        message: e.to_string(),
    })?;
    crate::output::write_bytes(&path, text.as_bytes())?;
    Ok(path)
}

/// The calibration a run needs, or an error saying how to make it.
pub fn require(dir: Option<&Path>, serial: &str) -> Result<Calibration, CalibrationError> {
    let dir = dir.ok_or(CalibrationError::NoConfigDir)?;
    match load(dir, serial)? {
        Some(cal) => Ok(cal),
        None => Err(CalibrationError::Missing {
            serial: serial.to_string(),
            path: path_for(dir, serial)?,
        }),
    }
}

/// A device whose encoder words are shifted so that the inkwell reads the docked pose.
pub struct Calibrated {
    inner: Box<dyn Device>,
    offset: [u16; 3],
}

impl Calibrated {
    pub fn new(inner: Box<dyn Device>, offset: [u16; 3]) -> Self {
        Calibrated { inner, offset }
    }
}

impl Device for Calibrated {
    fn kind(&self) -> &'static str {
        self.inner.kind()
    }

    fn serial(&self) -> Option<&str> {
        self.inner.serial()
    }

    fn exchange(&mut self, command: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError> {
        let mut sample = self.inner.exchange(command)?;
        for (j, &at) in STATE_LAYOUT.encoder.iter().enumerate() {
            if at + 2 <= sample.len {
                let raw = u16::from_le_bytes([sample.bytes[at], sample.bytes[at + 1]]);
                let v = raw.wrapping_sub(self.offset[j]);
                sample.bytes[at..at + 2].copy_from_slice(&v.to_le_bytes());
            }
        }
        Ok(sample)
    }

    fn close(&mut self) -> Result<(), DeviceError> {
        self.inner.close()
    }

    fn recorded_torque(&self) -> Option<[f64; 3]> {
        self.inner.recorded_torque()
    }

    fn plant_model(&self) -> Option<&crate::omni::Dynamics> {
        self.inner.plant_model()
    }
}

/// Exchange safe packets (zero torque, amplifiers off) until a packet says the stylus is
/// docked, then return the device with encoder zero set from `cal`. Gives up after
/// `max_packets` packets; the device is closed on every error.
pub fn zero_at_inkwell(
    mut device: Box<dyn Device>,
    cal: &Calibration,
    rad_per_count: f64,
    max_packets: u32,
) -> Result<Calibrated, CalibrationError> {
    for k in 0..max_packets {
        let safe = encode_command(&MotorCommand::safe(k as u8));
        match device.exchange(&safe) {
            Ok(sample) => {
                if let Ok(p) = decode_state(sample.packet()) {
                    if p.inkwell {
                        let offset = cal.offsets(p.encoder, rad_per_count);
                        return Ok(Calibrated::new(device, offset));
                    }
                }
            }
            Err(DeviceError::Missed(_)) | Err(DeviceError::Malformed(_)) => {}
            Err(e) => {
                let _ = device.close();
                return Err(e.into());
            }
        }
    }
    let _ = device.close();
    Err(CalibrationError::NotDocked {
        packets: max_packets,
    })
}

/// Run setup for real hardware: look up the device's calibration (refusing a device without
/// one, with instructions), set encoder zero at the inkwell, and return the device ready for
/// the servo loop.
pub fn prepare_for_torque(
    device: Box<dyn Device>,
    dir: Option<&Path>,
    rad_per_count: f64,
) -> Result<Box<dyn Device>, CalibrationError> {
    let kind = device.kind();
    let Some(serial) = device.serial().map(str::to_string) else {
        return Err(CalibrationError::NoSerial { kind });
    };
    let cal = require(dir, &serial)?;
    let calibrated = zero_at_inkwell(device, &cal, rad_per_count, INKWELL_WAIT_PACKETS)?;
    Ok(Box::new(calibrated))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::codec::{decode_command, encode_state, EncoderUnwrap, StatePacket};
    use std::sync::{Arc, Mutex};

    const RAD: f64 = std::f64::consts::TAU / 15000.0;

    /// A device whose arm sits at raw counts `raw`, docked from packet `docked_from` on;
    /// records what it was sent and whether it was closed.
    struct Arm {
        raw: [u16; 3],
        docked_from: u32,
        n: u32,
        log: ArmLog,
    }

    impl Device for Arm {
        fn kind(&self) -> &'static str {
            "test"
        }
        fn serial(&self) -> Option<&str> {
            Some("SN-7")
        }
        fn exchange(&mut self, command: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError> {
            self.log
                .lock()
                .unwrap()
                .0
                .push(decode_command(command).unwrap());
            let p = StatePacket {
                encoder: self.raw,
                inkwell: self.n >= self.docked_from,
                counter: self.n,
                ..Default::default()
            };
            self.n += 1;
            Ok(RawSample::new(encode_state(&p), self.n as f64 * 1e-3))
        }
        fn close(&mut self) -> Result<(), DeviceError> {
            self.log.lock().unwrap().1 = true;
            Ok(())
        }
    }

    /// What the test arm was sent, and whether it was closed.
    type ArmLog = Arc<Mutex<(Vec<MotorCommand>, bool)>>;

    fn arm(raw: [u16; 3], docked_from: u32) -> (Box<dyn Device>, ArmLog) {
        let log = Arc::new(Mutex::new((Vec::new(), false)));
        let a = Arm {
            raw,
            docked_from,
            n: 0,
            log: log.clone(),
        };
        (Box::new(a), log)
    }

    #[test]
    fn save_load_round_trip_per_serial() {
        let dir = tempfile::tempdir().unwrap();
        let cal = Calibration {
            serial: "A1".into(),
            docked_pose_rad: [0.01, 0.28, -0.36],
        };
        let path = save(dir.path(), &cal).unwrap();
        assert_eq!(path, dir.path().join("A1.toml"));
        assert_eq!(load(dir.path(), "A1").unwrap(), Some(cal));
        assert_eq!(load(dir.path(), "B2").unwrap(), None);
    }

    #[test]
    fn bad_files_and_serials_are_refused_with_reasons() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("X.toml"),
            "serial = \"Y\"\ndocked_pose_rad = [0,0,0]\n",
        )
        .unwrap();
        let e = load(dir.path(), "X").unwrap_err().to_string();
        assert!(e.contains("\"Y\""), "{e}");
        std::fs::write(
            dir.path().join("Z.toml"),
            "serial = \"Z\"\ndocked_pose_rad = [0, nan, 0]\n",
        )
        .unwrap();
        let e = load(dir.path(), "Z").unwrap_err().to_string();
        assert!(e.contains("docked_pose_rad[1]"), "{e}");
        // A fourth angle is refused, not dropped.
        std::fs::write(
            dir.path().join("V.toml"),
            "serial = \"V\"\ndocked_pose_rad = [0, 0.27, -0.37, 5]\n",
        )
        .unwrap();
        let e = load(dir.path(), "V").unwrap_err().to_string();
        assert!(
            e.contains("V.toml") && e.contains("exactly 3 values"),
            "{e}"
        );
        std::fs::write(dir.path().join("W.toml"), "serial = \"W\"\npose = 1\n").unwrap();
        assert!(load(dir.path(), "W")
            .unwrap_err()
            .to_string()
            .contains("pose"));
        for bad in ["", "../etc", ".hidden", "a b", "a/b"] {
            assert!(matches!(
                path_for(dir.path(), bad),
                Err(CalibrationError::BadSerial { .. })
            ));
        }
    }

    #[test]
    fn missing_calibration_says_how_to_calibrate() {
        let dir = tempfile::tempdir().unwrap();
        let e = require(Some(dir.path()), "SN-7").unwrap_err().to_string();
        assert!(
            e.contains("SN-7.toml") && e.contains("torque stays off"),
            "{e}"
        );
        assert!(e.contains("docked_pose_rad = [0.00, 0.27, -0.37]"), "{e}");
        assert!(e.contains("inkwell"));
        assert!(matches!(
            require(None, "SN-7"),
            Err(CalibrationError::NoConfigDir)
        ));
    }

    #[test]
    fn uncalibrated_device_is_refused_before_any_exchange() {
        let dir = tempfile::tempdir().unwrap();
        let (dev, log) = arm([0; 3], 0);
        let e = prepare_for_torque(dev, Some(dir.path()), RAD)
            .err()
            .unwrap();
        assert!(matches!(e, CalibrationError::Missing { .. }), "{e}");
        assert!(log.lock().unwrap().0.is_empty());
    }

    #[test]
    fn docking_sets_encoder_zero_to_the_stored_pose() {
        let dir = tempfile::tempdir().unwrap();
        let cal = Calibration {
            serial: "SN-7".into(),
            docked_pose_rad: [0.0, 0.27, -0.37],
        };
        save(dir.path(), &cal).unwrap();
        // Power-on counts are arbitrary (here near the 16-bit wrap on joint 1).
        let raw = [0xFFF0, 1234, 40];
        let (dev, log) = arm(raw, 5);
        let mut dev = prepare_for_torque(dev, Some(dir.path()), RAD).unwrap();
        {
            let l = log.lock().unwrap();
            // Waited for the dock with zero torque, amplifiers off.
            assert_eq!(l.0.len(), 6);
            assert!(l.0.iter().all(|c| c.is_safe()));
        }
        let s = dev
            .exchange(&encode_command(&MotorCommand::safe(0)))
            .unwrap();
        let p = decode_state(s.packet()).unwrap();
        let q = EncoderUnwrap::new().update(p.encoder);
        for (j, counts) in q.iter().enumerate() {
            let angle = *counts as f64 * RAD;
            assert!(
                (angle - cal.docked_pose_rad[j]).abs() <= RAD / 2.0 + 1e-12,
                "joint {j}: {angle} vs {}",
                cal.docked_pose_rad[j]
            );
        }
        dev.close().unwrap();
        assert!(log.lock().unwrap().1);
    }

    #[test]
    fn never_docked_is_refused_and_the_device_closed() {
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &Calibration::nominal("SN-7")).unwrap();
        let (dev, log) = arm([0; 3], u32::MAX);
        let e = prepare_for_torque(dev, Some(dir.path()), RAD)
            .err()
            .unwrap();
        assert!(
            e.to_string().contains("put the stylus in the inkwell"),
            "{e}"
        );
        let l = log.lock().unwrap();
        assert_eq!(l.0.len() as u32, INKWELL_WAIT_PACKETS);
        assert!(l.0.iter().all(|c| c.is_safe()) && l.1);
    }

    #[test]
    fn default_dir_follows_xdg_then_home() {
        // Read-only look at the environment this test runs in: the rule, not a value.
        let d = default_dir();
        match (
            std::env::var_os("XDG_CONFIG_HOME"),
            std::env::var_os("HOME"),
        ) {
            (Some(x), _) if PathBuf::from(&x).is_absolute() => {
                assert_eq!(d, Some(PathBuf::from(x).join("omnid/calibration")))
            }
            (_, Some(h)) if PathBuf::from(&h).is_absolute() => {
                assert_eq!(d, Some(PathBuf::from(h).join(".config/omnid/calibration")))
            }
            _ => assert_eq!(d, None),
        }
    }
}
