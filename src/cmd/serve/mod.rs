//! `omnid serve`: the daemon that lab software connects to (docs/PROTOCOL.md). It serves
//! every arm it is given — the devices on its command line, else the config's `[[arm]]`s,
//! else one simulated arm — each as its own unit: the pipeline `omnid run` assembles
//! (`pipeline`), started idle and fed through its station's mailbox, its own socket
//! (`<name>.sock`), lease, safety, heat and fault dumps, and its own threads. One arm's fault
//! ends that arm only, unless `[serve] fail_together` says the arms stop together.

use crate::arm::ArmIdentity;
use crate::cmd::assembly::{assemble, join_servo, Ending, ServoThreadResult};
use crate::cmd::run::{check_device_options, DeviceSpec, RunError, RunOptions};
use crate::config::ArmSpec;
use crate::config::Config;
use crate::servo::{ArmSignals, EndReason, ServoLink, Wake};
use crate::station::{StationLimits, StationSetup};
use crate::transport::access::Policy;
use crate::transport::default_socket;
use crate::transport::host::{Host, HostReport};
use crate::transport::socket::{self, Listener, SocketLock};
use crate::transport::unix::{SocketPort, SocketSetup};
use crate::transport::zenoh::port::ZenohPort;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

mod descriptors;

/// `omnid serve`'s options (the rest comes from the config).
#[derive(Debug, Clone)]
pub struct ServeOptions {
    /// The devices to serve, one arm each (`--device`, repeatable); empty: the config's
    /// `[[arm]]`s, else one simulated arm.
    pub devices: Vec<DeviceSpec>,
    /// Configured arms to serve by name (`--arm`, repeatable; a name that no `[[arm]]` has but
    /// that is a device kind, such as `firewire`, is that device's one arm); empty: see
    /// `devices`.
    pub arms: Vec<String>,
    /// The controller the daemon starts with (clients may switch).
    pub controller: crate::control::ControllerKind,
    /// Socket path (one arm only; None: `serve.socket`, else the default for the arm).
    pub socket: Option<PathBuf>,
    /// Identifier weights to start from (None: the shipped ones).
    pub weights: Option<PathBuf>,
    /// Keep the identifier's weights fixed (`--no-adapt`).
    pub no_adapt: bool,
    /// Skip malformed rows of a replayed log instead of failing (`--lenient`).
    pub lenient: bool,
    /// Faults to inject (`--inject`).
    pub inject: Vec<crate::device::inject::Fault>,
    /// Serve the live view (Foxglove WebSocket) on this address (`--foxglove`).
    pub foxglove: Option<std::net::SocketAddr>,
    /// Serve the arms over zenoh (`--zenoh`; also `[zenoh] enabled`).
    pub zenoh: bool,
}

impl Default for ServeOptions {
    /// `omnid serve` with no flags: the config's arms (else one simulated arm), NNIDC, the
    /// shipped weights, no live view, no zenoh unless the config enables it.
    fn default() -> Self {
        ServeOptions {
            devices: Vec::new(),
            arms: Vec::new(),
            controller: crate::control::ControllerKind::Nnidc,
            socket: None,
            weights: None,
            no_adapt: false,
            lenient: false,
            inject: Vec::new(),
            foxglove: None,
            zenoh: false,
        }
    }
}

/// How one arm ended.
pub struct ArmOutcome {
    /// The arm's name.
    pub name: String,
    /// The arm's whole session's summary (as `omnid run`'s).
    pub summary: crate::servo::summary::RunSummary,
    /// Why its servo loop ended.
    pub end: EndReason,
    /// A device error while sending the final safe packet or closing, if any.
    pub shutdown_error: Option<String>,
    /// Fault dumps written during the session.
    pub dumps: Vec<PathBuf>,
    /// An error of the recording in progress at the end, if any.
    pub recording_error: Option<String>,
    /// The socket the arm was served on.
    pub socket: PathBuf,
}

/// How the daemon ended.
pub struct ServeOutcome {
    /// Each arm, in the order they were served.
    pub arms: Vec<ArmOutcome>,
    /// A client asked for the shutdown (`omnid ctl shutdown`).
    pub shutdown_requested: bool,
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

fn prepare_socket(path: &Path, policy: &Policy) -> Result<(Listener, SocketLock), RunError> {
    let bad = |what: String| RunError::BadInput(format!("socket {}: {what}", path.display()));
    // Refuse what can be refused before anything is created.
    if path.as_os_str().len() >= 108 {
        return Err(bad(format!(
            "the path is {} bytes; a Unix socket's path must be under 108",
            path.as_os_str().len()
        )));
    }
    if let Ok(m) = std::fs::symlink_metadata(path) {
        if !std::os::unix::fs::FileTypeExt::is_socket(&m.file_type()) {
            return Err(bad(
                "a file that is not a socket is in the way (not replaced)".into(),
            ));
        }
    }
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty());
    let (mode, gid) = socket_permissions(policy);
    // A directory this process creates goes when its last socket does (`SocketLock`); another
    // daemon's may go just as this one sees it, so a vanished directory is made again.
    let mut attempts = 3;
    loop {
        attempts -= 1;
        if let Some(dir) = dir.filter(|d| !d.is_dir()) {
            crate::transport::socket::create_socket_dir(dir).map_err(|e| {
                bad(format!(
                    "cannot create its directory: {e} (pass --socket PATH in a writable \
                     directory, or run as the systemd service, udev/omnid@.service)"
                ))
            })?;
        }
        let vanished = || attempts > 0 && dir.is_some_and(|d| !d.is_dir());
        let lock = match SocketLock::acquire(path) {
            Ok(lock) => lock,
            Err(_) if vanished() => continue,
            Err(e) => {
                if let Some(d) = dir {
                    crate::transport::socket::remove_created_dirs(d);
                }
                return Err(bad(e));
            }
        };
        match Listener::bind(path, gid, mode) {
            Ok(listener) => return Ok((listener, lock)),
            Err(_) if vanished() => continue,
            // The lock, dropped, removes a directory made for nothing.
            Err(e) => return Err(bad(e.to_string())),
        }
    }
}

/// The socket file's mode and group. With one group configured, the socket belongs to it
/// (0660), so its members can connect. With both a read and a control group (and they
/// differ), no one group can hold the file, so it is open to connect (0666) and admission
/// rests on the peer's credentials alone (`access::Policy::decide`): everyone else is
/// answered with the reason and closed.
pub(crate) fn socket_permissions(policy: &Policy) -> (libc::mode_t, Option<u32>) {
    match (&policy.read_group, &policy.control_group) {
        (Some((_, r)), Some((_, c))) if r != c => (0o666, None),
        (Some((_, g)), _) | (None, Some((_, g))) => (0o660, Some(*g)),
        (None, None) => (0o660, None),
    }
}

/// An arm ready to start: its servo pipeline (started in idle, taking commands), its
/// station's setup and its socket, bound and locked.
pub struct Prepared {
    /// The servo loop, attached to the station's mailbox.
    pub pipeline: crate::cmd::assembly::Pipeline,
    /// What [`Host::new`] takes.
    pub station: StationSetup,
    /// The socket's port ([`SocketPort::new`]).
    pub socket: SocketSetup,
    name: String,
    socket_path: PathBuf,
    _socket_lock: SocketLock,
}

/// The arms to serve: the command line's devices, else the config's `[[arm]]`s, else the
/// simulator.
pub fn arms(opts: &ServeOptions, cfg: &Config) -> Result<Vec<ArmSpec>, RunError> {
    let arms = if !opts.arms.is_empty() {
        if !opts.devices.is_empty() {
            return Err(RunError::BadInput(
                "--arm and --device both choose what to serve: give one of them".into(),
            ));
        }
        let mut arms = Vec::new();
        for name in &opts.arms {
            let arm = match (cfg.arm_named(name), name.parse::<DeviceSpec>()) {
                (Ok(arm), _) => arm,
                (Err(_), Ok(device)) if !matches!(device, DeviceSpec::Replay(_)) => {
                    ArmSpec::single(device, cfg)
                }
                (Err(e), _) => return Err(RunError::BadInput(format!("--arm: {e}"))),
            };
            arms.push(arm);
        }
        arms
    } else if !opts.devices.is_empty() {
        ArmSpec::from_devices(&opts.devices, cfg)
    } else {
        let configured = cfg.arms().map_err(|e| RunError::BadInput(e.to_string()))?;
        if configured.is_empty() {
            vec![ArmSpec::single(DeviceSpec::Sim, cfg)]
        } else {
            configured
        }
    };
    if arms.len() > 1 && (opts.socket.is_some() || !cfg.serve.socket.is_empty()) {
        return Err(RunError::BadInput(format!(
            "--socket (or serve.socket) names one socket, but {} arms are served: each gets \
             <runtime dir>/<name>.sock, or its [[arm]] `socket`",
            arms.len()
        )));
    }
    Ok(arms)
}

/// Check the options, lock the arm and its socket, bind it, and assemble the pipeline
/// (`pipeline::assemble`, the same path as `omnid run`) attached to a new station. The
/// first arm of [`arms`] (the whole daemon when it serves one).
pub fn prepare(
    opts: &ServeOptions,
    cfg: &Config,
    stop: Arc<AtomicBool>,
) -> Result<Prepared, RunError> {
    let arm = arms(opts, cfg)?.remove(0);
    prepare_arm(&arm, opts, cfg, stop)
}

/// [`prepare`] for one arm.
pub fn prepare_arm(
    arm: &ArmSpec,
    opts: &ServeOptions,
    global: &Config,
    stop: Arc<AtomicBool>,
) -> Result<Prepared, RunError> {
    let cfg = &arm.config;
    let run_opts = RunOptions {
        device: arm.device.clone(),
        controller: opts.controller,
        duration_s: f64::INFINITY,
        lenient: opts.lenient,
        inject: opts.inject.clone(),
        weights: opts.weights.clone(),
        no_adapt: opts.no_adapt,
        arm: Some(arm.name.clone()),
        arm_configured: !global.arm.is_empty(),
        ..RunOptions::default()
    };
    let faults = check_device_options(&run_opts, cfg)?;
    let policy = policy(global)?;
    let socket_path = socket_path(arm, opts, global);
    let (listener, socket_lock) = prepare_socket(&socket_path, &policy)?;

    let wake = Arc::new(Wake::new().map_err(|e| RunError::Internal(format!("eventfd: {e}")))?);
    let signals = Arc::new(ArmSignals::new(global.serve.stale_fallback.activity()));
    let (tx, records) = crossbeam_channel::bounded(cfg.telemetry.channel_capacity);
    let (commands, command_rx) = crate::handoff::queue(256);
    let (reply_tx, replies) = crate::handoff::queue(64);
    let mut pipeline = assemble(&run_opts, cfg, &faults, tx, stop.clone())?;
    pipeline.weights_store = keep_weights(&run_opts, cfg, &arm.name, &mut pipeline);
    pipeline.servo.attach(ServoLink {
        commands: command_rx,
        replies: reply_tx,
        wake: wake.clone(),
        signals: signals.clone(),
    });
    let station = StationSetup {
        arm: ArmIdentity {
            name: arm.name.clone(),
            kind: arm.device.name(),
            serial: pipeline.servo.device_serial(),
            aliases: arm.aliases.clone(),
        },
        wake,
        records,
        commands,
        replies,
        signals,
        stop,
        limits: StationLimits {
            stream_ttl_ms: global.serve.stream_ttl_ms,
            stale_fallback: global.serve.stale_fallback.activity(),
            ring_s: global.serve.ring_s,
            dump_interval_s: global.serve.dump_interval_s,
            max_dumps: global.serve.max_dumps,
            log_format: global.serve.log_format,
        },
        rate_hz: cfg.device.rate_hz,
        period_ns: (1e9 / cfg.device.rate_hz).round() as u64,
        schema: pipeline.schema,
        geometry: cfg.geometry,
        identifier_cfg: pipeline.identifier.config().clone(),
        identifier: pipeline.identifier.clone(),
        controller: opts.controller,
        weights_label: pipeline.weights_label.clone(),
        seed: cfg.sim.seed,
        weights_store: pipeline.weights_store.clone(),
        weights_every_s: WEIGHTS_EVERY_S,
        state_dir: dump_dir(global),
        realtime: pipeline.realtime_taken.clone(),
        teleop: global.teleop.clone(),
        // This arm alone; `serve` joins the daemon's arms at one rendezvous.
        rendezvous: crate::teleop::Rendezvous::new(vec![arm.name.clone()]),
    };
    Ok(Prepared {
        pipeline,
        station,
        socket: SocketSetup {
            listener,
            policy,
            serve: global.serve.clone(),
        },
        name: arm.name.clone(),
        socket_path,
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

/// `--socket`, else the arm's `socket`, else `[serve] socket`, else the arm's default socket.
fn socket_path(arm: &ArmSpec, opts: &ServeOptions, cfg: &Config) -> PathBuf {
    opts.socket
        .clone()
        .or_else(|| arm.socket.clone())
        .or_else(|| (!cfg.serve.socket.is_empty()).then(|| PathBuf::from(&cfg.serve.socket)))
        .unwrap_or_else(|| default_socket(&arm.name))
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

/// Run the daemon until SIGINT/SIGTERM (`stop`), a client's shutdown, or the end of every arm.
pub fn serve(
    opts: &ServeOptions,
    cfg: &Config,
    stop: Arc<AtomicBool>,
) -> Result<ServeOutcome, RunError> {
    let arms = arms(opts, cfg)?;
    descriptor_budget(opts, cfg, arms.len() as u64);
    // Every arm ready before any starts: a daemon that cannot serve one serves none.
    let mut prepared = Vec::with_capacity(arms.len());
    for arm in &arms {
        prepared.push(prepare_arm(arm, opts, cfg, stop.clone())?);
    }
    announce(&prepared);
    // The live view is up before any arm starts: a port that cannot be had serves nothing.
    let view = start_live_view(opts)?;
    // zenoh is up before any arm starts, like the live view.
    let net = start_zenoh(opts, cfg)?;
    // The pairs a `teleop` op can form: between this daemon's arms, and with zenoh up with
    // other daemons' arms.
    let mut rendezvous =
        crate::teleop::Rendezvous::new(arms.iter().map(|a| a.name.clone()).collect());
    if let Some(n) = &net {
        rendezvous = rendezvous.with_remote(n.teleop());
    }
    for p in &mut prepared {
        p.station.rendezvous = rendezvous.clone();
    }
    let several = prepared.len() > 1;
    let mut threads = Vec::new();
    for p in prepared {
        let Prepared {
            pipeline,
            station,
            socket,
            name,
            socket_path,
            _socket_lock,
        } = p;
        let (servo, ending) = pipeline.spawn()?;
        let dump_dir = station.state_dir.clone();
        let kind = station.arm.kind;
        let (priority, fail_together) = (cfg.serve.hub_fifo_priority, cfg.serve.fail_together);
        let stop = stop.clone();
        let seed = cfg.sim.seed;
        let controller = opts.controller;
        let tap = view.as_ref().map(|v| v.tap_for(&station, several));
        let zenoh = match &net {
            Some(n) => Some(
                n.arm(&station, &cfg.serve)
                    .map_err(|e| RunError::BadInput(e.to_string()))?,
            ),
            None => None,
        };
        let thread = std::thread::Builder::new()
            .name(format!("omnid-hub-{name}"))
            .spawn(move || {
                let report = serve_clients(station, socket, priority, tap, zenoh);
                let outcome = end_arm(
                    ArmEnd {
                        name,
                        kind,
                        socket: socket_path,
                        dump_dir,
                        seed,
                        controller,
                    },
                    report,
                    servo,
                    ending,
                );
                // The socket's lock goes with the arm.
                drop(_socket_lock);
                if fail_together
                    && matches!(
                        outcome.as_ref().map(|(o, _)| &o.end),
                        Ok(EndReason::DeviceFault(_) | EndReason::SafetyFault(_)) | Err(_)
                    )
                {
                    stop.store(true, Ordering::SeqCst);
                }
                outcome
            })
            .map_err(|e| RunError::Internal(format!("cannot start a host thread: {e}")))?;
        threads.push(thread);
    }
    join_arms(threads)
}

/// `omnid devices`: the configured arms, each with its kind, serial, aliases, socket and
/// whether a daemon serves it now (its socket answers a hello).
pub fn arms_table(cfg: &Config) -> Result<String, RunError> {
    let arms = cfg.arms().map_err(|e| RunError::BadInput(e.to_string()))?;
    if arms.is_empty() {
        return Ok(String::new());
    }
    let mut out = String::from("Configured arms ([[arm]]):\n");
    for arm in &arms {
        let socket = arm
            .socket
            .clone()
            .unwrap_or_else(|| default_socket(&arm.name));
        let served = match crate::transport::client::Client::connect(&socket, "omnid devices") {
            Ok(c) if c.hello().arm == arm.name => "served".to_string(),
            Ok(c) => format!("socket answers as arm `{}`", c.hello().arm),
            Err(_) => "not served".to_string(),
        };
        out.push_str(&format!(
            "  {:<16} {:<9} serial {:<12} {}{}  ({})\n",
            arm.name,
            arm.device.name(),
            arm.serial.as_deref().unwrap_or("any"),
            socket.display(),
            if arm.aliases.is_empty() {
                String::new()
            } else {
                format!("  aliases {}", arm.aliases.join(", "))
            },
            served
        ));
    }
    Ok(out)
}

/// What an arm's end needs besides its reports.
struct ArmEnd {
    name: String,
    kind: &'static str,
    socket: PathBuf,
    dump_dir: PathBuf,
    seed: u64,
    controller: crate::control::ControllerKind,
}

/// How often a daemon saves what its arms learned while it runs, s.
const WEIGHTS_EVERY_S: f64 = 60.0;

/// Where the arm's learned weights are kept (`[identifier] persist`, not with `--weights` or a
/// replay), and the identifier started from them when they are there and can be believed
/// (docs/IDENTIFIER.md): said in one line, as is a file refused.
fn keep_weights(
    opts: &RunOptions,
    cfg: &crate::config::Config,
    arm: &str,
    pipeline: &mut crate::cmd::assembly::Pipeline,
) -> Option<(PathBuf, String, Option<String>)> {
    use crate::identifier::store;
    let replay = matches!(opts.device, crate::device::registry::DeviceSpec::Replay(_));
    if !cfg.identifier.persist || opts.weights.is_some() || replay {
        return None;
    }
    let path = store::weights_file(&crate::servo::thermal_store::state_dir()?, arm);
    let serial = start_from_kept(&path, opts.no_adapt, cfg, arm, pipeline);
    Some((path, arm.to_string(), serial))
}

/// Start the arm's identifier from the weights kept at `path` when they can be believed (said
/// in a line, as is a file refused); the device's serial.
fn start_from_kept(
    path: &Path,
    no_adapt: bool,
    cfg: &crate::config::Config,
    arm: &str,
    pipeline: &mut crate::cmd::assembly::Pipeline,
) -> Option<String> {
    use crate::identifier::store::{self, Loaded};
    // A save killed mid-write left its file whole and a temporary beside it: the litter goes.
    if let Some(dir) = path.parent() {
        let n = crate::output::remove_orphan_temporaries(dir);
        if n > 0 {
            crate::errln!(
                "omnid: arm {arm}: removed {n} temporary file(s) an interrupted save left in {}",
                dir.display()
            );
        }
    }
    let serial = pipeline.servo.device_serial();
    match store::load(path, &cfg.identifier, serial.as_deref()) {
        Loaded::None => {}
        Loaded::Weights(mut id, line) => {
            crate::errln!("omnid: arm {arm}: {line}");
            id.set_adapt(!no_adapt && cfg.identifier.adapt);
            pipeline.servo.set_identifier(*id);
        }
        Loaded::Refused(why) => crate::errln!(
            "omnid: warning: arm {arm}: the learned weights are not used: {why}; the identifier \
             starts from the {} weights",
            pipeline.weights_label
        ),
    }
    serial
}

/// The arm's servo has ended (the host saw its records stop): join it, keep its heat, dump on a
/// device fault, and sum up. Also whether a client asked for the shutdown.
fn end_arm(
    a: ArmEnd,
    mut host_report: HostReport,
    servo: std::thread::JoinHandle<ServoThreadResult>,
    ending: Ending,
) -> Result<(ArmOutcome, bool), RunError> {
    let (report, realtime) = join_servo(servo)?;
    ending.save_heat(&report);
    ending.save_weights(&report);
    let mut summary = crate::servo::summary::RunSummary::from_results(
        &crate::servo::summary::SummaryLabels {
            device: a.kind,
            // The law the daemon started with (clients may have switched since).
            controller: a.controller.as_str(),
            trajectory: "serve".into(),
            weights: ending.weights_label.clone(),
            seed: a.seed,
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
    let station = &mut host_report.station;
    summary.faults = station.faults.clone();
    summary.faults.extend(report.faults.iter().cloned());
    summary.realtime = realtime;
    if matches!(report.end, EndReason::DeviceFault(_)) {
        station.dump_device_fault(&a.dump_dir, &a.name);
    }
    let shutdown = station.shutdown_requested;
    let outcome = ArmOutcome {
        name: a.name,
        summary,
        end: report.end,
        shutdown_error: report.shutdown_error,
        dumps: std::mem::take(&mut station.dumps),
        recording_error: station.recording_error.take(),
        socket: a.socket,
    };
    // The clients' connections close only now, after the final safe packet went out.
    drop(host_report);
    Ok((outcome, shutdown))
}

/// Wait for every arm's host thread: the arms' outcomes, or the first error when no arm has
/// one (an error beside arms that ended is said, and their outcomes kept).
fn join_arms(
    threads: Vec<std::thread::JoinHandle<Result<(ArmOutcome, bool), RunError>>>,
) -> Result<ServeOutcome, RunError> {
    let mut outcome = ServeOutcome {
        arms: Vec::new(),
        shutdown_requested: false,
    };
    let mut first_error = None;
    for t in threads {
        match t.join() {
            Ok(Ok((arm, shutdown))) => {
                outcome.shutdown_requested |= shutdown;
                outcome.arms.push(arm);
            }
            Ok(Err(e)) => {
                first_error.get_or_insert(e);
            }
            Err(_) => {
                first_error.get_or_insert(RunError::Internal("a host thread panicked".into()));
            }
        }
    }
    match first_error {
        Some(e) if outcome.arms.is_empty() => Err(e),
        Some(e) => {
            crate::errln!("omnid serve: {e}");
            Ok(outcome)
        }
        None => Ok(outcome),
    }
}
/// Descriptors first: the ports are capped below the limit, and the rest is the Unix socket's
/// reserve (docs/ZENOH.md, "Ports and descriptors"); a budget past the limit is said.
fn descriptor_budget(opts: &ServeOptions, cfg: &Config, arms: u64) {
    let (_, limit) = descriptors::raise_limit();
    let zenoh_on = opts.zenoh || cfg.zenoh.enabled;
    let budget = descriptors::Budget {
        socket_clients: arms * (cfg.serve.max_clients as u64 + 8 + 32),
        zenoh: if zenoh_on { cfg.zenoh.descriptors() } else { 0 },
        live_view: if opts.foxglove.is_some() {
            3 * crate::transport::foxglove::MAX_CONNECTIONS as u64
        } else {
            0
        },
        arms,
    };
    if let Some(w) = budget.warning(limit) {
        crate::errln!("omnid: warning: {w}");
    }
}

/// Say where each arm is served, the shortest `omnid ctl` line that reaches it, and its
/// warnings.
fn announce(prepared: &[Prepared]) {
    let default_dirs = crate::transport::default_socket_dirs();
    for p in prepared {
        // The shortest `omnid ctl` line that reaches this arm.
        let in_default_dir = p
            .socket_path
            .parent()
            .is_some_and(|d| default_dirs.iter().any(|dd| dd == d));
        let ctl = match (in_default_dir, prepared.len()) {
            (true, 1) => "omnid ctl mode hold".to_string(),
            (true, _) => format!("omnid ctl --arm {} mode hold", p.name),
            (false, _) => format!("omnid ctl --socket {} mode hold", p.socket_path.display()),
        };
        crate::errln!(
            "omnid serve: arm `{}` ({}) on {} (amplifiers off until a client asks for a mode; \
             `{ctl}`)",
            p.name,
            p.station.arm.kind,
            p.socket_path.display(),
        );
        for w in &p.pipeline.warnings {
            crate::errln!("omnid: warning: {}: {w}", p.name);
        }
    }
}

/// The live view (`--foxglove`), said where it is and who can reach it.
fn start_live_view(
    opts: &ServeOptions,
) -> Result<Option<crate::transport::foxglove::LiveView>, RunError> {
    Ok(match opts.foxglove {
        Some(addr) => {
            let view = crate::transport::foxglove::LiveView::start(addr)
                .map_err(|e| RunError::BadInput(e.to_string()))?;
            crate::errln!(
                "omnid serve: live view on ws://{} (Foxglove, or Lichtblick 1.22.1 or later: open \
                 a connection, Foxglove WebSocket; layout in docs/omnid-layout.json)",
                view.addr()
            );
            if !view.addr().ip().is_loopback() {
                crate::errln!(
                    "omnid: warning: the live view on {} can be reached from other machines and \
                     asks no one who they are (it only sends; it takes no commands)",
                    view.addr()
                );
            }
            Some(view)
        }
        None => None,
    })
}

/// The daemon's zenoh session (`--zenoh`, `[zenoh] enabled`), said what it allows; or why a
/// `[zenoh]` section is ignored.
fn start_zenoh(
    opts: &ServeOptions,
    cfg: &Config,
) -> Result<Option<crate::transport::zenoh::ZenohNet>, RunError> {
    Ok(if opts.zenoh || cfg.zenoh.enabled {
        let net = crate::transport::zenoh::ZenohNet::start(&cfg.zenoh)
            .map_err(|e| RunError::BadInput(e.to_string()))?;
        crate::errln!(
            "omnid serve: zenoh session {} listening on {} (ROS 2 domain {}; {}; \
             docs/ZENOH.md)",
            net.zid(),
            net.listening().join(", "),
            cfg.zenoh.domain().unwrap_or(0),
            net.allows()
        );
        if cfg.zenoh.allow_commands
            && !net.exposure().reach.is_empty()
            && net.exposure().auth.is_none()
        {
            crate::errln!(
                "omnid: warning: [zenoh] insecure = true: anyone who reaches {} can command the \
                 arms (docs/ZENOH.md)",
                net.exposure().reach.join(", ")
            );
        }
        Some(net)
    } else {
        if let Some(w) = zenoh_ignored(&cfg.zenoh) {
            crate::errln!("omnid: warning: {w}");
        }
        None
    })
}

/// A `[zenoh]` section that says something while zenoh is off (no `enabled = true`, no
/// `--zenoh`) is ignored: say so, rather than leave a lab wondering why no one can reach the arm.
fn zenoh_ignored(z: &crate::transport::zenoh::ZenohConfig) -> Option<String> {
    (!z.enabled && *z != crate::transport::zenoh::ZenohConfig::default()).then(|| {
        "the config's [zenoh] section is ignored: zenoh is off (add `enabled = true` to \
         [zenoh], or pass --zenoh)"
            .to_string()
    })
}

/// Run the arm's host on this thread until the servo ends, at the configured realtime priority
/// (the host is on every stream client's round trip) and back on the normal scheduler
/// afterwards. Its ports: the socket, and zenoh when the daemon is on it.
fn serve_clients(
    station: StationSetup,
    socket: SocketSetup,
    fifo_priority: i32,
    tap: Option<Box<dyn crate::station::Tap>>,
    zenoh: Option<(
        Box<dyn crate::station::Tap>,
        crate::transport::zenoh::door::Door,
    )>,
) -> HostReport {
    if fifo_priority > 0 {
        if let Err(w) = crate::servo::realtime::set_fifo_priority(fifo_priority) {
            crate::errln!("omnid: warning: the arm's host thread: {w}");
        }
    }
    let hello_timeout_ms = socket.serve.hello_timeout_ms;
    let mut host = Host::new(station);
    host.add_port(Box::new(SocketPort::new(socket)));
    if let Some(tap) = tap {
        host.add_tap(tap);
    }
    if let Some((tap, door)) = zenoh {
        host.add_tap(tap);
        host.add_port(Box::new(ZenohPort::new(door, hello_timeout_ms)));
    }
    host.run()
}

#[cfg(test)]
mod station_tests;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_zenoh_section_left_off_is_said_to_be_ignored() {
        use crate::transport::zenoh::ZenohConfig;
        assert_eq!(zenoh_ignored(&ZenohConfig::default()), None);
        let said = ZenohConfig {
            allow_commands: true,
            ..ZenohConfig::default()
        };
        let w = zenoh_ignored(&said).expect("a section that says something, while off");
        assert!(w.contains("enabled = true") && w.contains("--zenoh"), "{w}");
        let on = ZenohConfig {
            enabled: true,
            ..said
        };
        assert_eq!(zenoh_ignored(&on), None);
    }

    #[test]
    fn with_both_groups_both_can_reach_the_socket() {
        let both = Policy {
            own_uid: 500,
            read_group: Some(("lab".into(), 20)),
            control_group: Some(("omnid".into(), 30)),
        };
        // No single group could own the file: it is open to connect, and the credentials
        // decide (a control member who is not in the read group is admitted to command).
        assert_eq!(socket_permissions(&both), (0o666, None));
        let member = crate::transport::socket::Peer {
            pid: 1,
            uid: 7,
            gid: 7,
            groups: vec![30],
        };
        assert_eq!(
            both.decide(&member),
            Ok(crate::transport::access::Access::Control)
        );
        let read_only = Policy {
            control_group: None,
            ..both.clone()
        };
        assert_eq!(socket_permissions(&read_only), (0o660, Some(20)));
        let control_only = Policy {
            read_group: None,
            ..both.clone()
        };
        assert_eq!(socket_permissions(&control_only), (0o660, Some(30)));
        assert_eq!(socket_permissions(&Policy::default()), (0o660, None));
    }
}
