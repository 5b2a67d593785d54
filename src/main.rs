//! The `omnid` command line: parse, build the pipeline, run, print. Exit codes: 0 success,
//! 1 internal or log error, 2 bad input, 3 device fault, 4 safety fault, 130 operator stop.

use anyhow::Context;
use clap::{Parser, Subcommand};
use omnid::config::Config;
use omnid::control::{ControllerKind, Trajectory};
use omnid::convert::{convert, SourceFormat};
use omnid::device::inject::Fault;
use omnid::run::{execute, DeviceSpec, RunError, RunOptions};
use omnid::servo::EndReason;
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
    /// The daemon: hold the device and serve clients on a Unix socket until SIGTERM
    /// (docs/PROTOCOL.md). Starts with the amplifiers off.
    Serve(ServeArgs),
    /// Live state from a running `omnid serve`.
    Watch(WatchArgs),
    /// Command a running `omnid serve`: status, mode, controller, record, weights, freeze,
    /// adapt, shutdown.
    Ctl(CtlArgs),
    /// Convert a recording into a replayable log (for `--device replay:OUT`).
    Convert(ConvertArgs),
    /// Pre-tune the identifier's networks on recorded logs and save the weights.
    Identify(IdentifyArgs),
    /// First contact with a FireWire Omni (docs/BRINGUP.md): identify it, dump its registers,
    /// and capture its packets with the amplifiers off while telling you what to do; with
    /// --outputs, guided lamp, amplifier and motor-sign steps at a few DAC counts, each asked
    /// first. Needs no calibration.
    Probe(ProbeArgs),
    /// List candidate devices (USB bridges, FireWire Omnis) with permission problems and fixes.
    Devices {
        /// TOML configuration file (its [usb] ids are the ones searched for).
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// Figures (PNG and SVG) from a log: angles, torque vs. the identifier's estimate,
    /// identification and tracking errors, control effort; a haptic run's tip path and forces.
    Plot {
        /// The CSV log (at least `t`; figures whose columns are missing are skipped).
        log: PathBuf,
        /// Directory for the figures (created if needed).
        #[arg(long)]
        out: PathBuf,
        /// The scene the run rendered: its walls are drawn on the tip path.
        #[arg(long, value_name = "SCENE.toml")]
        scene: Option<PathBuf>,
    },
    /// Reproduce the paper's experiments on the simulator, and the haptics experiment: runs,
    /// `DIR/report.md` with the tables, and the figures.
    Experiment {
        /// Which experiment.
        #[arg(value_parser = experiment_names())]
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
    let stop = stop_on_signal()?;
    let cfg = match load_config(args.config.as_deref(), Some(&stop)) {
        Ok(cfg) => cfg,
        Err(code) => return Ok(code),
    };
    let pretune_cfg = omnid::identifier::PretuneConfig {
        epochs: args.epochs,
        ..Default::default()
    };
    let bar = omnid::progress::bar(args.epochs as u64, "identify");
    let result = omnid::log_pretune::identify(
        &args.logs,
        &args.out,
        &cfg,
        &pretune_cfg,
        Some(&stop),
        |p| match p {
            omnid::identifier::Progress::Batch { .. } => {}
            omnid::identifier::Progress::Epoch(r) => {
                bar.inc(1);
                bar.suspend(|| omnid::errln!(
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
            omnid::outln!(
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
            omnid::errln!("omnid identify: {e}");
            Ok(error_exit(e.is_stopped(), e.is_bad_input()))
        }
    }
}

#[derive(clap::Args)]
struct RunArgs {
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
enum RunMode {
    Track,
    Free,
}

#[derive(clap::Args)]
struct ServeArgs {
    /// sim | replay:PATH | usb | firewire; repeat for several arms (the second of a kind is
    /// named `<kind>-2`) [default: the config's [[arm]]s, else sim]
    #[arg(long)]
    device: Vec<DeviceSpec>,
    /// A configured arm to serve (`[[arm]]` in --config; repeatable); a device kind (sim, usb,
    /// firewire) names that device's one arm [default: every configured arm]
    #[arg(long, value_name = "NAME")]
    arm: Vec<String>,
    /// The control law in effect when a client asks for hold, track or free (switchable).
    #[arg(long, value_enum, default_value = "nnidc")]
    controller: ControllerKind,
    /// Socket path, one arm only [default: $XDG_RUNTIME_DIR/omnid/<arm>.sock, /run/omnid/ as
    /// root].
    #[arg(long)]
    socket: Option<PathBuf>,
    /// TOML configuration file (its [serve] section: access groups, stream time to live).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Start the identifier from these weights (from `omnid identify`).
    #[arg(long, value_name = "WEIGHTS.json")]
    weights: Option<PathBuf>,
    /// Freeze the identifier: no online adaptation.
    #[arg(long)]
    no_adapt: bool,
    /// Replay: skip damaged rows of the log (reported) instead of refusing it.
    #[arg(long)]
    lenient: bool,
    /// Inject a fault (repeatable; as `run --inject`).
    #[arg(long, value_name = "SPEC")]
    inject: Vec<Fault>,
    /// Show every arm live in Foxglove or Lichtblick: a Foxglove WebSocket server on ADDR
    /// [default without ADDR: 127.0.0.1:8765, this machine only].
    #[arg(long, value_name = "ADDR", num_args = 0..=1,
          default_missing_value = omnid::serve::foxglove::DEFAULT_ADDR,
          value_parser = parse_view_addr)]
    foxglove: Option<std::net::SocketAddr>,
    /// Serve every arm over zenoh too: ROS 2 topics in rmw_zenoh's form and remote clients
    /// (loopback and read-only unless `[zenoh]` says otherwise; docs/ZENOH.md).
    #[arg(long)]
    zenoh: bool,
}

fn parse_view_addr(s: &str) -> Result<std::net::SocketAddr, String> {
    omnid::serve::foxglove::parse_addr(s).map_err(|e| e.to_string())
}

#[derive(clap::Args)]
struct WatchArgs {
    /// The daemon's socket [default: $OMNID_SOCKET, else the one in the default directory].
    #[arg(long)]
    socket: Option<PathBuf>,
    /// The arm, by name or alias (its socket `<name>.sock` in the default directories).
    #[arg(long, value_name = "NAME", conflicts_with = "socket")]
    arm: Option<String>,
    /// Stop after this many samples.
    #[arg(long)]
    count: Option<u64>,
    /// Samples per second (up to the device's rate).
    #[arg(long, default_value_t = 10.0)]
    rate: f64,
    /// One JSON object per line, for programs: each sample, and each event as the daemon
    /// sent it (without it: readable lines, events as sentences).
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct CtlArgs {
    /// The daemon's socket [default: $OMNID_SOCKET, else the one in the default directory].
    #[arg(long)]
    socket: Option<PathBuf>,
    /// The arm, by name or alias (its socket `<name>.sock` in the default directories).
    #[arg(long, value_name = "NAME", conflicts_with = "socket")]
    arm: Option<String>,
    /// Print the daemon's reply as JSON (for programs; `status`: the keys of
    /// docs/DESIGN.md §2.3) instead of the readable form; `teleop start`: a JSON object a line
    /// (`note`s, and each second a `pair` with each arm's latest state).
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    command: CtlCommand,
}

#[derive(Subcommand)]
enum CtlCommand {
    /// The mode, controller, lease, clients, faults, tracking, timing and recording (`--json`:
    /// the run summary so far with them).
    Status,
    /// idle, hold, track or free (track follows --trajectory).
    Mode {
        mode: String,
        #[arg(long, default_value = "sine")]
        trajectory: String,
    },
    /// Switch the control law (bumpless): pd, ct, nnidc, off.
    Controller { controller: String },
    /// Start or stop recording every tick to a log (CSV, as `omnid run` writes).
    Record {
        /// start or stop
        action: String,
        path: Option<PathBuf>,
    },
    /// Save the identifier's weights to a file, or load them from one.
    Weights {
        /// save or load
        action: String,
        path: PathBuf,
    },
    /// Freeze the identifier's online adaptation.
    Freeze,
    /// Resume the identifier's online adaptation.
    Adapt,
    /// Stop the daemon (zero torque, amplifiers off).
    Shutdown,
    /// Simulator: the hand presses, releases or clicks (press, then release 0.1 s later) a
    /// stylus button, 1 or 2.
    Button {
        /// 1 or 2
        button: u64,
        /// press, release or click
        action: String,
    },
    /// Simulator: the hand puts the stylus in its inkwell.
    Dock,
    /// Simulator: the hand takes the stylus out of its inkwell and holds it lightly.
    Undock,
    /// Teleoperation between two arms of the daemon (docs/TELEOP.md): `start` couples them
    /// and watches until Ctrl-C, which uncouples them (both hold).
    Teleop {
        #[command(subcommand)]
        action: TeleopAction,
    },
}

#[derive(Subcommand)]
enum TeleopAction {
    /// Couple a leader arm (a person moves it) and a follower arm (it copies the leader),
    /// with `[teleop]`'s settings and the changes given; runs until Ctrl-C or --seconds.
    Start {
        /// The leader arm, by name or alias.
        #[arg(long, value_name = "ARM")]
        leader: String,
        /// The follower arm, by name or alias.
        #[arg(long, value_name = "ARM")]
        follower: String,
        /// pp (position–position) or pf (position–force, from the follower's estimate).
        #[arg(long)]
        architecture: Option<String>,
        /// Follower mm per leader mm.
        #[arg(long)]
        motion_scale: Option<f64>,
        /// The leader feels this times the force.
        #[arg(long)]
        force_scale: Option<f64>,
        /// When the operator counts as present: button1 (held) or always.
        #[arg(long)]
        operator: Option<String>,
        /// Time-domain passivity off (on by default).
        #[arg(long)]
        no_passivity: bool,
        /// Uncouple after this many seconds.
        #[arg(long)]
        seconds: Option<f64>,
    },
}

#[derive(clap::Args)]
struct ProbeArgs {
    /// firewire (a USB bridge has no registers or bus timestamps to probe)
    #[arg(long, default_value = "firewire")]
    device: String,
    /// A configured arm (`[[arm]]` in --config): its sections, and its lock.
    #[arg(long, value_name = "NAME")]
    arm: Option<String>,
    /// Capture file [default: omnid-capture-<UTC time>.txt]; replayable after
    /// `omnid convert --from capture`.
    #[arg(long)]
    capture: Option<PathBuf>,
    /// How long to capture with the amplifiers off, s (ends early once every step was seen).
    #[arg(long, default_value_t = 60.0)]
    seconds: f64,
    /// Then the output steps: lamp, amplifiers at zero torque, each motor's sign.
    #[arg(long)]
    outputs: bool,
    /// DAC counts of the sign pulses (1..=200; the default is about 9 mN·m).
    #[arg(long, default_value_t = 40)]
    counts: u16,
    /// TOML configuration file ([firewire], device.rate_hz, device.nm_per_count).
    #[arg(long)]
    config: Option<PathBuf>,
}

fn probe_cmd(args: ProbeArgs) -> Result<u8, anyhow::Error> {
    use omnid::device::probe::{probe_firewire, ProbeError, ProbePlan, TerminalOperator};
    let mut cfg = match load_config(args.config.as_deref(), None) {
        Ok(cfg) => cfg,
        Err(code) => return Ok(code),
    };
    // The arm is this process's while it probes: a daemon or a run on it is refused, and so
    // is this probe while one of them has it.
    let arm = args.arm.clone().unwrap_or_else(|| "firewire".into());
    if args.arm.is_some() {
        match cfg.arm_named(&arm) {
            Ok(a) => cfg = a.config,
            Err(e) => {
                omnid::errln!("omnid probe: --arm: {e}");
                return Ok(EXIT_BAD_INPUT);
            }
        }
    }
    if args.device != "firewire" {
        omnid::errln!(
            "omnid probe: --device {}: only firewire can be probed (a USB bridge has no device \
             registers or bus timestamps; `omnid run --device usb` reports what it finds)",
            args.device
        );
        return Ok(EXIT_BAD_INPUT);
    }
    let stop = stop_on_signal()?;
    let plan = ProbePlan {
        capture: args.capture.unwrap_or_else(|| {
            PathBuf::from(format!(
                "omnid-capture-{}.txt",
                omnid::telemetry::utc_stamp(std::time::SystemTime::now())
            ))
        }),
        seconds: args.seconds,
        outputs: args.outputs,
        counts: args.counts,
        lock: args.arm.is_none().then(|| arm.clone()),
    };
    if let Err(e) = plan.check(&cfg) {
        omnid::errln!("omnid probe: {e}");
        return Ok(EXIT_BAD_INPUT);
    }
    // A named arm is locked now (it may be a daemon's); the default one once the Omni is found.
    let _lock = match args
        .arm
        .as_ref()
        .map(|_| omnid::arm::ArmLock::acquire(&arm))
    {
        Some(Err(e)) => {
            omnid::errln!("omnid probe: {e}");
            return Ok(EXIT_BAD_INPUT);
        }
        held => held,
    };
    let mut op = TerminalOperator { stop: &stop };
    match probe_firewire(&cfg, &plan, &mut op, &stop) {
        Ok(report) => {
            omnid::outln!(
                "omnid probe: serial {}; {} packets captured in {}",
                report.serial.as_deref().unwrap_or("?"),
                report.captured,
                plan.capture.display()
            );
            for (what, seen) in &report.checks {
                omnid::outln!("  [{}] {what}", if *seen { "x" } else { " " });
            }
            if let Some(s) = report.dac_sign {
                omnid::outln!("[firewire]\ndac_sign = [{}, {}, {}]", s[0], s[1], s[2]);
            }
            if let Some(why) = &report.aborted {
                omnid::errln!(
                    "omnid probe: output steps stopped: {why}; zero torque, amplifiers off"
                );
                return Ok(EXIT_OPERATOR_STOP);
            }
            Ok(0)
        }
        Err(e @ ProbeError::BadInput(_)) => {
            omnid::errln!("omnid probe: {e}");
            Ok(EXIT_BAD_INPUT)
        }
        Err(e @ ProbeError::Device(_)) => {
            omnid::errln!("omnid: {e}");
            Ok(EXIT_DEVICE_FAULT)
        }
        Err(e @ ProbeError::Capture { .. }) => {
            omnid::errln!("omnid probe: {e}");
            Ok(EXIT_INTERNAL)
        }
    }
}

#[derive(clap::Args)]
struct ConvertArgs {
    /// Format of the input.
    #[arg(long, value_enum)]
    from: SourceFormat,
    /// The recording to convert (CSV; `--from log`: CSV or MCAP).
    input: PathBuf,
    /// Where to write the replayable log (CSV; `--from log`: MCAP when it ends in .mcap).
    #[arg(long)]
    out: PathBuf,
    /// Skip damaged rows (reported) instead of refusing the file.
    #[arg(long)]
    lenient: bool,
}

fn plot_cmd(
    log: &std::path::Path,
    out: &std::path::Path,
    scene: Option<&std::path::Path>,
) -> Result<u8, anyhow::Error> {
    let stop = stop_on_signal()?;
    let effects = match scene.map(|p| omnid::haptics::scene::read_scene(p, Some(&stop))) {
        None => Vec::new(),
        Some(Ok(e)) => e,
        Some(Err(e)) => {
            omnid::errln!("omnid plot: {e}");
            return Ok(EXIT_BAD_INPUT);
        }
    };
    match omnid::plot::plot_log(log, out, &effects, Some(&stop)) {
        Ok(report) => {
            omnid::out!("{report}");
            Ok(0)
        }
        Err(e) => {
            omnid::errln!("omnid plot: {e}");
            Ok(error_exit(e.is_stopped(), e.is_bad_input()))
        }
    }
}

fn convert_cmd(args: ConvertArgs) -> Result<u8, anyhow::Error> {
    let stop = stop_on_signal()?;
    match convert(args.from, &args.input, &args.out, args.lenient, Some(&stop)) {
        Ok(report) => {
            omnid::outln!(
                "omnid convert: {} rows from {} to {} (columns: {})",
                report.rows,
                args.input.display(),
                args.out.display(),
                report.columns.join(",")
            );
            if report.skipped.count > 0 {
                omnid::errln!("omnid: warning: --lenient: {}", report.skipped);
            }
            Ok(0)
        }
        Err(e) if e.is_stopped() => {
            omnid::errln!("omnid: {e}; nothing written");
            Ok(EXIT_OPERATOR_STOP)
        }
        Err(e) => {
            omnid::errln!("omnid: {e}");
            Ok(error_exit(false, e.is_bad_input()))
        }
    }
}

/// `--mode`, `--scene` and `--hand`: the haptic part of a run (the hand goes into the
/// simulator's config).
fn haptic_options(
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

fn run(args: RunArgs) -> Result<u8, anyhow::Error> {
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
    let outcome = match execute(&opts, &cfg, stop) {
        Ok(o) => o,
        Err(e) => return run_failed(e),
    };
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
fn run_failed(e: RunError) -> Result<u8, anyhow::Error> {
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
fn report_ending(
    outcome: &omnid::run::RunOutcome,
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

const EXIT_REFUSED: u8 = 1;

/// The exit code of a command that failed: stopped by the operator, refused its input, or
/// failed on its own (a write part-way, an internal error).
fn error_exit(stopped: bool, bad_input: bool) -> u8 {
    if stopped {
        EXIT_OPERATOR_STOP
    } else if bad_input {
        EXIT_BAD_INPUT
    } else {
        EXIT_INTERNAL
    }
}

/// A flag that Ctrl-C and SIGTERM set (the `termination` feature also catches SIGHUP).
fn stop_on_signal() -> Result<Arc<AtomicBool>, anyhow::Error> {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst))
        .context("installing the Ctrl-C/SIGTERM handler")?;
    Ok(stop)
}

fn serve_cmd(args: ServeArgs) -> Result<u8, anyhow::Error> {
    let stop = stop_on_signal()?;
    let cfg = match load_config(args.config.as_deref(), Some(&stop)) {
        Ok(cfg) => cfg,
        Err(code) => return Ok(code),
    };
    let opts = omnid::daemon::ServeOptions {
        devices: args.device,
        arms: args.arm,
        controller: args.controller,
        socket: args.socket,
        weights: args.weights,
        no_adapt: args.no_adapt,
        lenient: args.lenient,
        inject: args.inject,
        foxglove: args.foxglove,
        zenoh: args.zenoh,
    };
    let outcome = match omnid::daemon::serve(&opts, &cfg, stop) {
        Ok(o) => o,
        Err(e) if e.is_stopped() => {
            omnid::errln!("omnid serve: {e}; nothing served");
            return Ok(EXIT_OPERATOR_STOP);
        }
        Err(e @ RunError::Device(_)) => {
            omnid::errln!("omnid: {e}");
            return Ok(EXIT_DEVICE_FAULT);
        }
        Err(e @ RunError::Internal(_)) => return Err(e.into()),
        Err(e) => {
            omnid::errln!("omnid: {e}");
            return Ok(EXIT_BAD_INPUT);
        }
    };
    // Each arm's summary; a closed stdout loses nothing else.
    let several = outcome.arms.len() > 1;
    for arm in &outcome.arms {
        if several {
            omnid::outln!("arm {}:", arm.name);
        }
        omnid::out!("{}", arm.summary.human());
    }
    // The worst ending decides the exit code (an operator's stop only when nothing failed).
    let codes: Vec<u8> = outcome
        .arms
        .iter()
        .map(|a| say_how_arm_ended(a, outcome.shutdown_requested, several))
        .collect();
    Ok(codes
        .iter()
        .copied()
        .filter(|&c| c != 0 && c != EXIT_OPERATOR_STOP)
        .max()
        .or_else(|| codes.iter().copied().max())
        .unwrap_or(0))
}

/// An arm's last words on stderr, and its exit code.
fn say_how_arm_ended(o: &omnid::daemon::ArmOutcome, shutdown_requested: bool, several: bool) -> u8 {
    let arm = if several {
        format!("arm {}: ", o.name)
    } else {
        String::new()
    };
    let stopped = if o.shutdown_error.is_none() {
        "zero torque sent, amplifiers off"
    } else {
        "the final zero-torque packet could not be delivered: switch the device off (whether it drops its amplifiers when packets stop is not known, docs/FIREWIRE.md §9)"
    };
    // Each fault dump was announced where it was written.
    if let Some(e) = &o.recording_error {
        omnid::errln!("omnid serve: {arm}the recording is incomplete: {e}");
    }
    if let Some(e) = &o.shutdown_error {
        omnid::errln!("omnid: warning: {arm}{e}");
    }
    let code = match &o.end {
        EndReason::OperatorStop if shutdown_requested => {
            omnid::errln!(
                "omnid serve: {arm}shut down by a client; {stopped}; socket {} removed",
                o.socket.display()
            );
            0
        }
        EndReason::OperatorStop => {
            omnid::errln!(
                "omnid serve: {arm}stopped by the operator; {stopped}; socket {} removed",
                o.socket.display()
            );
            EXIT_OPERATOR_STOP
        }
        EndReason::Completed | EndReason::EndOfData => {
            omnid::errln!("omnid serve: {arm}the replayed log ended; {stopped}");
            0
        }
        EndReason::DeviceFault(m) => {
            omnid::errln!("omnid serve: {arm}device fault: {m}; {stopped}");
            EXIT_DEVICE_FAULT
        }
        EndReason::SafetyFault(m) => {
            omnid::errln!("omnid serve: {arm}safety fault: {m}; {stopped}");
            EXIT_SAFETY_FAULT
        }
    };
    if code == 0 && o.shutdown_error.is_some() {
        EXIT_DEVICE_FAULT
    } else {
        code
    }
}

/// Connect to the daemon (exit code 3 and the reason when there is none).
fn connect(
    socket: Option<PathBuf>,
    arm: Option<&str>,
    name: &str,
) -> Result<omnid::serve::client::Client, u8> {
    let found = match (socket, arm) {
        (Some(p), _) => Ok(p),
        (None, Some(arm)) => omnid::serve::find_arm_socket(arm),
        (None, None) => omnid::serve::find_socket(),
    };
    let path = match found {
        Ok(p) => p,
        Err(e) => {
            omnid::errln!("omnid: {e}");
            return Err(EXIT_DEVICE_FAULT);
        }
    };
    omnid::serve::client::Client::connect(&path, name).map_err(|e| {
        omnid::errln!("omnid: {e}");
        match e {
            omnid::serve::client::ClientError::Refused(_) => EXIT_REFUSED,
            _ => EXIT_DEVICE_FAULT,
        }
    })
}

fn watch_cmd(args: WatchArgs) -> Result<u8, anyhow::Error> {
    use omnid::serve::client::Message;
    use std::io::Write;
    if !(args.rate.is_finite() && args.rate > 0.0) {
        omnid::errln!("omnid watch: --rate {} must be a number > 0", args.rate);
        return Ok(EXIT_BAD_INPUT);
    }
    let mut client = match connect(args.socket, args.arm.as_deref(), "omnid watch") {
        Ok(c) => c,
        Err(code) => return Ok(code),
    };
    if let Err(e) = client.request(serde_json::json!({ "op": "stream", "rate_hz": args.rate })) {
        omnid::errln!("omnid watch: {e}");
        return Ok(EXIT_REFUSED);
    }
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    let mut seen = 0u64;
    while args.count.is_none_or(|n| seen < n) {
        let line = match client.recv(-1) {
            Ok(Message::State(s)) => {
                seen += 1;
                if args.json {
                    let mut v = serde_json::to_value(&s)?;
                    v["type"] = serde_json::json!("state");
                    v.to_string()
                } else {
                    format!(
                        "{:>8} {:>9.3} s  {:<8} {:<5}  q {:>7.4} {:>7.4} {:>7.4} rad  tip {:>7.1} {:>7.1} {:>7.1} mm  buttons {}{}  tau {:>6.1} {:>6.1} {:>6.1} mN·m{}",
                        s.seq, s.t, s.mode, s.controller, s.q[0], s.q[1], s.q[2],
                        s.tip_mm[0], s.tip_mm[1], s.tip_mm[2],
                        u8::from(s.buttons[0]), u8::from(s.buttons[1]),
                        s.tau[0] * 1e3, s.tau[1] * 1e3, s.tau[2] * 1e3,
                        if s.flags != 0 { format!("  flags {}", s.flags) } else { String::new() }
                    )
                }
            }
            Ok(Message::Other(v)) if v["type"] == "bye" => {
                omnid::errln!("omnid watch: the daemon is stopping");
                return Ok(0);
            }
            Ok(Message::Other(v)) => {
                if args.json {
                    v.to_string()
                } else {
                    match omnid::human::event_line(&v) {
                        Some(line) => line,
                        None => continue,
                    }
                }
            }
            Err(omnid::serve::client::ClientError::Closed) => {
                omnid::errln!("omnid watch: the daemon closed the connection");
                return Ok(0);
            }
            Err(e) => {
                omnid::errln!("omnid watch: {e}");
                return Ok(EXIT_INTERNAL);
            }
        };
        // A closed stdout (`| head`) ends the watch quietly; any other failure (a full disk
        // under `> file`) is an error: the data did not arrive.
        if let Err(e) = writeln!(out, "{line}").and_then(|()| out.flush()) {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                return Ok(0);
            }
            omnid::errln!("omnid watch: cannot write to stdout: {e}; stopped");
            return Ok(EXIT_INTERNAL);
        }
    }
    Ok(0)
}

fn ctl_cmd(args: CtlArgs) -> Result<u8, anyhow::Error> {
    use serde_json::json;
    if let CtlCommand::Teleop { action } = args.command {
        return teleop_console(action, args.json);
    }
    let request = match &args.command {
        CtlCommand::Status => json!({ "op": "status" }),
        CtlCommand::Mode { mode, trajectory } => {
            json!({ "op": "mode", "mode": mode, "trajectory": trajectory })
        }
        CtlCommand::Controller { controller } => {
            json!({ "op": "controller", "controller": controller })
        }
        CtlCommand::Record { action, path } => match action.as_str() {
            "start" => json!({ "op": "record_start", "path": path }),
            "stop" => json!({ "op": "record_stop" }),
            other => {
                omnid::errln!("omnid ctl: record {other}: expected start or stop");
                return Ok(EXIT_BAD_INPUT);
            }
        },
        CtlCommand::Weights { action, path } => match action.as_str() {
            "save" => json!({ "op": "weights_save", "path": absolute(path) }),
            "load" => json!({ "op": "weights_load", "path": absolute(path) }),
            other => {
                omnid::errln!("omnid ctl: weights {other}: expected save or load");
                return Ok(EXIT_BAD_INPUT);
            }
        },
        CtlCommand::Freeze => json!({ "op": "adapt", "on": false }),
        CtlCommand::Adapt => json!({ "op": "adapt", "on": true }),
        CtlCommand::Shutdown => json!({ "op": "shutdown" }),
        CtlCommand::Button { button, action } => match action.as_str() {
            "press" | "release" | "click" => {
                json!({ "op": "stylus", "action": action, "button": button })
            }
            other => {
                omnid::errln!(
                    "omnid ctl: button {button} {}: expected press, release or click",
                    omnid::text::cut(other)
                );
                return Ok(EXIT_BAD_INPUT);
            }
        },
        CtlCommand::Dock => json!({ "op": "stylus", "action": "dock" }),
        CtlCommand::Undock => json!({ "op": "stylus", "action": "undock" }),
        CtlCommand::Teleop { .. } => unreachable!("handled above"),
    };
    // Paths are the daemon's to open: make relative ones relative to where ctl runs.
    let mut request = request;
    if let Some(p) = request
        .get("path")
        .and_then(|p| p.as_str())
        .map(String::from)
    {
        request["path"] = json!(absolute(std::path::Path::new(&p)));
    }
    let mut client = match connect(args.socket, args.arm.as_deref(), "omnid ctl") {
        Ok(c) => c,
        Err(code) => return Ok(code),
    };
    match client.request(request) {
        Ok(reply) => {
            let text = match &args.command {
                CtlCommand::Status if args.json => serde_json::to_string_pretty(&reply["status"])?,
                CtlCommand::Status => omnid::human::status_block(&reply["status"])
                    .trim_end()
                    .to_string(),
                _ if !args.json => omnid::human::reply_line(&reply),
                _ => {
                    let mut r = reply.clone();
                    if let Some(o) = r.as_object_mut() {
                        o.remove("type");
                        o.remove("id");
                    }
                    r.to_string()
                }
            };
            omnid::outln!("{text}");
            Ok(0)
        }
        Err(e) => {
            omnid::errln!("omnid ctl: {e}");
            Ok(EXIT_REFUSED)
        }
    }
}

/// `omnid ctl teleop start`: the pair's console, until Ctrl-C, SIGTERM or --seconds.
fn teleop_console(action: TeleopAction, json: bool) -> Result<u8, anyhow::Error> {
    use omnid::teleop::console::{self, ConsoleEnd, PairSettings};
    let TeleopAction::Start {
        leader,
        follower,
        architecture,
        motion_scale,
        force_scale,
        operator,
        no_passivity,
        seconds,
    } = action;
    if seconds.is_some_and(|s| !(s.is_finite() && s > 0.0)) {
        omnid::errln!("omnid ctl teleop: --seconds must be a number > 0");
        return Ok(EXIT_BAD_INPUT);
    }
    let stop = stop_on_signal()?;
    // Each arm on this PC, or served by another daemon (then its side is started there).
    let found = [&leader, &follower].map(|arm| omnid::serve::find_arm_socket(arm));
    if let [Err(a), Err(b)] = &found {
        omnid::errln!("omnid: {a}");
        omnid::errln!("omnid: {b}");
        return Ok(EXIT_DEVICE_FAULT);
    }
    let mut clients = Vec::new();
    for (p, who) in found.iter().zip(["leader", "follower"]) {
        clients.push(match p {
            Ok(p) => {
                let name = format!("omnid ctl teleop ({who})");
                match omnid::serve::client::Client::connect(p, &name) {
                    Ok(c) => Some(c),
                    Err(e) => {
                        omnid::errln!("omnid: {e}");
                        return Ok(match e {
                            omnid::serve::client::ClientError::Refused(_) => EXIT_REFUSED,
                            _ => EXIT_DEVICE_FAULT,
                        });
                    }
                }
            }
            Err(_) => None,
        });
    }
    let mut f_client = clients.pop().flatten();
    let mut l_client = clients.pop().flatten();
    fn side<'a>(c: Option<&'a mut omnid::serve::client::Client>, name: &str) -> console::Side<'a> {
        match c {
            Some(c) => console::Side::Here(c),
            None => console::Side::Elsewhere(name.to_string()),
        }
    }
    let settings = PairSettings {
        architecture,
        motion_scale,
        force_scale,
        operator,
        passivity: no_passivity.then_some(false),
    };
    let mut out = |line: &str| omnid::outln!("{line}");
    let mut say = console::Say {
        json,
        out: &mut out,
    };
    match console::run(
        side(l_client.as_mut(), &leader),
        side(f_client.as_mut(), &follower),
        &settings,
        seconds,
        &stop,
        &mut say,
    ) {
        Ok(ConsoleEnd::Elapsed) => {
            omnid::outln!(
                "teleop: uncoupled after {} s; both arms hold",
                seconds.unwrap_or(0.0)
            );
            Ok(0)
        }
        Ok(ConsoleEnd::Stopped) => {
            omnid::errln!(
                "omnid ctl teleop: stopped by the operator; both arms uncoupled, holding"
            );
            Ok(EXIT_OPERATOR_STOP)
        }
        Ok(ConsoleEnd::ArmLeft { arm, mode }) => {
            omnid::errln!(
                "omnid ctl teleop: {arm} left teleop (now {mode}): the pair is uncoupled (the \
                 follower holds, the leader's force faded); `omnid ctl --arm {arm} status` says why"
            );
            Ok(EXIT_DEVICE_FAULT)
        }
        Ok(ConsoleEnd::Gone(arm)) => {
            omnid::errln!("omnid ctl teleop: {arm}'s daemon closed the connection");
            Ok(EXIT_DEVICE_FAULT)
        }
        Err(e) => {
            omnid::errln!("omnid ctl teleop: {e}");
            Ok(EXIT_REFUSED)
        }
    }
}

fn absolute(p: &std::path::Path) -> PathBuf {
    std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf())
}

/// The config file, or the defaults; the exit code after printing why a file was refused
/// (`stop`: the operator's, which ends a wait on a config that is a pipe).
fn load_config(
    path: Option<&std::path::Path>,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<Config, u8> {
    match path.map(|p| Config::load(p, stop)) {
        None => Ok(Config::default()),
        Some(Ok(c)) => Ok(c),
        Some(Err(e)) => {
            omnid::errln!("omnid: {e}");
            Err(if e.is_stopped() {
                EXIT_OPERATOR_STOP
            } else {
                EXIT_BAD_INPUT
            })
        }
    }
}

/// The experiments' names as clap lists them in `--help` and checks them.
fn experiment_names() -> impl clap::builder::TypedValueParser<Value = omnid::experiment::Experiment>
{
    use clap::builder::TypedValueParser;
    use omnid::experiment::Experiment;
    clap::builder::PossibleValuesParser::new(Experiment::ALL.map(Experiment::as_str))
        .try_map(|name| name.parse::<Experiment>())
}

fn main() -> ExitCode {
    let mut code = run_cli();
    // Output that did not arrive (a full disk under `> file`) is not a success; a closed pipe
    // (`| head`) is the reader's choice.
    if let Some(e) = omnid::diag::stdout_failed() {
        omnid::errln!("omnid: cannot write to stdout: {e}; output was lost");
        if code == ExitCode::SUCCESS {
            code = ExitCode::from(EXIT_INTERNAL);
        }
    }
    // Diagnostics leave through their own thread: a bounded wait for the last of them (a
    // stderr nobody drains cannot hold the exit).
    omnid::diag::flush(std::time::Duration::from_secs(2));
    code
}

fn run_cli() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if !e.use_stderr() => e.exit(), // --help, --version
        // clap quotes a bad argument whole: a megabyte argument must not become a megabyte
        // message.
        Err(e) => {
            omnid::errln!("{}", omnid::text::cut_lines(&e.render().to_string(), 300));
            return ExitCode::from(EXIT_BAD_INPUT);
        }
    };
    let result = match cli.command {
        Command::Run(args) => run(args),
        Command::Serve(args) => serve_cmd(args),
        Command::Watch(args) => watch_cmd(args),
        Command::Ctl(args) => ctl_cmd(args),
        Command::Convert(args) => convert_cmd(args),
        Command::Probe(args) => probe_cmd(args),
        Command::Identify(args) => identify_cmd(args),
        Command::Devices { config } => match load_config(config.as_deref(), None) {
            Ok(cfg) => {
                omnid::out!("{}", omnid::device::list_devices(&cfg.usb));
                match omnid::daemon::arms_table(&cfg) {
                    Ok(table) => {
                        omnid::out!("{table}");
                        Ok(0)
                    }
                    Err(e) => {
                        omnid::errln!("omnid devices: {e}");
                        Ok(EXIT_BAD_INPUT)
                    }
                }
            }
            Err(code) => Ok(code),
        },
        Command::Plot { log, out, scene } => plot_cmd(&log, &out, scene.as_deref()),
        Command::Experiment { kind, out, quick } => {
            match omnid::experiment::run_experiment(kind, &out, quick) {
                Ok(report) => {
                    omnid::outln!(
                        "omnid experiment {}: report in {} ({} figure files)",
                        kind.as_str(),
                        report.report.display(),
                        report.figures.len()
                    );
                    Ok(0)
                }
                Err(e) => {
                    omnid::errln!("omnid experiment {}: {e}", kind.as_str());
                    Ok(error_exit(false, e.is_bad_input()))
                }
            }
        }
        Command::Config { print_default } => {
            if print_default {
                omnid::out!("{}", Config::default_toml());
                Ok(0)
            } else {
                omnid::errln!("omnid config: nothing to do; try --print-default");
                Ok(EXIT_BAD_INPUT)
            }
        }
    };
    match result {
        Ok(code) => ExitCode::from(code),
        Err(e) => {
            omnid::errln!("omnid: {e:#}");
            ExitCode::from(EXIT_INTERNAL)
        }
    }
}
