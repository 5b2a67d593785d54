//! The `omnid` command line: parse, build the pipeline, run, print. Exit codes: 0 success,
//! 1 internal or log error, 2 bad input, 3 device fault, 4 safety fault, 130 operator stop.

use anyhow::Context;
use clap::{Parser, Subcommand};
use omnid::config::Config;
use omnid::control::{ControllerKind, Trajectory};
use omnid::device::inject::Fault;
use omnid::run::{execute, DeviceSpec, RunError, RunOptions};
use omnid::servo::EndReason;
use omnid::telemetry::convert::{convert, ConvertError, SourceFormat};
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

const EXIT_INTERNAL: u8 = 1;
const EXIT_BAD_INPUT: u8 = 2;
const EXIT_DEVICE_FAULT: u8 = 3;
const EXIT_SAFETY_FAULT: u8 = 4;
const EXIT_OPERATOR_STOP: u8 = 130;

#[derive(Parser)]
#[command(
    name = "omnid",
    version,
    about = "Hardware I/O daemon for the Phantom Omni haptic device"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the 1 kHz servo loop on a device and log every tick.
    Run(RunArgs),
    /// Convert a recording into a replayable log (for `--device replay:OUT`).
    Convert(ConvertArgs),
    /// Pre-tune the identifier's networks on recorded logs and save the weights.
    Identify(IdentifyArgs),
    /// List candidate devices (USB bridges, FireWire Omnis) with permission problems and fixes.
    Devices {
        /// TOML configuration file (its [usb] ids are the ones searched for).
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// Figures (PNG and SVG) from a log: angles, torque vs. the identifier's estimate,
    /// identification and tracking errors, control effort.
    Plot {
        /// The CSV log (at least `t`; figures whose columns are missing are skipped).
        log: PathBuf,
        /// Directory for the figures (created if needed).
        #[arg(long)]
        out: PathBuf,
    },
    /// Reproduce the paper's experiments on the simulator (`validation`, `alpha`, `payload`):
    /// runs, `DIR/report.md` with the tables, and the figures.
    Experiment {
        /// validation, alpha or payload.
        kind: omnid::experiment::Experiment,
        /// Directory for the report, logs and figures (created if needed).
        #[arg(long)]
        out: PathBuf,
        /// Shortened runs and pre-tuning (seconds, not minutes; not the paper's numbers).
        #[arg(long)]
        quick: bool,
    },
    /// Configuration helpers.
    Config {
        /// Print the full default configuration, commented.
        #[arg(long)]
        print_default: bool,
    },
}

#[derive(clap::Args)]
struct IdentifyArgs {
    /// Logs to learn from (omnid logs, or any CSV with t, q1..3, tau1..3).
    #[arg(required = true)]
    logs: Vec<PathBuf>,
    /// Where to write the weights (JSON).
    #[arg(long)]
    out: PathBuf,
    /// Passes over the data.
    #[arg(long, default_value_t = 20)]
    epochs: usize,
    /// TOML configuration file (its [identifier] and [kalman] sections apply).
    #[arg(long)]
    config: Option<PathBuf>,
}

fn identify_cmd(args: IdentifyArgs) -> Result<u8, anyhow::Error> {
    let Some(cfg) = load_config(args.config.as_deref()) else {
        return Ok(EXIT_BAD_INPUT);
    };
    let pretune_cfg = omnid::ident::PretuneConfig {
        epochs: args.epochs,
        ..Default::default()
    };
    let bar = omnid::progress::bar(args.epochs as u64, "identify");
    let result = omnid::identify::identify(
        &args.logs,
        &args.out,
        &cfg,
        &pretune_cfg,
        |p| match p {
            omnid::ident::Progress::Batch { .. } => {}
            omnid::ident::Progress::Epoch(r) => {
                bar.inc(1);
                bar.suspend(|| eprintln!(
                    "epoch {:>3}/{}: train NRMSE {:.3} / {:.3} / {:.3}   validation {:.3} / {:.3} / {:.3}",
                    r.epoch,
                    r.epochs,
                    r.train_nrmse[0],
                    r.train_nrmse[1],
                    r.train_nrmse[2],
                    r.val_nrmse[0],
                    r.val_nrmse[1],
                    r.val_nrmse[2]
                ));
            }
        },
    );
    bar.finish_and_clear();
    match result {
        Ok(report) => {
            let best = &report.epochs[report.kept_epoch - 1];
            println!(
                "identify: {} training and {} validation samples; kept epoch {}: training NRMSE {:.3} / {:.3} / {:.3}, validation NRMSE {:.3} / {:.3} / {:.3}; weights in {}",
                report.train_samples,
                report.val_samples,
                report.kept_epoch,
                best.train_nrmse[0],
                best.train_nrmse[1],
                best.train_nrmse[2],
                best.val_nrmse[0],
                best.val_nrmse[1],
                best.val_nrmse[2],
                args.out.display()
            );
            Ok(0)
        }
        Err(e) => {
            eprintln!("omnid identify: {e}");
            Ok(EXIT_BAD_INPUT)
        }
    }
}

#[derive(clap::Args)]
struct RunArgs {
    /// sim | replay:PATH | usb | firewire
    #[arg(long, default_value = "sim")]
    device: DeviceSpec,
    /// Control law.
    #[arg(long, value_enum, default_value = "nnidc")]
    controller: ControllerKind,
    /// Reference trajectory.
    #[arg(long, value_enum, default_value = "sine")]
    trajectory: Trajectory,
    /// Run length, seconds of device time [default: 10; replay: the whole log].
    #[arg(long)]
    duration: Option<f64>,
    /// CSV log path (default: logs/omnid-<UTC time>.csv).
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
}

#[derive(clap::Args)]
struct ConvertArgs {
    /// Format of the input.
    #[arg(long, value_enum)]
    from: SourceFormat,
    /// The recording to convert (CSV).
    input: PathBuf,
    /// Where to write the replayable log (CSV).
    #[arg(long)]
    out: PathBuf,
    /// Skip damaged rows (reported) instead of refusing the file.
    #[arg(long)]
    lenient: bool,
}

fn convert_cmd(args: ConvertArgs) -> Result<u8, anyhow::Error> {
    match convert(args.from, &args.input, &args.out, args.lenient) {
        Ok(report) => {
            println!(
                "omnid convert: {} rows from {} to {} (columns: {})",
                report.rows,
                args.input.display(),
                args.out.display(),
                report.columns.join(",")
            );
            if report.skipped.count > 0 {
                eprintln!("omnid: warning: --lenient: {}", report.skipped);
            }
            Ok(0)
        }
        Err(e @ ConvertError::Write { .. }) => {
            eprintln!("omnid: {e}");
            Ok(EXIT_INTERNAL)
        }
        Err(e) => {
            eprintln!("omnid: {e}");
            Ok(EXIT_BAD_INPUT)
        }
    }
}

/// `logs/omnid-YYYYMMDD-HHMMSS.csv` in UTC.
fn default_log_path() -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    PathBuf::from(format!(
        "logs/omnid-{year:04}{month:02}{day:02}-{:02}{:02}{:02}.csv",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    ))
}

fn run(args: RunArgs) -> Result<u8, anyhow::Error> {
    let Some(cfg) = load_config(args.config.as_deref()) else {
        return Ok(EXIT_BAD_INPUT);
    };
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        // With the `termination` feature this also catches SIGTERM (and SIGHUP).
        ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst))
            .context("installing the Ctrl-C/SIGTERM handler")?;
    }
    let replay = matches!(args.device, DeviceSpec::Replay(_));
    let opts = RunOptions {
        device: args.device,
        controller: args.controller,
        trajectory: args.trajectory,
        duration_s: args
            .duration
            .unwrap_or(if replay { f64::INFINITY } else { 10.0 }),
        log: args.log.unwrap_or_else(default_log_path),
        fast: args.fast,
        lenient: args.lenient,
        inject: args.inject,
        weights: args.weights,
        no_adapt: args.no_adapt,
    };
    let outcome = match execute(&opts, &cfg, stop) {
        Ok(o) => o,
        Err(e @ RunError::BadInput(_)) | Err(e @ RunError::Replay(_)) => {
            eprintln!("omnid: {e}");
            return Ok(EXIT_BAD_INPUT);
        }
        Err(e @ RunError::Device(_)) => {
            eprintln!("omnid: {e}");
            return Ok(EXIT_DEVICE_FAULT);
        }
        Err(e @ RunError::Log { .. }) => {
            eprintln!("omnid: {e}");
            return Ok(EXIT_BAD_INPUT);
        }
        Err(e) => return Err(e.into()),
    };
    print!("{}", outcome.summary.human());
    for w in &outcome.warnings {
        eprintln!("omnid: warning: {w}");
    }
    if let Some(path) = &args.summary_json {
        let json = serde_json::to_string_pretty(&outcome.summary)?;
        std::fs::write(path, json + "\n")
            .with_context(|| format!("writing the summary to {}", path.display()))?;
    }
    let stopped = if outcome.shutdown_error.is_none() {
        "zero torque sent, amplifiers off"
    } else {
        "the final zero-torque packet could not be delivered; the device's own watchdog turns its amplifiers off when packets stop"
    };
    let mut code = match &outcome.end {
        EndReason::Completed | EndReason::EndOfData => 0,
        EndReason::OperatorStop => {
            eprintln!("omnid: stopped by the operator; {stopped}");
            EXIT_OPERATOR_STOP
        }
        EndReason::DeviceFault(m) => {
            eprintln!("omnid: device fault: {m}; {stopped}");
            EXIT_DEVICE_FAULT
        }
        EndReason::SafetyFault(m) => {
            eprintln!("omnid: safety fault: {m}; {stopped}");
            EXIT_SAFETY_FAULT
        }
    };
    if let Some(dump) = &outcome.dump {
        eprintln!(
            "omnid: the last ticks before the fault are in {}",
            dump.display()
        );
    }
    if let Some(e) = &outcome.shutdown_error {
        eprintln!("omnid: warning: {e}");
        if code == 0 {
            code = EXIT_DEVICE_FAULT;
        }
    }
    if let Some(e) = &outcome.log_error {
        eprintln!("omnid: writing the log failed part-way: {e}");
        if code == 0 {
            code = EXIT_INTERNAL;
        }
    }
    if outcome.summary.telemetry_dropped > 0 {
        eprintln!(
            "omnid: warning: {} log rows dropped (the writer fell behind)",
            outcome.summary.telemetry_dropped
        );
    }
    Ok(code)
}

/// The config file, or the defaults; `None` after printing why a file was refused.
fn load_config(path: Option<&std::path::Path>) -> Option<Config> {
    match path.map(Config::load) {
        None => Some(Config::default()),
        Some(Ok(c)) => Some(c),
        Some(Err(e)) => {
            eprintln!("omnid: {e}");
            None
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Run(args) => run(args),
        Command::Convert(args) => convert_cmd(args),
        Command::Identify(args) => identify_cmd(args),
        Command::Devices { config } => match load_config(config.as_deref()) {
            Some(cfg) => {
                print!("{}", omnid::device::discovery::list_devices(&cfg.usb));
                Ok(0)
            }
            None => Ok(EXIT_BAD_INPUT),
        },
        Command::Plot { log, out } => match omnid::plot::plot_log(&log, &out) {
            Ok(report) => {
                print!("{report}");
                Ok(0)
            }
            Err(e) => {
                eprintln!("omnid plot: {e}");
                Ok(if e.is_bad_input() {
                    EXIT_BAD_INPUT
                } else {
                    EXIT_INTERNAL
                })
            }
        },
        Command::Experiment { kind, out, quick } => {
            match omnid::experiment::run_experiment(kind, &out, quick) {
                Ok(report) => {
                    println!(
                        "omnid experiment {}: report in {} ({} figure files)",
                        kind.as_str(),
                        report.report.display(),
                        report.figures.len()
                    );
                    Ok(0)
                }
                Err(e) => {
                    eprintln!("omnid experiment {}: {e}", kind.as_str());
                    Ok(if e.is_bad_input() {
                        EXIT_BAD_INPUT
                    } else {
                        EXIT_INTERNAL
                    })
                }
            }
        }
        Command::Config { print_default } => {
            if print_default {
                print!("{}", Config::default_toml());
                Ok(0)
            } else {
                eprintln!("omnid config: nothing to do; try --print-default");
                Ok(EXIT_BAD_INPUT)
            }
        }
    };
    match result {
        Ok(code) => ExitCode::from(code),
        Err(e) => {
            eprintln!("omnid: {e:#}");
            ExitCode::from(EXIT_INTERNAL)
        }
    }
}
