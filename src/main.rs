//! The `omnid` command line: parse, build the pipeline, run, print. Exit codes: 0 success,
//! 1 internal or log error, 2 bad input, 3 device fault, 4 safety fault, 130 operator stop.

mod cli;

use anyhow::Context;
use clap::{CommandFactory, Parser, Subcommand};
use cli::{
    convert::convert_cmd, convert::ConvertArgs, ctl::ctl_cmd, ctl::CtlArgs, identify::identify_cmd,
    identify::IdentifyArgs, plot::plot_cmd, plot::PlotArgs, probe::probe_cmd, probe::ProbeArgs,
    run::run, run::RunArgs, serve::serve_cmd, serve::ServeArgs, watch::watch_cmd, watch::WatchArgs,
};
use omnid::config::Config;
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
    version = env!("OMNID_VERSION"),
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
    Plot(PlotArgs),
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
    /// Print a shell completion script to stdout, e.g.
    /// `omnid completions bash > ~/.local/share/bash-completion/completions/omnid`.
    Completions {
        /// The shell.
        shell: clap_complete::Shell,
    },
    /// Print the manual page (roff) to stdout, e.g.
    /// `omnid manpage > ~/.local/share/man/man1/omnid.1`, then `man omnid`.
    Manpage,
    /// Configuration helpers.
    Config {
        /// Print the full default configuration, commented.
        #[arg(long)]
        print_default: bool,
    },
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

/// Connect to the daemon (exit code 3 and the reason when there is none).
fn connect(
    socket: Option<PathBuf>,
    arm: Option<&str>,
    name: &str,
) -> Result<omnid::transport::client::Client, u8> {
    let found = match (socket, arm) {
        (Some(p), _) => Ok(p),
        (None, Some(arm)) => omnid::transport::find_arm_socket(arm).map_err(|e| (e, false)),
        (None, None) => omnid::transport::find_socket().map_err(|e| {
            let several = matches!(e, omnid::transport::FindError::Several { .. });
            (e.to_string(), several)
        }),
    };
    let path = match found {
        Ok(p) => p,
        Err((e, ambiguous)) => {
            omnid::errln!("omnid: {e}");
            // Which arm is the caller's to say (bad input); no daemon is the device missing.
            return Err(if ambiguous {
                EXIT_BAD_INPUT
            } else {
                EXIT_DEVICE_FAULT
            });
        }
    };
    omnid::transport::client::Client::connect(&path, name).map_err(|e| {
        omnid::errln!("omnid: {e}");
        match e {
            omnid::transport::client::ClientError::Refused(_) => EXIT_REFUSED,
            _ => EXIT_DEVICE_FAULT,
        }
    })
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
                match omnid::cmd::serve::arms_table(&cfg) {
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
        Command::Plot(args) => plot_cmd(args),
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
        Command::Completions { shell } => {
            let mut script = Vec::new();
            clap_complete::generate(shell, &mut Cli::command(), "omnid", &mut script);
            omnid::out!("{}", String::from_utf8_lossy(&script));
            Ok(0)
        }
        Command::Manpage => {
            let mut page = Vec::new();
            match clap_mangen::Man::new(Cli::command()).render(&mut page) {
                Ok(()) => {
                    omnid::out!("{}", String::from_utf8_lossy(&page));
                    Ok(0)
                }
                Err(e) => Err(anyhow::Error::new(e).context("rendering the manual page")),
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
