//! `omnid run`: build the pipeline (device, controller, reference, servo, log writer) from the
//! options, run it on its own thread, and turn the result into the run summary.

use crate::config::Config;
pub use crate::control::make_controller;
use crate::control::NanAfter;
use crate::control::{ControllerKind, ControllerSet, Reference, Trajectory};
use crate::device::calibration::{self, CalibrationError};
use crate::device::firewire::{find_firewire, FirewireConfig};
use crate::device::inject::{Fault, FaultyDevice};
use crate::device::replay::{ReplayDevice, ReplayError};
use crate::device::sim::SimOmni;
use crate::device::usb::open_usb_with_rate;
use crate::device::{Device, DeviceError};
use crate::identifier::{Identifier, WeightsFile};
use crate::servo::summary::{IdentifierState, RunSummary, SummaryLabels};
use crate::servo::{EndReason, Servo, ServoReport};
use crate::telemetry::reader::ReadError;
use crate::telemetry::{
    dump_path, spawn_writer, write_dump, LogError, LogFile, LogSchema, WriterReport,
};
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

/// `omnid run`'s options (the rest comes from the config); [`Default`] gives the CLI's
/// defaults.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// The device to run on.
    pub device: DeviceSpec,
    /// The controller.
    pub controller: ControllerKind,
    /// The reference trajectory to track.
    pub trajectory: Trajectory,
    /// Seconds of device time; `f64::INFINITY` (replay only): the whole log.
    pub duration_s: f64,
    /// The log; `None`: a new file `logs/omnid-<UTC time>.csv` (`-2`, `-3`, … when that name
    /// is taken).
    pub log: Option<PathBuf>,
    /// Where the caller will write the summary as JSON: checked with the run's other outputs
    /// before the run starts.
    pub summary_json: Option<PathBuf>,
    /// Run unpaced, as fast as the host allows (simulator and replay only; no realtime steps).
    pub fast: bool,
    /// Replay: skip damaged rows (and report them) instead of refusing the log.
    pub lenient: bool,
    /// Faults to inject (from `--inject`; the config's `[inject]` list is added).
    pub inject: Vec<Fault>,
    /// Start the identifier from these weights (else: shipped weights for NNIDC, fresh
    /// small random weights otherwise).
    pub weights: Option<PathBuf>,
    /// Freeze the identifier (no online adaptation).
    pub no_adapt: bool,
    /// Free mode and a scene of effects (docs/HAPTICS.md).
    pub haptics: crate::haptics::HapticRun,
}

impl Default for RunOptions {
    /// `omnid run` with no flags: NNIDC following the sine on the simulator for 10 s, paced.
    fn default() -> Self {
        RunOptions {
            device: DeviceSpec::Sim,
            controller: ControllerKind::Nnidc,
            trajectory: Trajectory::Sine,
            duration_s: 10.0,
            log: None,
            summary_json: None,
            fast: false,
            lenient: false,
            inject: Vec::new(),
            weights: None,
            no_adapt: false,
            haptics: Default::default(),
        }
    }
}

/// Weights pre-tuned on the simulator, shipped so that `--controller nnidc` works out of the
/// box (see mock/README.md for how they were made).
pub(crate) const SHIPPED_WEIGHTS: &str = include_str!("../mock/nnidc-pretuned.json");
pub(crate) const SHIPPED_WEIGHTS_NAME: &str = "mock/nnidc-pretuned.json";

/// The identifier a run starts with, and a label for the summary.
/// `stop`: the operator's, which ends a wait on a weights file that is a pipe (without it such
/// a file is refused).
pub fn make_identifier(
    cfg: &Config,
    controller: ControllerKind,
    weights: Option<&std::path::Path>,
    no_adapt: bool,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<(Identifier, String), RunError> {
    let mut id_cfg = cfg.identifier.clone();
    if no_adapt {
        id_cfg.adapt = false;
    }
    let bad = |e: &dyn std::fmt::Display| RunError::BadInput(e.to_string());
    match weights {
        Some(path) => match Identifier::from_weights_file(&id_cfg, path, stop) {
            Ok(id) => Ok((id, path.display().to_string())),
            Err(e) if e.is_stopped() => Err(RunError::Stopped(e.to_string())),
            Err(e) => Err(bad(&e)),
        },
        None if controller == ControllerKind::Nnidc => {
            let mut id = Identifier::new(&id_cfg).map_err(|e| bad(&e))?;
            let w = WeightsFile::from_json(SHIPPED_WEIGHTS, SHIPPED_WEIGHTS_NAME)
                .map_err(|e| bad(&e))?;
            id.apply_weights(&w, SHIPPED_WEIGHTS_NAME).map_err(|e| {
                RunError::BadInput(format!(
                    "{e} (the shipped weights fit the default [identifier] sizes; pass --weights \
                     with weights made by `omnid identify` for other sizes)"
                ))
            })?;
            Ok((id, "shipped".to_string()))
        }
        None => Ok((
            Identifier::new(&id_cfg).map_err(|e| bad(&e))?,
            "fresh".to_string(),
        )),
    }
}

/// Problems that stop a run before the loop starts (bad input, no device, no log file).
#[derive(Debug, Error)]
pub enum RunError {
    /// Options or inputs that cannot work together; the message says which.
    #[error("{0}")]
    BadInput(String),
    /// The log cannot be created, or another omnid writes it.
    #[error(transparent)]
    Log(#[from] LogError),
    /// The device cannot be opened.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The log given to `--device replay:PATH` cannot be replayed.
    #[error(transparent)]
    Replay(#[from] ReplayError),
    /// The servo thread could not be started, or it panicked.
    #[error("internal error: {0}")]
    Internal(String),
    /// Ctrl-C or SIGTERM before the loop started (while a log was checked or a file waited on).
    #[error("{0}")]
    Stopped(String),
}

impl RunError {
    /// The operator stopped it (exit code 130, as a run stopped in the loop).
    pub fn is_stopped(&self) -> bool {
        matches!(
            self,
            RunError::Stopped(_) | RunError::Replay(ReplayError::Read(ReadError::Stopped { .. }))
        )
    }
}

/// The outcome of a run that started.
pub struct RunOutcome {
    /// The run summary.
    pub summary: RunSummary,
    /// Why the loop ended.
    pub end: EndReason,
    /// Writing the log failed part-way (the loop was not affected).
    pub log_error: Option<String>,
    /// Sending the final safe packet or closing the device failed.
    pub shutdown_error: Option<String>,
    /// Things the operator should know that did not stop the run (e.g. rows skipped with
    /// `--lenient`).
    pub warnings: Vec<String>,
    /// Where the last ticks before a fault were written.
    pub dump: Option<PathBuf>,
    /// Why the fault dump could not be written.
    pub dump_error: Option<String>,
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

fn open_device(
    opts: &RunOptions,
    cfg: &Config,
    warnings: &mut Vec<String>,
    stop: &Arc<AtomicBool>,
) -> Result<Box<dyn Device>, RunError> {
    match &opts.device {
        DeviceSpec::Sim => Ok(Box::new(SimOmni::new(cfg, !opts.fast))),
        DeviceSpec::Replay(path) => {
            let device = ReplayDevice::open(path, &cfg.device, !opts.fast, opts.lenient, stop)?
                .with_duration_limit(opts.duration_s.is_finite().then_some(opts.duration_s));
            if device.info().skipped.count > 0 {
                warnings.push(format!(
                    "--lenient: {}: {}",
                    path.display(),
                    device.info().skipped
                ));
            }
            Ok(Box::new(device))
        }
        DeviceSpec::Usb => ready_for_torque(open_usb_with_rate(&cfg.usb, cfg.device.rate_hz)?, cfg),
        DeviceSpec::Firewire => {
            // Identify first (reads only), so that a machine without the Omni hears what was
            // looked for; then no torque before the motors' signs are known.
            let mut omni = find_firewire(&cfg.firewire, cfg.device.rate_hz)?;
            if let Some(why) = unmeasured_dac_signs(&cfg.firewire, omni.serial()) {
                return Err(RunError::BadInput(why));
            }
            omni.start()?;
            omni.check_rate()?;
            ready_for_torque(Box::new(omni), cfg)
        }
    }
}

/// Check the options that do not need the device: duration, `--fast`, the simulator's
/// substeps, the faults to inject (the command line's and the config's).
pub(crate) fn check_options(opts: &RunOptions, cfg: &Config) -> Result<Vec<Fault>, RunError> {
    let replay = matches!(opts.device, DeviceSpec::Replay(_));
    if !(opts.duration_s > 0.0 && (opts.duration_s.is_finite() || replay)) {
        return Err(RunError::BadInput(format!(
            "--duration {} is out of range: allowed a finite number of seconds > 0",
            opts.duration_s
        )));
    }
    check_device_options(opts, cfg)
}

/// The checks `run` and `serve` share.
pub(crate) fn check_device_options(
    opts: &RunOptions,
    cfg: &Config,
) -> Result<Vec<Fault>, RunError> {
    if opts.fast && matches!(opts.device, DeviceSpec::Usb | DeviceSpec::Firewire) {
        return Err(RunError::BadInput(
            "--fast works only with the sim and replay devices: real hardware paces itself".into(),
        ));
    }
    if matches!(opts.device, DeviceSpec::Sim) {
        cfg.check_sim()
            .map_err(|e| RunError::BadInput(e.to_string()))?;
    }
    let mut faults = opts.inject.clone();
    faults.extend(
        cfg.inject
            .parsed()
            .map_err(|e| RunError::BadInput(e.to_string()))?,
    );
    if faults.len() > crate::device::inject::MAX_FAULTS {
        return Err(RunError::BadInput(format!(
            "at most {} faults can be injected",
            crate::device::inject::MAX_FAULTS
        )));
    }
    Ok(faults)
}

/// Check every file a run will write before it starts: the log (not in use by another
/// omnid), the fault dump beside it, the summary JSON; and that no two of them, nor the
/// replay input, name the same file (one would destroy the other).
pub(crate) fn check_outputs(opts: &RunOptions) -> Result<(), RunError> {
    // Each file as the user named it, and its path.
    let mut named: Vec<(String, PathBuf)> = Vec::new();
    if let DeviceSpec::Replay(input) = &opts.device {
        named.push((
            format!("--device replay:{}", input.display()),
            input.clone(),
        ));
    }
    if let Some(log) = &opts.log {
        LogFile::check(log)?;
        named.push((format!("--log {}", log.display()), log.clone()));
        // A log that is a device (/dev/null) gets no dump beside it (see `execute`).
        if std::fs::metadata(log).map_or(true, |m| m.is_file()) {
            let dump = dump_path(log);
            crate::output::check_file(&dump).map_err(|e| {
                RunError::BadInput(format!("the fault dump of --log (written on a fault): {e}"))
            })?;
            named.push((
                format!("the fault dump of --log ({})", dump.display()),
                dump,
            ));
        }
    }
    if let Some(json) = &opts.summary_json {
        crate::output::check_file(json)
            .map_err(|e| RunError::BadInput(format!("--summary-json: {e}")))?;
        named.push((format!("--summary-json {}", json.display()), json.clone()));
    }
    for (i, (a, pa)) in named.iter().enumerate() {
        for (b, pb) in &named[i + 1..] {
            if crate::output::same_file(pa, pb) {
                return Err(RunError::BadInput(format!(
                    "{a} and {b} are the same file: a run's inputs and outputs must be \
                     distinct files"
                )));
            }
        }
    }
    Ok(())
}

/// A servo loop ready to start: the device open, the controllers and the identifier built,
/// the motors' heat loaded. `run` and `serve` both assemble it here.
pub struct Pipeline {
    /// The loop, ready to run.
    pub servo: Servo,
    /// The log columns this device feeds.
    pub(crate) schema: LogSchema,
    /// Where the identifier's weights came from (`shipped`, `fresh` or a path).
    pub(crate) weights_label: String,
    /// The identifier as it started (its shape; `serve` copies live weights into clones).
    pub(crate) identifier: Identifier,
    /// Where motor heat is carried over between runs (none for replays).
    pub(crate) heat_path: Option<PathBuf>,
    /// Things the operator should know that do not stop the run.
    pub(crate) warnings: Vec<String>,
    /// Realtime steps to take on the servo thread (paced runs only).
    pub(crate) realtime: Option<crate::servo::realtime::RealtimeConfig>,
    /// Which realtime steps took effect, once the servo thread has taken them (before its
    /// first tick): for a daemon's status while it runs.
    pub(crate) realtime_taken: Arc<std::sync::OnceLock<crate::servo::realtime::RealtimeReport>>,
}

/// Build the pipeline for `opts` with `faults` (from [`check_options`]); telemetry leaves
/// through `telemetry`, `stop` ends the loop.
pub(crate) fn assemble(
    opts: &RunOptions,
    cfg: &Config,
    faults: &[Fault],
    telemetry: crossbeam_channel::Sender<crate::telemetry::record::TickRecord>,
    stop: Arc<AtomicBool>,
) -> Result<Pipeline, RunError> {
    let replay = matches!(opts.device, DeviceSpec::Replay(_));
    let (controllers, identifier, weights_label) = laws(opts, cfg, faults, &stop)?;
    let mut warnings = Vec::new();
    let mut device = open_device(opts, cfg, &mut warnings, &stop)?;
    if !faults.is_empty() {
        device = Box::new(FaultyDevice::new(
            device,
            faults,
            cfg.sim.seed,
            stop.clone(),
        ));
    }
    let schema = LogSchema {
        model: device.plant_model().is_some(),
    };
    let reference = Reference::new(opts.trajectory, &cfg.reference, cfg.sim.seed);
    // A replay limits itself in device time (its rows need not come at rate_hz).
    let max_ticks = (!replay && opts.duration_s.is_finite())
        .then(|| (opts.duration_s * cfg.device.rate_hz).round() as u64);
    // A replay drives no motors: it neither inherits nor leaves heat (and stays reproducible).
    let heat_path = (cfg.safety.persist_heat && !replay)
        .then(crate::servo::thermal_store::state_dir)
        .flatten()
        .map(|d| crate::servo::thermal_store::heat_file(&d, opts.device.name()));
    let mut servo = Servo::new(
        cfg,
        device,
        controllers,
        reference,
        telemetry,
        stop,
        max_ticks,
        !opts.fast,
    );
    servo.set_identifier(identifier.clone());
    if opts.haptics.free {
        servo.start_free();
    }
    servo.set_effects(&opts.haptics.effects);
    if let Some(path) = &heat_path {
        servo.set_initial_heat(load_heat(path, cfg));
    }
    Ok(Pipeline {
        servo,
        schema,
        weights_label,
        identifier,
        heat_path,
        warnings,
        // Realtime steps only make sense when the loop is paced.
        realtime: (!opts.fast).then(|| cfg.realtime.clone()),
        realtime_taken: Arc::default(),
    })
}

/// The control laws and the identifier for `opts` (an injected NaN fault wraps the active
/// law), and the label of the weights the identifier starts from.
fn laws(
    opts: &RunOptions,
    cfg: &Config,
    faults: &[Fault],
    stop: &Arc<AtomicBool>,
) -> Result<(ControllerSet, Identifier, String), RunError> {
    let mut controllers = ControllerSet::new(cfg, opts.controller, cfg.serve.switch_fade_s);
    let (identifier, weights_label) = make_identifier(
        cfg,
        opts.controller,
        opts.weights.as_deref(),
        opts.no_adapt,
        Some(stop),
    )?;
    if weights_label == "shipped" {
        crate::errln!(
            "omnid: nnidc starts from the weights shipped in {SHIPPED_WEIGHTS_NAME} (pre-tuned on \
             the simulator); pass --weights FILE for your own (`omnid identify`)"
        );
    }
    if let Some(at_s) = faults.iter().find_map(|f| match f {
        Fault::Nan { at_s } => Some(*at_s),
        _ => None,
    }) {
        let inner = controllers.take(opts.controller);
        controllers.replace(opts.controller, Box::new(NanAfter { inner, at_s }));
    }
    Ok((controllers, identifier, weights_label))
}

/// The motors' heat left by the last run on this device (cold, with a warning, if it cannot
/// be read).
fn load_heat(path: &std::path::Path, cfg: &Config) -> [f64; 3] {
    let (heat, note) = crate::servo::thermal_store::load(path, &cfg.safety);
    if let Some(note) = note {
        crate::errln!("omnid: warning: {note}; starting with cold motors");
    }
    heat
}

/// The servo thread's result: the loop's report and which realtime steps took effect.
pub(crate) type ServoThreadResult = (ServoReport, Option<crate::servo::realtime::RealtimeReport>);

impl Pipeline {
    /// Start the loop on its own thread (realtime steps taken there, before the first tick).
    /// Returns what the caller keeps: the thread and the bookkeeping for the end.
    pub(crate) fn spawn(
        self,
    ) -> Result<(std::thread::JoinHandle<ServoThreadResult>, Ending), RunError> {
        let Pipeline {
            mut servo,
            schema,
            weights_label,
            identifier: _,
            heat_path,
            warnings,
            realtime,
            realtime_taken,
        } = self;
        let handle = std::thread::Builder::new()
            .name("omnid-servo".into())
            .stack_size(2 << 20)
            .spawn(move || {
                let realtime = realtime.as_ref().map(crate::servo::realtime::apply);
                // Before the first tick: one line per step that was not permitted.
                for w in realtime.iter().flat_map(|r| &r.warnings) {
                    crate::errln!("omnid: warning: {w}");
                }
                if let Some(r) = &realtime {
                    let _ = realtime_taken.set(r.clone());
                }
                let end = loop {
                    if let Some(end) = servo.tick() {
                        break end;
                    }
                };
                (servo.finish(end), realtime)
            })
            .map_err(|e| RunError::Internal(format!("cannot start the servo thread: {e}")))?;
        Ok((
            handle,
            Ending {
                schema,
                weights_label,
                heat_path,
                warnings,
            },
        ))
    }
}

/// What is needed once the loop has ended.
pub(crate) struct Ending {
    pub schema: LogSchema,
    pub weights_label: String,
    pub heat_path: Option<PathBuf>,
    pub warnings: Vec<String>,
}

impl Ending {
    /// Keep the motors' heat for the next run and warn about motors that ran hot.
    pub(crate) fn save_heat(&self, report: &ServoReport) {
        if let Some(path) = &self.heat_path {
            if let Err(e) = crate::servo::thermal_store::save(path, report.heat) {
                crate::errln!("omnid: warning: motor heat not saved: {e}");
            }
        }
        for (j, warned) in report.thermal_warned.iter().enumerate() {
            if *warned {
                crate::errln!(
                    "omnid: warning: motor {} reached its thermal warning level (heat {:.2})",
                    j + 1,
                    report.heat[j]
                );
            }
        }
    }
}

/// Injected faults scheduled after the run's end: reported, not silently dropped.
fn unreached_faults(faults: &[Fault], reached_s: f64) -> Vec<String> {
    faults
        .iter()
        .filter_map(|f| {
            // As the user wrote it (`--inject` syntax).
            let (at, spec) = match *f {
                Fault::Disconnect { at_s } => (at_s, format!("disconnect@{at_s}")),
                Fault::Nan { at_s } => (at_s, format!("nan@{at_s}")),
                Fault::Stall { at_s, ms } => (at_s, format!("stall@{at_s}:{ms}")),
                Fault::EncoderJump { at_s, counts } => {
                    (at_s, format!("encoder-jump@{at_s}:{counts}"))
                }
                Fault::Slow { at_s, ms } => (at_s, format!("slow@{at_s}:{ms}")),
                Fault::Corrupt { .. } => return None,
            };
            (at > reached_s).then(|| {
                format!(
                    "injected fault {spec} was scheduled at {at} s but the run ended at \
                     {reached_s:.3} s: it never acted"
                )
            })
        })
        .collect()
}

/// Join the servo thread.
pub(crate) fn join_servo(
    handle: std::thread::JoinHandle<ServoThreadResult>,
) -> Result<ServoThreadResult, RunError> {
    handle
        .join()
        .map_err(|_| RunError::Internal("the servo thread panicked".into()))
}

/// Validate options, open the device and the log, run the loop to its end.
pub fn execute(
    opts: &RunOptions,
    cfg: &Config,
    stop: Arc<AtomicBool>,
) -> Result<RunOutcome, RunError> {
    let faults = check_options(opts, cfg)?;
    check_outputs(opts)?;
    let (tx, rx) = crossbeam_channel::bounded(cfg.telemetry.channel_capacity);
    let pipeline = assemble(opts, cfg, &faults, tx, stop)?;
    let log = open_log(opts)?;
    let path = log.path.clone();
    let writer = spawn_writer(log, pipeline.schema, rx)
        .map_err(|source| RunError::Log(LogError::Io { path, source }))?;
    let (handle, ending) = pipeline.spawn()?;
    let (report, realtime) = join_servo(handle)?;
    let written = writer
        .join()
        .map_err(|_| RunError::Internal("the log writer thread panicked".into()))?;
    ending.save_heat(&report);

    let is_fault = matches!(
        report.end,
        EndReason::DeviceFault(_) | EndReason::SafetyFault(_)
    );
    let (dump, dump_error) = if is_fault {
        dump_beside(&written)
    } else {
        (None, None)
    };
    let log_incomplete = log_shortfall(&written, report.telemetry_dropped);
    let log_error = written.error.as_ref().map(|e| e.to_string());
    let mut summary = summarise(opts, cfg, &report, ending.weights_label.clone());
    let mut warnings = ending.warnings;
    warnings.extend(unreached_faults(&faults, summary.duration_s));
    summary.warnings = warnings.clone();
    summary.log_path = Some(written.path.display().to_string());
    summary.log_rows = written.rows;
    summary.log_complete = Some(log_incomplete.is_none());
    summary.log_error = log_incomplete;
    summary.realtime = realtime;
    Ok(RunOutcome {
        summary,
        end: report.end,
        log_error,
        shutdown_error: report.shutdown_error,
        warnings,
        dump,
        dump_error,
    })
}

/// The log file: `--log`, else a new time-stamped file under `logs/`.
fn open_log(opts: &RunOptions) -> Result<LogFile, RunError> {
    Ok(match &opts.log {
        Some(path) => LogFile::create(path)?,
        None => LogFile::create_unique(
            Path::new("logs"),
            &format!(
                "omnid-{}",
                crate::telemetry::utc_stamp(std::time::SystemTime::now())
            ),
        )?,
    })
}

/// Rows lost on the way to the file: a failed write (disk full), or dropped by a paced loop
/// whose writer fell behind.
fn log_shortfall(written: &WriterReport, dropped: u64) -> Option<String> {
    match &written.error {
        Some(e) => Some(format!(
            "{} of {} rows did not reach the file: {e}",
            written.received - written.rows,
            written.received
        )),
        None if dropped > 0 => Some(format!("{dropped} rows dropped (the writer fell behind)")),
        None => None,
    }
}

/// After a fault: the last ticks written beside the log (the dump's path, or why not).
fn dump_beside(written: &WriterReport) -> (Option<PathBuf>, Option<String>) {
    if !written.file.metadata().is_ok_and(|m| m.is_file()) {
        // Not beside /dev/null or a FIFO: /dev is no place for our files.
        let why = format!(
            "the log {} is not a file, so no dump is written beside it",
            written.path.display()
        );
        return (None, Some(why));
    }
    let path = dump_path(&written.path);
    match write_dump(&path, &written.schema, &written.tail) {
        Ok(()) => (Some(path), None),
        Err(e) => (None, Some(e.to_string())),
    }
}

/// The run's summary from what the loop reported (the log's fields are filled in after).
fn summarise(opts: &RunOptions, cfg: &Config, report: &ServoReport, weights: String) -> RunSummary {
    let mut summary = RunSummary::from_results(
        &SummaryLabels {
            device: opts.device.name(),
            controller: opts.controller.as_str(),
            trajectory: if opts.haptics.free {
                "free".into()
            } else {
                format!("{:?}", opts.trajectory).to_lowercase()
            },
            weights,
            seed: cfg.sim.seed,
            fast: opts.fast,
        },
        &report.stats,
        &report.timing,
        IdentifierState {
            adapt: cfg.identifier.adapt && !opts.no_adapt,
            fault: report.identifier.as_ref().and_then(|id| id.fault()),
        },
        report.telemetry_dropped,
        report.missed_packets,
    );
    summary.faults = report.faults.clone();
    summary.end = report.end.as_str().to_string();
    summary.estimator_restarts = report.estimator_restarts;
    summary.longest_gap_s = report.longest_gap_s;
    summary
}
