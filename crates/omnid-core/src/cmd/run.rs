//! `omnid run`: build the pipeline (device, controller, reference, servo, log writer) from the
//! options, run it on its own thread, and turn the result into the run summary.

pub(crate) use crate::cmd::assembly::{assemble, join_servo};
pub use crate::cmd::assembly::{make_identifier, Pipeline, RunError, RunOptions};
use crate::config::Config;
pub use crate::control::make_controller;
use crate::control::{ControllerKind, Trajectory};
use crate::device::inject::Fault;
pub use crate::device::registry::DeviceSpec;
use crate::omni::kinematics::Geometry;
use crate::servo::summary::{IdentifierState, RunSummary, SummaryLabels};
use crate::servo::{EndReason, ServoReport};
use crate::telemetry::mcap_log::LogFormat;
use crate::telemetry::{
    dump_path, spawn_writer_with, write_dump, writer::recorder, DumpTo, LogError, LogFile, Watch,
    WriterReport,
};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

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
            arm: None,
            arm_configured: false,
        }
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
pub fn check_device_options(opts: &RunOptions, cfg: &Config) -> Result<Vec<Fault>, RunError> {
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

/// Validate options, open the device and the log, run the loop to its end.
pub fn execute(
    opts: &RunOptions,
    cfg: &Config,
    stop: Arc<AtomicBool>,
) -> Result<RunOutcome, RunError> {
    let faults = check_options(opts, cfg)?;
    check_outputs(opts)?;
    let (tx, rx) = crossbeam_channel::bounded(cfg.telemetry.channel_capacity);
    let pipeline = assemble(opts, cfg, &faults, tx, stop.clone())?;
    let log = open_log(opts)?;
    let path = log.path.clone();
    // The operator's stop reaches the writer too: a log whose reader stopped reading cannot
    // hold the run past it.
    let watch = Watch {
        fault: None,
        stop: Some(stop),
    };
    let format = LogFormat::for_path(&path, cfg.geometry);
    let rec = recorder(pipeline.schema, format);
    let writer = spawn_writer_with(log, pipeline.schema, rec, rx, watch)
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
        dump_beside(&written, cfg.geometry)
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

/// The oracle beside an NNIDC run on the simulator: the same reference, device time and
/// configuration under computed torque with the simulator's exact model and its friction
/// (`[control] ct_friction = true`), in a second `--fast` pass with no log (so it costs a
/// fraction of a `--fast` run's time). Its tracking RMS, rad; None for any other run (another
/// controller or device, free mode, injected faults, a simulated payload), or when the pass
/// did not complete.
pub fn oracle_tracking(opts: &RunOptions, cfg: &Config) -> Option<[f64; 3]> {
    let eligible = opts.device == DeviceSpec::Sim
        && opts.controller == ControllerKind::Nnidc
        && !opts.haptics.free
        && opts.inject.is_empty()
        && opts.duration_s.is_finite()
        // A payload makes the plant differ from the model computed torque knows.
        && cfg.sim.payload_kg == 0.0;
    if !eligible {
        return None;
    }
    let mut cfg = cfg.clone();
    // The plant's own friction, when it has one.
    cfg.control.ct_friction = cfg.sim.friction;
    cfg.control.ct_model_scale = 1.0;
    // The oracle's pass leaves the motors' heat as the run left it.
    cfg.safety.persist_heat = false;
    let oracle = RunOptions {
        controller: ControllerKind::Ct,
        fast: true,
        log: None,
        summary_json: None,
        weights: None,
        ..opts.clone()
    };
    let (tx, rx) = crossbeam_channel::bounded(1);
    // No writer: the rows are not wanted (an unpaced loop counts them as dropped and goes on).
    drop(rx);
    let pipeline = assemble(&oracle, &cfg, &[], tx, Arc::new(AtomicBool::new(false))).ok()?;
    let (handle, _ending) = pipeline.spawn().ok()?;
    let (report, _) = join_servo(handle).ok()?;
    if report.end != EndReason::Completed {
        return None;
    }
    report.stats.tracking_rms()
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
            "csv",
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
fn dump_beside(written: &WriterReport, geometry: Geometry) -> (Option<PathBuf>, Option<String>) {
    if !written.file.metadata().is_ok_and(|m| m.is_file()) {
        // Not beside /dev/null or a FIFO: /dev is no place for our files.
        let why = format!(
            "the log {} is not a file, so no dump is written beside it",
            written.path.display()
        );
        return (None, Some(why));
    }
    let path = dump_path(&written.path);
    let format = LogFormat::for_path(&path, geometry);
    match write_dump(DumpTo::File(&path), &written.schema, format, &written.tail) {
        Ok(path) => (Some(path), None),
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
            } else if opts.controller == ControllerKind::Off {
                // No torque follows anything: the reference is not the arm's (a replay of a
                // person's recording, an identification pass).
                "none".into()
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
    if summary.trajectory == "none" {
        summary.tracking_rms_rad = None;
        summary.tracking_max_rad = None;
    }
    summary.estimator_restarts = report.estimator_restarts;
    summary.longest_gap_s = report.longest_gap_s;
    summary
}
