//! The adaptive identifier of docs/DESIGN.md §3: M-, C-, G- (and F-) networks, the errors e1..e4,
//! the weighted augmented error ε, the modified error α·e + ė = ε, and the update
//! Δθ = −T·Γ·(∂ε/∂θ)ᵀe with dead zone, σ-modification, projection and a non-finite guard.
//!
//! Everything per tick works in preallocated buffers (the networks' own) and fixed-size
//! nalgebra types; nothing allocates after `new`.

use super::mlp::{Mlp, MlpError, NetScaling};
use super::settings::IdentifierConfig;
use crate::config_check::ConfigError;
use crate::estimate::kalman::AccelLag;
use nalgebra::{Matrix3, SVector, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use thiserror::Error;
use wide::f64x2;

/// Weighted augmented error ε = [e1; λ1·e2; λ2·e3; λ3·e4] (dimensionless, see `torque_scale`).
pub(crate) type Wae = SVector<f64, 12>;

/// Longest step the update integrates over: a stalled loop must not turn into one huge step.
const MAX_DT: f64 = 0.01;

/// Upper-triangle entries of M̂ in the M-net's output order.
const SYM: [(usize, usize); 6] = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];
/// Off-diagonal pairs (n, i), i < n, of e3, and their index among the M-net outputs.
const PAIRS: [(usize, usize, usize); 3] = [(1, 0, 1), (2, 0, 2), (2, 1, 4)];
/// M-net output index of each diagonal entry.
const DIAG: [usize; 3] = [0, 3, 5];

/// Why an identifier could not be built.
#[derive(Debug, Error)]
pub enum IdentError {
    /// The `[identifier]` section is out of range.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A network could not be built with these sizes or scalings.
    #[error("{net}-net: {source}")]
    Net {
        /// Which network (`M`, `C`, `G`, `F`).
        net: &'static str,
        /// What was wrong with it.
        #[source]
        source: MlpError,
    },
}

/// The networks of the identifier.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub(crate) enum Net {
    /// The inertia matrix M̂(q) (six outputs: its distinct entries).
    M,
    /// The Coriolis matrix Ĉ(q, q̇).
    C,
    /// The gravity torque Ĝ(q).
    G,
    /// The friction torque F̂(q̇) (only with `identifier.friction_net`).
    F,
}

impl Net {
    pub(crate) const ALL: [Net; 4] = [Net::M, Net::C, Net::G, Net::F];

    pub(crate) fn name(self) -> &'static str {
        match self {
            Net::M => "M",
            Net::C => "C",
            Net::G => "G",
            Net::F => "F",
        }
    }

    /// (inputs, outputs) of this network.
    pub(crate) fn io(self) -> (usize, usize) {
        match self {
            Net::M => (3, 6),
            Net::C => (6, 9),
            Net::G => (3, 3),
            Net::F => (3, 3),
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// Why the identifier stopped adapting.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Fault {
    /// q, q̇, q̈, τ or dt was not finite.
    NonFiniteInput,
    /// The networks produced a non-finite prediction or error.
    NonFiniteOutput,
    /// The weight step was not finite; it was not applied.
    NonFiniteUpdate,
}

impl std::fmt::Display for Fault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Fault::NonFiniteInput => "identifier: non-finite input (q, q̇, q̈, τ or dt)",
            Fault::NonFiniteOutput => "identifier: non-finite prediction",
            Fault::NonFiniteUpdate => "identifier: non-finite weight update (not applied)",
        })
    }
}

/// What one `update` saw, for logging.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ErrorSnapshot {
    /// Prediction τ̂ with the weights before this tick's update, N·m.
    pub tau_hat: Vector3<f64>,
    /// e1 = τ − τ̂, N·m.
    pub e1: Vector3<f64>,
    /// ‖ε‖ (dimensionless).
    pub wae_norm: f64,
    /// The modified error at the scale of ε (α·‖e‖, or ‖e‖ with a unit-gain filter) in N·m:
    /// the dead zone's measure.
    pub modified_norm: f64,
    /// An eigenvalue of M̂ was outside [eig_min, eig_max].
    pub e4_active: bool,
    /// The weights were changed this tick.
    pub updated: bool,
    /// ‖Δθ‖ over all networks this tick.
    pub step_norm: f64,
}

/// The adaptive neural-network identifier.
#[derive(Debug, Clone)]
pub struct Identifier {
    cfg: IdentifierConfig,
    m: Mlp,
    c: Mlp,
    g: Mlp,
    f: Option<Mlp>,
    /// Pre-tuned (or initial) weights: the σ-modification's anchor.
    theta0: [Vec<f64>; 4],
    /// θ0 holds pre-tuned or loaded weights. Fresh random weights are no anchor worth leaking
    /// toward, so the σ-modification acts only once this is set.
    anchored: bool,
    rates: [[f64; 2]; 4],
    /// Modified error e.
    e: Wae,
    fault: Option<Fault>,
    snap: ErrorSnapshot,
    // Quantities of the last evaluation, reused by the gradient.
    mhat: Matrix3<f64>,
    mdot: Matrix3<f64>,
    chat: Matrix3<f64>,
    ghat: Vector3<f64>,
    fhat: Vector3<f64>,
    /// F̂(0) with the same weights as `fhat`: the G- and F-nets share the torque's constant part
    /// (only Ĝ + F̂ is learned, not how a constant splits between them), so the learned model's
    /// torque at rest is Ĝ(q) + F̂(0) and F̂(q̇) − F̂(0) its friction.
    frest: Vector3<f64>,
    tau_hat: Vector3<f64>,
    qd: Vector3<f64>,
    qdd: Vector3<f64>,
    /// ∂e4_n/∂λ_n (0 or 1) and the eigenvectors (columns) of M̂.
    e4_slope: Vector3<f64>,
    eigvecs: Matrix3<f64>,
    /// (q, q̇) at which M̂, Ĉ, Ĝ, F̂ and the networks' activations were last computed, while
    /// they are still valid: the controller and the update of one tick evaluate the same
    /// point with the same weights, so the second pass is skipped. Cleared by every weight
    /// change and by the single-network accessors.
    forward_at: Option<(Vector3<f64>, Vector3<f64>)>,
    /// Ṁ̂ (the M-net's tangent along q̇) is valid for `forward_at`.
    tangent_done: bool,
    /// (q, q̇) at which `mhat`, `chat`, `ghat` and `fhat` were last computed. Unlike
    /// `forward_at` an adaptation step leaves it: the values are then the model this tick's
    /// sample was seen with (what the momentum observer integrates). Cleared when weights are
    /// replaced from outside.
    model_at: Option<(Vector3<f64>, Vector3<f64>)>,
    /// The lag-matched e1's filters (`lag_match`), once the servo has said what its estimator's
    /// acceleration response is.
    lag: Option<LagMatch>,
    /// Per joint, seconds its e1 row stays out of the update after a velocity reversal
    /// (`reversal_speed`).
    reversal_left: [f64; 3],
}

/// Lag-match states below this (N·m-scale values) are zero (see `LagMatch::step`).
const FLUSH_BELOW: f64 = 1e-150;

/// The lag-matched e1's filter (docs/IDENTIFIER.md, "Lag-matched e1"): τ − Ĉq̇ − Ĝ − F̂ per
/// joint through the estimator's acceleration response L.
#[derive(Debug, Clone, Copy)]
struct LagMatch {
    resp: AccelLag,
    /// Per joint: L's error state.
    d: [Vector3<f64>; 3],
    /// The previous input.
    prev: Vector3<f64>,
    /// The filter holds a history (cleared by a tick that does not learn).
    running: bool,
}

impl LagMatch {
    fn new(resp: AccelLag) -> Self {
        LagMatch {
            resp,
            d: [Vector3::zeros(); 3],
            prev: Vector3::zeros(),
            running: false,
        }
    }

    /// L[u] for this tick's input u (a restarted filter starts settled at u).
    fn step(&mut self, u: &Vector3<f64>) -> Vector3<f64> {
        let mut out = *u;
        for j in 0..3 {
            self.d[j] = if self.running {
                self.resp.a * self.d[j] - self.resp.b * (u[j] - self.prev[j])
            } else {
                Vector3::zeros()
            };
            // On a constant input the state decays geometrically into subnormal numbers, whose
            // arithmetic is many times slower: flush what is far below any torque to zero.
            self.d[j].apply(|x| {
                if x.abs() < FLUSH_BELOW {
                    *x = 0.0;
                }
            });
            out[j] += self.d[j][2];
        }
        self.prev = *u;
        self.running = true;
        out
    }
}

fn sym_from6(m: &[f64]) -> Matrix3<f64> {
    Matrix3::new(m[0], m[1], m[2], m[1], m[3], m[4], m[2], m[4], m[5])
}

fn finite3(v: &Vector3<f64>) -> bool {
    v.iter().all(|x| x.is_finite())
}

/// True if every Gershgorin disc of `m` lies in [lo, hi], so all eigenvalues do.
fn gershgorin_inside(m: &Matrix3<f64>, lo: f64, hi: f64) -> bool {
    (0..3).all(|i| {
        let r: f64 = (0..3).filter(|&j| j != i).map(|j| m[(i, j)].abs()).sum();
        m[(i, i)] - r >= lo && m[(i, i)] + r <= hi
    })
}

impl Identifier {
    /// Fresh networks with small random weights (seeded), M̂ starting at `init_mass_diag`.
    pub fn new(cfg: &IdentifierConfig) -> Result<Self, IdentError> {
        cfg.validate()?;
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        let mut make =
            |net: Net| -> Result<Mlp, IdentError> {
                let (inputs, outputs) = net.io();
                let mut mlp = Mlp::new(inputs, cfg.hidden, outputs, scaling_for(cfg, net))
                    .map_err(|source| IdentError::Net {
                        net: net.name(),
                        source,
                    })?;
                mlp.init_random(&mut rng, cfg.init_std_hidden, cfg.init_std_output);
                Ok(mlp)
            };
        let mut m = make(Net::M)?;
        let c = make(Net::C)?;
        let g = make(Net::G)?;
        let f = if cfg.friction_net {
            Some(make(Net::F)?)
        } else {
            None
        };
        // Start M̂ near a plausible inertia so e4 and the first predictions are sane.
        let b2 = m.params().len() - 6;
        for (k, &o) in DIAG.iter().enumerate() {
            m.params_mut()[b2 + o] = cfg.init_mass_diag[k] / cfg.inertia_scale;
        }
        let mut id = Identifier {
            cfg: cfg.clone(),
            m,
            c,
            g,
            f,
            theta0: Default::default(),
            anchored: false,
            rates: [cfg.rate_m, cfg.rate_c, cfg.rate_g, cfg.rate_f],
            e: Wae::zeros(),
            fault: None,
            snap: ErrorSnapshot::default(),
            mhat: Matrix3::zeros(),
            mdot: Matrix3::zeros(),
            chat: Matrix3::zeros(),
            ghat: Vector3::zeros(),
            fhat: Vector3::zeros(),
            frest: Vector3::zeros(),
            tau_hat: Vector3::zeros(),
            qd: Vector3::zeros(),
            qdd: Vector3::zeros(),
            e4_slope: Vector3::zeros(),
            eigvecs: Matrix3::identity(),
            forward_at: None,
            tangent_done: false,
            model_at: None,
            lag: None,
            reversal_left: [0.0; 3],
        };
        id.set_anchor();
        id.anchored = false;
        Ok(id)
    }

    /// The settings this identifier runs with.
    pub fn config(&self) -> &IdentifierConfig {
        &self.cfg
    }

    /// The network `net` (None for F when `friction_net` is off).
    pub(crate) fn net(&self, net: Net) -> Option<&Mlp> {
        match net {
            Net::M => Some(&self.m),
            Net::C => Some(&self.c),
            Net::G => Some(&self.g),
            Net::F => self.f.as_ref(),
        }
    }

    pub(crate) fn net_mut(&mut self, net: Net) -> Option<&mut Mlp> {
        self.forward_at = None;
        self.model_at = None;
        match net {
            Net::M => Some(&mut self.m),
            Net::C => Some(&mut self.c),
            Net::G => Some(&mut self.g),
            Net::F => self.f.as_mut(),
        }
    }

    fn nets_mut(&mut self) -> [Option<&mut Mlp>; 4] {
        [
            Some(&mut self.m),
            Some(&mut self.c),
            Some(&mut self.g),
            self.f.as_mut(),
        ]
    }

    /// Replace a network wholesale (weights loading); sizes must match the configuration.
    pub(crate) fn replace_net(&mut self, net: Net, mlp: Mlp) {
        self.forward_at = None;
        self.model_at = None;
        match net {
            Net::M => self.m = mlp,
            Net::C => self.c = mlp,
            Net::G => self.g = mlp,
            Net::F => self.f = Some(mlp),
        }
    }

    /// Take the current weights as θ0, the anchor of the σ-modification (after pre-tuning or
    /// loading), and restart the modified error.
    pub fn set_anchor(&mut self) {
        for net in Net::ALL {
            let p = self
                .net(net)
                .map(|n| n.params().to_vec())
                .unwrap_or_default();
            self.theta0[net.index()] = p;
        }
        self.anchored = true;
        self.e = Wae::zeros();
    }

    /// Frobenius norm of each network's parameters, [M, C, G, F] (F = 0 when off).
    pub fn weights_norm(&self) -> [f64; 4] {
        Net::ALL.map(|n| self.net(n).map_or(0.0, Mlp::params_norm))
    }

    /// ‖θ − θ0‖ over all networks: how far adaptation has moved from the anchor.
    pub fn weight_change_norm(&self) -> f64 {
        Net::ALL
            .iter()
            .filter_map(|&n| self.net(n).map(|m| (m, &self.theta0[n.index()])))
            .flat_map(|(m, t0)| m.params().iter().zip(t0))
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt()
    }

    /// All parameters, networks in the order M, C, G, F, appended to `out` (cleared first).
    #[cfg(test)]
    pub(crate) fn parameter_vector(&self, out: &mut Vec<f64>) {
        out.clear();
        for n in Net::ALL {
            if let Some(m) = self.net(n) {
                out.extend_from_slice(m.params());
            }
        }
    }

    /// False once a non-finite value was seen; adaptation has stopped and NNIDC falls back to
    /// PD for as long as this identifier is in use (a new run, or a weights load in
    /// `omnid serve`, brings a new one).
    pub fn healthy(&self) -> bool {
        self.fault.is_none()
    }

    /// Why the identifier stopped learning, once it has (a non-finite value).
    pub fn fault(&self) -> Option<Fault> {
        self.fault
    }

    /// Freeze (`false`) or resume (`true`) online adaptation.
    pub fn set_adapt(&mut self, on: bool) {
        self.cfg.adapt = on;
    }

    /// Copy `other`'s network weights into this identifier without allocating (the servo
    /// loop uses this to hand its weights out). False, and nothing changed, when the networks
    /// differ in size.
    pub(crate) fn copy_weights_from(&mut self, other: &Identifier) -> bool {
        let nets = [Net::M, Net::C, Net::G, Net::F];
        let fits = nets.iter().all(|&n| match (self.net(n), other.net(n)) {
            (Some(a), Some(b)) => a.params().len() == b.params().len(),
            (None, None) => true,
            _ => false,
        });
        if !fits {
            return false;
        }
        for n in nets {
            if let (Some(dst), Some(src)) = (self.net_mut(n), other.net(n)) {
                dst.params_mut().copy_from_slice(src.params());
            }
        }
        true
    }

    /// Stop as a non-finite prediction would: for the tests of what is told when it happens
    /// (the `omnid` crate's station tests too, hence public but hidden).
    #[doc(hidden)]
    pub fn trip_for_test(&mut self) {
        self.trip(Fault::NonFiniteOutput);
    }

    /// Clear the fault: adapt again from the current (last good) weights. Only the tests
    /// need it; a run never resumes a stopped identifier.
    #[cfg(test)]
    pub(crate) fn reset_fault(&mut self) {
        self.fault = None;
        self.e = Wae::zeros();
    }

    /// Errors of the last `update`.
    pub fn last_errors(&self) -> &ErrorSnapshot {
        &self.snap
    }

    /// The modified error e.
    #[cfg(test)]
    pub(crate) fn modified_error(&self) -> &Wae {
        &self.e
    }

    fn trip(&mut self, fault: Fault) {
        self.fault.get_or_insert(fault);
        self.e = Wae::zeros();
    }

    // ---- model accessors (they overwrite the networks' activations; &mut for the buffers) ----

    /// M̂(q), kg·m².
    pub fn mass(&mut self, q: &Vector3<f64>) -> Matrix3<f64> {
        self.forward_at = None;
        sym_from6(self.m.forward(q.as_slice()))
    }

    /// Ṁ̂ = Σ_k ∂M̂/∂q_k q̇_k, exact through the M-net, kg·m²/s.
    #[cfg(test)]
    pub(crate) fn mass_derivative(&mut self, q: &Vector3<f64>, qd: &Vector3<f64>) -> Matrix3<f64> {
        self.forward_at = None;
        self.m.forward(q.as_slice());
        sym_from6(self.m.tangent(qd.as_slice()))
    }

    /// Ĉ(q, q̇), kg·m²/s (multiplies q̇).
    pub fn coriolis(&mut self, q: &Vector3<f64>, qd: &Vector3<f64>) -> Matrix3<f64> {
        self.forward_at = None;
        let x = [q[0], q[1], q[2], qd[0], qd[1], qd[2]];
        Matrix3::from_row_slice(self.c.forward(&x))
    }

    /// Ĝ(q), N·m.
    pub fn gravity(&mut self, q: &Vector3<f64>) -> Vector3<f64> {
        self.forward_at = None;
        Vector3::from_column_slice(self.g.forward(q.as_slice()))
    }

    /// F̂(q̇), N·m (zero without the F-net).
    pub fn friction(&mut self, qd: &Vector3<f64>) -> Vector3<f64> {
        self.forward_at = None;
        match &mut self.f {
            Some(f) => Vector3::from_column_slice(f.forward(qd.as_slice())),
            None => Vector3::zeros(),
        }
    }

    /// NNIDC's law: M̂(q)·v + Ĉ(q, q̇)·q̇ + Ĝ(q) + F̂(q̇) for a commanded acceleration v.
    pub fn inverse_dynamics(
        &mut self,
        q: &Vector3<f64>,
        qd: &Vector3<f64>,
        v: &Vector3<f64>,
    ) -> Vector3<f64> {
        self.forward(q, qd, false);
        self.mhat * v + self.chat * qd + self.ghat + self.fhat
    }

    /// The learned model's M̂(q) and n̂(q, q̇) = Ĉ(q, q̇)·q̇ + Ĝ(q) + F̂(0), for the momentum
    /// observer (docs/TELEOP.md §2): like the parametric observer's model, without friction (a
    /// learned Coulomb step on the near-rest, noisy q̇ of a contact shakes the estimate). At the
    /// point this tick's prediction or update already evaluated, the values it saw (with the
    /// weights before that tick's adaptation step) are returned without another network pass.
    pub(crate) fn momentum_model(
        &mut self,
        q: &Vector3<f64>,
        qd: &Vector3<f64>,
    ) -> (Matrix3<f64>, Vector3<f64>) {
        if self.model_at != Some((*q, *qd)) {
            self.forward(q, qd, false);
        }
        (self.mhat, self.chat * qd + self.ghat + self.frest)
    }

    /// Ĉ(q, q̇)·q̇ + Ĝ(q) + F̂(0): the learned model's torque at rest and in motion, without its
    /// friction (a teleoperation coupling's compensation: docs/TELEOP.md §2).
    pub fn gravity_coriolis(&mut self, q: &Vector3<f64>, qd: &Vector3<f64>) -> Vector3<f64> {
        self.forward(q, qd, false);
        self.chat * qd + self.ghat + self.frest
    }

    /// τ̂ = M̂q̈ + Ĉq̇ + Ĝ (+ F̂) without adapting.
    pub fn predict(
        &mut self,
        q: &Vector3<f64>,
        qd: &Vector3<f64>,
        qdd: &Vector3<f64>,
    ) -> Vector3<f64> {
        // A tick that does not learn breaks the lag-matched e1's history.
        if let Some(lag) = &mut self.lag {
            lag.running = false;
        }
        self.inverse_dynamics(q, qd, qdd)
    }

    /// The servo's estimator: the acceleration response the lag-matched e1 passes the torque
    /// through (`lag_match`; nothing changes without it, or when it is already this one).
    pub(crate) fn match_estimator(&mut self, resp: &AccelLag) {
        if !self.cfg.lag_match || self.lag.as_ref().is_some_and(|l| l.resp == *resp) {
            return;
        }
        self.lag = Some(LagMatch::new(*resp));
    }

    fn forward(&mut self, q: &Vector3<f64>, qd: &Vector3<f64>, tangent: bool) {
        if self.forward_at != Some((*q, *qd)) {
            self.mhat = sym_from6(self.m.forward(q.as_slice()));
            let x = [q[0], q[1], q[2], qd[0], qd[1], qd[2]];
            self.chat = Matrix3::from_row_slice(self.c.forward(&x));
            self.ghat = Vector3::from_column_slice(self.g.forward(q.as_slice()));
            (self.frest, self.fhat) = match &mut self.f {
                // At rest first, so the F-net's activations are the ones at q̇ (the update's).
                Some(f) => (
                    Vector3::from_column_slice(f.forward(&[0.0; 3])),
                    Vector3::from_column_slice(f.forward(qd.as_slice())),
                ),
                None => (Vector3::zeros(), Vector3::zeros()),
            };
            self.forward_at = Some((*q, *qd));
            self.model_at = Some((*q, *qd));
            self.tangent_done = false;
        }
        if tangent && !self.tangent_done {
            self.mdot = sym_from6(self.m.tangent(qd.as_slice()));
            self.tangent_done = true;
        }
    }

    /// 1/(DC gain) of the modified-error filter: α for eq. 21, 1 with `unit_gain_filter`.
    fn filter_gain(&self) -> f64 {
        if self.cfg.unit_gain_filter {
            1.0
        } else {
            self.cfg.alpha
        }
    }

    fn needs_tangent(&self) -> bool {
        self.cfg.lambda1 != 0.0 || self.cfg.lambda2 != 0.0
    }

    /// ε at one sample with the current weights. The activations stay for
    /// `accumulate_gradient`, which must follow before any other evaluation.
    pub(crate) fn evaluate_wae(
        &mut self,
        q: &Vector3<f64>,
        qd: &Vector3<f64>,
        qdd: &Vector3<f64>,
        tau: &Vector3<f64>,
    ) -> Wae {
        let tangent = self.needs_tangent();
        self.forward(q, qd, tangent);
        self.qd = *qd;
        self.qdd = *qdd;
        self.tau_hat = self.mhat * qdd + self.chat * qd + self.ghat + self.fhat;
        let ts = 1.0 / self.cfg.torque_scale;
        let mut eps = Wae::zeros();
        let e1 = tau - self.tau_hat;
        for n in 0..3 {
            eps[n] = e1[n] * ts;
        }
        let (l1, l2, l3) = (self.cfg.lambda1, self.cfg.lambda2, self.cfg.lambda3);
        if l1 != 0.0 {
            for n in 0..3 {
                eps[3 + n] = l1 * ts * (self.mdot[(n, n)] - 2.0 * self.chat[(n, n)]);
            }
        }
        if l2 != 0.0 {
            for (k, &(n, i, _)) in PAIRS.iter().enumerate() {
                let md = self.mdot[(n, i)] + self.mdot[(i, n)];
                eps[6 + k] = l2 * ts * (md - 2.0 * (self.chat[(n, i)] + self.chat[(i, n)]));
            }
        }
        self.e4_slope = Vector3::zeros();
        let (lo, hi) = (self.cfg.eig_min, self.cfg.eig_max);
        let mhat_ok = self.mhat.iter().all(|x| x.is_finite());
        if l3 != 0.0 && mhat_ok && !gershgorin_inside(&self.mhat, lo, hi) {
            // Bounded iterations: never loop on a pathological matrix.
            if let Some(se) = nalgebra::SymmetricEigen::try_new(self.mhat, f64::EPSILON, 200) {
                self.eigvecs = se.eigenvectors;
                for n in 0..3 {
                    let lam = se.eigenvalues[n];
                    let e4 = if lam < lo {
                        lam - lo
                    } else if lam > hi {
                        lam - hi
                    } else {
                        continue;
                    };
                    self.e4_slope[n] = 1.0;
                    eps[9 + n] = l3 * e4 / self.cfg.inertia_scale;
                }
            }
        }
        eps
    }

    /// Add (∂ε/∂θ)ᵀw to every network's gradient buffer, at the point of the last
    /// `evaluate_wae`. Reverse mode: w is the cotangent of ε; it becomes cotangents on the
    /// network outputs M̂ (6), Ṁ̂ (6), Ĉ (9), Ĝ (3), F̂ (3), which each network back-propagates.
    pub(crate) fn accumulate_gradient(&mut self, w: &Wae) {
        let ts = 1.0 / self.cfg.torque_scale;
        let (l1, l2, l3) = (self.cfg.lambda1, self.cfg.lambda2, self.cfg.lambda3);
        // e1 = τ − M̂q̈ − Ĉq̇ − Ĝ − F̂, scaled by ts.
        let w1 = Vector3::new(w[0], w[1], w[2]) * ts;
        // Cotangent on M̂ as a full matrix, then folded onto its 6 free entries.
        let mut mbar = -(w1 * self.qdd.transpose());
        if l3 != 0.0 && self.e4_slope.iter().any(|&s| s != 0.0) {
            // dλ_n/dM = v_n v_nᵀ.
            for n in 0..3 {
                let k = l3 / self.cfg.inertia_scale * w[9 + n] * self.e4_slope[n];
                if k != 0.0 {
                    let v = self.eigvecs.column(n);
                    mbar += k * v * v.transpose();
                }
            }
        }
        let mut m_bar = [0.0; 6];
        for (o, &(i, j)) in SYM.iter().enumerate() {
            m_bar[o] = if i == j {
                mbar[(i, i)]
            } else {
                mbar[(i, j)] + mbar[(j, i)]
            };
        }
        let mut c_bar = [0.0; 9];
        for i in 0..3 {
            for j in 0..3 {
                c_bar[3 * i + j] = -w1[i] * self.qd[j];
            }
        }
        let tangent = self.needs_tangent();
        let mut mdot_bar = [0.0; 6];
        if l1 != 0.0 {
            for n in 0..3 {
                let k = l1 * ts * w[3 + n];
                mdot_bar[DIAG[n]] += k;
                c_bar[4 * n] -= 2.0 * k;
            }
        }
        if l2 != 0.0 {
            for (k, &(n, i, o)) in PAIRS.iter().enumerate() {
                let s = l2 * ts * w[6 + k];
                // Ṁ̂_ni + Ṁ̂_in = 2·(output o) since Ṁ̂ is symmetric.
                mdot_bar[o] += 2.0 * s;
                c_bar[3 * n + i] -= 2.0 * s;
                c_bar[3 * i + n] -= 2.0 * s;
            }
        }
        let g_bar = [-w1[0], -w1[1], -w1[2]];
        self.m.backward(&m_bar, tangent.then_some(&mdot_bar[..]));
        self.c.backward(&c_bar, None);
        self.g.backward(&g_bar, None);
        if let Some(f) = &mut self.f {
            f.backward(&g_bar, None);
        }
    }

    /// Zero every network's gradient buffer.
    pub(crate) fn zero_grads(&mut self) {
        for m in self.nets_mut().into_iter().flatten() {
            m.zero_grad();
        }
    }

    /// One servo tick: predict τ̂ with the current weights, form ε and the modified error e,
    /// and (if adapting, healthy and outside the dead zone) take the step
    /// Δθ = −T·Γ·((∂ε/∂θ)ᵀe + σ(θ − θ0)), projected onto ‖θ‖ ≤ w_max per network.
    /// Returns τ̂ (zero when the inputs are not finite; see `healthy`).
    pub fn update(
        &mut self,
        q: &Vector3<f64>,
        qd: &Vector3<f64>,
        qdd: &Vector3<f64>,
        tau: &Vector3<f64>,
        dt: f64,
    ) -> Vector3<f64> {
        self.snap.updated = false;
        self.snap.step_norm = 0.0;
        if !(finite3(q) && finite3(qd) && finite3(qdd) && finite3(tau) && dt.is_finite()) {
            self.trip(Fault::NonFiniteInput);
            self.snap.tau_hat = Vector3::zeros();
            self.snap.e1 = Vector3::zeros();
            return Vector3::zeros();
        }
        let mut eps = self.evaluate_wae(q, qd, qdd, tau);
        if self.lag.is_some() {
            self.lag_match_e1(&mut eps, qd, qdd, tau);
        }
        self.mask_reversals(&mut eps, qd, dt.min(MAX_DT));
        if !(eps.iter().all(|x| x.is_finite()) && finite3(&self.tau_hat)) {
            self.trip(Fault::NonFiniteOutput);
            self.snap.tau_hat = Vector3::zeros();
            self.snap.e1 = Vector3::zeros();
            return Vector3::zeros();
        }
        let t = dt.min(MAX_DT);
        if t > 0.0 {
            let a = (-self.cfg.alpha * t).exp();
            self.e = a * self.e + ((1.0 - a) / self.filter_gain()) * eps;
        }
        self.snap.tau_hat = self.tau_hat;
        self.snap.e1 = tau - self.tau_hat;
        self.snap.wae_norm = eps.norm();
        self.snap.modified_norm = self.filter_gain() * self.e.norm() * self.cfg.torque_scale;
        self.snap.e4_active = self.e4_slope.iter().any(|&s| s != 0.0);
        if self.cfg.adapt
            && self.healthy()
            && t > 0.0
            && self.snap.modified_norm > self.cfg.dead_zone
        {
            self.adapt_step(t);
        }
        self.tau_hat
    }

    /// Velocity reversals: a joint whose estimated speed is below `reversal_speed`, or was
    /// within the last `reversal_hold_s`, has its row of e1 set to zero for this tick. The
    /// plant's Coulomb step comes at the true velocity's zero, the filter's q̇ crosses zero some
    /// 10 ms later, so e1 spikes at every reversal whatever the model; learning from the
    /// spikes moved every network and left a low-frequency error after each reversal
    /// (docs/IDENTIFIER.md, "fifth round"). Like the dead zone, it only decides when the
    /// update runs (on which error); the law is unchanged. Only with the friction net.
    fn mask_reversals(&mut self, eps: &mut Wae, qd: &Vector3<f64>, dt: f64) {
        let v = self.cfg.reversal_speed;
        // Without the F-net no network holds a Coulomb step, and the online law is what
        // compensates it along the path (docs/IDENTIFIER.md, "Measured"): it needs these rows.
        if v <= 0.0 || self.f.is_none() {
            return;
        }
        for j in 0..3 {
            // NaN speeds are caught (and trip the identifier) before this.
            self.reversal_left[j] -= dt;
            if qd[j].abs() < v {
                self.reversal_left[j] = self.cfg.reversal_hold_s;
                eps[j] = 0.0;
            } else if self.reversal_left[j] > 0.0 {
                eps[j] = 0.0;
            }
        }
    }

    /// The lag-matched e1: e1 = L[τ − Ĉq̇ − Ĝ − F̂] − M̂·q̈ with L the estimator's acceleration
    /// response, so a torque meets the estimated acceleration it caused with the lag that
    /// estimate has (M̂ varies slowly against L: L[M̂a] ≈ M̂·L[a]); replaces ε's first three
    /// entries. The gradient stays the unfiltered regressor's (docs/IDENTIFIER.md).
    fn lag_match_e1(
        &mut self,
        eps: &mut Wae,
        qd: &Vector3<f64>,
        qdd: &Vector3<f64>,
        tau: &Vector3<f64>,
    ) {
        let Some(lag) = self.lag.as_mut() else { return };
        let n = self.chat * qd + self.ghat + self.fhat;
        let filtered = lag.step(&(tau - n));
        let e1 = filtered - self.mhat * qdd;
        let ts = 1.0 / self.cfg.torque_scale;
        for j in 0..3 {
            eps[j] = e1[j] * ts;
        }
    }

    fn adapt_step(&mut self, t: f64) {
        self.zero_grads();
        let e = self.e;
        self.accumulate_gradient(&e);
        let sigma = if self.anchored { self.cfg.sigma } else { 0.0 };
        let w_max = self.cfg.w_max;
        let rates = self.rates;
        let theta0 = std::mem::take(&mut self.theta0);
        let mut ok = true;
        let mut step2 = 0.0;
        let mut new_norm2 = [0.0; 4];
        // Phase 1: turn each gradient buffer into the step, write the stepped weights beside
        // the current ones, and check them.
        for (k, net) in self.nets_mut().into_iter().enumerate() {
            let Some(net) = net else { continue };
            let hl = net.hidden_len();
            let (p, g, next) = net.step_buffers();
            let p0 = &theta0[k];
            debug_assert_eq!(
                p0.len(),
                p.len(),
                "θ0 is taken from networks of the same size"
            );
            // Hidden layer and output layer have their own rates Γ.
            let mut sums = Sums::default();
            for (range, rate) in [(0..hl, rates[k][0]), (hl..p.len(), rates[k][1])] {
                let gain = -t * rate;
                sums.step(
                    &mut g[range.clone()],
                    &mut next[range.clone()],
                    &p[range.clone()],
                    &p0[range],
                    gain,
                    sigma,
                );
            }
            // Projection: on or beyond the bound, drop the outward radial part of the step
            // (rare: only then is g·p needed, and the step's sums are taken again).
            let pp = sums.pp.reduce_add();
            if w_max > 0.0 && pp >= w_max * w_max {
                let dot = outward(g, p, hl);
                if dot > 0.0 {
                    let c = dot / pp;
                    for (gi, pi) in g.iter_mut().zip(p.iter()) {
                        *gi -= c * pi;
                    }
                    sums = Sums::default();
                    sums.of_step(g, next, p);
                }
            }
            let (s2, pp_new) = (sums.s2.reduce_add(), sums.pp_new.reduce_add());
            // A non-finite step or weight makes these sums non-finite (so would weights
            // beyond 1e154, which are as unusable).
            ok &= s2.is_finite() && pp_new.is_finite();
            step2 += s2;
            new_norm2[k] = pp_new;
        }
        self.theta0 = theta0;
        if !ok {
            self.trip(Fault::NonFiniteUpdate);
            return;
        }
        // Phase 2: take all steps (all-or-nothing, so the weights stay the last good ones).
        self.forward_at = None;
        for (k, net) in self.nets_mut().into_iter().enumerate() {
            let Some(net) = net else { continue };
            net.commit_step();
            // The discrete step can still cross the sphere tangentially: pull back onto it.
            let pp = new_norm2[k];
            if w_max > 0.0 && pp > w_max * w_max {
                let s = w_max / pp.sqrt();
                net.params_mut().iter_mut().for_each(|pi| *pi *= s);
            }
        }
        self.snap.updated = true;
        self.snap.step_norm = step2.sqrt();
    }
}

/// Partial sums over one network's step, two lanes each (a single running sum would be one
/// long chain of dependent adds over the ~660 weights): pᵢ² (for the projection), and for the
/// step as it stands gᵢ² and (pᵢ + gᵢ)².
#[derive(Default)]
struct Sums {
    pp: f64x2,
    s2: f64x2,
    pp_new: f64x2,
}

impl Sums {
    /// gᵢ ← gain·(gᵢ + σ(pᵢ − p0ᵢ)) and nextᵢ ← pᵢ + gᵢ, with the sums.
    fn step(
        &mut self,
        g: &mut [f64],
        next: &mut [f64],
        p: &[f64],
        p0: &[f64],
        gain: f64,
        sigma: f64,
    ) {
        let n = g.len() / 2 * 2;
        let (g_body, g_tail) = g.split_at_mut(n);
        let (next_body, next_tail) = next.split_at_mut(n);
        let (gain2, sigma2) = (f64x2::splat(gain), f64x2::splat(sigma));
        for (((gc, nc), pc), p0c) in g_body
            .chunks_exact_mut(2)
            .zip(next_body.chunks_exact_mut(2))
            .zip(p.chunks_exact(2))
            .zip(p0.chunks_exact(2))
        {
            let (gv, pv, p0v) = (pair(gc), pair(pc), pair(p0c));
            let sv = gain2 * (gv + sigma2 * (pv - p0v));
            let qv = pv + sv;
            gc.copy_from_slice(sv.as_array_ref());
            nc.copy_from_slice(qv.as_array_ref());
            self.add(sv, pv, qv);
        }
        for (((gi, ni), pi), p0i) in g_tail
            .iter_mut()
            .zip(next_tail.iter_mut())
            .zip(&p[n..])
            .zip(&p0[n..])
        {
            *gi = gain * (*gi + sigma * (pi - p0i));
            *ni = pi + *gi;
            self.add(lane0(*gi), lane0(*pi), lane0(*ni));
        }
    }

    /// nextᵢ ← pᵢ + gᵢ for a step already in `g`, with its sums.
    fn of_step(&mut self, g: &[f64], next: &mut [f64], p: &[f64]) {
        for ((gi, ni), pi) in g.iter().zip(next.iter_mut()).zip(p) {
            *ni = pi + gi;
            self.add(lane0(*gi), lane0(*pi), lane0(*ni));
        }
    }

    #[inline(always)]
    fn add(&mut self, g: f64x2, p: f64x2, q: f64x2) {
        self.pp += p * p;
        self.s2 += g * g;
        self.pp_new += q * q;
    }
}

/// g·p over a network's step, summed in the same lanes and order as `Sums::step` walks the
/// hidden layer (`..hl`) and the output layer.
fn outward(g: &[f64], p: &[f64], hl: usize) -> f64 {
    let mut dot = f64x2::ZERO;
    for range in [0..hl, hl..g.len()] {
        let (g, p) = (&g[range.clone()], &p[range]);
        let n = g.len() / 2 * 2;
        for (gc, pc) in g[..n].chunks_exact(2).zip(p[..n].chunks_exact(2)) {
            dot += pair(gc) * pair(pc);
        }
        for (gi, pi) in g[n..].iter().zip(&p[n..]) {
            dot += lane0(gi * pi);
        }
    }
    dot.reduce_add()
}

#[inline(always)]
fn lane0(x: f64) -> f64x2 {
    f64x2::new([x, 0.0])
}

#[inline(always)]
fn pair(c: &[f64]) -> f64x2 {
    f64x2::new([c[0], c[1]])
}

/// Input/output scaling of `net` from the configuration.
pub(crate) fn scaling_for(cfg: &IdentifierConfig, net: Net) -> NetScaling {
    let q_c = cfg.q_center.to_vec();
    let q_s = cfg.q_scale.to_vec();
    match net {
        Net::M => NetScaling {
            in_center: q_c,
            in_scale: q_s,
            out_scale: vec![cfg.inertia_scale; 6],
        },
        Net::C => NetScaling {
            in_center: [cfg.q_center, [0.0; 3]].concat(),
            in_scale: [cfg.q_scale, cfg.qd_scale].concat(),
            out_scale: vec![cfg.coriolis_scale; 9],
        },
        Net::G => NetScaling {
            in_center: q_c,
            in_scale: q_s,
            out_scale: vec![cfg.gravity_scale; 3],
        },
        Net::F => NetScaling {
            in_center: vec![0.0; 3],
            in_scale: cfg.friction_qd_scale.to_vec(),
            out_scale: vec![cfg.friction_scale; 3],
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::identifier::testdata::{multisine_samples, plant, random_samples};

    fn state() -> (Vector3<f64>, Vector3<f64>, Vector3<f64>) {
        (
            Vector3::new(0.2, 0.7, 0.1),
            Vector3::new(0.5, -0.8, 0.3),
            Vector3::new(4.0, -2.0, 6.0),
        )
    }

    fn params(id: &Identifier) -> Vec<f64> {
        let mut v = Vec::new();
        id.parameter_vector(&mut v);
        v
    }

    #[test]
    fn prediction_is_the_sum_of_the_terms() {
        let mut id = Identifier::new(&IdentifierConfig::default()).unwrap();
        let (q, qd, qdd) = state();
        let m = id.mass(&q);
        assert_eq!(m, m.transpose());
        let sum = m * qdd + id.coriolis(&q, &qd) * qd + id.gravity(&q) + id.friction(&qd);
        let p = id.predict(&q, &qd, &qdd);
        assert!((p - sum).norm() < 1e-15);
        assert_eq!(id.inverse_dynamics(&q, &qd, &qdd), p);
        let tau = Vector3::new(0.01, 0.02, -0.03);
        assert_eq!(id.update(&q, &qd, &qdd, &tau, 1e-3), p);
        assert_eq!(id.last_errors().tau_hat, p);
        assert_eq!(id.last_errors().e1, tau - p);
        assert!(id.last_errors().updated);
        // The update changed the weights, so the next prediction differs.
        assert_ne!(id.predict(&q, &qd, &qdd), p);
        assert!(id.weight_change_norm() > 0.0);
    }

    #[test]
    fn a_reused_network_pass_gives_the_update_of_a_fresh_one() {
        let (q, qd, qdd) = state();
        let tau = Vector3::new(0.01, 0.02, -0.03);
        let mut fresh = Identifier::new(&IdentifierConfig::default()).unwrap();
        let mut reused = fresh.clone();
        // The controller's pass at (q, q̇) is the one the update reuses.
        reused.inverse_dynamics(&q, &qd, &Vector3::zeros());
        let a = reused.update(&q, &qd, &qdd, &tau, 1e-3);
        let b = fresh.update(&q, &qd, &qdd, &tau, 1e-3);
        assert_eq!(a, b);
        assert_eq!(params(&reused), params(&fresh));
        // A single-network accessor moves the activations elsewhere: nothing may be reused.
        reused.inverse_dynamics(&q, &qd, &Vector3::zeros());
        reused.mass(&(q * 0.5));
        reused.coriolis(&(q * 0.5), &qd);
        reused.update(&q, &qd, &qdd, &tau, 1e-3);
        fresh.update(&q, &qd, &qdd, &tau, 1e-3);
        assert_eq!(params(&reused), params(&fresh));
    }

    #[test]
    fn modified_error_follows_the_discretised_filter() {
        let (q, qd, qdd) = state();
        let tau = Vector3::new(0.02, -0.01, 0.05);
        for unit in [false, true] {
            let cfg = IdentifierConfig {
                adapt: false,
                unit_gain_filter: unit,
                ..IdentifierConfig::default()
            };
            let mut id = Identifier::new(&cfg).unwrap();
            let eps = id.evaluate_wae(&q, &qd, &qdd, &tau);
            let dt = 1e-3;
            for _ in 0..40 {
                id.update(&q, &qd, &qdd, &tau, dt);
            }
            let a = (-cfg.alpha * dt).exp();
            let gain = if unit { 1.0 } else { 1.0 / cfg.alpha };
            let expect = eps * (1.0 - a.powi(40)) * gain;
            assert!((id.modified_error() - expect).norm() < 1e-12 * expect.norm());
            let snap = id.last_errors();
            assert!((snap.wae_norm - eps.norm()).abs() < 1e-12 * eps.norm());
            assert!(!snap.updated);
        }
    }

    #[test]
    fn without_adaptation_the_weights_stay() {
        let mut id = Identifier::new(&IdentifierConfig {
            adapt: false,
            ..IdentifierConfig::default()
        })
        .unwrap();
        let before = params(&id);
        for s in multisine_samples(0.5, 1e-3, 1) {
            id.update(&s.q, &s.qd, &s.qdd, &s.tau, 1e-3);
        }
        assert_eq!(params(&id), before);
    }

    #[test]
    fn non_finite_input_stops_adaptation_until_reset() {
        let mut id = Identifier::new(&IdentifierConfig::default()).unwrap();
        let (q, qd, qdd) = state();
        let tau = Vector3::new(0.01, 0.02, 0.03);
        id.update(&q, &qd, &qdd, &tau, 1e-3);
        let good = params(&id);
        let bad = Vector3::new(0.1, f64::NAN, 0.0);
        assert_eq!(id.update(&q, &bad, &qdd, &tau, 1e-3), Vector3::zeros());
        assert!(!id.healthy());
        assert_eq!(id.fault(), Some(Fault::NonFiniteInput));
        assert_eq!(params(&id), good);
        // Faulted: predictions continue, adaptation does not.
        let p = id.update(&q, &qd, &qdd, &tau, 1e-3);
        assert!(p.iter().all(|x| x.is_finite()));
        assert_eq!(params(&id), good);
        assert_eq!(
            id.update(&q, &qd, &qdd, &tau, f64::INFINITY),
            Vector3::zeros()
        );
        id.reset_fault();
        assert!(id.healthy());
        id.update(&q, &qd, &qdd, &tau, 1e-3);
        assert_ne!(params(&id), good);
    }

    #[test]
    fn non_finite_step_is_not_applied() {
        let r = [1e9, 1e9];
        let mut id = Identifier::new(&IdentifierConfig {
            rate_m: r,
            rate_c: r,
            rate_g: r,
            rate_f: r,
            w_max: 0.0,
            ..IdentifierConfig::default()
        })
        .unwrap();
        let (q, qd, qdd) = state();
        let before = params(&id);
        id.update(&q, &qd, &qdd, &Vector3::new(1e306, 0.0, 0.0), 1e-2);
        assert_eq!(id.fault(), Some(Fault::NonFiniteUpdate));
        assert_eq!(params(&id), before);
        assert!(!id.last_errors().updated);
    }

    #[test]
    fn dead_zone_blocks_small_errors_only() {
        let (q, qd, qdd) = state();
        let tau = Vector3::new(0.01, 0.02, 0.03);
        for (d0, moves) in [(1.0, false), (0.0, true)] {
            let mut id = Identifier::new(&IdentifierConfig {
                dead_zone: d0,
                ..IdentifierConfig::default()
            })
            .unwrap();
            let before = params(&id);
            for _ in 0..10 {
                id.update(&q, &qd, &qdd, &tau, 1e-3);
            }
            assert_eq!(params(&id) != before, moves, "dead zone {d0}");
            assert_eq!(id.last_errors().updated, moves);
        }
    }

    #[test]
    fn a_reversing_joint_leaves_its_e1_row_out_for_the_hold() {
        let mut id = Identifier::new(&IdentifierConfig {
            reversal_speed: 0.02,
            reversal_hold_s: 0.005,
            ..IdentifierConfig::default()
        })
        .unwrap();
        let ones = Wae::from_element(1.0);
        let mut step = |qd: [f64; 3]| {
            let mut eps = ones;
            id.mask_reversals(&mut eps, &Vector3::from(qd), 1e-3);
            eps
        };
        // Joint 2 slow: only its row is zeroed; the WAE terms beyond e1 are kept.
        let e = step([0.5, 0.01, -0.5]);
        assert_eq!([e[0], e[1], e[2]], [1.0, 0.0, 1.0]);
        assert!(e.rows(3, 9).iter().all(|&x| x == 1.0));
        // Fast again: still out for the hold (5 ms), then back.
        for _ in 0..4 {
            assert_eq!(step([0.5, -0.3, -0.5])[1], 0.0);
        }
        assert_eq!(step([0.5, -0.3, -0.5])[1], 1.0);
        // Off, or the paper's three nets: nothing is masked, however slow.
        for (speed, friction_net) in [(0.0, true), (0.02, false)] {
            let mut off = Identifier::new(&IdentifierConfig {
                reversal_speed: speed,
                friction_net,
                ..IdentifierConfig::default()
            })
            .unwrap();
            let mut eps = ones;
            off.mask_reversals(&mut eps, &Vector3::zeros(), 1e-3);
            assert_eq!(eps, ones);
        }
    }

    #[test]
    fn sigma_modification_leaks_toward_the_anchor_at_the_layer_rates() {
        let (q, qd, qdd) = state();
        let tau = Vector3::new(0.01, 0.02, 0.03);
        let (sigma, dt) = (0.3, 1e-3);
        let rates = [[7.0, 3.0], [5.0, 11.0], [2.0, 13.0], [17.0, 19.0]];
        let make = |sigma: f64| {
            let mut id = Identifier::new(&IdentifierConfig {
                sigma,
                dead_zone: 0.0,
                w_max: 0.0,
                rate_m: rates[0],
                rate_c: rates[1],
                rate_g: rates[2],
                rate_f: rates[3],
                ..IdentifierConfig::default()
            })
            .unwrap();
            // Take the current weights as the anchor θ0, then move every weight away from it.
            id.set_anchor();
            for net in Net::ALL {
                for (i, p) in id.net_mut(net).unwrap().params_mut().iter_mut().enumerate() {
                    *p += 0.01 * ((i % 7) as f64 - 3.0);
                }
            }
            id
        };
        let (mut plain, mut leaky) = (make(0.0), make(sigma));
        let displaced: Vec<Vec<f64>> = Net::ALL
            .iter()
            .map(|&n| plain.net(n).unwrap().params().to_vec())
            .collect();
        plain.update(&q, &qd, &qdd, &tau, dt);
        leaky.update(&q, &qd, &qdd, &tau, dt);
        for (k, net) in Net::ALL.into_iter().enumerate() {
            let hl = plain.net(net).unwrap().hidden_len();
            let t0 = &leaky.theta0[k];
            for (i, ((a, b), (d, p0))) in plain
                .net(net)
                .unwrap()
                .params()
                .iter()
                .zip(leaky.net(net).unwrap().params())
                .zip(displaced[k].iter().zip(t0))
                .enumerate()
            {
                let rate = rates[k][usize::from(i >= hl)];
                let expect = -dt * rate * sigma * (d - p0);
                assert!(((b - a) - expect).abs() < 1e-13, "{} param {i}", net.name());
            }
        }
    }

    #[test]
    fn projection_keeps_each_network_inside_its_bound() {
        let probe = Identifier::new(&IdentifierConfig::default()).unwrap();
        let w_max = probe.weights_norm().iter().cloned().fold(0.0, f64::max) * 1.002;
        let r = [2000.0, 2000.0];
        let mut id = Identifier::new(&IdentifierConfig {
            w_max,
            rate_m: r,
            rate_c: r,
            rate_g: r,
            rate_f: r,
            ..IdentifierConfig::default()
        })
        .unwrap();
        let mut max_seen: f64 = 0.0;
        for s in multisine_samples(3.0, 1e-3, 4) {
            id.update(&s.q, &s.qd, &s.qdd, &s.tau, 1e-3);
            for n in id.weights_norm() {
                assert!(n <= w_max * (1.0 + 1e-12), "{n} > {w_max}");
                max_seen = max_seen.max(n);
            }
        }
        assert!(
            max_seen > w_max * (1.0 - 1e-6),
            "bound never reached: {max_seen}"
        );
        assert!(id.healthy());
    }

    #[test]
    fn e4_lifts_the_eigenvalues_of_m_into_the_bounds() {
        // M̂ starts near zero; with q̈ = 0 only e4 reaches the M-net.
        let mut id = Identifier::new(&IdentifierConfig {
            init_mass_diag: [0.0; 3],
            lambda1: 0.0,
            lambda2: 0.0,
            lambda3: 5.0,
            eig_min: 5e-4,
            dead_zone: 0.0,
            rate_m: [500.0, 500.0],
            ..IdentifierConfig::default()
        })
        .unwrap();
        let (q, qd, _) = state();
        let lam_min = |id: &mut Identifier| id.mass(&q).symmetric_eigenvalues().min();
        assert!(lam_min(&mut id) < 2e-4);
        let tau = plant().inverse_dynamics(&q, &qd, &Vector3::zeros());
        for _ in 0..3000 {
            id.update(&q, &qd, &Vector3::zeros(), &tau, 1e-3);
        }
        let l = lam_min(&mut id);
        assert!(l > 4.5e-4, "smallest eigenvalue {l}");
    }

    #[test]
    fn three_net_variant_has_no_friction_net() {
        let mut id = Identifier::new(&IdentifierConfig {
            friction_net: false,
            ..IdentifierConfig::default()
        })
        .unwrap();
        assert!(id.net(Net::F).is_none());
        assert_eq!(id.weights_norm()[3], 0.0);
        let (q, qd, qdd) = state();
        assert_eq!(id.friction(&qd), Vector3::zeros());
        id.update(&q, &qd, &qdd, &Vector3::new(0.01, 0.0, 0.0), 1e-3);
        assert!(id.healthy() && id.last_errors().updated);
    }

    /// NRMSE per joint of the predictions made online over `samples`.
    fn online_nrmse(id: &mut Identifier, samples: &[crate::identifier::Sample]) -> [f64; 3] {
        let (mut e2, mut t2) = (Vector3::zeros(), Vector3::zeros());
        for s in samples {
            let e = s.tau - id.update(&s.q, &s.qd, &s.qdd, &s.tau, 1e-3);
            e2 += e.component_mul(&e);
            t2 += s.tau.component_mul(&s.tau);
        }
        std::array::from_fn(|j| (e2[j] / t2[j]).sqrt())
    }

    #[test]
    fn online_identification_from_scratch_improves_over_the_stream() {
        let mut id = Identifier::new(&IdentifierConfig::default()).unwrap();
        let s = multisine_samples(60.0, 1e-3, 3);
        let first = online_nrmse(&mut id, &s[..5000]);
        online_nrmse(&mut id, &s[5000..55000]);
        let last = online_nrmse(&mut id, &s[55000..]);
        eprintln!("online NRMSE first 5 s {first:.3?}, last 5 s {last:.3?}");
        for j in 0..3 {
            assert!(last[j] < 0.6 * first[j], "joint {j}: {first:?} → {last:?}");
            assert!(last[j] < 0.2, "joint {j}: {last:?}");
        }
        assert!(id.healthy());
    }

    #[test]
    fn pretuned_identifier_adapts_to_a_payload() {
        use crate::identifier::pretune::{pretune, PretuneConfig};
        let mut id = Identifier::new(&IdentifierConfig::default()).unwrap();
        let pcfg = PretuneConfig {
            epochs: 8,
            block_len: 200,
            ..PretuneConfig::default()
        };
        pretune(&mut id, &random_samples(6000, 8), &pcfg, None, |_| {}).unwrap();
        // The plant changes: a 50 g tip payload the networks never saw.
        let mut heavy = plant();
        heavy.payload_kg = 0.05;
        let mut s = multisine_samples(30.0, 1e-3, 6);
        for x in &mut s {
            x.tau = heavy.inverse_dynamics(&x.q, &x.qd, &x.qdd);
        }
        let mut frozen = id.clone();
        let before = crate::identifier::nrmse(&mut frozen, &s[25000..], None);
        let first = online_nrmse(&mut id, &s[..5000]);
        online_nrmse(&mut id, &s[5000..25000]);
        let last = online_nrmse(&mut id, &s[25000..]);
        eprintln!("payload: frozen {before:.3?}, online first {first:.3?}, last {last:.3?}");
        for j in 1..3 {
            assert!(
                last[j] < 0.7 * before[j],
                "joint {j}: {before:?} → {last:?}"
            );
        }
    }
}
