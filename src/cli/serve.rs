//! `omnid serve`: the daemon, and how each arm ended.

use crate::{
    load_config, stop_on_signal, EXIT_BAD_INPUT, EXIT_DEVICE_FAULT, EXIT_OPERATOR_STOP,
    EXIT_SAFETY_FAULT,
};
use omnid::cmd::run::{DeviceSpec, RunError};
use omnid::control::ControllerKind;
use omnid::device::inject::Fault;
use omnid::servo::EndReason;
use std::path::PathBuf;

#[derive(clap::Args)]
pub(crate) struct ServeArgs {
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
          default_missing_value = omnid::transport::foxglove::DEFAULT_ADDR,
          value_parser = parse_view_addr)]
    foxglove: Option<std::net::SocketAddr>,
    /// Serve every arm over zenoh too: ROS 2 topics in rmw_zenoh's form and remote clients
    /// (loopback and read-only unless `[zenoh]` says otherwise; docs/ZENOH.md).
    #[arg(long)]
    zenoh: bool,
}

pub(crate) fn parse_view_addr(s: &str) -> Result<std::net::SocketAddr, String> {
    omnid::transport::foxglove::parse_addr(s).map_err(|e| e.to_string())
}

pub(crate) fn serve_cmd(args: ServeArgs) -> Result<u8, anyhow::Error> {
    let stop = stop_on_signal()?;
    let cfg = match load_config(args.config.as_deref(), Some(&stop)) {
        Ok(cfg) => cfg,
        Err(code) => return Ok(code),
    };
    let opts = omnid::cmd::serve::ServeOptions {
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
    let outcome = match omnid::cmd::serve::serve(&opts, &cfg, stop) {
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
pub(crate) fn say_how_arm_ended(
    o: &omnid::cmd::serve::ArmOutcome,
    shutdown_requested: bool,
    several: bool,
) -> u8 {
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
