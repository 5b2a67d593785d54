//! `omnid run`: build the pipeline (device, controller, reference, servo, log writer) from the
//! options, run it on its own thread, and turn the result into the run summary.

use crate::config::Config;
use crate::control::{Controller, ControllerKind, Off, Pd, Reference, Trajectory};
use crate::device::calibration::{self, CalibrationError};
use crate::device::firewire::{open_firewire_with_rate, FirewireConfig};
use crate::device::sim::SimOmni;
use crate::device::usb::{open_usb_with_rate, UsbConfig};
use crate::device::{Device, DeviceError};
use crate::servo::{EndReason, Servo};
use crate::telemetry::summary::{IdentifierSummary, RunSummary, TimingSummary};
use crate::telemetry::{spawn_writer, LogSchema};
use std::path::PathBuf;
use std::str::FromStr;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// `--device`: which Omni to talk to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum DeviceSpec {
    Sim,
    Replay(PathBuf),
    Usb,
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
    pub fn name(&self) -> &'static str {
        match self {
            DeviceSpec::Sim => "sim",
            DeviceSpec::Replay(_) => "replay",
            DeviceSpec::Usb => "usb",
            DeviceSpec::Firewire => "firewire",
        }
    }
}

#[derive(Debug, Clone)]
pub struct RunOptions {
    pub device: DeviceSpec,
    pub controller: ControllerKind,
    pub trajectory: Trajectory,
    pub duration_s: f64,
    pub log: PathBuf,
    pub fast: bool,
}

/// Problems that stop a run before the loop starts (bad input, no device, no log file).
#[derive(Debug, Error)]
pub enum RunError {
    #[error("{0}")]
    BadInput(String),
    #[error("cannot create log {path}: {source}")]
    Log {
        path: String,
        source: std::io::Error,
    },
    #[error(transparent)]
    Device(#[from] DeviceError),
    #[error("internal error: {0}")]
    Internal(String),
}

/// The outcome of a run that started.
pub struct RunOutcome {
    pub summary: RunSummary,
    pub end: EndReason,
    /// Writing the log failed part-way (the loop was not affected).
    pub log_error: Option<String>,
    /// Sending the final safe packet or closing the device failed.
    pub shutdown_error: Option<String>,
}

/// Real hardware gets encoder zero at the inkwell from its stored calibration before the
/// loop starts; a device without one is refused (the message says how to calibrate).
fn ready_for_torque(device: Box<dyn Device>, cfg: &Config) -> Result<Box<dyn Device>, RunError> {
    calibration::prepare_for_torque(
        device,
        calibration::default_dir().as_deref(),
        cfg.device.rad_per_count(),
    )
    .map_err(|e| match e {
        CalibrationError::Device(d) => RunError::Device(d),
        e => RunError::BadInput(e.to_string()),
    })
}

fn open_device(spec: &DeviceSpec, cfg: &Config, fast: bool) -> Result<Box<dyn Device>, RunError> {
    match spec {
        DeviceSpec::Sim => Ok(Box::new(SimOmni::new(cfg, !fast))),
        // TODO(config): `cfg.usb` / `cfg.firewire` once Config has them.
        DeviceSpec::Usb => ready_for_torque(
            open_usb_with_rate(&UsbConfig::default(), cfg.device.rate_hz)?,
            cfg,
        ),
        DeviceSpec::Firewire => ready_for_torque(
            open_firewire_with_rate(&FirewireConfig::default(), cfg.device.rate_hz)?,
            cfg,
        ),
        other => Err(RunError::BadInput(format!(
            "device `{}` is not available in this build yet; use --device sim",
            other.name()
        ))),
    }
}

fn make_controller(kind: ControllerKind, cfg: &Config) -> Result<Box<dyn Controller>, RunError> {
    match kind {
        ControllerKind::Pd => Ok(Box::new(Pd::from_config(cfg))),
        ControllerKind::Off => Ok(Box::new(Off)),
        other => Err(RunError::BadInput(format!(
            "controller `{}` is not available in this build yet; use --controller pd or off",
            other.as_str()
        ))),
    }
}

/// Validate options, open the device and the log, run the loop to its end.
pub fn execute(
    opts: &RunOptions,
    cfg: &Config,
    stop: Arc<AtomicBool>,
) -> Result<RunOutcome, RunError> {
    if !(opts.duration_s.is_finite() && opts.duration_s > 0.0) {
        return Err(RunError::BadInput(format!(
            "--duration {} is out of range: allowed a finite number of seconds > 0",
            opts.duration_s
        )));
    }
    if opts.fast && matches!(opts.device, DeviceSpec::Usb | DeviceSpec::Firewire) {
        return Err(RunError::BadInput(
            "--fast works only with the sim and replay devices: real hardware paces itself".into(),
        ));
    }
    let controller = make_controller(opts.controller, cfg)?;
    let device = open_device(&opts.device, cfg, opts.fast)?;
    let schema = LogSchema {
        model: device.plant_model().is_some(),
    };
    let (tx, rx) = crossbeam_channel::bounded(cfg.telemetry.channel_capacity);
    let writer = spawn_writer(&opts.log, schema, rx).map_err(|source| RunError::Log {
        path: opts.log.display().to_string(),
        source,
    })?;
    let reference = Reference::new(opts.trajectory, &cfg.reference, cfg.sim.seed);
    let max_ticks = (opts.duration_s * cfg.device.rate_hz).round() as u64;
    let servo = Servo::new(
        cfg,
        device,
        controller,
        reference,
        tx,
        stop,
        Some(max_ticks),
        !opts.fast,
    );
    let report = std::thread::Builder::new()
        .name("omnid-servo".into())
        .spawn(move || servo.run())
        .map_err(|e| RunError::Internal(format!("cannot start the servo thread: {e}")))?
        .join()
        .map_err(|_| RunError::Internal("the servo thread panicked".into()))?;
    let written = writer
        .join()
        .map_err(|_| RunError::Internal("the log writer thread panicked".into()))?;

    let stats = &report.stats;
    let summary = RunSummary {
        device: opts.device.name().to_string(),
        controller: opts.controller.as_str().to_string(),
        trajectory: format!("{:?}", opts.trajectory).to_lowercase(),
        ticks: stats.ticks,
        duration_s: stats.first_t.map(|t0| stats.last_t - t0).unwrap_or(0.0),
        tracking_rms_rad: stats.tracking_rms(),
        tracking_max_rad: stats.tracking_max(),
        torque_rms_nm: stats.torque_rms(),
        torque_total_variation_nm: stats.torque_total_variation(),
        identifier: IdentifierSummary {
            nrmse: None,
            nrmse_last_20pct: None,
            nrmse_oracle: stats.oracle_nrmse(),
        },
        timing_us: TimingSummary::from_timing(&report.timing),
        faults: report.faults,
        telemetry_dropped: report.telemetry_dropped,
        end: report.end.as_str().to_string(),
        missed_packets: report.missed_packets,
        clamped_ticks: stats.clamped_ticks,
        log_path: Some(written.path.display().to_string()),
        log_rows: written.rows,
        seed: cfg.sim.seed,
        fast: opts.fast,
    };
    Ok(RunOutcome {
        summary,
        end: report.end,
        log_error: written.error.map(|e| e.to_string()),
        shutdown_error: report.shutdown_error,
    })
}
