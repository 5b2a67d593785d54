//! An arm's pipeline: the device open (from the registry), the controllers and the
//! identifier built, the motors' heat loaded under the arm's name; started on its own thread.
//! `omnid run` and `omnid serve` both assemble it here.

use crate::arm::ArmLock;
use crate::config::Config;
use crate::control::NanAfter;
use crate::control::Trajectory;
use crate::control::{ControllerKind, ControllerSet, Reference};
use crate::device::inject::{Fault, FaultyDevice};
use crate::device::registry::DeviceSpec;
use crate::device::registry::{self, OpenError, OpenOptions};
use crate::device::replay::ReplayError;
use crate::device::DeviceError;
use crate::identifier::Identifier;
use crate::servo::{Servo, ServoReport};
use crate::telemetry::reader::ReadError;
use crate::telemetry::{LogError, LogSchema};
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

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
    /// The arm's name (`--arm`, or a configured `[[arm]]`): keys its heat file and its lock.
    /// `None`: the device kind, as a one-arm set-up has always named it.
    pub arm: Option<String>,
    /// The arm is one the config names (`[[arm]]`): a simulated one is locked too, as real
    /// hardware always is, so a `run` cannot take an arm a `serve` has.
    pub arm_configured: bool,
}

impl RunOptions {
    /// The arm's name: `arm`, else the device kind.
    pub fn arm_name(&self) -> &str {
        self.arm.as_deref().unwrap_or(self.device.name())
    }
}

pub use crate::identifier::store::{SHIPPED_WEIGHTS, SHIPPED_WEIGHTS_NAME};

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
        None if controller == ControllerKind::Nnidc => Ok((
            crate::identifier::store::shipped(&id_cfg).map_err(RunError::BadInput)?,
            "shipped".to_string(),
        )),
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

impl From<OpenError> for RunError {
    fn from(e: OpenError) -> Self {
        match e {
            OpenError::BadInput(m) => RunError::BadInput(m),
            OpenError::Device(d) => RunError::Device(d),
            OpenError::Replay(r) => RunError::Replay(r),
        }
    }
}

/// A servo loop ready to start: the device open, the controllers and the identifier built,
/// the motors' heat loaded. `run` and `serve` both assemble it here.
pub struct Pipeline {
    /// The loop, ready to run.
    pub servo: Servo,
    /// The log columns this device feeds.
    pub schema: LogSchema,
    /// Where the identifier's weights came from (`shipped`, `fresh` or a path).
    pub weights_label: String,
    /// The identifier as it started (its shape; `serve` copies live weights into clones).
    pub identifier: Identifier,
    /// Where motor heat is carried over between runs (none for replays).
    pub heat_path: Option<PathBuf>,
    /// Things the operator should know that do not stop the run.
    pub warnings: Vec<String>,
    /// Realtime steps to take on the servo thread (paced runs only).
    pub realtime: Option<crate::servo::realtime::RealtimeConfig>,
    /// Which realtime steps took effect, once the servo thread has taken them (before its
    /// first tick): for a daemon's status while it runs.
    pub realtime_taken: Arc<std::sync::OnceLock<crate::servo::realtime::RealtimeReport>>,
    /// The arm's lock, held until the loop has sent its final safe packet.
    pub lock: Option<ArmLock>,
    /// `omnid serve`: where the arm's learned weights are kept, its name and serial.
    pub weights_store: Option<(PathBuf, String, Option<String>)>,
}

/// Build the pipeline for `opts` with `faults` (from `run::check_options`); telemetry leaves
/// through `telemetry`, `stop` ends the loop.
pub fn assemble(
    opts: &RunOptions,
    cfg: &Config,
    faults: &[Fault],
    telemetry: crossbeam_channel::Sender<crate::telemetry::record::TickRecord>,
    stop: Arc<AtomicBool>,
) -> Result<Pipeline, RunError> {
    let replay = matches!(opts.device, DeviceSpec::Replay(_));
    // One process per arm: real hardware always, a configured arm by name too.
    // Real hardware is locked host-wide; a simulated or replayed arm per user, so two users'
    // `sim` (or configured `left`) do not collide (docs/ARCHITECTURE.md, `arm`).
    let real = matches!(opts.device, DeviceSpec::Usb | DeviceSpec::Firewire);
    let lock = if real {
        Some(ArmLock::acquire(opts.arm_name()).map_err(RunError::BadInput)?)
    } else if opts.arm_configured {
        Some(ArmLock::acquire_simulated(opts.arm_name()).map_err(RunError::BadInput)?)
    } else {
        None
    };
    let (controllers, identifier, weights_label) = laws(opts, cfg, faults, &stop)?;
    let mut warnings = Vec::new();
    let how = OpenOptions {
        paced: !opts.fast,
        lenient: opts.lenient,
        duration_s: opts.duration_s.is_finite().then_some(opts.duration_s),
        stop: &stop,
    };
    let mut device = registry::open(&opts.device, cfg, how, &mut warnings)?;
    if !faults.is_empty() {
        device = Box::new(FaultyDevice::new(
            device,
            faults,
            cfg.sim.seed,
            stop.clone(),
        ));
    }
    let schema = LogSchema::new(device.plant_model().is_some());
    let reference = Reference::new(opts.trajectory, &cfg.reference, cfg.sim.seed);
    // A replay limits itself in device time (its rows need not come at rate_hz).
    let max_ticks = (!replay && opts.duration_s.is_finite())
        .then(|| (opts.duration_s * cfg.device.rate_hz).round() as u64);
    let heat_path = heat_path(opts, cfg, crate::servo::thermal_store::state_dir());
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
        lock,
        weights_store: None,
    })
}

/// Where the motors' heat of the arm `opts` runs persists in `state_dir`: one file per arm
/// name, so that two arms of one kind (two FireWire Omnis) never share one. A replay drives no
/// motors: it neither inherits nor leaves heat (and stays reproducible).
pub(crate) fn heat_path(
    opts: &RunOptions,
    cfg: &Config,
    state_dir: Option<PathBuf>,
) -> Option<PathBuf> {
    let replay = matches!(opts.device, DeviceSpec::Replay(_));
    (cfg.safety.persist_heat && !replay)
        .then_some(state_dir)
        .flatten()
        .map(|d| crate::servo::thermal_store::heat_file(&d, opts.arm_name()))
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
    // Said once per command: an experiment assembles many pipelines.
    static TOLD: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
    if weights_label == "shipped" && !TOLD.swap(true, std::sync::atomic::Ordering::Relaxed) {
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

/// The motors' heat left by the last run on this arm (at the thermal limit, with a warning, if
/// the file cannot be believed).
fn load_heat(path: &std::path::Path, cfg: &Config) -> [f64; 3] {
    let (heat, note) = crate::servo::thermal_store::load(path, &cfg.safety);
    if let Some(note) = note {
        crate::errln!("omnid: warning: {note}");
    }
    heat
}

/// The servo thread's result: the loop's report and which realtime steps took effect.
pub type ServoThreadResult = (ServoReport, Option<crate::servo::realtime::RealtimeReport>);

impl Pipeline {
    /// Start the loop on its own thread (realtime steps taken there, before the first tick).
    /// Returns what the caller keeps: the thread and the bookkeeping for the end.
    pub fn spawn(self) -> Result<(std::thread::JoinHandle<ServoThreadResult>, Ending), RunError> {
        let Pipeline {
            mut servo,
            schema: _,
            weights_label,
            identifier: _,
            heat_path,
            warnings,
            realtime,
            realtime_taken,
            lock,
            weights_store,
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
                let report = servo.finish(end);
                drop(lock);
                (report, realtime)
            })
            .map_err(|e| RunError::Internal(format!("cannot start the servo thread: {e}")))?;
        Ok((
            handle,
            Ending {
                weights_label,
                heat_path,
                warnings,
                weights_store,
            },
        ))
    }
}

/// What is needed once the loop has ended.
pub struct Ending {
    /// The weights the identifier started from, as the summary names them.
    pub weights_label: String,
    /// Where the motor heat is kept between runs (none: not kept).
    pub heat_path: Option<PathBuf>,
    /// Lines to say once the run has ended (what was refused or replaced at start).
    pub warnings: Vec<String>,
    /// `omnid serve`: where the arm's learned weights are kept, its name and serial.
    pub weights_store: Option<(PathBuf, String, Option<String>)>,
}

impl Ending {
    /// Keep what the arm learned for the next daemon (a healthy identifier only: one stopped
    /// on a non-finite value keeps the file as it was).
    pub fn save_weights(&self, report: &ServoReport) {
        let (Some((path, arm, serial)), Some(id)) = (&self.weights_store, &report.identifier)
        else {
            return;
        };
        if !id.healthy() {
            crate::errln!(
                "omnid: the identifier stopped on a non-finite value: its weights are not kept \
                 ({} keeps the last saved)",
                path.display()
            );
            return;
        }
        match crate::identifier::store::save(path, id, arm, serial.as_deref()) {
            Ok(()) => crate::errln!(
                "omnid: arm {arm}: learned weights kept in {}",
                path.display()
            ),
            Err(e) => crate::errln!("omnid: warning: arm {arm}: learned weights not kept: {e}"),
        }
    }

    /// Keep the motors' heat for the next run and warn about motors that ran hot.
    pub fn save_heat(&self, report: &ServoReport) {
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

/// Join the servo thread.
pub fn join_servo(
    handle: std::thread::JoinHandle<ServoThreadResult>,
) -> Result<ServoThreadResult, RunError> {
    handle
        .join()
        .map_err(|_| RunError::Internal("the servo thread panicked".into()))
}
