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

use crate::fast_tanh::tanh_in_place;
use nalgebra::{Const, Dim, Dyn};
use rand::Rng;
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Why a network could not be built or loaded.
#[derive(Debug, Error, PartialEq)]
pub enum MlpError {
    /// A layer with no neurons.
    #[error(
        "network sizes must be at least 1 (inputs {inputs}, hidden {hidden}, outputs {outputs})"
    )]
    Size {
        /// Inputs asked for.
        inputs: usize,
        /// Hidden neurons asked for.
        hidden: usize,
        /// Outputs asked for.
        outputs: usize,
    },
    /// A vector (parameters, scaling) of the wrong length for the sizes.
    #[error("{what} has {got} entries, expected {expected}")]
    Length {
        /// Which vector.
        what: &'static str,
        /// Its length.
        got: usize,
        /// The length the sizes call for.
        expected: usize,
    },
    /// A value that is not finite, or not positive where it must be.
    #[error("{what}[{index}] = {value} must be finite{positive}")]
    Value {
        /// Which vector.
        what: &'static str,
        /// The entry's index.
        index: usize,
        /// The entry.
        value: f64,
        /// `" and > 0"` where the value must be positive too, else empty.
        positive: &'static str,
    },
}

/// Input offset/scale and output scale of one network (physical units ↔ O(1) net units).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct NetScaling {
    /// Subtracted from each input (the workspace centre).
    pub(crate) in_center: Vec<f64>,
    /// Each centred input is divided by this.
    pub(crate) in_scale: Vec<f64>,
    /// Each raw net output is multiplied by this (the physical unit of that output).
    pub(crate) out_scale: Vec<f64>,
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
pub(crate) struct Mlp {
    inputs: usize,
    hidden: usize,
    outputs: usize,
    scaling: NetScaling,
    in_gain: Vec<f64>,
    params: Vec<f64>,
    grad: Vec<f64>,
    // The weight update writes the stepped parameters here, then swaps them in (`commit_step`).
    next: Vec<f64>,
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
    // Whether omnid's own sizes take the compile-time-sized loops (tests turn it off to
    // compare the two).
    specialised: bool,
}

/// The sizes omnid builds (M̂ 3→6, Ĉ 6→9, Ĝ and F̂ 3→3) run the per-tick loops with
/// compile-time input and output counts, so their short inner loops unroll; any other size
/// runs the same code with run-time counts.
macro_rules! with_dims {
    ($net:ident, $kernel:ident ( $($arg:expr),* )) => {
        match ($net.specialised, $net.inputs, $net.outputs) {
            (true, 3, 6) => $net.$kernel(Const::<3>, Const::<6>, $($arg),*),
            (true, 6, 9) => $net.$kernel(Const::<6>, Const::<9>, $($arg),*),
            (true, 3, 3) => $net.$kernel(Const::<3>, Const::<3>, $($arg),*),
            (_, p, o) => $net.$kernel(Dyn(p), Dyn(o), $($arg),*),
        }
    };
}

/// Dot product of a short (input-sized) row, summed in order.
#[inline(always)]
fn dot_short(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(a, b)| a * b).sum()
}

/// Dot product over the hidden layer, in four independent partial sums: one running sum
/// would make every multiply wait for the previous add.
#[inline(always)]
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (a[..n].chunks_exact(4), b[..n].chunks_exact(4));
    let tail: f64 = dot_short(a.remainder(), b.remainder());
    let mut s = [0.0; 4];
    for (a, b) in a.zip(b) {
        for k in 0..4 {
            s[k] += a[k] * b[k];
        }
    }
    (s[0] + s[1]) + (s[2] + s[3]) + tail
}

/// y += α·x.
#[inline(always)]
fn axpy(alpha: f64, x: &[f64], y: &mut [f64]) {
    for (y, x) in y.iter_mut().zip(x) {
        *y += alpha * x;
    }
}

impl Mlp {
    /// A network with all parameters zero; see `init_random` and `set_params`.
    pub(crate) fn new(
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
            next: vec![0.0; n],
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
            specialised: true,
        })
    }

    pub(crate) fn inputs(&self) -> usize {
        self.inputs
    }
    pub(crate) fn hidden(&self) -> usize {
        self.hidden
    }
    pub(crate) fn outputs(&self) -> usize {
        self.outputs
    }
    pub(crate) fn scaling(&self) -> &NetScaling {
        &self.scaling
    }

    /// Number of parameters of the hidden layer (W1, b1); they come first in `params`.
    pub(crate) fn hidden_len(&self) -> usize {
        self.hidden * (self.inputs + 1)
    }

    pub(crate) fn params(&self) -> &[f64] {
        &self.params
    }
    pub(crate) fn params_mut(&mut self) -> &mut [f64] {
        &mut self.params
    }

    /// Replace all parameters (length must match).
    pub(crate) fn set_params(&mut self, p: &[f64]) -> Result<(), MlpError> {
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
    #[cfg(test)]
    pub(crate) fn grad(&self) -> &[f64] {
        &self.grad
    }
    pub(crate) fn zero_grad(&mut self) {
        self.grad.fill(0.0);
    }
    /// Parameters and gradient together (the update reads one and writes the other).
    pub(crate) fn params_and_grad_mut(&mut self) -> (&mut [f64], &mut [f64]) {
        (&mut self.params, &mut self.grad)
    }
    /// The online update's buffers: the parameters, the gradient (the update turns it into
    /// the step) and the stepped parameters, written in the same pass and taken by
    /// `commit_step` once every network's step has been checked.
    pub(crate) fn step_buffers(&mut self) -> (&[f64], &mut [f64], &mut [f64]) {
        (&self.params, &mut self.grad, &mut self.next)
    }
    /// Make the parameters written by the update through `step_buffers` the current ones.
    pub(crate) fn commit_step(&mut self) {
        std::mem::swap(&mut self.params, &mut self.next);
    }

    /// Small random weights: hidden layer uniform with standard deviation
    /// `std_hidden/√inputs` (so the tanh units see O(1) arguments on O(1) inputs, i.e. the
    /// features are diverse but not saturated), output layer uniform with `std_output`.
    pub(crate) fn init_random<R: Rng>(&mut self, rng: &mut R, std_hidden: f64, std_output: f64) {
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
    pub(crate) fn params_norm(&self) -> f64 {
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
    pub(crate) fn forward(&mut self, x: &[f64]) -> &[f64] {
        debug_assert_eq!(x.len(), self.inputs);
        with_dims!(self, forward_dims(x));
        self.has_tangent = false;
        &self.y
    }

    fn forward_dims<P: Dim, O: Dim>(&mut self, p: P, o: O, x: &[f64]) {
        let (inp, out, hid) = (p.value(), o.value(), self.hidden);
        let scaled = self.x[..inp].iter_mut().zip(&x[..inp]);
        let centre_gain = self.scaling.in_center[..inp]
            .iter()
            .zip(&self.in_gain[..inp]);
        for ((xs, xi), (c, g)) in scaled.zip(centre_gain) {
            *xs = (xi - c) * g;
        }
        let xs = &self.x[..inp];
        let w1 = &self.params[..self.b1_at()];
        let b1 = &self.params[self.b1_at()..self.w2_at()];
        let w2 = &self.params[self.w2_at()..self.b2_at()];
        let b2 = &self.params[self.b2_at()..];
        for ((hj, row), bj) in self.h.iter_mut().zip(w1.chunks_exact(inp)).zip(b1) {
            *hj = dot_short(row, xs) + bj;
        }
        // The layer's units at once: the tanh vectorises (src/fast_tanh.rs).
        tanh_in_place(&mut self.h[..hid]);
        let out_rows = w2.chunks_exact(hid).zip(&b2[..out]);
        for ((yo, (row, bo)), so) in self.y[..out]
            .iter_mut()
            .zip(out_rows)
            .zip(&self.scaling.out_scale[..out])
        {
            *yo = so * (dot(row, &self.h) + bo);
        }
    }

    /// Output of the last forward pass.
    #[cfg(test)]
    pub(crate) fn output(&self) -> &[f64] {
        &self.y
    }

    /// Directional derivative ẏ = (∂y/∂x)·u at the last forward point, for a physical-unit
    /// direction `u`. `backward` then also accepts a cotangent on ẏ.
    pub(crate) fn tangent(&mut self, u: &[f64]) -> &[f64] {
        debug_assert_eq!(u.len(), self.inputs);
        with_dims!(self, tangent_dims(u));
        self.has_tangent = true;
        &self.ydot
    }

    fn tangent_dims<P: Dim, O: Dim>(&mut self, p: P, o: O, u: &[f64]) {
        let (inp, out, hid) = (p.value(), o.value(), self.hidden);
        for ((us, ui), g) in self.u[..inp]
            .iter_mut()
            .zip(&u[..inp])
            .zip(&self.in_gain[..inp])
        {
            *us = ui * g;
        }
        let us = &self.u[..inp];
        let w1 = &self.params[..self.b1_at()];
        let w2 = &self.params[self.w2_at()..self.b2_at()];
        for (((ad, hd), row), hj) in self
            .adot
            .iter_mut()
            .zip(self.hdot.iter_mut())
            .zip(w1.chunks_exact(inp))
            .zip(&self.h)
        {
            *ad = dot_short(row, us);
            *hd = (1.0 - hj * hj) * *ad;
        }
        for ((yd, row), so) in self.ydot[..out]
            .iter_mut()
            .zip(w2.chunks_exact(hid))
            .zip(&self.scaling.out_scale[..out])
        {
            *yd = so * dot(row, &self.hdot);
        }
    }

    /// Tangent of the last `tangent` call.
    #[cfg(test)]
    pub(crate) fn tangent_output(&self) -> &[f64] {
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
    pub(crate) fn backward(&mut self, y_bar: &[f64], ydot_bar: Option<&[f64]>) {
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
        with_dims!(self, backward_dims(tangent));
    }

    fn backward_dims<P: Dim, O: Dim>(&mut self, p: P, o: O, tangent: bool) {
        let (inp, out, hid) = (p.value(), o.value(), self.hidden);
        let (b1_at, w2_at, b2_at) = (self.b1_at(), self.w2_at(), self.b2_at());
        let w2 = &self.params[w2_at..b2_at];
        let (gw1, grest) = self.grad.split_at_mut(b1_at);
        let (gb1, grest) = grest.split_at_mut(hid);
        let (gw2, gb2) = grest.split_at_mut(out * hid);
        let (r, rdot) = (&self.r[..out], &self.rdot[..out]);
        let (h, hdot, adot) = (&self.h[..hid], &self.hdot[..hid], &self.adot[..hid]);

        for (g, r) in gb2[..out].iter_mut().zip(r) {
            *g += r;
        }
        // W2's rows give ∂L/∂W2 and, summed, W2ᵀr (in `abar`) and W2ᵀṙ (in `adotbar`).
        let (abar, adotbar) = (&mut self.abar[..hid], &mut self.adotbar[..hid]);
        abar.fill(0.0);
        adotbar.fill(0.0);
        let rows = gw2.chunks_exact_mut(hid).zip(w2.chunks_exact(hid));
        for ((grow, wrow), (&ro, &rd)) in rows.zip(r.iter().zip(rdot)) {
            axpy(ro, h, grow);
            axpy(ro, wrow, abar);
            if tangent {
                axpy(rd, hdot, grow);
                axpy(rd, wrow, adotbar);
            }
        }
        if tangent {
            for (((a, ad), hj), adj) in abar.iter_mut().zip(adotbar.iter_mut()).zip(h).zip(adot) {
                let d = 1.0 - hj * hj;
                *a = d * (*a - 2.0 * hj * *ad * adj);
                *ad *= d;
            }
        } else {
            for (a, hj) in abar.iter_mut().zip(h) {
                *a *= 1.0 - hj * hj;
            }
        }
        for (g, a) in gb1.iter_mut().zip(abar.iter()) {
            *g += a;
        }
        let (xs, us) = (&self.x[..inp], &self.u[..inp]);
        for ((grow, &a), &ad) in gw1
            .chunks_exact_mut(inp)
            .zip(abar.iter())
            .zip(adotbar.iter())
        {
            axpy(a, xs, grow);
            if tangent {
                axpy(ad, us, grow);
            }
        }
    }

    /// ∂(ȳᵀy)/∂x in physical input units at the last forward point, written to `x_bar`.
    #[cfg(test)]
    pub(crate) fn input_gradient(&mut self, y_bar: &[f64], x_bar: &mut [f64]) {
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
        sized_net(seed, 4, 7, 3)
    }

    /// A random network of the given size with uneven scalings.
    fn sized_net(seed: u64, inputs: usize, hidden: usize, outputs: usize) -> Mlp {
        let scaling = NetScaling {
            in_center: (0..inputs).map(|i| 0.3 * i as f64 - 0.2).collect(),
            in_scale: (0..inputs).map(|i| 0.4 + 0.3 * i as f64).collect(),
            out_scale: (0..outputs).map(|o| 1e-3 * (1 + 7 * o) as f64).collect(),
        };
        let mut m = Mlp::new(inputs, hidden, outputs, scaling).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        // Larger than the defaults so every term of the derivatives matters.
        m.init_random(&mut rng, 1.5, 0.8);
        m
    }

    /// omnid's own sizes (compile-time loops) and two others (run-time loops; hidden 7 is
    /// not a multiple of the four partial sums).
    const SIZES: [(usize, usize, usize); 5] =
        [(4, 7, 3), (3, 16, 6), (6, 16, 9), (3, 16, 3), (2, 5, 1)];

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
        for (trial, &(p, hid, o)) in SIZES.iter().cycle().take(10).enumerate() {
            let mut m = sized_net(trial as u64, p, hid, o);
            let x = rand_vec(&mut rng, p, 1.0);
            let u = rand_vec(&mut rng, p, 2.0);
            // The value term and the tangent term separately, then together.
            for (use_y, use_yd) in [(true, false), (false, true), (true, true)] {
                let yb = if use_y {
                    rand_vec(&mut rng, o, 1.0)
                } else {
                    vec![0.0; o]
                };
                let ydb = if use_yd {
                    rand_vec(&mut rng, o, 1.0)
                } else {
                    vec![0.0; o]
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
                    assert!(
                        e < 1e-6,
                        "{name} ({p}→{hid}→{o}, y {use_y}, ẏ {use_yd}): rel err {e:e}"
                    );
                }
            }
        }
    }

    #[test]
    fn compile_time_and_run_time_loops_agree_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for &(p, hid, o) in &SIZES {
            let mut fixed = sized_net(9, p, hid, o);
            let mut generic = fixed.clone();
            generic.specialised = false;
            let (x, u) = (rand_vec(&mut rng, p, 1.0), rand_vec(&mut rng, p, 2.0));
            let (yb, ydb) = (rand_vec(&mut rng, o, 1.0), rand_vec(&mut rng, o, 1.0));
            for m in [&mut fixed, &mut generic] {
                m.forward(&x);
                m.tangent(&u);
                m.backward(&yb, Some(&ydb));
                m.backward(&yb, None);
            }
            assert_eq!(fixed.output(), generic.output(), "{p}→{hid}→{o}");
            assert_eq!(fixed.tangent_output(), generic.tangent_output());
            assert_eq!(fixed.grad(), generic.grad());
            assert!(fixed.grad().iter().all(|g| g.is_finite() && *g != 0.0));
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
