//! `omnid run`: the servo loop on a device for a fixed time, its log and summary.

use crate::{
    load_config, stop_on_signal, EXIT_BAD_INPUT, EXIT_DEVICE_FAULT, EXIT_INTERNAL,
    EXIT_OPERATOR_STOP, EXIT_SAFETY_FAULT,
};
use omnid::cmd::run::{execute, oracle_tracking, DeviceSpec, RunError, RunOptions};
use omnid::control::{ControllerKind, Trajectory};
use omnid::device::inject::Fault;
use omnid::servo::EndReason;
use std::path::PathBuf;

#[derive(clap::Args)]
pub(crate) struct RunArgs {
    /// sim | replay:PATH | usb | firewire [default: sim, or the --arm's device]
    #[arg(long)]
    device: Option<DeviceSpec>,
    /// A configured arm (`[[arm]]` in --config): its device, serial and sections; its lock is
    /// taken, so a run cannot take an arm a daemon serves.
    #[arg(long, value_name = "NAME")]
    arm: Option<String>,
    /// Control law.
    #[arg(long, value_enum, default_value = "nnidc")]
    controller: ControllerKind,
    /// Reference trajectory.
    #[arg(long, value_enum, default_value = "sine")]
    trajectory: Trajectory,
    /// Run length, seconds of device time [default: 10; replay: the whole log].
    #[arg(long)]
    duration: Option<f64>,
    /// Log path: CSV, or MCAP when it ends in .mcap (default: logs/omnid-<UTC time>.csv).
    #[arg(long)]
    log: Option<PathBuf>,
    /// Write the run summary as JSON here.
    #[arg(long)]
    summary_json: Option<PathBuf>,
    /// TOML configuration file (see `omnid config --print-default`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// No pacing: run as fast as the CPU allows, same results (sim and replay only).
    #[arg(long)]
    fast: bool,
    /// Inject a fault (repeatable): disconnect@T, stall@T:MS, corrupt:P,
    /// encoder-jump@T:COUNTS, nan@T, slow@T:MS (T in s of device time).
    #[arg(long, value_name = "SPEC")]
    inject: Vec<Fault>,
    /// Replay: skip damaged rows of the log (reported) instead of refusing it.
    #[arg(long)]
    lenient: bool,
    /// Start the identifier from these weights (from `omnid identify`).
    #[arg(long, value_name = "WEIGHTS.json")]
    weights: Option<PathBuf>,
    /// Freeze the identifier: no online adaptation.
    #[arg(long)]
    no_adapt: bool,
    /// track: follow --trajectory; free: only the controller's compensation and the
    /// scene's effects, the arm moved by a hand (docs/HAPTICS.md).
    #[arg(long, value_enum, default_value = "track")]
    mode: RunMode,
    /// Haptic effects in TOML, one [[effect]] table each (rendered in free mode).
    #[arg(long, value_name = "FILE")]
    scene: Option<PathBuf>,
    /// Simulator: a simulated hand on the stylus: none, hold, path, push+x .. push-z
    /// ([haptics.hand] sets its grip).
    #[arg(long, value_name = "PATTERN")]
    hand: Option<String>,
}

/// What `omnid run` does with the arm.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub(crate) enum RunMode {
    Track,
    Free,
}

/// `--mode`, `--scene` and `--hand`: the haptic part of a run (the hand goes into the
/// simulator's config).
pub(crate) fn haptic_options(
    args: &RunArgs,
    cfg: &mut omnid::config::Config,
    stop: &std::sync::Arc<std::sync::atomic::AtomicBool>,
) -> Result<omnid::haptics::HapticRun, String> {
    if let Some(name) = &args.hand {
        if args.device.as_ref().is_some_and(|d| *d != DeviceSpec::Sim) {
            return Err("--hand needs the simulator (--device sim)".into());
        }
        cfg.haptics.hand.pattern = omnid::haptics::HandPattern::try_from(name.clone())
            .map_err(|e| format!("--hand: {e}"))?;
    }
    let effects = match &args.scene {
        Some(path) => omnid::haptics::scene::read_scene(path, Some(stop))?,
        None => Vec::new(),
    };
    if !effects.is_empty() && args.mode != RunMode::Free {
        return Err("--scene: effects are rendered in free mode; add --mode free".into());
    }
    Ok(omnid::haptics::HapticRun {
        free: args.mode == RunMode::Free,
        effects,
    })
}

pub(crate) fn run(args: RunArgs) -> Result<u8, anyhow::Error> {
    let stop = stop_on_signal()?;
    let mut cfg = match load_config(args.config.as_deref(), Some(&stop)) {
        Ok(cfg) => cfg,
        Err(code) => return Ok(code),
    };
    // `--arm NAME`: that arm's device and whole configuration.
    let mut device = args.device.clone().unwrap_or(DeviceSpec::Sim);
    if let Some(name) = &args.arm {
        match cfg.arm_named(name) {
            Ok(arm) => {
                if args.device.as_ref().is_some_and(|d| *d != arm.device) {
                    omnid::errln!(
                        "omnid: --device {} and --arm {name} (device {}) disagree; give one",
                        args.device.as_ref().map_or("", |d| d.name()),
                        arm.device.name()
                    );
                    return Ok(EXIT_BAD_INPUT);
                }
                device = arm.device;
                cfg = arm.config;
            }
            Err(e) => {
                omnid::errln!("omnid: --arm: {e}");
                return Ok(EXIT_BAD_INPUT);
            }
        }
    }
    let replay = matches!(device, DeviceSpec::Replay(_));
    let haptics = match haptic_options(&args, &mut cfg, &stop) {
        Ok(h) => h,
        Err(e) => {
            omnid::errln!("omnid: {e}");
            return Ok(EXIT_BAD_INPUT);
        }
    };
    let opts = RunOptions {
        arm_configured: args.arm.is_some(),
        arm: args.arm.clone(),
        device,
        controller: args.controller,
        trajectory: args.trajectory,
        duration_s: args
            .duration
            .unwrap_or(if replay { f64::INFINITY } else { 10.0 }),
        log: args.log,
        summary_json: args.summary_json.clone(),
        fast: args.fast,
        lenient: args.lenient,
        inject: args.inject,
        weights: args.weights,
        no_adapt: args.no_adapt,
        haptics,
    };
    let mut outcome = match execute(&opts, &cfg, stop) {
        Ok(o) => o,
        Err(e) => return run_failed(e),
    };
    // Beside a completed NNIDC run on the simulator: the oracle's tracking, for the ratio.
    if outcome.end == EndReason::Completed && outcome.summary.tracking_rms_rad.is_some() {
        outcome.summary.oracle_tracking_rms_rad = oracle_tracking(&opts, &cfg);
    }
    omnid::out!("{}", outcome.summary.human());
    for w in &outcome.warnings {
        omnid::errln!("omnid: warning: {w}");
    }
    // Checked before the run; only a failing disk can stop it now.
    let mut json_error = None;
    if let Some(path) = &args.summary_json {
        let json = serde_json::to_string_pretty(&outcome.summary)?;
        json_error = omnid::output::write_bytes(path, (json + "\n").as_bytes()).err();
    }
    Ok(report_ending(&outcome, json_error))
}

/// The exit code of a run that could not start or ended in error, its message printed.
pub(crate) fn run_failed(e: RunError) -> Result<u8, anyhow::Error> {
    let code = match &e {
        e if e.is_stopped() => {
            omnid::errln!("omnid: {e}; nothing ran");
            return Ok(EXIT_OPERATOR_STOP);
        }
        RunError::BadInput(_) | RunError::Replay(_) | RunError::Log(_) => EXIT_BAD_INPUT,
        RunError::Device(_) => EXIT_DEVICE_FAULT,
        _ => return Err(e.into()),
    };
    omnid::errln!("omnid: {e}");
    Ok(code)
}

/// How the run ended, said on stderr (fault, dump, incomplete log or summary, dropped rows),
/// and the exit code it gives.
pub(crate) fn report_ending(
    outcome: &omnid::cmd::run::RunOutcome,
    json_error: Option<omnid::output::OutputError>,
) -> u8 {
    let stopped = if outcome.shutdown_error.is_none() {
        "zero torque sent, amplifiers off"
    } else {
        "the final zero-torque packet could not be delivered: switch the device off (whether it drops its amplifiers when packets stop is not known, docs/FIREWIRE.md §9)"
    };
    let mut code = match &outcome.end {
        EndReason::Completed | EndReason::EndOfData => 0,
        EndReason::OperatorStop => {
            omnid::errln!("omnid: stopped by the operator; {stopped}");
            EXIT_OPERATOR_STOP
        }
        EndReason::DeviceFault(m) => {
            omnid::errln!("omnid: device fault: {m}; {stopped}");
            EXIT_DEVICE_FAULT
        }
        EndReason::SafetyFault(m) => {
            omnid::errln!("omnid: safety fault: {m}; {stopped}");
            EXIT_SAFETY_FAULT
        }
    };
    if let Some(dump) = &outcome.dump {
        omnid::errln!(
            "omnid: the last ticks before the fault are in {}",
            dump.display()
        );
    }
    if let Some(e) = &outcome.dump_error {
        omnid::errln!("omnid: no fault dump: {e}");
    }
    if let Some(e) = &outcome.shutdown_error {
        omnid::errln!("omnid: warning: {e}");
        if code == 0 {
            code = EXIT_DEVICE_FAULT;
        }
    }
    if let Some(e) = &outcome.log_error {
        omnid::errln!(
            "omnid: writing the log failed part-way: {e}; the log is incomplete ({} rows in it)",
            outcome.summary.log_rows
        );
        if code == 0 {
            code = EXIT_INTERNAL;
        }
    }
    if let Some(e) = &json_error {
        omnid::errln!("omnid: --summary-json: {e}");
        if code == 0 {
            code = EXIT_INTERNAL;
        }
    }
    if outcome.summary.telemetry_dropped > 0 {
        omnid::errln!(
            "omnid: warning: {} log rows dropped (the writer fell behind)",
            outcome.summary.telemetry_dropped
        );
    }
    code
}
