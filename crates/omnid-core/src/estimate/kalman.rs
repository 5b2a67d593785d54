//! Per-joint Kalman filter (docs/DESIGN.md §4.3): constant-acceleration model driven by white
//! jerk, the standard continuous white-noise discretisation, time step from the device
//! timestamps.

use crate::config_check::{self as check, ConfigError};
use crate::omni::Joint3;
use nalgebra::{Matrix3, RowVector3, Vector3};
use serde::{Deserialize, Serialize};

/// `[kalman]`: the noise model of the per-joint filter.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct KalmanConfig {
    /// Spectral density of the white jerk driving the model, rad²/s⁵.
    pub jerk_psd: f64,
    /// Measurement variance R, rad² (default Δ²/12 of the encoder step).
    pub measurement_var: f64,
}

impl Default for KalmanConfig {
    fn default() -> Self {
        let step = std::f64::consts::TAU / 15000.0;
        KalmanConfig {
            jerk_psd: 100.0,
            measurement_var: step * step / 12.0,
        }
    }
}

/// The Kalman filter must follow a sinusoidal motion of this frequency (a fast hand motion)...
pub(crate) const KALMAN_CHECK_HZ: f64 = 5.0;
/// ... with a position error of at most this fraction of the motion (the default: 1 %).
pub(crate) const KALMAN_MAX_LAG: f64 = 0.2;

impl KalmanConfig {
    /// Check every value at the servo rate `rate_hz`; the first problem names its field.
    pub(crate) fn validate(&self, rate_hz: f64) -> Result<(), ConfigError> {
        check::positive("kalman.jerk_psd", self.jerk_psd)?;
        check::positive("kalman.measurement_var", self.measurement_var)?;
        // The safety limits also watch the encoders, but control acts on the estimate: one
        // that cannot follow a hand-speed motion is refused before any torque is sent.
        let lag = tracking_error(
            self.jerk_psd,
            self.measurement_var,
            1.0 / rate_hz,
            KALMAN_CHECK_HZ,
        );
        if lag.is_nan() || lag > KALMAN_MAX_LAG {
            return Err(check::invalid(
                "kalman.jerk_psd",
                format!(
                    "{} with kalman.measurement_var = {:e}",
                    self.jerk_psd, self.measurement_var
                ),
                format!(
                    "an estimate that follows a {KALMAN_CHECK_HZ} Hz motion within {:.0} % (this \
                     one is off by {:.0} %): raise kalman.jerk_psd or lower \
                     kalman.measurement_var",
                    KALMAN_MAX_LAG * 100.0,
                    lag * 100.0
                ),
            ));
        }
        Ok(())
    }
}

/// Initial variances of velocity and acceleration when the filter starts from one reading.
const INITIAL_VEL_VAR: f64 = 1.0;
const INITIAL_ACC_VAR: f64 = 100.0;

/// Kalman filter of one joint: state [q, q̇, q̈].
#[derive(Debug, Clone, Copy)]
pub(crate) struct JointKalman {
    x: Vector3<f64>,
    p: Matrix3<f64>,
    jerk_psd: f64,
    r: f64,
    // F and Q for the last step length, reused while T does not change.
    cached_t: f64,
    f: Matrix3<f64>,
    q: Matrix3<f64>,
}

impl JointKalman {
    pub(crate) fn new(jerk_psd: f64, measurement_var: f64) -> Self {
        JointKalman {
            x: Vector3::zeros(),
            p: Matrix3::zeros(),
            jerk_psd,
            r: measurement_var,
            cached_t: f64::NAN,
            f: Matrix3::identity(),
            q: Matrix3::zeros(),
        }
    }

    /// Start from one measurement, at rest.
    pub(crate) fn reset(&mut self, z: f64) {
        self.x = Vector3::new(z, 0.0, 0.0);
        self.p = Matrix3::from_diagonal(&Vector3::new(self.r, INITIAL_VEL_VAR, INITIAL_ACC_VAR));
    }

    fn model(&mut self, t: f64) {
        if t == self.cached_t {
            return;
        }
        let (t2, t3) = (t * t, t * t * t);
        let (t4, t5) = (t3 * t, t3 * t2);
        self.f = Matrix3::new(1.0, t, t2 / 2.0, 0.0, 1.0, t, 0.0, 0.0, 1.0);
        self.q = self.jerk_psd
            * Matrix3::new(
                t5 / 20.0,
                t4 / 8.0,
                t3 / 6.0,
                t4 / 8.0,
                t3 / 3.0,
                t2 / 2.0,
                t3 / 6.0,
                t2 / 2.0,
                t,
            );
        self.cached_t = t;
    }

    /// Predict over `dt` seconds, then correct with measurement `z`.
    pub(crate) fn step(&mut self, dt: f64, z: f64) {
        self.predict(dt);
        self.correct(z);
    }

    /// The model's prediction over `dt` seconds (none for `dt` ≤ 0).
    pub(crate) fn predict(&mut self, dt: f64) {
        if dt > 0.0 {
            self.model(dt);
            self.x = self.f * self.x;
            self.p = self.f * self.p * self.f.transpose() + self.q;
        }
    }

    /// The correction by measurement `z`.
    pub(crate) fn correct(&mut self, z: f64) {
        // H = [1, 0, 0]: innovation and gain use only the first row/column of P.
        let s = self.p[(0, 0)] + self.r;
        let k: Vector3<f64> = self.p.column(0) / s;
        let innovation = z - self.x[0];
        self.x += k * innovation;
        let h_p: RowVector3<f64> = self.p.row(0).into_owned();
        self.p -= k * h_p;
        // Keep P exactly symmetric against round-off.
        self.p = (self.p + self.p.transpose()) * 0.5;
    }

    /// [q, q̇, q̈].
    pub(crate) fn state(&self) -> Vector3<f64> {
        self.x
    }

    /// The state's covariance.
    pub(crate) fn covariance(&self) -> Matrix3<f64> {
        self.p
    }

    /// The transition F and process noise Q of a step of `dt` seconds.
    pub(crate) fn transition(&mut self, dt: f64) -> (Matrix3<f64>, Matrix3<f64>) {
        self.model(dt);
        (self.f, self.q)
    }
}

/// The settled filter's acceleration estimate as a response to the true acceleration: with
/// the acceleration u_k held over the interval ending at sample k, the estimate's error
/// d = x̂ − [q, q̇, u] obeys d_k = A·d_{k−1} − b·(u_k − u_{k−1}), and the estimate of u_k is
/// u_k + d_k[2] (A = (I − KH)F, b = (I − KH)F·e₃, K the steady-state gain). The identifier
/// passes its torque through the same response, so its error compares like with like
/// (docs/IDENTIFIER.md, "Lag-matched e1").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AccelLag {
    pub(crate) a: Matrix3<f64>,
    pub(crate) b: Vector3<f64>,
}

/// The steady-state gain K and transition F of the filter at step `dt`.
fn steady_state(jerk_psd: f64, measurement_var: f64, dt: f64) -> (Matrix3<f64>, Vector3<f64>) {
    let mut kf = JointKalman::new(jerk_psd, measurement_var);
    kf.reset(0.0);
    // Iterate the covariance to its steady state (the measurements do not enter it).
    let mut last = f64::INFINITY;
    for _ in 0..1_000_000 {
        kf.step(dt, 0.0);
        let p00 = kf.p[(0, 0)];
        if (p00 - last).abs() <= 1e-12 * p00.abs() {
            break;
        }
        last = p00;
    }
    kf.model(dt);
    let prior = kf.f * kf.p * kf.f.transpose() + kf.q;
    let k: Vector3<f64> = prior.column(0) / (prior[(0, 0)] + kf.r);
    (kf.f, k)
}

impl AccelLag {
    /// The response of the `[kalman]` filter at the servo step `dt`, s.
    pub fn of(cfg: &KalmanConfig, dt: f64) -> AccelLag {
        let (f, k) = steady_state(cfg.jerk_psd, cfg.measurement_var, dt);
        let mut a = f;
        for c in 0..3 {
            let f0 = f[(0, c)];
            for r in 0..3 {
                a[(r, c)] -= k[r] * f0;
            }
        }
        let f3 = f.column(2).into_owned();
        AccelLag {
            a,
            b: f3 - k * f3[0],
        }
    }
}

/// How far the filter's position estimate falls behind a sinusoidal motion of `freq_hz`
/// sampled every `dt`, once the filter has settled: |1 − G(e^{jωT})| with G the steady-state
/// transfer from measurement to estimate (0: tracks exactly; 1: as large as the motion
/// itself). A config can then be refused before torque is sent when the estimate could not
/// follow a hand-speed motion, instead of letting the safety limits act on a lagging estimate.
pub(crate) fn tracking_error(jerk_psd: f64, measurement_var: f64, dt: f64, freq_hz: f64) -> f64 {
    use nalgebra::Complex;
    let (f, k) = steady_state(jerk_psd, measurement_var, dt);
    // x̂ₖ = A x̂ₖ₋₁ + K zₖ with A = (I − K H) F, so q̂/z = H (I − A z⁻¹)⁻¹ K.
    let mut a = f;
    for c in 0..3 {
        let f0 = f[(0, c)];
        for r in 0..3 {
            a[(r, c)] -= k[r] * f0;
        }
    }
    let z_inv = Complex::from_polar(1.0, -std::f64::consts::TAU * freq_hz * dt);
    let m = Matrix3::<Complex<f64>>::identity() - a.map(|v| Complex::new(v, 0.0)) * z_inv;
    match m.try_inverse() {
        Some(inv) => {
            let g = (inv * k.map(|v| Complex::new(v, 0.0)))[0];
            (Complex::new(1.0, 0.0) - g).norm()
        }
        None => 1.0,
    }
}

/// Across a gap in the device time longer than this, the filter restarts from the next
/// measurement at rest instead of extrapolating its motion through the gap (a hand changes
/// direction within 50 ms; a prediction over longer gaps is a guess that can trip the speed
/// limit on an arm at rest).
pub(crate) const RESTART_GAP_S: f64 = 0.05;

/// One filter per joint, driven by the device time stamps.
#[derive(Debug, Clone, Copy)]
pub struct KalmanBank {
    joints: [JointKalman; 3],
    last_time: Option<f64>,
    restarts: u64,
    /// The latest gap restarted across: (device time after it, its length), s.
    last_gap: Option<(f64, f64)>,
    longest_gap_s: f64,
}

/// Joint-space estimate.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Estimate {
    /// Joint angles q1..q3, rad.
    pub q: Joint3,
    /// Joint velocities, rad/s.
    pub qd: Joint3,
    /// Joint accelerations, rad/s².
    pub qdd: Joint3,
}

impl KalmanBank {
    /// Three filters with the noise model of `cfg`, started by the first measurement.
    pub fn new(cfg: &KalmanConfig) -> Self {
        KalmanBank {
            joints: [JointKalman::new(cfg.jerk_psd, cfg.measurement_var); 3],
            last_time: None,
            restarts: 0,
            last_gap: None,
            longest_gap_s: 0.0,
        }
    }

    /// Feed the measured angles at device time `t`; returns the new estimate. A time that does
    /// not advance is treated as a repeated measurement (no prediction step).
    pub fn update(&mut self, t: f64, q: &Joint3) -> Estimate {
        match self.last_time {
            None => {
                for (j, kf) in self.joints.iter_mut().enumerate() {
                    kf.reset(q[j]);
                }
            }
            Some(last) if t - last > RESTART_GAP_S => {
                for (j, kf) in self.joints.iter_mut().enumerate() {
                    kf.reset(q[j]);
                }
                self.restarts += 1;
                self.last_gap = Some((t, t - last));
                self.longest_gap_s = self.longest_gap_s.max(t - last);
            }
            Some(last) => {
                let dt = (t - last).max(0.0);
                for (j, kf) in self.joints.iter_mut().enumerate() {
                    kf.step(dt, q[j]);
                }
            }
        }
        self.last_time = Some(t);
        self.estimate()
    }

    /// Restarts across gaps longer than [`RESTART_GAP_S`] so far.
    pub(crate) fn restarts(&self) -> u64 {
        self.restarts
    }

    /// The latest gap restarted across: (device time after it, its length), s.
    pub(crate) fn last_gap(&self) -> Option<(f64, f64)> {
        self.last_gap
    }

    /// The longest gap restarted across, s (0 if none).
    pub(crate) fn longest_gap_s(&self) -> f64 {
        self.longest_gap_s
    }

    pub(crate) fn estimate(&self) -> Estimate {
        let s = |j: usize| self.joints[j].state();
        Estimate {
            q: Joint3::new(s(0)[0], s(1)[0], s(2)[0]),
            qd: Joint3::new(s(0)[1], s(1)[1], s(2)[1]),
            qdd: Joint3::new(s(0)[2], s(1)[2], s(2)[2]),
        }
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn tracking_error_matches_a_filter_run_on_a_sampled_sine() {
        // Independent check of the transfer-function formula: run the filter itself on a
        // sine, let it settle, and measure the amplitude of the error.
        for (q, r, f) in [
            (100.0, 1.46e-8, 5.0),
            (1.0, 1.46e-8, 5.0),
            (1e-2, 1.46e-8, 2.0),
            (100.0, 1e-4, 5.0),
        ] {
            let dt = 1e-3;
            let mut kf = super::JointKalman::new(q, r);
            kf.reset(0.0);
            let w = std::f64::consts::TAU * f;
            let mut worst: f64 = 0.0;
            for k in 1..40_000 {
                let t = k as f64 * dt;
                kf.step(dt, (w * t).sin());
                if t > 20.0 {
                    worst = worst.max((kf.state()[0] - (w * t).sin()).abs());
                }
            }
            let e = super::tracking_error(q, r, dt, f);
            assert!(
                (worst - e).abs() < 0.01 * e + 1e-6,
                "{q} {r} {f}: run {worst}, formula {e}"
            );
        }
    }

    #[test]
    fn the_acceleration_response_is_what_the_filter_does_to_an_acceleration() {
        // The filter itself on the positions an acceleration history gives (held over each
        // interval, integrated exactly), against the response's prediction of its q̈.
        let cfg = super::KalmanConfig::default();
        let dt = 1e-3;
        let lag = super::AccelLag::of(&cfg, dt);
        let mut kf = super::JointKalman::new(cfg.jerk_psd, cfg.measurement_var);
        kf.reset(0.0);
        // Settle at rest: the estimate's error is then zero and the gain steady.
        for _ in 0..20_000 {
            kf.step(dt, 0.0);
        }
        let (mut p, mut v, mut prev) = (0.0, 0.0, 0.0);
        let mut d = nalgebra::Vector3::zeros();
        let (mut worst, mut lagged): (f64, f64) = (0.0, 0.0);
        for k in 0..3000 {
            let t = k as f64 * dt;
            // A sine with a step in it: the kind of torque a reversal gives.
            let u = 2.0 * (9.0 * t).sin() + if t > 1.5 { 1.0 } else { 0.0 };
            p += v * dt + 0.5 * u * dt * dt;
            v += u * dt;
            kf.step(dt, p);
            d = lag.a * d - lag.b * (u - prev);
            prev = u;
            worst = worst.max((kf.state()[2] - (u + d[2])).abs());
            lagged = lagged.max((kf.state()[2] - u).abs());
        }
        assert!(lagged > 0.5, "the estimate lags the acceleration: {lagged}");
        assert!(worst < 1e-6 * lagged, "response {worst} vs lag {lagged}");
    }

    use super::*;
    use std::f64::consts::{PI, TAU};

    const STEP: f64 = TAU / 15000.0;

    fn quantise(x: f64) -> f64 {
        (x / STEP).round() * STEP
    }

    /// The textbook filter written out plainly with arrays: x = F x; P = F P Fᵀ + Q;
    /// K = P Hᵀ / (H P Hᵀ + R); x += K (z − H x); P = (I − K H) P.
    struct Reference {
        x: [f64; 3],
        p: [[f64; 3]; 3],
    }

    fn matmul(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
        let mut c = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                for k in 0..3 {
                    c[i][j] += a[i][k] * b[k][j];
                }
            }
        }
        c
    }

    impl Reference {
        fn step(&mut self, t: f64, qj: f64, r: f64, z: f64) {
            let f = [[1.0, t, t * t / 2.0], [0.0, 1.0, t], [0.0, 0.0, 1.0]];
            let q = [
                [t.powi(5) / 20.0, t.powi(4) / 8.0, t.powi(3) / 6.0],
                [t.powi(4) / 8.0, t.powi(3) / 3.0, t.powi(2) / 2.0],
                [t.powi(3) / 6.0, t.powi(2) / 2.0, t],
            ];
            let mut x = [0.0; 3];
            for i in 0..3 {
                for k in 0..3 {
                    x[i] += f[i][k] * self.x[k];
                }
            }
            let mut ft = [[0.0; 3]; 3];
            for i in 0..3 {
                for j in 0..3 {
                    ft[i][j] = f[j][i];
                }
            }
            let mut p = matmul(&matmul(&f, &self.p), &ft);
            for i in 0..3 {
                for j in 0..3 {
                    p[i][j] += qj * q[i][j];
                }
            }
            let s = p[0][0] + r;
            let k = [p[0][0] / s, p[1][0] / s, p[2][0] / s];
            let y = z - x[0];
            for i in 0..3 {
                x[i] += k[i] * y;
            }
            let mut ikh = [[0.0; 3]; 3];
            for i in 0..3 {
                for j in 0..3 {
                    ikh[i][j] = if i == j { 1.0 } else { 0.0 } - if j == 0 { k[i] } else { 0.0 };
                }
            }
            self.x = x;
            self.p = matmul(&ikh, &p);
        }
    }

    #[test]
    fn tracks_a_quantised_sinusoid() {
        let (amp, w, dt) = (0.5, TAU * 1.0, 1e-3);
        let cfg = KalmanConfig::default();
        let mut kf = JointKalman::new(cfg.jerk_psd, cfg.measurement_var);
        kf.reset(quantise(0.0));
        let (mut ev, mut ea, mut n) = (0.0, 0.0, 0.0);
        for k in 1..10_000 {
            let t = k as f64 * dt;
            kf.step(dt, quantise(amp * (w * t).sin()));
            if t > 2.0 {
                let s = kf.state();
                ev += (s[1] - amp * w * (w * t).cos()).powi(2);
                ea += (s[2] + amp * w * w * (w * t).sin()).powi(2);
                n += 1.0;
            }
        }
        let v_rms_rel = (ev / n).sqrt() / (amp * w);
        let a_rms_rel = (ea / n).sqrt() / (amp * w * w);
        assert!(
            v_rms_rel < 0.01,
            "velocity RMS error {v_rms_rel:.4} of peak"
        );
        assert!(
            a_rms_rel < 0.15,
            "acceleration RMS error {a_rms_rel:.4} of peak"
        );
    }

    #[test]
    fn equals_the_textbook_filter() {
        let cfg = KalmanConfig::default();
        let mut kf = JointKalman::new(cfg.jerk_psd, cfg.measurement_var);
        let z0 = quantise(0.3);
        kf.reset(z0);
        let mut reference = Reference {
            x: [z0, 0.0, 0.0],
            p: [
                [cfg.measurement_var, 0.0, 0.0],
                [0.0, INITIAL_VEL_VAR, 0.0],
                [0.0, 0.0, INITIAL_ACC_VAR],
            ],
        };
        // Irregular steps, as from a jittery 100 Hz log.
        let mut t = 0.0;
        for k in 1..3000 {
            let dt = 0.01 + 0.002 * ((k as f64) * 0.7).sin();
            t += dt;
            let z = quantise(0.3 + 0.4 * (PI * t).sin());
            kf.step(dt, z);
            reference.step(dt, cfg.jerk_psd, cfg.measurement_var, z);
            let s = kf.state();
            for i in 0..3 {
                let scale = reference.x[i].abs().max(1.0);
                assert!(
                    (s[i] - reference.x[i]).abs() <= 1e-12 * scale,
                    "step {k} state {i}: {} vs {}",
                    s[i],
                    reference.x[i]
                );
            }
        }
    }

    #[test]
    fn bank_uses_device_time_steps() {
        let mut bank = KalmanBank::new(&KalmanConfig::default());
        // A constant-velocity ramp sampled at uneven times must give that velocity.
        let mut t = 0.0;
        for k in 0..2000 {
            t += if k % 3 == 0 { 0.002 } else { 0.001 };
            bank.update(t, &Joint3::repeat(quantise(0.2 * t)));
        }
        let e = bank.estimate();
        assert!((e.qd[0] - 0.2).abs() < 0.01, "qd {}", e.qd[0]);
    }
}
