//! Batch pre-tuning (`omnid identify`): the identifier's own loss ½‖ε‖² over recorded samples,
//! mini-batch Adam on the hand-derived gradients, several epochs, a held-out validation split
//! of every k-th block of consecutive samples (neighbouring samples are nearly equal, so a
//! random split would validate on the training data), per-joint NRMSE per epoch through a
//! callback, and the best-validation weights kept at the end.

use super::adaptive::{Identifier, Net};
use nalgebra::Vector3;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicBool, Ordering};
use thiserror::Error;

/// One training sample: estimated state and the torque that acted on it.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Sample {
    /// Joint angles, rad.
    pub q: Vector3<f64>,
    /// Joint velocities, rad/s.
    pub qd: Vector3<f64>,
    /// Joint accelerations, rad/s².
    pub qdd: Vector3<f64>,
    /// Applied joint torques, N·m.
    pub tau: Vector3<f64>,
}

impl Sample {
    fn is_finite(&self) -> bool {
        [self.q, self.qd, self.qdd, self.tau]
            .iter()
            .all(|v| v.iter().all(|x| x.is_finite()))
    }
}

/// How `omnid identify` trains the identifier's networks offline (mini-batch Adam).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PretuneConfig {
    /// Passes over the training samples, 1 ..= 100000.
    pub epochs: usize,
    /// Samples per mini-batch (one Adam step each), 1 ..= 1000000.
    pub batch_size: usize,
    /// Adam step size (the parameters are O(1) thanks to the scalings).
    pub learning_rate: f64,
    /// The step size decays geometrically to this fraction of `learning_rate` at the last
    /// epoch (1 = constant).
    pub final_rate_fraction: f64,
    /// Adam's decay of the first-moment (mean gradient) estimate, 0 ..< 1.
    pub beta1: f64,
    /// Adam's decay of the second-moment (squared gradient) estimate, 0 ..< 1.
    pub beta2: f64,
    /// Share of the samples held out for validation (0 = none).
    pub validation_fraction: f64,
    /// Length of the blocks of consecutive samples the split works on.
    pub block_len: usize,
    /// Seed of the mini-batch shuffling.
    pub seed: u64,
    /// Keep the weights of the epoch with the best mean validation NRMSE.
    pub keep_best: bool,
}

impl Default for PretuneConfig {
    fn default() -> Self {
        PretuneConfig {
            epochs: 20,
            batch_size: 32,
            learning_rate: 3e-3,
            final_rate_fraction: 0.1,
            beta1: 0.9,
            beta2: 0.999,
            validation_fraction: 0.2,
            block_len: 1000,
            seed: 1,
            keep_best: true,
        }
    }
}

/// Why pre-tuning refused the samples or stopped.
#[derive(Debug, Error, PartialEq)]
pub enum PretuneError {
    /// No samples at all.
    #[error("no samples to pre-tune on")]
    NoSamples,
    /// Fewer samples than a validation split needs.
    #[error("{got} samples are too few to pre-tune with a validation split (need {need})")]
    TooFew {
        /// Samples given.
        got: usize,
        /// The fewest accepted.
        need: usize,
    },
    /// A sample holds a NaN or an infinity.
    #[error("sample {index} is not finite (q, q̇, q̈ or τ)")]
    NonFinite {
        /// Its 0-based index.
        index: usize,
    },
    /// A [`PretuneConfig`] value is out of range.
    #[error("pre-tuning: `{field}` = {value} is out of range: allowed {allowed}")]
    Invalid {
        /// The field's name.
        field: &'static str,
        /// Its value, as written.
        value: String,
        /// The allowed range.
        allowed: &'static str,
    },
    /// The loss or the weights became non-finite; the best (or initial) weights are back.
    #[error("pre-tuning diverged in epoch {epoch} (non-finite loss); weights restored")]
    Diverged {
        /// The epoch it happened in, 1-based.
        epoch: usize,
    },
    /// Nothing to learn a joint from, nor to measure its error against (its NRMSE would be
    /// 0/0).
    #[error("joint {joint} has zero torque in every {split} sample")]
    NoTorque {
        /// The joint, 1-based.
        joint: usize,
        /// `training` or `validation`.
        split: &'static str,
    },
    /// The operator's stop flag ended it; the identifier holds unfinished weights.
    #[error("pre-tuning stopped by the operator in epoch {epoch}")]
    Stopped {
        /// The epoch it happened in, 1-based.
        epoch: usize,
    },
}

/// Errors after one epoch. NRMSE = RMS(τ − τ̂)/RMS(τ) per joint (NaN where RMS(τ) = 0 or the
/// split is empty).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EpochReport {
    /// 1-based.
    pub epoch: usize,
    /// Epochs in the whole run.
    pub epochs: usize,
    /// Mean ½‖ε‖² over the epoch's mini-batches.
    pub train_loss: f64,
    /// NRMSE per joint on the training split.
    pub train_nrmse: [f64; 3],
    /// NRMSE per joint on the validation split (NaN without one).
    pub val_nrmse: [f64; 3],
}

/// What the callback sees: every mini-batch (for a progress bar) and every epoch.
#[derive(Debug, Clone, Copy)]
pub enum Progress<'a> {
    /// A mini-batch has been trained on.
    Batch {
        /// 1-based.
        epoch: usize,
        /// 1-based, within the epoch.
        batch: usize,
        /// Mini-batches per epoch.
        batches: usize,
    },
    /// An epoch has ended; its errors.
    Epoch(&'a EpochReport),
}

/// What a whole pre-tuning did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PretuneReport {
    /// Every epoch's errors, in order.
    pub epochs: Vec<EpochReport>,
    /// Epoch whose weights were kept (1-based).
    pub kept_epoch: usize,
    /// Samples in the training split.
    pub train_samples: usize,
    /// Samples in the validation split.
    pub val_samples: usize,
}

impl PretuneConfig {
    fn validate(&self) -> Result<(), PretuneError> {
        let bad = |field, value: String, allowed| {
            Err(PretuneError::Invalid {
                field,
                value,
                allowed,
            })
        };
        if !(1..=100_000).contains(&self.epochs) {
            return bad("epochs", self.epochs.to_string(), "1 ..= 100000");
        }
        if !(1..=1_000_000).contains(&self.batch_size) {
            return bad("batch_size", self.batch_size.to_string(), "1 ..= 1000000");
        }
        let lr = self.learning_rate;
        if !(lr.is_finite() && lr > 0.0 && lr <= 1.0) {
            return bad("learning_rate", lr.to_string(), "> 0 and ≤ 1");
        }
        let f = self.final_rate_fraction;
        if !(f.is_finite() && f > 0.0 && f <= 1.0) {
            return bad("final_rate_fraction", f.to_string(), "> 0 and ≤ 1");
        }
        for (field, b) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(b.is_finite() && (0.0..1.0).contains(&b)) {
                return bad(field, b.to_string(), "0 ..< 1");
            }
        }
        let v = self.validation_fraction;
        if !(v.is_finite() && (0.0..=0.5).contains(&v)) {
            return bad("validation_fraction", v.to_string(), "0 ..= 0.5");
        }
        if self.block_len == 0 {
            return bad("block_len", "0".into(), "≥ 1");
        }
        Ok(())
    }
}

/// Indices of the training and validation samples: every k-th block is held out, k =
/// round(1/validation_fraction); blocks are shortened for short logs so that at least two
/// blocks are held out.
fn split(n: usize, cfg: &PretuneConfig) -> (Vec<usize>, Vec<usize>) {
    if cfg.validation_fraction == 0.0 {
        return ((0..n).collect(), Vec::new());
    }
    let k = (1.0 / cfg.validation_fraction).round().max(2.0) as usize;
    let block = cfg.block_len.min(n / (2 * k)).max(1);
    (0..n).partition(|i| (i / block) % k != k - 1)
}

/// Per-joint NRMSE of the identifier's prediction over `samples[idx]` (all if `idx` is None;
/// indices past the end are ignored).
pub fn nrmse(id: &mut Identifier, samples: &[Sample], idx: Option<&[usize]>) -> [f64; 3] {
    let mut err2 = Vector3::zeros();
    let mut tau2 = Vector3::zeros();
    let mut visit = |s: &Sample| {
        let e = s.tau - id.predict(&s.q, &s.qd, &s.qdd);
        err2 += e.component_mul(&e);
        tau2 += s.tau.component_mul(&s.tau);
    };
    match idx {
        Some(idx) => idx
            .iter()
            .filter_map(|&i| samples.get(i))
            .for_each(&mut visit),
        None => samples.iter().for_each(&mut visit),
    }
    std::array::from_fn(|j| {
        if tau2[j] > 0.0 {
            (err2[j] / tau2[j]).sqrt()
        } else {
            f64::NAN
        }
    })
}

/// Adam's moment estimates for one network.
struct Moments {
    m: Vec<f64>,
    v: Vec<f64>,
}

fn snapshot(id: &Identifier) -> Vec<Vec<f64>> {
    Net::ALL
        .iter()
        .map(|&n| id.net(n).map(|m| m.params().to_vec()).unwrap_or_default())
        .collect()
}

fn restore(id: &mut Identifier, saved: &[Vec<f64>]) {
    for (n, p) in Net::ALL.iter().zip(saved) {
        if let Some(m) = id.net_mut(*n) {
            // Same identifier, same sizes: cannot fail.
            let _ = m.set_params(p);
        }
    }
}

/// Pre-tune `id` on `samples` (in recording order). On success the kept weights become the
/// σ-modification's anchor θ0. `stop` (the operator's) is looked at before every batch; once
/// set, pre-tuning ends with [`PretuneError::Stopped`] and `id` holds unfinished weights.
pub fn pretune(
    id: &mut Identifier,
    samples: &[Sample],
    cfg: &PretuneConfig,
    stop: Option<&AtomicBool>,
    mut progress: impl FnMut(Progress<'_>),
) -> Result<PretuneReport, PretuneError> {
    cfg.validate()?;
    let (mut train, val) = check_and_split(samples, cfg)?;
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let mut adam = Adam::new(id);
    let initial = snapshot(id);
    let mut best: Option<(f64, usize, Vec<Vec<f64>>)> = None;
    let mut reports = Vec::with_capacity(cfg.epochs);
    let decay = cfg
        .final_rate_fraction
        .powf(1.0 / (cfg.epochs.max(2) - 1) as f64);

    for epoch in 1..=cfg.epochs {
        let lr = cfg.learning_rate * decay.powi(epoch as i32 - 1);
        train.shuffle(&mut rng);
        let pass = Epoch {
            samples,
            train: &train,
            cfg,
            epoch,
            lr,
        };
        let train_loss = pass.train(id, &mut adam, stop, &mut progress)?;
        if !train_loss.is_finite() || id.weights_norm().iter().any(|w| !w.is_finite()) {
            let saved = best.map_or(initial, |b| b.2);
            restore(id, &saved);
            return Err(PretuneError::Diverged { epoch });
        }
        let (report, score) = pass.report(id, &val, train_loss);
        // NaN scores (no torque on a joint) never win against a number.
        let better = match &best {
            None => true,
            Some((s, _, _)) => score < *s || (s.is_nan() && !score.is_nan()),
        };
        if cfg.keep_best && better {
            best = Some((score, epoch, snapshot(id)));
        }
        progress(Progress::Epoch(&report));
        reports.push(report);
    }
    let kept_epoch = match best {
        Some((_, epoch, saved)) if cfg.keep_best => {
            restore(id, &saved);
            epoch
        }
        _ => cfg.epochs,
    };
    id.set_anchor();
    Ok(PretuneReport {
        epochs: reports,
        kept_epoch,
        train_samples: train.len(),
        val_samples: val.len(),
    })
}

/// Refuse samples that cannot be learnt from (none, a non-finite one, too few, a joint
/// without torque in a split), else the training and validation indices ([`split`]).
fn check_and_split(
    samples: &[Sample],
    cfg: &PretuneConfig,
) -> Result<(Vec<usize>, Vec<usize>), PretuneError> {
    if samples.is_empty() {
        return Err(PretuneError::NoSamples);
    }
    if let Some(index) = samples.iter().position(|s| !s.is_finite()) {
        return Err(PretuneError::NonFinite { index });
    }
    let need = if cfg.validation_fraction > 0.0 { 10 } else { 1 };
    if samples.len() < need {
        return Err(PretuneError::TooFew {
            got: samples.len(),
            need,
        });
    }
    let (train, val) = split(samples.len(), cfg);
    for (idx, name) in [(&train, "training"), (&val, "validation")] {
        for joint in 0..3 {
            if !idx.is_empty() && idx.iter().all(|&i| samples[i].tau[joint] == 0.0) {
                return Err(PretuneError::NoTorque {
                    joint: joint + 1,
                    split: name,
                });
            }
        }
    }
    Ok((train, val))
}

/// One epoch: the training indices (already shuffled) and its learning rate.
struct Epoch<'a> {
    samples: &'a [Sample],
    train: &'a [usize],
    cfg: &'a PretuneConfig,
    /// 1-based.
    epoch: usize,
    lr: f64,
}

impl Epoch<'_> {
    /// One pass of mini-batch Adam over the training indices; the summed ½‖ε‖² over the
    /// epoch divided by the training samples (the mean loss).
    fn train(
        &self,
        id: &mut Identifier,
        adam: &mut Adam,
        stop: Option<&AtomicBool>,
        progress: &mut impl FnMut(Progress<'_>),
    ) -> Result<f64, PretuneError> {
        let batches = self.train.len().div_ceil(self.cfg.batch_size);
        let mut loss_sum = 0.0;
        for (b, chunk) in self.train.chunks(self.cfg.batch_size).enumerate() {
            if stop.is_some_and(|s| s.load(Ordering::Relaxed)) {
                return Err(PretuneError::Stopped { epoch: self.epoch });
            }
            id.zero_grads();
            for &i in chunk {
                let s = &self.samples[i];
                let eps = id.evaluate_wae(&s.q, &s.qd, &s.qdd, &s.tau);
                loss_sum += 0.5 * eps.norm_squared();
                // ∂(½‖ε‖²)/∂θ = (∂ε/∂θ)ᵀε.
                id.accumulate_gradient(&eps);
            }
            adam.step(id, self.cfg, self.lr, chunk.len() as f64);
            progress(Progress::Batch {
                epoch: self.epoch,
                batch: b + 1,
                batches,
            });
        }
        Ok(loss_sum / self.train.len() as f64)
    }

    /// The epoch's report and its score (the summed validation NRMSE, or the training one
    /// without a validation split): lower is better.
    fn report(&self, id: &mut Identifier, val: &[usize], train_loss: f64) -> (EpochReport, f64) {
        let report = EpochReport {
            epoch: self.epoch,
            epochs: self.cfg.epochs,
            train_loss,
            train_nrmse: nrmse(id, self.samples, Some(self.train)),
            val_nrmse: if val.is_empty() {
                [f64::NAN; 3]
            } else {
                nrmse(id, self.samples, Some(val))
            },
        };
        let score = if val.is_empty() {
            report.train_nrmse.iter().sum::<f64>()
        } else {
            report.val_nrmse.iter().sum::<f64>()
        };
        (report, score)
    }
}

/// Adam's state: the moment estimates of every network present, and the step count.
struct Adam {
    moments: Vec<Option<Moments>>,
    t: i32,
}

impl Adam {
    fn new(id: &Identifier) -> Adam {
        let moments = Net::ALL
            .iter()
            .map(|&n| {
                id.net(n).map(|m| Moments {
                    m: vec![0.0; m.params().len()],
                    v: vec![0.0; m.params().len()],
                })
            })
            .collect();
        Adam { moments, t: 0 }
    }

    /// One step on the gradients accumulated over a batch of `batch` samples.
    fn step(&mut self, id: &mut Identifier, cfg: &PretuneConfig, lr: f64, batch: f64) {
        self.t += 1;
        adam_step(id, &mut self.moments, cfg, lr, self.t, batch);
    }
}

fn adam_step(
    id: &mut Identifier,
    moments: &mut [Option<Moments>],
    cfg: &PretuneConfig,
    lr: f64,
    t: i32,
    batch: f64,
) {
    const EPS: f64 = 1e-8;
    let (b1, b2) = (cfg.beta1, cfg.beta2);
    let c1 = 1.0 - b1.powi(t);
    let c2 = 1.0 - b2.powi(t);
    for (n, mo) in Net::ALL.iter().zip(moments.iter_mut()) {
        let (Some(net), Some(mo)) = (id.net_mut(*n), mo.as_mut()) else {
            continue;
        };
        let (p, g) = net.params_and_grad_mut();
        for (((pi, gi), mi), vi) in p.iter_mut().zip(g.iter()).zip(&mut mo.m).zip(&mut mo.v) {
            let gi = gi / batch;
            *mi = b1 * *mi + (1.0 - b1) * gi;
            *vi = b2 * *vi + (1.0 - b2) * gi * gi;
            *pi -= lr * (*mi / c1) / ((*vi / c2).sqrt() + EPS);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::identifier::testdata::{multisine_samples, random_samples};
    use crate::identifier::IdentifierConfig;

    #[test]
    fn split_holds_out_every_kth_block() {
        let cfg = PretuneConfig {
            block_len: 10,
            validation_fraction: 0.2,
            ..PretuneConfig::default()
        };
        let (train, val) = split(200, &cfg);
        assert_eq!((train.len(), val.len()), (160, 40));
        assert!(val.contains(&40) && val.contains(&49) && !val.contains(&50));
        // A short log still gets at least two held-out blocks.
        let (train, val) = split(30, &PretuneConfig::default());
        assert!(val.len() >= 2 && train.len() + val.len() == 30);
    }

    #[test]
    fn bad_input_is_an_error() {
        let mut id = Identifier::new(&IdentifierConfig::default()).unwrap();
        let cfg = PretuneConfig::default();
        assert_eq!(
            pretune(&mut id, &[], &cfg, None, |_| {}),
            Err(PretuneError::NoSamples)
        );
        let mut s = random_samples(50, 1);
        s[17].qdd[2] = f64::NAN;
        assert_eq!(
            pretune(&mut id, &s, &cfg, None, |_| {}),
            Err(PretuneError::NonFinite { index: 17 })
        );
        let bad = PretuneConfig {
            validation_fraction: 0.9,
            ..cfg
        };
        let e = pretune(&mut id, &random_samples(50, 1), &bad, None, |_| {}).unwrap_err();
        assert!(e.to_string().contains("validation_fraction"), "{e}");
        // A joint without torque carries nothing to learn (its NRMSE would be 0/0).
        let mut z = random_samples(50, 1);
        z.iter_mut().for_each(|s| s.tau[1] = 0.0);
        assert_eq!(
            pretune(&mut id, &z, &cfg, None, |_| {}),
            Err(PretuneError::NoTorque {
                joint: 2,
                split: "training"
            })
        );
    }

    #[test]
    fn pretuning_learns_the_plant_and_generalises() {
        let cfg = IdentifierConfig::default();
        let mut id = Identifier::new(&cfg).unwrap();
        let samples = random_samples(8000, 5);
        let pcfg = PretuneConfig {
            epochs: 15,
            block_len: 200,
            ..PretuneConfig::default()
        };
        let mut epochs_seen = 0;
        let mut batches_seen = 0;
        let report = pretune(&mut id, &samples, &pcfg, None, |p| match p {
            Progress::Batch { .. } => batches_seen += 1,
            Progress::Epoch(r) => {
                epochs_seen += 1;
                eprintln!(
                    "epoch {:2} loss {:.4} train {:.3?} val {:.3?}",
                    r.epoch, r.train_loss, r.train_nrmse, r.val_nrmse
                );
            }
        })
        .unwrap();
        assert_eq!(epochs_seen, 15);
        assert_eq!(batches_seen, 15 * 6400usize.div_ceil(32));
        let first = &report.epochs[0];
        let kept = &report.epochs[report.kept_epoch - 1];
        for j in 0..3 {
            assert!(kept.val_nrmse[j] < 0.1, "joint {j}: {:?}", kept.val_nrmse);
            assert!(kept.val_nrmse[j] < first.val_nrmse[j]);
        }
        // A fresh trajectory the networks never saw.
        let fresh = nrmse(&mut id, &multisine_samples(20.0, 0.005, 77), None);
        eprintln!("fresh multisine NRMSE {fresh:.3?}");
        assert!(fresh.iter().all(|e| *e < 0.3), "{fresh:?}");
        // The kept weights are the anchor.
        assert_eq!(id.weight_change_norm(), 0.0);
    }

    /// Relative error of Ĉ against the plant's C, and the symmetric part of Ṁ̂ − 2Ĉ relative
    /// to ‖C‖, over fresh random states.
    fn coriolis_errors(id: &mut Identifier) -> (f64, f64) {
        let d = crate::identifier::testdata::plant();
        let (mut ec, mut nc, mut sk) = (0.0, 0.0, 0.0);
        for s in random_samples(1000, 99) {
            let c = d.coriolis(&s.q, &s.qd);
            let ch = id.coriolis(&s.q, &s.qd);
            let n = id.mass_derivative(&s.q, &s.qd) - 2.0 * ch;
            ec += (ch - c).norm_squared();
            nc += c.norm_squared();
            sk += (n + n.transpose()).norm_squared();
        }
        ((ec / nc).sqrt(), (sk / nc).sqrt())
    }

    #[test]
    fn skew_symmetry_terms_make_c_identifiable() {
        let samples = random_samples(6000, 5);
        let pcfg = PretuneConfig {
            epochs: 8,
            block_len: 200,
            ..PretuneConfig::default()
        };
        let mut result = Vec::new();
        for lambda in [2.0, 0.0] {
            let mut id = Identifier::new(&IdentifierConfig {
                lambda1: lambda,
                lambda2: lambda,
                ..IdentifierConfig::default()
            })
            .unwrap();
            pretune(&mut id, &samples, &pcfg, None, |_| {}).unwrap();
            result.push(coriolis_errors(&mut id));
        }
        let ((c_on, skew_on), (c_off, skew_off)) = (result[0], result[1]);
        eprintln!("Ĉ rel. error on {c_on:.3} off {c_off:.3}; skew residual on {skew_on:.3} off {skew_off:.3}");
        assert!(skew_on < 0.3 * skew_off);
        assert!(c_on < 0.6 * c_off);
    }
}
