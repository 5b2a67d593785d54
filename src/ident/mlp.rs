//! One-hidden-layer tanh MLP (paper eq. 2) with input offset/scale and output scale, and its
//! hand-derived derivatives:
//! - forward pass y(x),
//! - forward-mode directional derivative ẏ = (∂y/∂x)·u (for Ṁ̂ = Σ_k ∂M̂/∂q_k q̇_k),
//! - reverse-mode gradient of L = ȳᵀy + ẏ̄ᵀẏ w.r.t. all weights and biases (the second term is
//!   what e2/e3 need: the weight gradient of a directional derivative),
//! - reverse-mode gradient of ȳᵀy w.r.t. the inputs.
//!
//! All buffers are allocated in `new`; the per-tick methods only write into them.
//!
//! With x̃ = (x − c)/s_in, a = W1 x̃ + b1, h = tanh(a), y = s_out ⊙ (W2 h + b2).
//! Parameters live in one flat vector `[W1 (H×P, row-major) | b1 (H) | W2 (O×H) | b2 (O)]`, so
//! leakage, projection, norms, saving and Adam all work on plain slices.

use crate::fastmath::tanh;
use rand::Rng;
use serde::{Deserialize, Serialize};
use thiserror::Error;

#[derive(Debug, Error, PartialEq)]
pub enum MlpError {
    #[error(
        "network sizes must be at least 1 (inputs {inputs}, hidden {hidden}, outputs {outputs})"
    )]
    Size {
        inputs: usize,
        hidden: usize,
        outputs: usize,
    },
    #[error("{what} has {got} entries, expected {expected}")]
    Length {
        what: &'static str,
        got: usize,
        expected: usize,
    },
    #[error("{what}[{index}] = {value} must be finite{positive}")]
    Value {
        what: &'static str,
        index: usize,
        value: f64,
        positive: &'static str,
    },
}

/// Input offset/scale and output scale of one network (physical units ↔ O(1) net units).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetScaling {
    /// Subtracted from each input (the workspace centre).
    pub in_center: Vec<f64>,
    /// Each centred input is divided by this.
    pub in_scale: Vec<f64>,
    /// Each raw net output is multiplied by this (the physical unit of that output).
    pub out_scale: Vec<f64>,
}

impl NetScaling {
    fn check(&self, inputs: usize, outputs: usize) -> Result<(), MlpError> {
        let lengths = [
            ("in_center", self.in_center.len(), inputs),
            ("in_scale", self.in_scale.len(), inputs),
            ("out_scale", self.out_scale.len(), outputs),
        ];
        for (what, got, expected) in lengths {
            if got != expected {
                return Err(MlpError::Length {
                    what,
                    got,
                    expected,
                });
            }
        }
        for (i, v) in self.in_center.iter().enumerate() {
            if !v.is_finite() {
                return Err(MlpError::Value {
                    what: "in_center",
                    index: i,
                    value: *v,
                    positive: "",
                });
            }
        }
        for (what, vals) in [("in_scale", &self.in_scale), ("out_scale", &self.out_scale)] {
            for (i, v) in vals.iter().enumerate() {
                if !(v.is_finite() && *v > 0.0) {
                    return Err(MlpError::Value {
                        what,
                        index: i,
                        value: *v,
                        positive: " and > 0",
                    });
                }
            }
        }
        Ok(())
    }
}

/// Tanh MLP with preallocated work buffers.
#[derive(Debug, Clone)]
pub struct Mlp {
    inputs: usize,
    hidden: usize,
    outputs: usize,
    scaling: NetScaling,
    in_gain: Vec<f64>,
    params: Vec<f64>,
    grad: Vec<f64>,
    // Last forward pass: scaled input, activations, physical output.
    x: Vec<f64>,
    h: Vec<f64>,
    y: Vec<f64>,
    // Last tangent pass: scaled direction, ȧ = W1 ũ, ḣ = (1 − h²) ⊙ ȧ, physical ẏ.
    u: Vec<f64>,
    adot: Vec<f64>,
    hdot: Vec<f64>,
    ydot: Vec<f64>,
    has_tangent: bool,
    // Backward scratch.
    r: Vec<f64>,
    rdot: Vec<f64>,
    abar: Vec<f64>,
    adotbar: Vec<f64>,
}

impl Mlp {
    /// A network with all parameters zero; see `init_random` and `set_params`.
    pub fn new(
        inputs: usize,
        hidden: usize,
        outputs: usize,
        scaling: NetScaling,
    ) -> Result<Self, MlpError> {
        if inputs == 0 || hidden == 0 || outputs == 0 {
            return Err(MlpError::Size {
                inputs,
                hidden,
                outputs,
            });
        }
        scaling.check(inputs, outputs)?;
        let n = hidden * inputs + hidden + outputs * hidden + outputs;
        Ok(Mlp {
            inputs,
            hidden,
            outputs,
            in_gain: scaling.in_scale.iter().map(|s| 1.0 / s).collect(),
            scaling,
            params: vec![0.0; n],
            grad: vec![0.0; n],
            x: vec![0.0; inputs],
            h: vec![0.0; hidden],
            y: vec![0.0; outputs],
            u: vec![0.0; inputs],
            adot: vec![0.0; hidden],
            hdot: vec![0.0; hidden],
            ydot: vec![0.0; outputs],
            has_tangent: false,
            r: vec![0.0; outputs],
            rdot: vec![0.0; outputs],
            abar: vec![0.0; hidden],
            adotbar: vec![0.0; hidden],
        })
    }

    pub fn inputs(&self) -> usize {
        self.inputs
    }
    pub fn hidden(&self) -> usize {
        self.hidden
    }
    pub fn outputs(&self) -> usize {
        self.outputs
    }
    pub fn scaling(&self) -> &NetScaling {
        &self.scaling
    }

    /// Number of parameters of the hidden layer (W1, b1); they come first in `params`.
    pub fn hidden_len(&self) -> usize {
        self.hidden * (self.inputs + 1)
    }

    pub fn params(&self) -> &[f64] {
        &self.params
    }
    pub fn params_mut(&mut self) -> &mut [f64] {
        &mut self.params
    }

    /// Replace all parameters (length must match).
    pub fn set_params(&mut self, p: &[f64]) -> Result<(), MlpError> {
        if p.len() != self.params.len() {
            return Err(MlpError::Length {
                what: "parameter vector",
                got: p.len(),
                expected: self.params.len(),
            });
        }
        self.params.copy_from_slice(p);
        Ok(())
    }

    /// Accumulated gradient (same layout as `params`).
    pub fn grad(&self) -> &[f64] {
        &self.grad
    }
    pub fn grad_mut(&mut self) -> &mut [f64] {
        &mut self.grad
    }
    pub fn zero_grad(&mut self) {
        self.grad.fill(0.0);
    }
    /// Parameters and gradient together (the update reads one and writes the other).
    pub fn params_and_grad_mut(&mut self) -> (&mut [f64], &mut [f64]) {
        (&mut self.params, &mut self.grad)
    }

    /// Small random weights: hidden layer uniform with standard deviation
    /// `std_hidden/√inputs` (so the tanh units see O(1) arguments on O(1) inputs, i.e. the
    /// features are diverse but not saturated), output layer uniform with `std_output`.
    pub fn init_random<R: Rng>(&mut self, rng: &mut R, std_hidden: f64, std_output: f64) {
        let hl = self.hidden_len();
        let sh = std_hidden / (self.inputs as f64).sqrt();
        // Uniform on [−√3σ, √3σ] has standard deviation σ.
        let s3 = 3f64.sqrt();
        for (i, p) in self.params.iter_mut().enumerate() {
            let s = if i < hl { sh } else { std_output };
            *p = s * s3 * (2.0 * rng.random::<f64>() - 1.0);
        }
    }

    /// Frobenius norm of all parameters.
    pub fn params_norm(&self) -> f64 {
        self.params.iter().map(|p| p * p).sum::<f64>().sqrt()
    }

    // Offsets in the flat parameter vector.
    fn b1_at(&self) -> usize {
        self.hidden * self.inputs
    }
    fn w2_at(&self) -> usize {
        self.hidden_len()
    }
    fn b2_at(&self) -> usize {
        self.hidden_len() + self.outputs * self.hidden
    }

    /// Forward pass on physical inputs `x`; the activations stay for `tangent`/`backward`.
    pub fn forward(&mut self, x: &[f64]) -> &[f64] {
        debug_assert_eq!(x.len(), self.inputs);
        for ((xs, xi), (c, g)) in self
            .x
            .iter_mut()
            .zip(x)
            .zip(self.scaling.in_center.iter().zip(&self.in_gain))
        {
            *xs = (xi - c) * g;
        }
        let (w1, rest) = self.params.split_at(self.b1_at());
        let (b1, rest) = rest.split_at(self.hidden);
        let (w2, b2) = rest.split_at(self.outputs * self.hidden);
        for ((hj, row), bj) in self.h.iter_mut().zip(w1.chunks_exact(self.inputs)).zip(b1) {
            let a: f64 = row.iter().zip(&self.x).map(|(w, x)| w * x).sum::<f64>() + bj;
            *hj = tanh(a);
        }
        for (((yo, row), bo), so) in self
            .y
            .iter_mut()
            .zip(w2.chunks_exact(self.hidden))
            .zip(b2)
            .zip(&self.scaling.out_scale)
        {
            let z: f64 = row.iter().zip(&self.h).map(|(w, h)| w * h).sum::<f64>() + bo;
            *yo = so * z;
        }
        self.has_tangent = false;
        &self.y
    }

    /// Output of the last forward pass.
    pub fn output(&self) -> &[f64] {
        &self.y
    }

    /// Directional derivative ẏ = (∂y/∂x)·u at the last forward point, for a physical-unit
    /// direction `u`. `backward` then also accepts a cotangent on ẏ.
    pub fn tangent(&mut self, u: &[f64]) -> &[f64] {
        debug_assert_eq!(u.len(), self.inputs);
        for ((us, ui), g) in self.u.iter_mut().zip(u).zip(&self.in_gain) {
            *us = ui * g;
        }
        let (w1, rest) = self.params.split_at(self.b1_at());
        let w2 = &rest[self.hidden..self.hidden + self.outputs * self.hidden];
        for (((ad, hd), row), hj) in self
            .adot
            .iter_mut()
            .zip(self.hdot.iter_mut())
            .zip(w1.chunks_exact(self.inputs))
            .zip(&self.h)
        {
            *ad = row.iter().zip(&self.u).map(|(w, u)| w * u).sum();
            *hd = (1.0 - hj * hj) * *ad;
        }
        for ((yd, row), so) in self
            .ydot
            .iter_mut()
            .zip(w2.chunks_exact(self.hidden))
            .zip(&self.scaling.out_scale)
        {
            *yd = so * row.iter().zip(&self.hdot).map(|(w, h)| w * h).sum::<f64>();
        }
        self.has_tangent = true;
        &self.ydot
    }

    /// Tangent of the last `tangent` call.
    pub fn tangent_output(&self) -> &[f64] {
        &self.ydot
    }

    /// Accumulate ∂L/∂θ into `grad` for L = ȳᵀy + ẏ̄ᵀẏ at the last forward (and tangent)
    /// point. `ydot_bar` is used only if `tangent` was called after the last `forward`.
    ///
    /// Derivation (d = 1 − h², r = s_out ⊙ ȳ, ṙ = s_out ⊙ ẏ̄):
    ///   ∂L/∂b2 = r,  ∂L/∂W2 = r hᵀ + ṙ ḣᵀ,
    ///   h̄ = W2ᵀr − 2h ⊙ (W2ᵀṙ) ⊙ ȧ   (the second term: ḣ depends on h through d),
    ///   ā = d ⊙ h̄,  ǡ = d ⊙ (W2ᵀṙ),
    ///   ∂L/∂b1 = ā,  ∂L/∂W1 = ā x̃ᵀ + ǡ ũᵀ.
    pub fn backward(&mut self, y_bar: &[f64], ydot_bar: Option<&[f64]>) {
        debug_assert_eq!(y_bar.len(), self.outputs);
        let tangent = match ydot_bar {
            Some(v) if self.has_tangent => {
                debug_assert_eq!(v.len(), self.outputs);
                for ((r, v), s) in self.rdot.iter_mut().zip(v).zip(&self.scaling.out_scale) {
                    *r = v * s;
                }
                true
            }
            _ => false,
        };
        for ((r, v), s) in self.r.iter_mut().zip(y_bar).zip(&self.scaling.out_scale) {
            *r = v * s;
        }
        let (b1_at, w2_at, b2_at) = (self.b1_at(), self.w2_at(), self.b2_at());
        let (hid, inp) = (self.hidden, self.inputs);
        let w2 = &self.params[w2_at..b2_at];
        let (gw1, grest) = self.grad.split_at_mut(b1_at);
        let (gb1, grest) = grest.split_at_mut(hid);
        let (gw2, gb2) = grest.split_at_mut(self.outputs * hid);

        for (g, r) in gb2.iter_mut().zip(&self.r) {
            *g += r;
        }
        for (o, grow) in gw2.chunks_exact_mut(hid).enumerate() {
            let r = self.r[o];
            for (g, h) in grow.iter_mut().zip(&self.h) {
                *g += r * h;
            }
            if tangent {
                let rd = self.rdot[o];
                for (g, hd) in grow.iter_mut().zip(&self.hdot) {
                    *g += rd * hd;
                }
            }
        }
        // ā and ǡ per hidden unit; W2 is walked by column j.
        for j in 0..hid {
            let mut hbar = 0.0;
            let mut hdbar = 0.0;
            for o in 0..self.outputs {
                let w = w2[o * hid + j];
                hbar += w * self.r[o];
                if tangent {
                    hdbar += w * self.rdot[o];
                }
            }
            let hj = self.h[j];
            let d = 1.0 - hj * hj;
            if tangent {
                hbar -= 2.0 * hj * hdbar * self.adot[j];
                self.adotbar[j] = d * hdbar;
            } else {
                self.adotbar[j] = 0.0;
            }
            self.abar[j] = d * hbar;
        }
        for (g, a) in gb1.iter_mut().zip(&self.abar) {
            *g += a;
        }
        for ((grow, a), ad) in gw1.chunks_exact_mut(inp).zip(&self.abar).zip(&self.adotbar) {
            for (g, x) in grow.iter_mut().zip(&self.x) {
                *g += a * x;
            }
            if tangent {
                for (g, u) in grow.iter_mut().zip(&self.u) {
                    *g += ad * u;
                }
            }
        }
    }

    /// ∂(ȳᵀy)/∂x in physical input units at the last forward point, written to `x_bar`.
    pub fn input_gradient(&mut self, y_bar: &[f64], x_bar: &mut [f64]) {
        debug_assert_eq!(y_bar.len(), self.outputs);
        debug_assert_eq!(x_bar.len(), self.inputs);
        let (hid, inp) = (self.hidden, self.inputs);
        let w1 = &self.params[..self.b1_at()];
        let w2 = &self.params[self.w2_at()..self.b2_at()];
        for j in 0..hid {
            let mut hbar = 0.0;
            for o in 0..self.outputs {
                hbar += w2[o * hid + j] * y_bar[o] * self.scaling.out_scale[o];
            }
            self.abar[j] = (1.0 - self.h[j] * self.h[j]) * hbar;
        }
        for (i, xb) in x_bar.iter_mut().enumerate() {
            let s: f64 = (0..hid).map(|j| w1[j * inp + i] * self.abar[j]).sum();
            *xb = s * self.in_gain[i];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn net(seed: u64) -> Mlp {
        let scaling = NetScaling {
            in_center: vec![0.1, 0.6, -0.2, 0.0],
            in_scale: vec![0.5, 0.4, 0.7, 2.0],
            out_scale: vec![1e-3, 2e-3, 5e-2],
        };
        let mut m = Mlp::new(4, 7, 3, scaling).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        // Larger than the defaults so every term of the derivatives matters.
        m.init_random(&mut rng, 1.5, 0.8);
        m
    }

    fn rand_vec(rng: &mut ChaCha8Rng, n: usize, s: f64) -> Vec<f64> {
        (0..n)
            .map(|_| s * (2.0 * rng.random::<f64>() - 1.0))
            .collect()
    }

    /// L(θ) = ȳᵀy + ẏ̄ᵀẏ evaluated from scratch.
    fn loss(m: &mut Mlp, x: &[f64], u: &[f64], yb: &[f64], ydb: &[f64]) -> f64 {
        let y: f64 = m.forward(x).iter().zip(yb).map(|(a, b)| a * b).sum();
        let yd: f64 = m.tangent(u).iter().zip(ydb).map(|(a, b)| a * b).sum();
        y + yd
    }

    fn rel_err(a: &[f64], b: &[f64]) -> f64 {
        let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>();
        let den: f64 = b.iter().map(|y| y * y).sum::<f64>();
        (num / den).sqrt()
    }

    #[test]
    fn weight_gradients_match_finite_differences_per_layer_and_term() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for trial in 0..5 {
            let mut m = net(trial);
            let x = rand_vec(&mut rng, 4, 1.0);
            let u = rand_vec(&mut rng, 4, 2.0);
            // The value term and the tangent term separately, then together.
            for (use_y, use_yd) in [(true, false), (false, true), (true, true)] {
                let yb = if use_y {
                    rand_vec(&mut rng, 3, 1.0)
                } else {
                    vec![0.0; 3]
                };
                let ydb = if use_yd {
                    rand_vec(&mut rng, 3, 1.0)
                } else {
                    vec![0.0; 3]
                };
                m.zero_grad();
                m.forward(&x);
                m.tangent(&u);
                m.backward(&yb, Some(&ydb));
                let analytic = m.grad().to_vec();
                let h = 1e-6;
                let fd: Vec<f64> = (0..m.params().len())
                    .map(|i| {
                        let p0 = m.params()[i];
                        m.params_mut()[i] = p0 + h;
                        let lp = loss(&mut m, &x, &u, &yb, &ydb);
                        m.params_mut()[i] = p0 - h;
                        let lm = loss(&mut m, &x, &u, &yb, &ydb);
                        m.params_mut()[i] = p0;
                        (lp - lm) / (2.0 * h)
                    })
                    .collect();
                let (b1, w2, b2) = (m.b1_at(), m.w2_at(), m.b2_at());
                for (name, range) in [
                    ("W1", 0..b1),
                    ("b1", b1..w2),
                    ("W2", w2..b2),
                    ("b2", b2..fd.len()),
                ] {
                    let e = rel_err(&analytic[range.clone()], &fd[range.clone()]);
                    // b2 does not enter ẏ: its gradient is exactly zero for the tangent term.
                    if !use_y && name == "b2" {
                        assert!(analytic[range].iter().all(|g| *g == 0.0));
                        continue;
                    }
                    assert!(e < 1e-6, "{name} (y {use_y}, ẏ {use_yd}): rel err {e:e}");
                }
            }
        }
    }

    #[test]
    fn backward_without_tangent_ignores_the_tangent_cotangent() {
        let mut m = net(3);
        let x = [0.2, 0.5, 0.1, -1.0];
        m.forward(&x);
        m.zero_grad();
        m.backward(&[1.0, -2.0, 0.5], Some(&[9.0, 9.0, 9.0]));
        let with = m.grad().to_vec();
        m.zero_grad();
        m.backward(&[1.0, -2.0, 0.5], None);
        assert_eq!(with, m.grad());
    }

    #[test]
    fn tangent_and_input_gradient_match_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        for trial in 0..5 {
            let mut m = net(100 + trial);
            let x = rand_vec(&mut rng, 4, 1.0);
            let u = rand_vec(&mut rng, 4, 2.0);
            m.forward(&x);
            let ydot = m.tangent(&u).to_vec();
            let h = 1e-6;
            let xp: Vec<f64> = x.iter().zip(&u).map(|(a, b)| a + h * b).collect();
            let xm: Vec<f64> = x.iter().zip(&u).map(|(a, b)| a - h * b).collect();
            let yp = m.forward(&xp).to_vec();
            let ym = m.forward(&xm).to_vec();
            let fd: Vec<f64> = yp
                .iter()
                .zip(&ym)
                .map(|(a, b)| (a - b) / (2.0 * h))
                .collect();
            assert!(rel_err(&ydot, &fd) < 1e-6, "tangent {ydot:?} vs {fd:?}");

            let yb = rand_vec(&mut rng, 3, 1.0);
            m.forward(&x);
            let mut xb = vec![0.0; 4];
            m.input_gradient(&yb, &mut xb);
            let fd: Vec<f64> = (0..4)
                .map(|i| {
                    let mut xp = x.clone();
                    let mut xm = x.clone();
                    xp[i] += h;
                    xm[i] -= h;
                    let lp: f64 = m.forward(&xp).iter().zip(&yb).map(|(a, b)| a * b).sum();
                    let lm: f64 = m.forward(&xm).iter().zip(&yb).map(|(a, b)| a * b).sum();
                    (lp - lm) / (2.0 * h)
                })
                .collect();
            assert!(rel_err(&xb, &fd) < 1e-6, "input gradient {xb:?} vs {fd:?}");
        }
    }

    #[test]
    fn scaling_maps_inputs_and_outputs() {
        let scaling = NetScaling {
            in_center: vec![1.0],
            in_scale: vec![2.0],
            out_scale: vec![1e-3],
        };
        let mut m = Mlp::new(1, 1, 1, scaling).unwrap();
        // y = 1e-3·(w2·tanh(w1·(x − 1)/2 + b1) + b2)
        m.set_params(&[1.0, 0.0, 3.0, 0.5]).unwrap();
        let y = m.forward(&[2.0])[0];
        assert!((y - 1e-3 * (3.0 * 0.5f64.tanh() + 0.5)).abs() < 1e-15);
        assert!((m.forward(&[1.0])[0] - 0.5e-3).abs() < 1e-15);
    }

    #[test]
    fn bad_sizes_and_scalings_are_errors() {
        let ok = NetScaling {
            in_center: vec![0.0; 2],
            in_scale: vec![1.0; 2],
            out_scale: vec![1.0],
        };
        assert!(matches!(
            Mlp::new(2, 0, 1, ok.clone()),
            Err(MlpError::Size { .. })
        ));
        assert!(matches!(
            Mlp::new(3, 4, 1, ok.clone()),
            Err(MlpError::Length { .. })
        ));
        let mut bad = ok.clone();
        bad.in_scale[1] = 0.0;
        assert!(matches!(
            Mlp::new(2, 4, 1, bad),
            Err(MlpError::Value { .. })
        ));
        let mut bad = ok;
        bad.in_center[0] = f64::NAN;
        assert!(matches!(
            Mlp::new(2, 4, 1, bad),
            Err(MlpError::Value { .. })
        ));
        let mut m = Mlp::new(
            1,
            1,
            1,
            NetScaling {
                in_center: vec![0.0],
                in_scale: vec![1.0],
                out_scale: vec![1.0],
            },
        )
        .unwrap();
        assert!(m.set_params(&[1.0; 3]).is_err());
    }
}
