//! `omnid experiment workspace --out DIR` (docs/IDENTIFIER.md, "Across the workspace"): the
//! README's sine (`omnid run --fast --duration 30`, NNIDC from the shipped weights, learning)
//! moved to five centres spread over the Omni's workspace, and beside each the oracle —
//! computed torque with the simulator's exact model and its friction — on the same sine in the
//! same process. NNIDC runs twice per centre: with the defaults and with the lag-matched preset
//! `mock/nnidc-lagmatch.toml`. Per centre: the tracking RMS, NNIDC's ratio to the oracle per
//! joint and the identifier's torque NRMSE. Writes `report.md`, `results.json` and each NNIDC
//! run's log.
//!
//! A centre where NNIDC faults is a result, not a failed experiment: its row says where and
//! why it stopped (the other centres still run).

use super::{num, ExperimentError, ExperimentReport};
use crate::cmd::run::{execute, oracle_tracking, RunOptions};
use crate::config::Config;
use crate::control::{ControllerKind, Trajectory};
use crate::servo::summary::RunSummary;
use serde::{Deserialize, Serialize};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// The five centres (`[reference] center`, rad): the README's (the default) and four spread
/// over the joint ranges, each far enough inside the limits that the sine (±0.4 / 0.3 / 0.3
/// rad) and the pre-tuning multisine (±0.45 / 0.32 / 0.32 rad) about it stay inside them.
pub const WORKSPACE_CENTRES: [[f64; 3]; 5] = [
    [0.0, 0.65, 0.3],
    [-0.35, 0.45, 0.0],
    [0.35, 0.45, 0.65],
    [-0.35, 1.05, 0.65],
    [0.35, 1.05, 0.0],
];

/// Seconds of sine per centre: the README's 30 s; `--quick` 5 s.
pub fn workspace_secs(quick: bool) -> f64 {
    if quick {
        5.0
    } else {
        30.0
    }
}

/// The lag-matched preset NNIDC also runs with (docs/IDENTIFIER.md, "Third round").
pub const PRESET: &str = include_str!("../../mock/nnidc-lagmatch.toml");

/// The NNIDC runs of each centre: name (and log file stem) and whether the preset applies.
pub const WORKSPACE_RUNS: [(&str, bool); 2] = [("nnidc", false), ("preset", true)];

/// One centre's outcome, as `results.json` holds it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CentreResult {
    /// `[reference] center`, rad.
    pub centre: [f64; 3],
    /// The oracle's tracking RMS on the same sine, rad (none if it did not complete).
    pub oracle_tracking_rms_rad: Option<[f64; 3]>,
    /// NNIDC's runs, in [`WORKSPACE_RUNS`] order.
    pub runs: Vec<NnidcResult>,
}

/// One NNIDC run about a centre.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NnidcResult {
    /// As [`WORKSPACE_RUNS`] names it.
    pub name: String,
    /// Its log, relative to the output directory.
    pub log: String,
    /// Tracking RMS per joint after the start-up blend, rad (none if it faulted).
    pub tracking_rms_rad: Option<[f64; 3]>,
    /// NNIDC ÷ oracle per joint; only when NNIDC completed the run.
    pub ratio: Option<[f64; 3]>,
    /// The identifier's torque NRMSE over the run.
    pub nrmse: Option<[f64; 3]>,
    /// The same over the last 20 % of the run.
    pub nrmse_last: Option<[f64; 3]>,
    /// The first fault of the run: class, time and message.
    pub fault: Option<String>,
}

/// `results.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct WorkspaceResults {
    /// Seconds of sine per centre.
    pub duration_s: f64,
    /// Tracking statistics start here, s (`[reference] settle_s`).
    pub settle_s: f64,
    /// One entry per [`WORKSPACE_CENTRES`], in order.
    pub centres: Vec<CentreResult>,
}

/// The directory of centre `i` (0-based) under the output directory.
pub fn centre_dir(i: usize) -> String {
    format!("centre-{}", i + 1)
}

/// Every directory and file the experiment writes, for the check before the first run.
pub(super) fn outputs(out: &Path, dirs: &mut Vec<PathBuf>, files: &mut Vec<PathBuf>) {
    files.push(out.join("results.json"));
    for i in 0..WORKSPACE_CENTRES.len() {
        let dir = out.join(centre_dir(i));
        for (name, _) in WORKSPACE_RUNS {
            files.push(dir.join(format!("{name}.csv")));
        }
        dirs.push(dir);
    }
}

/// Run NNIDC and the oracle about every centre; the results and the report's markdown.
pub(super) fn run_workspace(out: &Path, quick: bool) -> Result<ExperimentReport, ExperimentError> {
    let secs = workspace_secs(quick);
    let base = Config::default();
    let preset: Config =
        toml::from_str(PRESET).map_err(|e| ExperimentError::Internal(e.to_string()))?;
    let bar = crate::progress::bar(WORKSPACE_CENTRES.len() as u64, "workspace");
    let mut centres = Vec::new();
    for (i, &centre) in WORKSPACE_CENTRES.iter().enumerate() {
        let mut cfg = base.clone();
        cfg.reference.center = centre;
        // Cold motors every run, so the experiment reproduces.
        cfg.safety.persist_heat = false;
        let opts = RunOptions {
            controller: ControllerKind::Nnidc,
            trajectory: Trajectory::Sine,
            duration_s: secs,
            fast: true,
            ..RunOptions::default()
        };
        let oracle = oracle_tracking(&opts, &cfg);
        let mut runs = Vec::new();
        for (name, with_preset) in WORKSPACE_RUNS {
            let mut run_cfg = cfg.clone();
            if with_preset {
                run_cfg.identifier = preset.identifier.clone();
            }
            let rel = format!("{}/{name}.csv", centre_dir(i));
            let label = format!("centre {} ({centre:?}), {name}", i + 1);
            runs.push(one_run(out, &label, name, rel, &opts, &run_cfg, oracle)?);
        }
        centres.push(CentreResult {
            centre,
            oracle_tracking_rms_rad: oracle,
            runs,
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    let results = WorkspaceResults {
        duration_s: secs,
        settle_s: base.reference.settle_s,
        centres,
    };
    let markdown = report(&results, quick, base.sim.seed);
    let text = serde_json::to_string_pretty(&results)
        .map_err(|e| ExperimentError::Internal(e.to_string()))?;
    crate::output::write_bytes(&out.join("results.json"), text.as_bytes())?;
    let report = out.join("report.md");
    crate::output::write_bytes(&report, markdown.as_bytes())?;
    Ok(ExperimentReport {
        report,
        figures: Vec::new(),
        markdown,
    })
}

/// One NNIDC run about a centre, with its ratio to the centre's `oracle`.
fn one_run(
    out: &Path,
    label: &str,
    name: &str,
    rel: String,
    opts: &RunOptions,
    cfg: &Config,
    oracle: Option<[f64; 3]>,
) -> Result<NnidcResult, ExperimentError> {
    let log = out.join(&rel);
    if let Some(dir) = log.parent() {
        super::make_dir(dir)?;
    }
    let opts = RunOptions {
        log: Some(log),
        ..opts.clone()
    };
    let run = execute(&opts, cfg, Arc::new(AtomicBool::new(false))).map_err(|source| {
        ExperimentError::Run {
            name: label.to_string(),
            source: Box::new(source),
        }
    })?;
    if let Some(e) = run.log_error {
        return Err(ExperimentError::RunFailed {
            name: label.to_string(),
            why: format!("log: {e}"),
        });
    }
    let s: RunSummary = run.summary;
    let fault = s
        .faults
        .first()
        .map(|f| format!("{} at t = {:.3} s: {}", f.class, f.t, f.message));
    let rms = if fault.is_none() {
        s.tracking_rms_rad
    } else {
        None
    };
    Ok(NnidcResult {
        name: name.to_string(),
        log: rel,
        tracking_rms_rad: rms,
        ratio: rms.zip(oracle).map(|(n, o)| [0, 1, 2].map(|j| n[j] / o[j])),
        nrmse: s.identifier.nrmse,
        nrmse_last: s.identifier.nrmse_last_20pct,
        fault,
    })
}

/// The report: one table row per centre, then the faults.
fn report(r: &WorkspaceResults, quick: bool, seed: u64) -> String {
    let mut md = String::new();
    let _ = writeln!(
        md,
        "# NNIDC against the oracle across the workspace\n\n\
         Simulated Omni, `--fast`, seed {seed}, the README's 0.5 Hz sine for {} s{} about five \
         centres (`[reference] center`, rad). NNIDC starts from the shipped weights and learns, \
         with the defaults (`nnidc`) and with the lag-matched preset `mock/nnidc-lagmatch.toml` \
         (`preset`); the oracle is computed torque with the simulator's exact model and its \
         friction on the same sine. Tracking RMS after {} s (mrad), NNIDC ÷ oracle per joint, \
         and the identifier's torque NRMSE over the run (last 20 % in brackets).\n\n\
         | centre | run | NNIDC J1 | J2 | J3 | oracle J1 | J2 | J3 | ratio J1 | J2 | J3 | NRMSE |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        r.duration_s,
        if quick { " (`--quick`: shortened)" } else { "" },
        r.settle_s,
    );
    let cells = |v: Option<[f64; 3]>, scale: f64, digits: usize| {
        [0, 1, 2].map(|j| match v {
            Some(v) => num(Some(v[j] * scale), digits),
            None => "—".to_string(),
        })
    };
    for (i, c, run) in r
        .centres
        .iter()
        .enumerate()
        .flat_map(|(i, c)| c.runs.iter().map(move |run| (i, c, run)))
    {
        let [n1, n2, n3] = cells(run.tracking_rms_rad, 1e3, 3);
        let [o1, o2, o3] = cells(c.oracle_tracking_rms_rad, 1e3, 3);
        let [r1, r2, r3] = cells(run.ratio, 1.0, 2);
        let nrmse = match (run.nrmse, run.nrmse_last) {
            (Some(a), Some(b)) => format!(
                "{} / {} / {} ({} / {} / {})",
                num(Some(a[0]), 2),
                num(Some(a[1]), 2),
                num(Some(a[2]), 2),
                num(Some(b[0]), 2),
                num(Some(b[1]), 2),
                num(Some(b[2]), 2)
            ),
            _ => "—".to_string(),
        };
        let _ = writeln!(
            md,
            "| {}: {:.2}, {:.2}, {:.2} | {} | {n1} | {n2} | {n3} | {o1} | {o2} | {o3} | {r1} | {r2} | {r3} | {nrmse} |",
            i + 1,
            c.centre[0],
            c.centre[1],
            c.centre[2],
            run.name,
        );
    }
    let faults: Vec<String> = r
        .centres
        .iter()
        .enumerate()
        .flat_map(|(i, c)| {
            c.runs.iter().filter_map(move |run| {
                run.fault
                    .as_ref()
                    .map(|f| format!("- centre {}, {}: NNIDC stopped, {f}", i + 1, run.name))
            })
        })
        .collect();
    if !faults.is_empty() {
        md.push_str("\nRuns that did not complete (no tracking figure, no ratio):\n\n");
        md.push_str(&faults.join("\n"));
        md.push('\n');
    }
    md.push_str(
        "\nLogs: `centre-N/nnidc.csv` and `centre-N/preset.csv`; numbers: `results.json`.\n",
    );
    md
}
