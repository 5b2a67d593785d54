//! `omnid identify`: batch pre-tuning of the identifier's networks on recorded logs. Each log
//! goes through the same estimator as a live run (encoder angles → Kalman → q, q̇, q̈, with the
//! log's own time steps), paired with the torque that acted up to each sample, so weights
//! tuned here predict what the identifier sees online.

use crate::config::Config;
use crate::estimate::{smoother, KalmanBank};
use crate::identifier::{
    pretune, save, Identifier, PretuneConfig, PretuneError, PretuneReport, Progress, Sample,
    WeightsError,
};
use crate::omni::Joint3;
use crate::output::OutputError;
use crate::telemetry::reader::{LogReader, ReadError};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// Samples dropped at the start of each log while the Kalman filter settles.
pub(crate) const WARMUP_SAMPLES: usize = 200;

/// Why `omnid identify` wrote no weights.
#[derive(Debug, Error)]
pub enum IdentifyError {
    /// A log could not be read, or a row of it is bad.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// The identifier could not be built from the configuration, or pre-tuning failed.
    #[error("{0}")]
    Ident(String),
    /// No log had more rows than the Kalman warm-up drops.
    #[error(
        "no usable samples in {0:?} (each log needs more than {WARMUP_SAMPLES} rows, {twice} \
         when smoothed)",
        twice = 2 * WARMUP_SAMPLES
    )]
    NoSamples(Vec<PathBuf>),
    /// A joint has zero torque throughout: nothing to learn it from.
    #[error(
        "{}: {detail}: the data carry no information to identify it from (a recording without \
         torque, e.g. one converted with `convert --from ros-touch`, cannot be identified)",
        files(.logs)
    )]
    NoInformation {
        /// The logs given.
        logs: Vec<PathBuf>,
        /// Which joint and split lack torque.
        detail: String,
    },
    /// The weights file cannot be written there (checked before the work), or its writing
    /// failed.
    #[error("--out: {0}")]
    Output(#[from] OutputError),
    /// The operator's stop flag ended the training.
    #[error("stopped by the operator in epoch {epoch}; no weights written")]
    Stopped {
        /// The epoch it happened in, 1-based.
        epoch: usize,
    },
}

impl IdentifyError {
    /// The user's input is at fault (exit code 2), not a write that failed part-way.
    pub fn is_bad_input(&self) -> bool {
        match self {
            IdentifyError::Output(e) => e.is_bad_input(),
            _ => true,
        }
    }
}

fn files(logs: &[PathBuf]) -> String {
    let names: Vec<String> = logs.iter().map(|p| p.display().to_string()).collect();
    names.join(", ")
}

impl IdentifyError {
    /// The operator stopped it (reading a log, or training).
    pub fn is_stopped(&self) -> bool {
        matches!(
            self,
            IdentifyError::Stopped { .. } | IdentifyError::Read(ReadError::Stopped { .. })
        )
    }
}

/// Which estimates of the joint states the training samples carry.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum States {
    /// The whole log smoothed (fixed-interval Kalman smoother): q̇ and q̈ without the live
    /// filter's lag, so the networks learn the arm's dynamics rather than a lagged version of
    /// them (docs/IDENTIFIER.md, "Pre-tuning on smoothed states").
    #[default]
    Smoothed,
    /// The live loop's causal Kalman filter, sample by sample (what the servo sees online).
    Filtered,
}

/// The identifier's training samples from one log (`stop`: the operator's, see
/// [`LogReader::open`]). Each log is estimated on its own, with the servo's `[kalman]` model and
/// the log's own time steps; the first and (smoothed) last 200 samples (`WARMUP_SAMPLES`)
/// are dropped.
pub fn samples_from_log(
    path: &Path,
    cfg: &Config,
    states: States,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<Vec<Sample>, IdentifyError> {
    let mut reader = LogReader::open(path, false, stop)?;
    let rad_per_count = cfg.device.rad_per_count();
    let (mut t, mut q, mut tau) = (Vec::new(), Vec::new(), Vec::new());
    while let Some(row) = reader.next_row()? {
        if row.is_stop() {
            break;
        }
        // The live loop sees encoder counts: use them when the log has them.
        q.push(match row.enc {
            Some(e) => Joint3::new(
                e[0] as f64 * rad_per_count,
                e[1] as f64 * rad_per_count,
                e[2] as f64 * rad_per_count,
            ),
            None => Joint3::from(row.q),
        });
        t.push(row.t);
        tau.push(Joint3::from(row.tau));
    }
    Ok(match states {
        States::Filtered => filtered_samples(cfg, &t, &q, &tau),
        States::Smoothed => smoothed_samples(cfg, &t, &q, &tau),
    })
}

/// Each sample's estimate with the torque that acted up to it (the previous row's).
fn filtered_samples(cfg: &Config, t: &[f64], q: &[Joint3], tau: &[Joint3]) -> Vec<Sample> {
    let mut kalman = KalmanBank::new(&cfg.kalman);
    let mut out = Vec::new();
    for k in 0..t.len() {
        let est = kalman.update(t[k], &q[k]);
        if k >= WARMUP_SAMPLES.max(1) {
            out.push(Sample {
                q: est.q,
                qd: est.qd,
                qdd: est.qdd,
                tau: tau[k - 1],
            });
        }
    }
    out
}

/// The smoothed estimate at each sample, with the mean of the torques held before and after it:
/// a torque is held over a tick, so the acceleration at the sample's instant steps from the one
/// to the other, and the smoothed q̈ (an estimate from both sides) sits between them.
fn smoothed_samples(cfg: &Config, t: &[f64], q: &[Joint3], tau: &[Joint3]) -> Vec<Sample> {
    let est = smoother::smooth(&cfg.kalman, t, q);
    let n = est.len();
    (WARMUP_SAMPLES.max(1)..n.saturating_sub(WARMUP_SAMPLES))
        .map(|k| Sample {
            q: est[k].q,
            qd: est[k].qd,
            qdd: est[k].qdd,
            tau: (tau[k - 1] + tau[k]) * 0.5,
        })
        .collect()
}

/// Pre-tune fresh networks on `logs` and save them to `out`. `stop` (the operator's) ends the
/// reading and the training; nothing is written then.
pub fn identify(
    logs: &[PathBuf],
    out: &Path,
    cfg: &Config,
    pretune_cfg: &PretuneConfig,
    states: States,
    stop: Option<&Arc<AtomicBool>>,
    progress: impl FnMut(Progress<'_>),
) -> Result<PretuneReport, IdentifyError> {
    // Before the work: a bad --out is found now, not after the training.
    crate::output::check_file(out)?;
    let mut samples = Vec::new();
    for log in logs {
        samples.extend(samples_from_log(log, cfg, states, stop)?);
    }
    if samples.is_empty() {
        return Err(IdentifyError::NoSamples(logs.to_vec()));
    }
    let mut id =
        Identifier::new(&cfg.identifier).map_err(|e| IdentifyError::Ident(e.to_string()))?;
    let report = pretune(&mut id, &samples, pretune_cfg, stop.map(|s| &**s), progress).map_err(
        |e| match e {
            PretuneError::Stopped { epoch } => IdentifyError::Stopped { epoch },
            PretuneError::NoTorque { .. } => IdentifyError::NoInformation {
                logs: logs.to_vec(),
                detail: e.to_string(),
            },
            e => IdentifyError::Ident(e.to_string()),
        },
    )?;
    save(&id, out).map_err(|e| match e {
        WeightsError::Write(e) => IdentifyError::Output(e),
        e => IdentifyError::Ident(e.to_string()),
    })?;
    Ok(report)
}
