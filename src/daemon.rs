//! `omnid serve`: the daemon that lab software connects to (docs/PROTOCOL.md). The servo
//! thread is the same pipeline `omnid run` assembles (`run::assemble`), started in `idle`
//! and fed commands through a bounded mailbox; a second thread (`serve::hub`) serves clients
//! on a Unix SOCK_SEQPACKET socket.

use crate::config::Config;
use crate::run::{assemble, check_device_options, join_servo, DeviceSpec, RunError, RunOptions};
use crate::serve::access::Policy;
use crate::serve::socket::{self, DeviceLock, Listener, PathLock};
use crate::serve::{default_socket, hub};
use crate::servo::{EndReason, ServoLink, Wake};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// `omnid serve`'s options (the rest comes from the config).
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// The device to serve.
    pub device: DeviceSpec,
    /// The controller the daemon starts with (clients may switch).
    pub controller: crate::control::ControllerKind,
    /// Socket path (None: `serve.socket`, else the default for the device).
    pub socket: Option<PathBuf>,
    /// Identifier weights to start from (None: the shipped ones).
    pub weights: Option<PathBuf>,
    /// Keep the identifier's weights fixed (`--no-adapt`).
    pub no_adapt: bool,
    /// Skip malformed rows of a replayed log instead of failing (`--lenient`).
    pub lenient: bool,
    /// Faults to inject (`--inject`).
    pub inject: Vec<crate::device::inject::Fault>,
}

/// How the daemon ended.
pub struct ServeOutcome {
    /// The whole session's summary (as `omnid run`'s).
    pub summary: crate::servo::summary::RunSummary,
    /// Why the servo loop ended.
    pub end: EndReason,
    /// A client asked for the shutdown (`omnid ctl shutdown`).
    pub shutdown_requested: bool,
    /// A device error while sending the final safe packet or closing, if any.
    pub shutdown_error: Option<String>,
    /// Fault dumps written during the session.
    pub dumps: Vec<PathBuf>,
    /// An error of the recording in progress at the end, if any.
    pub recording_error: Option<String>,
    /// The socket the daemon listened on.
    pub socket: PathBuf,
}

fn group(field: &str, name: &str) -> Result<Option<(String, u32)>, RunError> {
    if name.is_empty() {
        return Ok(None);
    }
    match socket::group_id(name) {
        Some(gid) => Ok(Some((name.to_string(), gid))),
        None => Err(RunError::BadInput(format!(
            "config: `{field}` = {name:?}: no such group on this machine"
        ))),
    }
}

fn prepare_socket(path: &Path, policy: &Policy) -> Result<(Listener, PathLock), RunError> {
    let bad = |what: String| RunError::BadInput(format!("socket {}: {what}", path.display()));
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        if !dir.is_dir() {
            std::fs::create_dir_all(dir).map_err(|e| {
                bad(format!(
                    "cannot create its directory: {e} (pass --socket PATH in a writable \
                     directory, or run as the systemd service, udev/omnid@.service)"
                ))
            })?;
        }
    }
    let mut lock_name = path.as_os_str().to_owned();
    lock_name.push(".lock");
    let lock = PathLock::acquire(Path::new(&lock_name)).map_err(&bad)?;
    // The socket belongs to the group that may read (else the one that may command), so
    // its members can connect through the 0660 mode.
    let gid = policy
        .read_group
        .as_ref()
        .or(policy.control_group.as_ref())
        .map(|(_, g)| *g);
    let listener = Listener::bind(path, gid).map_err(|e| bad(e.to_string()))?;
    Ok((listener, lock))
}

/// A daemon ready to start: the servo pipeline (started in idle, taking commands) and the
/// hub that will serve its clients, the socket bound and locked.
pub struct Prepared {
    /// The servo loop, attached to the hub's mailbox.
    pub pipeline: crate::run::Pipeline,
    /// What [`hub::Hub::new`] takes.
    pub hub: hub::HubSetup,
    pub(crate) socket: PathBuf,
    _device_lock: Option<DeviceLock>,
    _socket_lock: PathLock,
}

/// Check the options, lock the device and the socket, bind it, and assemble the pipeline
/// (`run::assemble`, the same path as `omnid run`) attached to a new hub.
pub fn prepare(
    opts: &ServeOptions,
    cfg: &Config,
    stop: Arc<AtomicBool>,
) -> Result<Prepared, RunError> {
    let run_opts = RunOptions {
        device: opts.device.clone(),
        controller: opts.controller,
        duration_s: f64::INFINITY,
        lenient: opts.lenient,
        inject: opts.inject.clone(),
        weights: opts.weights.clone(),
        no_adapt: opts.no_adapt,
        ..RunOptions::default()
    };
    let faults = check_device_options(&run_opts, cfg)?;
    let policy = policy(cfg)?;
    let socket_path = socket_path(opts, cfg);
    // Real hardware is one per daemon: a second `serve` (or a `run`) is refused, not raced.
    let device_lock = match opts.device {
        DeviceSpec::Usb | DeviceSpec::Firewire => {
            Some(DeviceLock::acquire(opts.device.name()).map_err(RunError::BadInput)?)
        }
        _ => None,
    };
    let (listener, socket_lock) = prepare_socket(&socket_path, &policy)?;

    let wake = Arc::new(Wake::new().map_err(|e| RunError::Internal(format!("eventfd: {e}")))?);
    let (tx, records) = crossbeam_channel::bounded(cfg.telemetry.channel_capacity);
    let (commands, command_rx) = crossbeam_channel::bounded(256);
    let (reply_tx, replies) = crossbeam_channel::bounded(64);
    let mut pipeline = assemble(&run_opts, cfg, &faults, tx, stop.clone())?;
    pipeline.servo.attach(ServoLink {
        commands: command_rx,
        replies: reply_tx,
        wake: wake.clone(),
        stale_fallback: cfg.serve.stale_fallback.activity(),
    });
    let state_dir = dump_dir(cfg);
    let setup = hub::HubSetup {
        listener,
        wake,
        records,
        commands,
        replies,
        stop,
        policy,
        serve: cfg.serve.clone(),
        device: opts.device.name().to_string(),
        serial: pipeline.servo.device_serial(),
        rate_hz: cfg.device.rate_hz,
        period_ns: (1e9 / cfg.device.rate_hz).round() as u64,
        schema: pipeline.schema,
        geometry: cfg.geometry,
        identifier_cfg: pipeline.identifier.config().clone(),
        identifier: pipeline.identifier.clone(),
        controller: opts.controller,
        weights_label: pipeline.weights_label.clone(),
        seed: cfg.sim.seed,
        state_dir,
        realtime: pipeline.realtime_taken.clone(),
    };
    Ok(Prepared {
        pipeline,
        hub: setup,
        socket: socket_path,
        _device_lock: device_lock,
        _socket_lock: socket_lock,
    })
}

/// Who may read and who may command (`[serve] read_group`, `control_group`).
fn policy(cfg: &Config) -> Result<Policy, RunError> {
    Ok(Policy {
        // SAFETY: geteuid has no arguments and cannot fail.
        own_uid: unsafe { libc::geteuid() },
        read_group: group("serve.read_group", &cfg.serve.read_group)?,
        control_group: group("serve.control_group", &cfg.serve.control_group)?,
    })
}

/// `--socket`, else `[serve] socket`, else the device's default socket.
fn socket_path(opts: &ServeOptions, cfg: &Config) -> PathBuf {
    opts.socket
        .clone()
        .or_else(|| (!cfg.serve.socket.is_empty()).then(|| PathBuf::from(&cfg.serve.socket)))
        .unwrap_or_else(|| default_socket(opts.device.name()))
}

/// Where fault dumps go: `[serve] dump_dir`, else the state directory (else the temporary
/// directory).
fn dump_dir(cfg: &Config) -> PathBuf {
    if cfg.serve.dump_dir.is_empty() {
        crate::servo::thermal_store::state_dir().unwrap_or_else(std::env::temp_dir)
    } else {
        PathBuf::from(&cfg.serve.dump_dir)
    }
}

/// Run the daemon until SIGINT/SIGTERM (`stop`), a client's shutdown, or a device fault.
pub fn serve(
    opts: &ServeOptions,
    cfg: &Config,
    stop: Arc<AtomicBool>,
) -> Result<ServeOutcome, RunError> {
    let Prepared {
        pipeline,
        hub: setup,
        socket: socket_path,
        _device_lock,
        _socket_lock,
    } = prepare(opts, cfg, stop)?;
    crate::errln!(
        "omnid serve: {} on {} (amplifiers off until a client asks for a mode; `omnid ctl \
         --socket {} mode hold`)",
        opts.device.name(),
        socket_path.display(),
        socket_path.display()
    );
    for w in &pipeline.warnings {
        crate::errln!("omnid: warning: {w}");
    }
    let (handle, ending) = pipeline.spawn()?;
    let dump_dir = setup.state_dir.clone();
    let hub_report = serve_clients(setup, cfg.serve.hub_fifo_priority);
    let (report, realtime) = join_servo(handle)?;
    ending.save_heat(&report);
    let mut summary = crate::servo::summary::RunSummary::from_results(
        &crate::servo::summary::SummaryLabels {
            device: opts.device.name(),
            // The law the daemon started with (clients may have switched since).
            controller: opts.controller.as_str(),
            trajectory: "serve".into(),
            weights: ending.weights_label.clone(),
            seed: cfg.sim.seed,
            fast: false,
        },
        &report.stats,
        &report.timing,
        crate::servo::summary::IdentifierState {
            adapt: report
                .identifier
                .as_ref()
                .is_some_and(|id| id.config().adapt),
            fault: report.identifier.as_ref().and_then(|id| id.fault()),
        },
        report.telemetry_dropped,
        report.missed_packets,
    );
    summary.end = report.end.as_str().to_string();
    summary.faults = hub_report.faults.clone();
    summary.faults.extend(report.faults.iter().cloned());
    summary.realtime = realtime;
    let mut dumps = hub_report.dumps;
    if matches!(report.end, EndReason::DeviceFault(_)) {
        dumps.extend(hub::write_fault_dump(
            &dump_dir,
            &ending.schema,
            &hub_report.ring,
            "device",
        ));
    }
    // The clients' connections close only now, after the final safe packet went out.
    drop(hub_report.clients);
    Ok(ServeOutcome {
        summary,
        end: report.end,
        shutdown_requested: hub_report.shutdown_requested,
        shutdown_error: report.shutdown_error,
        dumps,
        recording_error: hub_report.recording_error,
        socket: socket_path,
    })
}

/// Run the hub on this thread until the servo ends, at the configured realtime priority (the
/// hub is on every stream client's round trip) and back on the normal scheduler afterwards.
fn serve_clients(setup: hub::HubSetup, fifo_priority: i32) -> hub::HubReport {
    if fifo_priority > 0 {
        if let Err(w) = crate::servo::realtime::set_fifo_priority(fifo_priority) {
            crate::errln!("omnid: warning: the client hub: {w}");
        }
    }
    let report = hub::Hub::new(setup).run();
    if fifo_priority > 0 {
        let _ = crate::servo::realtime::set_fifo_priority(0);
    }
    report
}
