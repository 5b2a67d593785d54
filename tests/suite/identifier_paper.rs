//! The paper's remaining claims on the simulated Omni (fixed seeds, --fast; numbers in
//! docs/IDENTIFIER.md, "Measured"): the skew-symmetry terms make Ĉ closer to the plant's C, a
//! larger α converges sooner and moves the weights more (Figs. 5–6), and the paper's three
//! networks, pre-tuned and adapting, track better than PD and close to computed torque.

use nalgebra::Matrix3;
use omnid::cmd::identify::{samples_from_log, States};
use omnid::cmd::run::{execute, RunOptions, RunOutcome};
use omnid::config::Config;
use omnid::control::{ControllerKind, Trajectory};
use omnid::identifier::{pretune, Identifier, IdentifierConfig, PretuneConfig, Sample};
use omnid::omni::{Dynamics, Geometry, ModelParams};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

fn run(
    cfg: &Config,
    controller: ControllerKind,
    trajectory: Trajectory,
    secs: f64,
    log: &Path,
    weights: Option<PathBuf>,
) -> RunOutcome {
    let mut cfg = cfg.clone();
    cfg.safety.persist_heat = false;
    let opts = RunOptions {
        controller,
        trajectory,
        duration_s: secs,
        log: Some(log.to_path_buf()),
        fast: true,
        weights,
        ..RunOptions::default()
    };
    let out = execute(&opts, &cfg, Arc::new(AtomicBool::new(false))).expect("run starts");
    assert!(out.summary.faults.is_empty(), "{:?}", out.summary.faults);
    out
}

/// Kalman-estimated samples of a PD multisine run of `secs` with simulator seed `seed`, as the
/// live loop sees them.
fn multisine_samples(dir: &Path, seed: u64, secs: f64) -> Vec<Sample> {
    let mut cfg = Config::default();
    cfg.sim.seed = seed;
    // The study's log starts free, out of the inkwell (its pop at the start of a run moves the
    // thresholds this test orders).
    cfg.sim.docked = false;
    let log = dir.join(format!("ms{seed}.csv"));
    run(
        &cfg,
        ControllerKind::Pd,
        Trajectory::Multisine,
        secs,
        &log,
        None,
    );
    samples_from_log(&log, &cfg, States::Filtered, None).unwrap()
}

/// ‖Ĉ − C‖_F/‖C‖_F over the states of `samples` against the simulator's plant: the ratio of
/// the sums of squares (an RMS over the states), and the mean of the per-state ratios over the
/// states where ‖C‖_F is at least 10 % of its RMS (elsewhere the ratio is noise over ~0).
fn coriolis_error(id: &mut Identifier, samples: &[Sample]) -> (f64, f64) {
    let plant = Dynamics::new(ModelParams::default(), Geometry::default());
    let pairs: Vec<(Matrix3<f64>, Matrix3<f64>)> = samples
        .iter()
        .map(|s| (id.coriolis(&s.q, &s.qd), plant.coriolis(&s.q, &s.qd)))
        .collect();
    let sum_c2: f64 = pairs.iter().map(|(_, c)| c.norm_squared()).sum();
    let sum_e2: f64 = pairs.iter().map(|(ch, c)| (ch - c).norm_squared()).sum();
    let floor = 0.1 * (sum_c2 / pairs.len() as f64).sqrt();
    let ratios: Vec<f64> = pairs
        .iter()
        .filter(|(_, c)| c.norm() >= floor)
        .map(|(ch, c)| (ch - c).norm() / c.norm())
        .collect();
    (
        (sum_e2 / sum_c2).sqrt(),
        ratios.iter().sum::<f64>() / ratios.len() as f64,
    )
}

/// Item 1: with e2/e3 (λ1 = λ2 = 2, the default) the learned Ĉ is closer to the plant's
/// Christoffel C than with λ1 = λ2 = 0. Both pre-tuned identically (same fresh weights, same
/// 30 s PD multisine log of seed 11, 6 epochs), evaluated on the states of a 10 s multisine
/// log of seed 21.
#[test]
#[ignore = "paced"]
fn skew_symmetry_terms_bring_c_hat_closer_to_the_plant() {
    let dir = tempfile::tempdir().unwrap();
    let train = multisine_samples(dir.path(), 11, 30.0);
    let val = multisine_samples(dir.path(), 21, 10.0);
    let pcfg = PretuneConfig {
        epochs: 6,
        ..PretuneConfig::default()
    };
    let mut errs = Vec::new();
    for lambda in [2.0, 0.0] {
        let mut id = Identifier::new(&IdentifierConfig {
            lambda1: lambda,
            lambda2: lambda,
            ..IdentifierConfig::default()
        })
        .unwrap();
        let rep = pretune(&mut id, &train, &pcfg, None, |_| {}).unwrap();
        let (rms, mean) = coriolis_error(&mut id, &val);
        let nrmse = omnid::identifier::nrmse(&mut id, &val, None);
        eprintln!(
            "λ1 = λ2 = {lambda}: ‖Ĉ − C‖/‖C‖ {rms:.3} (mean per state {mean:.3}); τ̂ NRMSE on \
             the validation log {nrmse:.3?} (kept epoch {})",
            rep.kept_epoch
        );
        errs.push((rms, mean));
    }
    let ((on, on_mean), (off, off_mean)) = (errs[0], errs[1]);
    assert!(on < 0.8 * off, "with e2/e3 {on} vs without {off}");
    assert!(on_mean < 0.8 * off_mean, "{on_mean} vs {off_mean}");
}

/// Item 2, the α effect of the paper's Figs. 5–6, measured with `unit_gain_filter = true`: the
/// modified error e then has unit DC gain (e → ε), so α only sets the filter's bandwidth and
/// the back-propagation rate stays Γ. This equals eq. 21 as written with the rates scaled by α
/// (Γ_eq21 = α·Γ). With eq. 21 as written and a fixed Γ the effective rate is Γ/α and the
/// ordering reverses (docs/IDENTIFIER.md).
///
/// From the shipped pre-tuned weights (four nets), each α adapts online on the same 30 s PD
/// multisine log (seed 5), one `update` per sample with the log's 1 ms: the time until the
/// running RMS of ‖e1‖ (exponential window, 1 s) first drops below 10 mN·m, and ‖θ − θ0‖ at
/// the end. The time is ordered α = 500 < 50 < 5 (α = 5 never gets there: its 200 ms filter
/// lag makes the descent direction stale, the error stays near its initial level and the
/// weights wander). The paper's second claim, that larger α moves the weights more, does not
/// hold robustly here: α = 5 moves them the most without converging, and α = 50 against 500
/// flips with small changes of the setting (σ, start weights). So the weight change is
/// printed, not asserted.
#[test]
#[ignore = "paced"]
fn larger_alpha_converges_sooner_and_moves_the_weights_more() {
    let dir = tempfile::tempdir().unwrap();
    let samples = multisine_samples(dir.path(), 5, 30.0);
    let weights = Path::new(env!("CARGO_MANIFEST_DIR")).join("mock/nnidc-pretuned.json");
    const DT: f64 = 1e-3;
    const WINDOW_S: f64 = 1.0;
    const THRESHOLD: f64 = 0.01; // N·m, running RMS of ‖e1‖
    let k = DT / WINDOW_S;
    let mut results = Vec::new();
    for alpha in [5.0, 50.0, 500.0] {
        // σ-modification off: the study is of the update law itself (the leakage pulls the
        // weights back toward θ0 and would mask how far each α moves them).
        let cfg = IdentifierConfig {
            alpha,
            unit_gain_filter: true,
            sigma: 0.0,
            ..IdentifierConfig::default()
        };
        let mut id = Identifier::from_weights_file(&cfg, &weights, None).unwrap();
        id.set_anchor();
        let mut ms = None::<f64>;
        let mut reached = None;
        let mut tail = (0.0, 0usize);
        for (i, s) in samples.iter().enumerate() {
            id.update(&s.q, &s.qd, &s.qdd, &s.tau, DT);
            let e2 = id.last_errors().e1.norm_squared();
            let m = ms.map_or(e2, |m| m + k * (e2 - m));
            ms = Some(m);
            let t = i as f64 * DT;
            // The window needs a second to fill before its value means anything.
            if reached.is_none() && t >= WINDOW_S && m.sqrt() < THRESHOLD {
                reached = Some(t);
            }
            if t >= 25.0 {
                tail.0 += e2;
                tail.1 += 1;
            }
        }
        assert!(id.healthy());
        let change = id.weight_change_norm();
        let late = (tail.0 / tail.1 as f64).sqrt();
        eprintln!(
            "α = {alpha}: running RMS ‖e1‖ < {THRESHOLD} N·m at {reached:?} s; ‖θ − θ0‖ \
             {change:.3}; RMS ‖e1‖ over 25–30 s {:.2} mN·m",
            late * 1e3
        );
        results.push((reached.unwrap_or(f64::INFINITY), change));
    }
    for w in results.windows(2) {
        assert!(w[1].0 < w[0].0, "time to threshold: {results:?}");
    }
    assert!(results[1].0.is_finite(), "{results:?}");
    // The weight change is reported, not asserted: its ordering is not robust here (see the
    // doc comment and docs/IDENTIFIER.md).
}

/// Items 3 and 4: the 0.5 Hz sine (10 s) with PD, CT, NNIDC (shipped four nets, defaults) and
/// NNIDC with the paper's three nets (`mock/nnidc-pretuned-3net.json` with
/// `mock/nnidc-3net.toml`: `friction_net = false`, σ = 0.05), all adapting online. Tracking
/// and the control effort (RMS, total variation) are printed for docs/IDENTIFIER.md.
#[test]
#[ignore = "paced"]
fn three_net_nnidc_beats_pd_and_stays_near_computed_torque() {
    let dir = tempfile::tempdir().unwrap();
    let mock = Path::new(env!("CARGO_MANIFEST_DIR")).join("mock");
    let three = Config::load(&mock.join("nnidc-3net.toml"), None).unwrap();
    assert!(!three.identifier.friction_net);
    let cases = [
        ("pd", ControllerKind::Pd, Config::default(), None),
        ("ct", ControllerKind::Ct, Config::default(), None),
        ("nnidc-4net", ControllerKind::Nnidc, Config::default(), None),
        (
            "nnidc-3net",
            ControllerKind::Nnidc,
            three.clone(),
            Some(mock.join("nnidc-pretuned-3net.json")),
        ),
    ];
    let mut rms = Vec::new();
    for (name, controller, cfg, weights) in cases {
        let out = run(
            &cfg,
            controller,
            Trajectory::Sine,
            10.0,
            &dir.path().join(format!("{name}.csv")),
            weights,
        );
        let s = &out.summary;
        let track = s.tracking_rms_rad.unwrap();
        eprintln!(
            "{name}: tracking {:.2?} mrad, torque RMS {:.2?} mN·m, TV {:.2?} N·m",
            track.map(|v| v * 1e3),
            s.torque_rms_nm.unwrap().map(|v| v * 1e3),
            s.torque_total_variation_nm
        );
        rms.push(track);
    }
    // The feedback gain NNIDC multiplies by: M̂ of each weights file against the plant's M on
    // the states of the PD run (the torque's total variation scales with it).
    let states = samples_from_log(
        &dir.path().join("pd.csv"),
        &Config::default(),
        States::Filtered,
        None,
    )
    .unwrap();
    let plant = Dynamics::new(ModelParams::default(), Geometry::default());
    for (file, cfg) in [
        ("nnidc-pretuned.json", IdentifierConfig::default()),
        ("nnidc-pretuned-3net.json", three.identifier.clone()),
    ] {
        let mut id = Identifier::from_weights_file(&cfg, &mock.join(file), None).unwrap();
        let (mut num, mut den) = ([0.0; 3], [0.0; 3]);
        for s in &states {
            let (mh, m) = (id.mass(&s.q), plant.mass(&s.q));
            for j in 0..3 {
                num[j] += mh[(j, j)];
                den[j] += m[(j, j)];
            }
        }
        let ratio: [f64; 3] = std::array::from_fn(|j| num[j] / den[j]);
        eprintln!("{file}: mean diagonal of M̂ / M on the sine {ratio:.2?}");
    }
    let (pd, ct, nn4, nn3) = (rms[0], rms[1], rms[2], rms[3]);
    for j in 0..3 {
        assert!(
            nn3[j] < pd[j],
            "joint {}: 3 nets {} vs PD {}",
            j + 1,
            nn3[j],
            pd[j]
        );
        assert!(
            nn3[j] <= 1.5 * ct[j],
            "joint {}: 3 nets {} vs CT {}",
            j + 1,
            nn3[j],
            ct[j]
        );
        assert!(
            nn4[j] <= ct[j],
            "joint {}: 4 nets {} vs CT {}",
            j + 1,
            nn4[j],
            ct[j]
        );
    }
    assert!(
        nn3[2] <= 0.5 * pd[2],
        "joint 3: 3 nets {} vs PD {}",
        nn3[2],
        pd[2]
    );
}
