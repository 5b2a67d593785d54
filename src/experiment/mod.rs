//! `omnid experiment`: the paper's experiments in one command each, on the simulated Omni
//! (`--fast` runs through [`crate::cmd::run::execute`], fixed seeds), each writing `report.md`
//! with its tables and figures into an output directory.
//!
//! - [`Experiment::Validation`] (Figs. 8–12): pre-tune the networks on PD multisine logs, then
//!   PD, computed torque and NNIDC (those weights, adapting) on the same sine.
//! - [`Experiment::Alpha`] (Figs. 5–6): the α sweep of the adaptation law on one log.
//! - [`Experiment::Payload`]: a tip payload added mid-run; NNIDC adapting, frozen, and CT.
//! - [`Experiment::Workspace`]: NNIDC and the oracle on the sine about five centres spread over
//!   the workspace, NNIDC's ratio to the oracle per joint and centre.
//!
//! `--quick` shortens every run and the pre-tuning so the whole experiment takes seconds (for
//! tests and smoke checks); its numbers are not the paper's.

mod haptics;
pub mod teleop;
pub mod workspace;

use crate::cmd::assembly::{SHIPPED_WEIGHTS, SHIPPED_WEIGHTS_NAME};
use crate::cmd::identify::{identify, samples_from_log, IdentifyError, States};
use crate::cmd::run::{execute, oracle_tracking, RunError, RunOptions};
use crate::config::Config;
use crate::control::{ControllerKind, Trajectory};
use crate::identifier::{Identifier, PretuneConfig, PretuneReport, Progress, Sample, WeightsFile};
use crate::output::OutputError;
use crate::plot::figures::{Role, FIGURES};
use crate::plot::render::{self, Figure, Line, Panel, FORMATS};
use crate::plot::{plot_log, PlotError};
use crate::servo::summary::RunSummary;
use crate::telemetry::reader::ColumnReader;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// Which experiment to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Experiment {
    /// PD, computed torque and NNIDC on the sine, after pre-tuning (`validation`).
    Validation,
    /// The adaptation law's α sweep on one PD multisine log (`alpha`).
    Alpha,
    /// A tip payload added mid-run: adapting NNIDC, frozen NNIDC and CT (`payload`).
    Payload,
    /// NNIDC and the oracle on the sine about five centres over the workspace (`workspace`).
    Workspace,
    /// Haptics: transparency, walls, force accuracy (`haptics`).
    Haptics,
    /// Teleoperation between two simulated Omnis: architectures, passivity, delay and loss
    /// (`teleop`).
    Teleop,
}

impl FromStr for Experiment {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "validation" => Ok(Experiment::Validation),
            "alpha" => Ok(Experiment::Alpha),
            "payload" => Ok(Experiment::Payload),
            "workspace" => Ok(Experiment::Workspace),
            "haptics" => Ok(Experiment::Haptics),
            "teleop" => Ok(Experiment::Teleop),
            _ => Err(format!(
                "unknown experiment `{}`: expected one of {}",
                crate::text::cut(s),
                Experiment::ALL.map(Experiment::as_str).join(", ")
            )),
        }
    }
}

impl Experiment {
    /// Every experiment, in the order help and docs list them (the one source of that list).
    pub const ALL: [Experiment; 6] = [
        Experiment::Validation,
        Experiment::Alpha,
        Experiment::Payload,
        Experiment::Workspace,
        Experiment::Haptics,
        Experiment::Teleop,
    ];

    /// The name the command line takes.
    pub fn as_str(self) -> &'static str {
        match self {
            Experiment::Validation => "validation",
            Experiment::Alpha => "alpha",
            Experiment::Payload => "payload",
            Experiment::Workspace => "workspace",
            Experiment::Haptics => "haptics",
            Experiment::Teleop => "teleop",
        }
    }
}

/// Why an experiment failed.
#[derive(Debug, Error)]
pub enum ExperimentError {
    /// The output directory cannot be used (the user's input is at fault).
    #[error("--out: output directory: {0}")]
    OutDir(OutputError),
    /// A file or directory the experiment writes cannot be written there (checked first).
    #[error("--out: {0}")]
    Output(#[from] OutputError),
    /// One of the simulator runs could not be started or ended in an error.
    #[error("run `{name}`: {source}")]
    Run {
        /// The run, as the report names it.
        name: String,
        /// Why.
        source: Box<RunError>,
    },
    /// A run ended, but with a fault.
    #[error("run `{name}` did not complete cleanly: {why}")]
    RunFailed {
        /// The run, as the report names it.
        name: String,
        /// The first fault: class, time and message.
        why: String,
    },
    /// Pre-tuning failed.
    #[error(transparent)]
    Identify(Box<IdentifyError>),
    /// A figure could not be drawn.
    #[error(transparent)]
    Plot(Box<PlotError>),
    /// A report or figure file could not be written.
    #[error("writing {}: {source}", path.display())]
    Write {
        /// The file or directory.
        path: PathBuf,
        /// What the operating system said.
        source: std::io::Error,
    },
    /// A run's log could not be read back.
    #[error("reading {}: {why}", path.display())]
    ReadLog {
        /// The log.
        path: PathBuf,
        /// The reader's message (line, column, field).
        why: String,
    },
    /// Something the experiment relies on did not hold (a bug, not the user's input).
    #[error("{0}")]
    Internal(String),
}

impl From<IdentifyError> for ExperimentError {
    fn from(e: IdentifyError) -> Self {
        ExperimentError::Identify(Box::new(e))
    }
}

impl From<PlotError> for ExperimentError {
    fn from(e: PlotError) -> Self {
        ExperimentError::Plot(Box::new(e))
    }
}

impl ExperimentError {
    /// The user's input is at fault (exit code 2), not the program.
    pub fn is_bad_input(&self) -> bool {
        matches!(
            self,
            ExperimentError::OutDir(_) | ExperimentError::Output(_)
        )
    }
}

/// What an experiment wrote.
#[derive(Debug, Clone)]
pub struct ExperimentReport {
    /// `DIR/report.md`.
    pub report: PathBuf,
    /// Every figure file written (PNG and SVG).
    pub figures: Vec<PathBuf>,
    /// The report's text.
    pub markdown: String,
}

/// Run `experiment` into `out` (created if needed).
pub fn run_experiment(
    experiment: Experiment,
    out: &Path,
    quick: bool,
) -> Result<ExperimentReport, ExperimentError> {
    check_outputs(experiment, out, quick)?;
    let mut figures = Vec::new();
    let markdown = match experiment {
        Experiment::Validation => validation(out, quick, &mut figures)?,
        Experiment::Alpha => alpha(out, quick, &mut figures)?,
        Experiment::Payload => payload(out, quick, &mut figures)?,
        // These write their own report and results.json.
        Experiment::Workspace => return workspace::run_workspace(out, quick),
        Experiment::Haptics => return haptics::run_haptics(out, quick),
        Experiment::Teleop => return teleop::run_teleop(out, quick),
    };
    let report = out.join("report.md");
    crate::output::write_bytes(&report, markdown.as_bytes())?;
    Ok(ExperimentReport {
        report,
        figures,
        markdown,
    })
}

/// Every directory and file `experiment` writes in `out`, checked before its first run: an
/// unusable path is found at once, not after minutes of runs.
fn check_outputs(experiment: Experiment, out: &Path, quick: bool) -> Result<(), ExperimentError> {
    crate::output::check_dir(out).map_err(ExperimentError::OutDir)?;
    let mut dirs = Vec::new();
    let mut files = vec![out.join("report.md")];
    // A run's directory: its log and the figures drawn from it.
    let mut run_dir = |dir: PathBuf| {
        files.push(dir.join("log.csv"));
        for f in FIGURES {
            for format in FORMATS {
                files.push(dir.join(format!("{}.{}", f.name, format.extension())));
            }
        }
        dirs.push(dir);
    };
    match experiment {
        Experiment::Validation => {
            for c in VALIDATION_CONTROLLERS {
                run_dir(out.join(c));
            }
            let pre = out.join("pretune");
            files.extend(pretune_seeds(quick).iter().map(|&s| pretune_log(&pre, s)));
            files.push(pre.join("weights.json"));
            dirs.push(pre);
        }
        Experiment::Alpha => {
            files.push(out.join("pd-multisine.csv"));
            files.extend(FORMATS.map(|f| out.join(format!("alpha-e1.{}", f.extension()))));
        }
        Experiment::Payload => {
            for (name, _, _) in PAYLOAD_RUNS {
                run_dir(out.join(name));
            }
        }
        Experiment::Workspace => workspace::outputs(out, &mut dirs, &mut files),
        // Check their own outputs.
        Experiment::Haptics | Experiment::Teleop => {}
    }
    for dir in &dirs {
        crate::output::check_dir(dir)?;
    }
    for file in &files {
        crate::output::check_file(file)?;
    }
    Ok(())
}

/// One `--fast` simulator run; a run that faults or loses log rows is an error (its numbers
/// would not mean what the report says).
#[allow(clippy::too_many_arguments)]
fn sim_run(
    name: &str,
    cfg: &Config,
    controller: ControllerKind,
    trajectory: Trajectory,
    secs: f64,
    log: &Path,
    weights: Option<PathBuf>,
    no_adapt: bool,
) -> Result<RunSummary, ExperimentError> {
    let mut cfg = cfg.clone();
    // Cold motors every run, so the experiment reproduces.
    cfg.safety.persist_heat = false;
    if let Some(dir) = log.parent() {
        make_dir(dir)?;
    }
    let opts = RunOptions {
        controller,
        trajectory,
        duration_s: secs,
        log: Some(log.to_path_buf()),
        fast: true,
        weights,
        no_adapt,
        ..RunOptions::default()
    };
    let out = execute(&opts, &cfg, Arc::new(AtomicBool::new(false))).map_err(|source| {
        ExperimentError::Run {
            name: name.to_string(),
            source: Box::new(source),
        }
    })?;
    let failed = |why: String| ExperimentError::RunFailed {
        name: name.to_string(),
        why,
    };
    if let Some(f) = out.summary.faults.first() {
        return Err(failed(format!(
            "{} at t = {:.3} s: {}",
            f.class, f.t, f.message
        )));
    }
    if let Some(e) = out.log_error {
        return Err(failed(format!("log: {e}")));
    }
    if out.summary.telemetry_dropped > 0 {
        return Err(failed(format!(
            "{} log rows dropped",
            out.summary.telemetry_dropped
        )));
    }
    Ok(out.summary)
}

/// Create `dir` (and its parents) for an experiment's outputs; a failure names it.
pub(crate) fn make_dir(dir: &Path) -> Result<(), ExperimentError> {
    std::fs::create_dir_all(dir).map_err(|source| ExperimentError::Write {
        path: dir.to_path_buf(),
        source,
    })
}

/// Figures of one run's log into `dir`; returns the markdown that shows them.
fn figures_of(
    log: &Path,
    dir: &Path,
    rel: &str,
    files: &mut Vec<PathBuf>,
) -> Result<String, ExperimentError> {
    let rep = plot_log(log, dir, &[], &crate::plot::PlotOptions::default(), None)?;
    files.extend(rep.files.iter().cloned());
    let mut md = String::new();
    for name in &rep.figures {
        let _ = writeln!(
            md,
            "![{rel}: {name}]({rel}/{name}.png) ([SVG]({rel}/{name}.svg))\n"
        );
    }
    Ok(md)
}

/// A number for a table: `digits` decimals; a missing or non-finite value is written as such
/// (the tests refuse reports with them).
fn num(v: Option<f64>, digits: usize) -> String {
    match v {
        Some(v) if v.is_finite() => format!("{v:.digits$}"),
        Some(v) => format!("{v}"),
        None => "n/a".to_string(),
    }
}

fn joints_row(md: &mut String, label: &str, v: Option<[f64; 3]>, scale: f64, digits: usize) {
    let cell = |j: usize| num(v.map(|v| v[j] * scale), digits);
    let _ = writeln!(md, "| {label} | {} | {} | {} |", cell(0), cell(1), cell(2));
}

fn run_table(md: &mut String, s: &RunSummary) {
    md.push_str("| | joint 1 | joint 2 | joint 3 |\n|---|---:|---:|---:|\n");
    joints_row(md, "tracking RMS (mrad)", s.tracking_rms_rad, 1e3, 3);
    joints_row(md, "tracking max (mrad)", s.tracking_max_rad, 1e3, 3);
    joints_row(md, "torque RMS (mN·m)", s.torque_rms_nm, 1e3, 3);
    joints_row(
        md,
        "torque total variation (N·m)",
        Some(s.torque_total_variation_nm),
        1.0,
        3,
    );
    joints_row(md, "identification NRMSE", s.identifier.nrmse, 1.0, 4);
    joints_row(md, "oracle NRMSE", s.identifier.nrmse_oracle, 1.0, 4);
    md.push('\n');
}

fn shipped_identifier(cfg: &Config) -> Result<Identifier, ExperimentError> {
    let internal = |e: &dyn std::fmt::Display| ExperimentError::Internal(e.to_string());
    let mut id = Identifier::new(&cfg.identifier).map_err(|e| internal(&e))?;
    let w =
        WeightsFile::from_json(SHIPPED_WEIGHTS, SHIPPED_WEIGHTS_NAME).map_err(|e| internal(&e))?;
    id.apply_weights(&w, SHIPPED_WEIGHTS_NAME)
        .map_err(|e| internal(&e))?;
    Ok(id)
}

// ---------------------------------------------------------------------------------------------
// validation

/// The controllers of the validation experiment, in report order.
pub const VALIDATION_CONTROLLERS: [&str; 3] = ["pd", "ct", "nnidc"];

/// The seeds of the pre-tuning logs.
fn pretune_seeds(quick: bool) -> &'static [u64] {
    if quick {
        &[11]
    } else {
        &[11, 12, 13]
    }
}

fn pretune_log(pre: &Path, seed: u64) -> PathBuf {
    pre.join(format!("pd-multisine-seed{seed}.csv"))
}

fn validation(
    out: &Path,
    quick: bool,
    files: &mut Vec<PathBuf>,
) -> Result<String, ExperimentError> {
    // `--quick` keeps one full-length log: weights from 20 s and 3 epochs drive NNIDC into
    // the joint-speed limit within the first second (measured), which is no validation.
    let pre = PretunePlan {
        seeds: pretune_seeds(quick),
        secs: 60.0,
        epochs: if quick { 8 } else { 20 },
    };
    let sine_secs = 10.0;
    let steps = pre.seeds.len() + 1 + VALIDATION_CONTROLLERS.len() * 2;
    let bar = crate::progress::bar(steps as u64, "validation");
    let (weights, pre_report) = validation_pretune(out, &pre, &bar)?;

    let cfg = Config::default();
    let mut md = validation_intro(&cfg, quick, &pre, sine_secs, &pre_report);
    let mut figs_md = String::new();
    let mut overview = Vec::new();
    for name in VALIDATION_CONTROLLERS {
        let (kind, w) = match name {
            "pd" => (ControllerKind::Pd, None),
            "ct" => (ControllerKind::Ct, None),
            _ => (ControllerKind::Nnidc, Some(weights.clone())),
        };
        let dir = out.join(name);
        let log = dir.join("log.csv");
        let s = sim_run(
            name,
            &cfg,
            kind,
            Trajectory::Sine,
            sine_secs,
            &log,
            w,
            false,
        )?;
        bar.inc(1);
        let _ = writeln!(md, "## {}\n", name.to_uppercase());
        run_table(&mut md, &s);
        let _ = writeln!(figs_md, "### {}\n", name.to_uppercase());
        figs_md.push_str(&figures_of(&log, &dir, name, files)?);
        bar.inc(1);
        overview.push((name, s));
    }
    if std::fs::read_to_string(&weights).is_ok_and(|w| w == SHIPPED_WEIGHTS) {
        md.insert_str(
            md.find("\n## ").unwrap_or(md.len()),
            "\nThe pre-tuned weights are byte for byte the shipped \
             `mock/nnidc-pretuned.json`: the pipeline reproduces them.\n",
        );
    }
    // The oracle beside NNIDC: computed torque with the exact model and the plant's friction
    // on the same sine (docs/IDENTIFIER.md).
    let mut oracle_cfg = cfg.clone();
    oracle_cfg.safety.persist_heat = false;
    let oracle = oracle_tracking(
        &RunOptions {
            trajectory: Trajectory::Sine,
            duration_s: sine_secs,
            fast: true,
            ..RunOptions::default()
        },
        &oracle_cfg,
    );
    tracking_side_by_side(&mut md, &overview, oracle);
    md.push_str("\n## Figures\n\n");
    md.push_str(&figs_md);
    bar.finish_and_clear();
    Ok(md)
}

/// How the validation pre-tunes NNIDC's weights: PD multisine logs, one per seed, each `secs`
/// long, then `epochs` passes of `omnid identify` over them.
struct PretunePlan {
    seeds: &'static [u64],
    secs: f64,
    epochs: usize,
}

/// Record the pre-tuning logs under `out/pretune` and pre-tune on them, as mock/README.md
/// makes the shipped weights: the weights file and the pre-tuning report.
fn validation_pretune(
    out: &Path,
    plan: &PretunePlan,
    bar: &indicatif::ProgressBar,
) -> Result<(PathBuf, PretuneReport), ExperimentError> {
    let pre = out.join("pretune");
    let mut logs = Vec::new();
    for &seed in plan.seeds {
        let mut cfg = Config::default();
        cfg.sim.seed = seed;
        let log = pretune_log(&pre, seed);
        sim_run(
            &format!("pre-tune log, seed {seed}"),
            &cfg,
            ControllerKind::Pd,
            Trajectory::Multisine,
            plan.secs,
            &log,
            None,
            false,
        )?;
        logs.push(log);
        bar.inc(1);
    }
    let weights = pre.join("weights.json");
    let pcfg = PretuneConfig {
        epochs: plan.epochs,
        ..PretuneConfig::default()
    };
    let epoch_bar = crate::progress::bar(plan.epochs as u64, "pre-tuning");
    let report = identify(
        &logs,
        &weights,
        &Config::default(),
        &pcfg,
        States::Smoothed,
        None,
        |p| {
            if let Progress::Epoch(_) = p {
                epoch_bar.inc(1);
            }
        },
    )?;
    epoch_bar.finish_and_clear();
    bar.inc(1);
    Ok((weights, report))
}

/// The validation report's opening: the set-up and the pre-tuning's outcome.
fn validation_intro(
    cfg: &Config,
    quick: bool,
    pre: &PretunePlan,
    sine_secs: f64,
    report: &PretuneReport,
) -> String {
    let kept = &report.epochs[report.kept_epoch - 1];
    let mut md = String::new();
    let _ = writeln!(
        md,
        "# Validation: PD, computed torque and NNIDC on the sine (paper Figs. 8–12)\n\n\
         Simulated Omni, `--fast`, seed {}, 0.5 Hz sine for {sine_secs} s{}.\n\n\
         Pre-tuning: {} PD multisine log(s) of {ms_secs} s (seeds {}), {epochs} epochs \
         (`omnid identify`); kept epoch {}: validation NRMSE {} / {} / {}. Weights: \
         [`pretune/weights.json`](pretune/weights.json). NNIDC starts from them and adapts \
         online; PD and CT run the identifier alongside (fresh weights, adapting) so their \
         identification NRMSE is that of learning from scratch.\n\n\
         The oracle NRMSE is that of the exact plant model against the measured torque: the \
         floor set by sensor noise and estimation.\n",
        cfg.sim.seed,
        if quick {
            " (`--quick`: shortened pre-tuning)"
        } else {
            ""
        },
        pre.seeds.len(),
        pre.seeds
            .iter()
            .map(|s| s.to_string())
            .collect::<Vec<_>>()
            .join(", "),
        report.kept_epoch,
        num(Some(kept.val_nrmse[0]), 4),
        num(Some(kept.val_nrmse[1]), 4),
        num(Some(kept.val_nrmse[2]), 4),
        ms_secs = pre.secs,
        epochs = pre.epochs,
    );
    md
}

/// The tracking RMS of every controller's run, one row each, mrad; then the oracle's (computed
/// torque with the exact model and friction) and NNIDC's ratio to it.
fn tracking_side_by_side(
    md: &mut String,
    overview: &[(&str, RunSummary)],
    oracle: Option<[f64; 3]>,
) {
    md.push_str("## Tracking RMS side by side (mrad)\n\n| controller | joint 1 | joint 2 | joint 3 |\n|---|---:|---:|---:|\n");
    let row = |md: &mut String, name: &str, v: Option<[f64; 3]>, scale: f64, digits: usize| {
        let cell = |j: usize| num(v.map(|v| v[j] * scale), digits);
        let _ = writeln!(md, "| {name} | {} | {} | {} |", cell(0), cell(1), cell(2));
    };
    for (name, s) in overview {
        row(md, name, s.tracking_rms_rad, 1e3, 3);
    }
    row(md, "oracle (ct, exact model and friction)", oracle, 1e3, 3);
    let nnidc = overview
        .iter()
        .find(|(name, _)| *name == "nnidc")
        .and_then(|(_, s)| s.tracking_rms_rad);
    let ratio = nnidc
        .zip(oracle)
        .map(|(n, o)| [0, 1, 2].map(|j| n[j] / o[j]));
    row(md, "nnidc ÷ oracle (×)", ratio, 1.0, 2);
}

// ---------------------------------------------------------------------------------------------
// alpha

/// The α values of the sweep (paper Figs. 5–6).
pub(crate) const ALPHAS: [f64; 3] = [5.0, 50.0, 500.0];
/// The running RMS of ‖e1‖: exponential window, s.
pub(crate) const ALPHA_WINDOW_S: f64 = 1.0;
/// Convergence threshold on the running RMS of ‖e1‖, N·m.
pub(crate) const ALPHA_THRESHOLD_NM: f64 = 0.01;

fn alpha(out: &Path, quick: bool, files: &mut Vec<PathBuf>) -> Result<String, ExperimentError> {
    let secs = if quick { 10.0 } else { 30.0 };
    let seed = 5;
    let mut cfg = Config::default();
    cfg.sim.seed = seed;
    let log = out.join("pd-multisine.csv");
    sim_run(
        "α sweep log",
        &cfg,
        ControllerKind::Pd,
        Trajectory::Multisine,
        secs,
        &log,
        None,
        false,
    )?;
    let samples = samples_from_log(&log, &cfg, States::Filtered, None)?;
    if samples.is_empty() {
        return Err(ExperimentError::Internal(
            "the α sweep log has no samples".into(),
        ));
    }
    let dt = 1.0 / cfg.device.rate_hz;
    let span = samples.len() as f64 * dt;
    let bar = crate::progress::bar((ALPHAS.len() * samples.len()) as u64, "α sweep");
    let mut runs = Vec::new();
    for &alpha in &ALPHAS {
        runs.push(alpha_run(&cfg, alpha, &samples, dt, &bar)?);
    }
    bar.finish_and_clear();

    let mut md = String::new();
    let _ = writeln!(
        md,
        "# α sweep of the adaptation law (paper Figs. 5–6)\n\n\
         One PD multisine log of {secs} s (simulated Omni, seed {seed}); for each α the \
         identifier starts from the same weights (the shipped pre-tuned ones) and adapts on \
         every sample with the log's {:.0} ms, `unit_gain_filter = true` (α sets only the \
         filter's bandwidth) and σ = 0 (no leakage toward the start weights), as in \
         `tests/suite/identifier_paper.rs`.{}\n\n\
         Time to threshold: the first time (after the first {ALPHA_WINDOW_S} s) the running RMS \
         of ‖e1‖ (exponential window, {ALPHA_WINDOW_S} s) drops below {} mN·m; `> {span:.3}` \
         means never within the log.\n",
        dt * 1e3,
        if quick {
            " `--quick`: shortened log."
        } else {
            ""
        },
        ALPHA_THRESHOLD_NM * 1e3,
    );
    alpha_table(&mut md, &runs, span);
    alpha_figure(out, runs, span, files)?;
    md.push_str("\n![‖e1‖ over time per α](alpha-e1.png) ([SVG](alpha-e1.svg))\n");
    Ok(md)
}

/// One α of the sweep: what its row of the table and its line of the figure show.
struct AlphaRun {
    alpha: f64,
    /// When the running RMS of ‖e1‖ first fell below [`ALPHA_THRESHOLD_NM`], s.
    reached: Option<f64>,
    /// ‖θ − θ0‖ at the end.
    change: f64,
    /// RMS of ‖e1‖ over the log's tail, N·m.
    late: f64,
    healthy: bool,
    /// The running RMS of ‖e1‖ over time, (s, mN·m), thinned to about 3000 points.
    points: Vec<(f64, f64)>,
}

/// Adapt the shipped identifier over every sample with this `alpha` (unit-gain filter, no
/// leakage), tracking the running RMS of ‖e1‖.
fn alpha_run(
    cfg: &Config,
    alpha: f64,
    samples: &[Sample],
    dt: f64,
    bar: &indicatif::ProgressBar,
) -> Result<AlphaRun, ExperimentError> {
    let k = dt / ALPHA_WINDOW_S;
    let n = samples.len();
    let span = n as f64 * dt;
    let stride = (n / 3000).max(1);
    let mut c = cfg.clone();
    c.identifier.alpha = alpha;
    c.identifier.unit_gain_filter = true;
    c.identifier.sigma = 0.0;
    let mut id = shipped_identifier(&c)?;
    id.set_anchor();
    let mut ms = None::<f64>;
    let mut reached = None;
    let mut tail = (0.0, 0usize);
    let mut points = Vec::with_capacity(n / stride + 1);
    for (i, s) in samples.iter().enumerate() {
        id.update(&s.q, &s.qd, &s.qdd, &s.tau, dt);
        let e2 = id.last_errors().e1.norm_squared();
        let m = ms.map_or(e2, |m| m + k * (e2 - m));
        ms = Some(m);
        let t = i as f64 * dt;
        if reached.is_none() && t >= ALPHA_WINDOW_S && m.sqrt() < ALPHA_THRESHOLD_NM {
            reached = Some(t);
        }
        if t >= span - 5.0_f64.min(span / 2.0) {
            tail.0 += e2;
            tail.1 += 1;
        }
        if i % stride == 0 {
            points.push((t, m.sqrt() * 1e3));
        }
        if i % 1000 == 999 {
            bar.inc(1000);
        }
    }
    Ok(AlphaRun {
        alpha,
        reached,
        change: id.weight_change_norm(),
        late: (tail.0 / tail.1.max(1) as f64).sqrt(),
        healthy: id.healthy(),
        points,
    })
}

/// The sweep's table, one row per α, and a note for each α whose identifier ended unhealthy.
fn alpha_table(md: &mut String, runs: &[AlphaRun], span: f64) {
    let tail_s = 5.0_f64.min(span / 2.0);
    let _ = writeln!(
        md,
        "| α | time to threshold (s) | ‖θ − θ0‖ | RMS ‖e1‖ over the last {tail_s} s (mN·m) |\n|---:|---:|---:|---:|"
    );
    for run in runs {
        let t = match run.reached {
            Some(t) => num(Some(t), 3),
            None => format!("> {span:.3}"),
        };
        let _ = writeln!(
            md,
            "| {} | {t} | {} | {} |",
            run.alpha,
            num(Some(run.change), 4),
            num(Some(run.late * 1e3), 3)
        );
    }
    for run in runs {
        if !run.healthy {
            let _ = writeln!(md, "\nα = {}: the identifier ended unhealthy.", run.alpha);
        }
    }
}

/// `out/alpha-e1.{png,svg}`: every α's running RMS of ‖e1‖ over time, and the threshold.
fn alpha_figure(
    out: &Path,
    runs: Vec<AlphaRun>,
    span: f64,
    files: &mut Vec<PathBuf>,
) -> Result<(), ExperimentError> {
    let roles = [Role::Measured, Role::Estimate, Role::Error];
    let mut lines: Vec<Line> = runs
        .into_iter()
        .zip(roles)
        .map(|(run, role)| Line {
            points: run.points,
            role,
        })
        .collect();
    // The threshold, for reading the crossings off the figure.
    lines.push(Line {
        points: vec![
            (0.0, ALPHA_THRESHOLD_NM * 1e3),
            (span, ALPHA_THRESHOLD_NM * 1e3),
        ],
        role: Role::Target,
    });
    let figure = Figure {
        size: (crate::plot::render::WIDTH, crate::plot::render::HEIGHT),
        font_scale: 1.0,
        title: "Identification error ‖e1‖ (running RMS, 1 s) for α = 5, 50, 500",
        y_desc: "‖e1‖ (mN·m)",
        x_range: (0.0, span),
        shade_until: None,
        zero_line: true,
        legend: vec![
            ("α = 5", Role::Measured),
            ("α = 50", Role::Estimate),
            ("α = 500", Role::Error),
            ("threshold", Role::Target),
        ],
        panels: vec![Panel {
            title: "norm over the three joints",
            lines,
        }],
    };
    write_figure(&figure, out, "alpha-e1", files)
}

/// Draw `figure` as `dir/name.png` and `.svg`, adding the files to `files`.
fn write_figure(
    figure: &Figure,
    dir: &Path,
    name: &str,
    files: &mut Vec<PathBuf>,
) -> Result<(), ExperimentError> {
    for format in FORMATS {
        let file = dir.join(format!("{name}.{}", format.extension()));
        render::write(figure, format, &file).map_err(|source| {
            ExperimentError::from(PlotError::Render {
                file: file.clone(),
                source,
            })
        })?;
        files.push(file);
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// payload

/// Tracking RMS per joint over `from..to` s of a log: reference against the filtered angle,
/// control ticks only.
pub fn window_rms(log: &Path, from: f64, to: f64) -> Result<[f64; 3], ExperimentError> {
    const COLUMNS: [&str; 8] = ["t", "mode", "ref1", "ref2", "ref3", "qf1", "qf2", "qf3"];
    let bad = |why: String| ExperimentError::ReadLog {
        path: log.to_path_buf(),
        why,
    };
    // The one log reader (as replay, plot, convert and identify use): named columns,
    // every field checked, errors naming the line and the column.
    let mut r = ColumnReader::open(log, &COLUMNS, false, None).map_err(|e| bad(e.to_string()))?;
    let col = |n: &str| r.require(n, &COLUMNS).map_err(|e| bad(e.to_string()));
    let mode = col("mode")?;
    let refs = [col("ref1")?, col("ref2")?, col("ref3")?];
    let qf = [col("qf1")?, col("qf2")?, col("qf3")?];
    let (mut s, mut n) = ([0.0; 3], 0.0);
    while let Some(errors) = r
        .next_with(|row| {
            if row.t < from || row.t >= to || row.field(mode) == b"stop" {
                return Ok(None);
            }
            let mut e = [0.0; 3];
            for j in 0..3 {
                e[j] = row.f64(refs[j])? - row.f64(qf[j])?;
            }
            Ok(Some(e))
        })
        .map_err(|e| bad(e.to_string()))?
    {
        if let Some(e) = errors {
            for j in 0..3 {
                s[j] += e[j] * e[j];
            }
            n += 1.0;
        }
    }
    if n == 0.0 {
        return Err(bad(format!("no control rows in {from}..{to} s")));
    }
    Ok(s.map(|v| (v / n).sqrt()))
}

/// The payload experiment's runs, in report order: name, controller, frozen identifier.
pub const PAYLOAD_RUNS: [(&str, ControllerKind, bool); 3] = [
    ("nnidc", ControllerKind::Nnidc, false),
    ("nnidc-no-adapt", ControllerKind::Nnidc, true),
    ("ct", ControllerKind::Ct, false),
];

fn payload(out: &Path, quick: bool, files: &mut Vec<PathBuf>) -> Result<String, ExperimentError> {
    // (payload at, duration, before window, after window)
    let (at, secs, before, after) = if quick {
        (5.0, 10.0, (2.0, 5.0), (7.0, 10.0))
    } else {
        (10.0, 30.0, (2.0, 10.0), (20.0, 30.0))
    };
    let mass = 0.02;
    let mut cfg = Config::default();
    cfg.sim.payload_kg = mass;
    cfg.sim.payload_at_s = at;
    let bar = crate::progress::bar(PAYLOAD_RUNS.len() as u64 * 2, "payload");
    let mut md = String::new();
    let _ = writeln!(
        md,
        "# Payload: {:.0} g added at the tip at t = {at} s\n\n\
         Simulated Omni, `--fast`, seed {}, 0.5 Hz sine for {secs} s{}. NNIDC starts from the \
         shipped pre-tuned weights, adapting or frozen (`--no-adapt`); computed torque uses \
         the nominal model (without the payload).\n\n\
         Tracking RMS per joint (mrad, reference against the filtered angle) before the \
         payload ({}–{} s) and after it ({}–{} s, once adaptation has had time):\n\n\
         | run | before J1 | before J2 | before J3 | after J1 | after J2 | after J3 |\n\
         |---|---:|---:|---:|---:|---:|---:|",
        mass * 1e3,
        cfg.sim.seed,
        if quick { " (`--quick`: shortened)" } else { "" },
        before.0,
        before.1,
        after.0,
        after.1,
    );
    let mut figs_md = String::new();
    for (name, kind, frozen) in PAYLOAD_RUNS {
        let dir = out.join(name);
        let log = dir.join("log.csv");
        sim_run(name, &cfg, kind, Trajectory::Sine, secs, &log, None, frozen)?;
        bar.inc(1);
        let b = window_rms(&log, before.0, before.1)?;
        let a = window_rms(&log, after.0, after.1)?;
        let c = |v: f64| num(Some(v * 1e3), 3);
        let _ = writeln!(
            md,
            "| {name} | {} | {} | {} | {} | {} | {} |",
            c(b[0]),
            c(b[1]),
            c(b[2]),
            c(a[0]),
            c(a[1]),
            c(a[2])
        );
        let _ = writeln!(figs_md, "### {name}\n");
        figs_md.push_str(&figures_of(&log, &dir, name, files)?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    md.push_str("\n## Figures\n\n");
    md.push_str(&figs_md);
    Ok(md)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn window_rms_reads_through_the_log_reader_and_names_a_bad_field() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("log.csv");
        let head = "t,mode,ref1,ref2,ref3,qf1,qf2,qf3\n";
        std::fs::write(
            &log,
            format!(
                "{head}0.0,track,1,1,1,0,0,0\n0.001,track,3,1,1,0,0,0\n0.002,stop,9,9,9,0,0,0\n"
            ),
        )
        .unwrap();
        let rms = window_rms(&log, 0.0, 1.0).unwrap();
        assert!(
            (rms[0] - 5f64.sqrt()).abs() < 1e-12 && rms[1] == 1.0,
            "{rms:?}"
        );
        std::fs::write(
            &log,
            format!("{head}0.0,track,1,1,1,0,0,0\n0.001,track,1,x,1,0,0,0\n"),
        )
        .unwrap();
        let e = window_rms(&log, 0.0, 1.0).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("ref2"), "{e}");
    }
}
