//! Fixed-interval smoothing of a recorded run (docs/IDENTIFIER.md, "Pre-tuning on smoothed
//! states"): the Rauch–Tung–Striebel smoother of the servo's own per-joint Kalman model. Each
//! estimate uses the whole recording, before and after it, so offline identification sees
//! q̇ and q̈ without the causal filter's lag. Never on the servo thread: it needs the whole log.

use super::kalman::{JointKalman, KalmanConfig, RESTART_GAP_S};
use super::Estimate;
use crate::omni::Joint3;
use nalgebra::{Matrix3, Vector3};

/// Smoothed (q, q̇, q̈) for measurements `q` at device times `t` (seconds), one per sample.
/// Where the live filter restarts (a gap longer than its restart gap), the recording is split
/// and each stretch is smoothed on its own, from the same start as the filter's.
pub fn smooth(cfg: &KalmanConfig, t: &[f64], q: &[Joint3]) -> Vec<Estimate> {
    let n = t.len().min(q.len());
    let mut out = vec![Estimate::default(); n];
    let mut start = 0;
    while start < n {
        let mut end = start + 1;
        while end < n && t[end] - t[end - 1] <= RESTART_GAP_S {
            end += 1;
        }
        for j in 0..3 {
            smooth_joint(cfg, &t[start..end], &q[start..end], j, &mut out[start..end]);
        }
        start = end;
    }
    out
}

/// One joint over one stretch: the filter forward (exactly the live filter's steps), then the
/// backward pass x̂ₖ|ₙ = x̂ₖ|ₖ + Cₖ(x̂ₖ₊₁|ₙ − F x̂ₖ|ₖ), Cₖ = Pₖ|ₖ Fᵀ (F Pₖ|ₖ Fᵀ + Q)⁻¹.
fn smooth_joint(cfg: &KalmanConfig, t: &[f64], q: &[Joint3], j: usize, out: &mut [Estimate]) {
    let n = t.len();
    if n == 0 {
        return;
    }
    let mut kf = JointKalman::new(cfg.jerk_psd, cfg.measurement_var);
    let mut filtered: Vec<(Vector3<f64>, Matrix3<f64>)> = Vec::with_capacity(n);
    kf.reset(q[0][j]);
    filtered.push((kf.state(), kf.covariance()));
    for k in 1..n {
        kf.step((t[k] - t[k - 1]).max(0.0), q[k][j]);
        filtered.push((kf.state(), kf.covariance()));
    }
    let mut x = filtered[n - 1].0;
    put(&mut out[n - 1], j, &x);
    for k in (0..n - 1).rev() {
        let (xf, pf) = filtered[k];
        let dt = (t[k + 1] - t[k]).max(0.0);
        // A repeated time stamp is a repeated measurement: no motion between the two.
        let (f, noise) = if dt > 0.0 {
            kf.transition(dt)
        } else {
            (Matrix3::identity(), Matrix3::zeros())
        };
        let prior = f * pf * f.transpose() + noise;
        // A prior that cannot be inverted carries no information forward: keep the filter's.
        if let Some(inv) = prior.try_inverse() {
            x = xf + pf * f.transpose() * inv * (x - f * xf);
        } else {
            x = xf;
        }
        put(&mut out[k], j, &x);
    }
}

fn put(e: &mut Estimate, j: usize, x: &Vector3<f64>) {
    e.q[j] = x[0];
    e.qd[j] = x[1];
    e.qdd[j] = x[2];
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimate::KalmanBank;
    use nalgebra::{DMatrix, DVector};

    fn joints(z: &[f64]) -> Vec<Joint3> {
        z.iter()
            .enumerate()
            .map(|(i, &v)| Joint3::new(v, -0.5 * v, v * v + i as f64 * 1e-4))
            .collect()
    }

    #[test]
    fn the_last_sample_is_the_live_filters_estimate() {
        // Nothing comes after the last sample, so smoothing leaves it as the filter had it;
        // the forward pass is the live filter's own arithmetic.
        let cfg = KalmanConfig::default();
        let t: Vec<f64> = (0..500).map(|k| k as f64 * 1e-3).collect();
        let z: Vec<f64> = t.iter().map(|t| (3.0 * t).sin()).collect();
        let q = joints(&z);
        let s = smooth(&cfg, &t, &q);
        let mut bank = KalmanBank::new(&cfg);
        let mut last = Estimate::default();
        for (t, q) in t.iter().zip(&q) {
            last = bank.update(*t, q);
        }
        assert_eq!(s[499], last);
    }

    #[test]
    fn equals_the_least_squares_solution_over_the_whole_record() {
        // Steps stay under the restart gap (one stretch). Independent computation: the
        // smoothed states are the minimiser of the model's
        // quadratic cost over all states at once (prior at the start, process noise between
        // samples, measurement noise), solved here as one dense linear system.
        let cfg = KalmanConfig {
            jerk_psd: 50.0,
            measurement_var: 1e-3,
        };
        let n = 14;
        let t: Vec<f64> = (0..n)
            .map(|k| 0.03 * k as f64 + 0.005 * (k % 3) as f64)
            .collect();
        let z: Vec<f64> = t
            .iter()
            .map(|t| (2.0 * t).sin() + 0.03 * (7.0 * t).cos())
            .collect();
        let q: Vec<Joint3> = z.iter().map(|&v| Joint3::new(v, 0.0, 0.0)).collect();
        let s = smooth(&cfg, &t, &q);

        let dim = 3 * n;
        let mut h = DMatrix::<f64>::zeros(dim, dim);
        let mut b = DVector::<f64>::zeros(dim);
        let r = cfg.measurement_var;
        // Prior: x0 ~ N([z0, 0, 0], diag(r, 1, 100)) (the filter's start).
        for (i, var) in [r, 1.0, 100.0].iter().enumerate() {
            h[(i, i)] += 1.0 / var;
        }
        b[0] += z[0] / r;
        let mut kf = JointKalman::new(cfg.jerk_psd, cfg.measurement_var);
        for k in 1..n {
            let (f, qn) = kf.transition(t[k] - t[k - 1]);
            let w = qn.try_inverse().expect("Q invertible at these steps");
            // (x_k − F x_{k−1})ᵀ W (x_k − F x_{k−1}) over the stacked [x_{k−1}; x_k].
            let mut a = DMatrix::<f64>::zeros(3, dim);
            for r_ in 0..3 {
                for c in 0..3 {
                    a[(r_, 3 * (k - 1) + c)] = -f[(r_, c)];
                }
                a[(r_, 3 * k + r_)] = 1.0;
            }
            let wd = DMatrix::from_fn(3, 3, |r_, c| w[(r_, c)]);
            h += a.transpose() * wd * a;
            h[(3 * k, 3 * k)] += 1.0 / r;
            b[3 * k] += z[k] / r;
        }
        let x = h.lu().solve(&b).expect("the cost has one minimiser");
        for k in 0..n {
            let got = [s[k].q[0], s[k].qd[0], s[k].qdd[0]];
            for i in 0..3 {
                let want = x[3 * k + i];
                assert!(
                    (got[i] - want).abs() <= 1e-6 * (1.0 + want.abs()),
                    "sample {k}, state {i}: smoother {} against least squares {want}",
                    got[i]
                );
            }
        }
    }

    #[test]
    fn a_quantised_motion_is_estimated_without_the_filters_lag() {
        // The encoder's steps on a 1 Hz sine at 1 kHz: the smoothed acceleration is centred
        // on the true one, the filter's trails it by several milliseconds.
        let cfg = KalmanConfig::default();
        let step = std::f64::consts::TAU / 15000.0;
        let w = std::f64::consts::TAU;
        let n = 4000;
        let t: Vec<f64> = (0..n).map(|k| k as f64 * 1e-3).collect();
        let truth: Vec<f64> = t.iter().map(|t| 0.3 * (w * t).sin()).collect();
        let acc: Vec<f64> = t.iter().map(|t| -0.3 * w * w * (w * t).sin()).collect();
        let q: Vec<Joint3> = truth
            .iter()
            .map(|v| Joint3::new((v / step).round() * step, 0.0, 0.0))
            .collect();
        let s = smooth(&cfg, &t, &q);
        let mut bank = KalmanBank::new(&cfg);
        let f: Vec<Estimate> = t.iter().zip(&q).map(|(t, q)| bank.update(*t, q)).collect();
        let inner = 500..n - 500;
        let rms = |est: &[Estimate], lag: usize| -> f64 {
            let sum: f64 = inner
                .clone()
                .map(|k| (est[k].qdd[0] - acc[k - lag]).powi(2))
                .sum();
            (sum / inner.len() as f64).sqrt()
        };
        let best_lag =
            |est: &[Estimate]| (0..40).min_by(|&a, &b| rms(est, a).total_cmp(&rms(est, b)));
        assert_eq!(best_lag(&s), Some(0), "the smoothed q̈ is not centred");
        let filter_lag = best_lag(&f).unwrap();
        assert!(filter_lag >= 5, "the filter's q̈ lags {filter_lag} ms only");
        assert!(
            rms(&s, 0) < 0.3 * rms(&f, 0),
            "smoothed q̈ error {} against the filter's {}",
            rms(&s, 0),
            rms(&f, 0)
        );
    }

    #[test]
    fn a_gap_the_filter_restarts_at_splits_the_record() {
        let cfg = KalmanConfig::default();
        let mut t: Vec<f64> = (0..300).map(|k| k as f64 * 1e-3).collect();
        t.extend((0..300).map(|k| 1.0 + k as f64 * 1e-3));
        let z: Vec<f64> = t.iter().map(|t| (2.0 * t).sin()).collect();
        let q = joints(&z);
        let whole = smooth(&cfg, &t, &q);
        let first = smooth(&cfg, &t[..300], &q[..300]);
        let second = smooth(&cfg, &t[300..], &q[300..]);
        assert_eq!(&whole[..300], &first[..]);
        assert_eq!(&whole[300..], &second[..]);
        assert!(smooth(&cfg, &[], &[]).is_empty());
    }
}
