//! Acceptance of the adaptive identifier and NNIDC on the simulated Omni (fixed seeds, --fast):
//! online learning from scratch, pre-tuned prediction on an unseen log, the skew-symmetry
//! terms, and NNIDC's tracking against PD and computed torque.

use omnid::cmd::run::{execute, DeviceSpec, RunOptions, RunOutcome};
use omnid::config::Config;
use omnid::control::{ControllerKind, Trajectory};
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
    device: DeviceSpec,
) -> RunOutcome {
    let mut cfg = cfg.clone();
    cfg.safety.persist_heat = false;
    let opts = RunOptions {
        device,
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

fn seeded(seed: u64) -> Config {
    let mut cfg = Config::default();
    cfg.sim.seed = seed;
    cfg
}

#[test]
fn online_from_scratch_reaches_the_oracle_floor() {
    let dir = tempfile::tempdir().unwrap();
    // 60 s of PD on the multisine from fresh weights.
    let pd_run = |cfg: &Config, log: &str| {
        let log = dir.path().join(log);
        run(
            cfg,
            ControllerKind::Pd,
            Trajectory::Multisine,
            60.0,
            &log,
            None,
            DeviceSpec::Sim,
        )
    };
    // The paper's law as written (the defaults' lag match and slower G/F rates are tuned for
    // a pre-tuned start; from scratch they learn more slowly).
    let scratch = || {
        let mut cfg = paper_law();
        cfg.sim.seed = 5;
        cfg
    };
    let out = pd_run(&scratch(), "pd.csv");
    let id = &out.summary.identifier;
    assert_eq!(id.weights.as_deref(), Some("fresh"));
    let (all, late) = (id.nrmse.unwrap(), id.nrmse_last_20pct.unwrap());
    let oracle = id.nrmse_oracle_last_20pct.unwrap();
    eprintln!("online from scratch: NRMSE {all:?}, last 20 % {late:?}, oracle {oracle:?}");
    for j in 0..3 {
        assert!(
            late[j] <= 2.0 * oracle[j],
            "joint {}: {} vs oracle {}",
            j + 1,
            late[j],
            oracle[j]
        );
    }
    // Learning: PD's run does not depend on the identifier, so the same run with adaptation
    // off sees the same torques; its fresh, frozen networks predict them far worse.
    let mut frozen_cfg = scratch();
    frozen_cfg.identifier.adapt = false;
    let frozen = pd_run(&frozen_cfg, "frozen.csv");
    assert_eq!(
        frozen.summary.torque_rms_nm, out.summary.torque_rms_nm,
        "the same run"
    );
    let untrained = frozen.summary.identifier.nrmse_last_20pct.unwrap();
    eprintln!("frozen fresh networks: last 20 % {untrained:?} (whole run {all:?} adapting)");
    for j in 0..3 {
        assert!(
            late[j] < 0.5 * untrained[j],
            "joint {}: {} adapting vs {} frozen",
            j + 1,
            late[j],
            untrained[j]
        );
    }
}

#[test]
fn shipped_pretuned_weights_predict_an_unseen_log_near_the_oracle() {
    // The shipped weights were pre-tuned on seven 60 s multisine logs, seeds 11–17
    // (mock/README.md); this log has seed 21.
    let dir = tempfile::tempdir().unwrap();
    let sim_log = dir.path().join("val.csv");
    let sim = run(
        &seeded(21),
        ControllerKind::Pd,
        Trajectory::Multisine,
        30.0,
        &sim_log,
        None,
        DeviceSpec::Sim,
    );
    let oracle = sim.summary.identifier.nrmse_oracle.unwrap();
    let weights = Path::new(env!("CARGO_MANIFEST_DIR")).join("mock/nnidc-pretuned.json");
    // Open loop: replay the log with frozen weights.
    let mut cfg = seeded(21);
    cfg.identifier.adapt = false;
    let rep = run(
        &cfg,
        ControllerKind::Off,
        Trajectory::Hold,
        f64::INFINITY,
        &dir.path().join("replay.csv"),
        Some(weights),
        DeviceSpec::Replay(sim_log),
    );
    let val = rep.summary.identifier.nrmse.unwrap();
    eprintln!("pre-tuned, unseen log: NRMSE {val:?}, oracle {oracle:?}");
    for j in 0..3 {
        assert!(
            val[j] <= 1.5 * oracle[j],
            "joint {}: {} vs oracle {}",
            j + 1,
            val[j],
            oracle[j]
        );
    }
}

#[test]
fn pretuned_nnidc_tracks_better_than_computed_torque_and_pd() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::default();
    let mut rms = Vec::new();
    for c in [
        ControllerKind::Pd,
        ControllerKind::Ct,
        ControllerKind::Nnidc,
    ] {
        let out = run(
            &cfg,
            c,
            Trajectory::Sine,
            10.0,
            &dir.path().join(format!("{}.csv", c.as_str())),
            None,
            DeviceSpec::Sim,
        );
        let s = &out.summary;
        eprintln!(
            "{}: tracking {:?} rad, torque RMS {:?}, TV {:?}",
            c.as_str(),
            s.tracking_rms_rad.unwrap(),
            s.torque_rms_nm.unwrap(),
            s.torque_total_variation_nm
        );
        rms.push(s.tracking_rms_rad.unwrap());
    }
    let (pd, ct, nn) = (rms[0], rms[1], rms[2]);
    for j in 0..3 {
        assert!(
            nn[j] <= ct[j],
            "joint {}: nnidc {} vs ct {}",
            j + 1,
            nn[j],
            ct[j]
        );
        assert!(ct[j] < pd[j]);
    }
}

/// Tracking RMS per joint over `from..to` seconds of a log (reference against estimate).
fn window_rms(log: &Path, from: f64, to: f64) -> [f64; 3] {
    let mut r = csv::Reader::from_path(log).unwrap();
    let h = r.headers().unwrap().clone();
    let col = |n: &str| h.iter().position(|x| x == n).unwrap();
    let (t, mode) = (col("t"), col("mode"));
    let refs = [col("ref1"), col("ref2"), col("ref3")];
    let qf = [col("qf1"), col("qf2"), col("qf3")];
    let (mut s, mut n) = ([0.0; 3], 0.0);
    for rec in r.records() {
        let rec = rec.unwrap();
        let tt: f64 = rec[t].parse().unwrap();
        if tt >= from && tt < to && &rec[mode] != "stop" {
            for j in 0..3 {
                let e: f64 =
                    rec[refs[j]].parse::<f64>().unwrap() - rec[qf[j]].parse::<f64>().unwrap();
                s[j] += e * e;
            }
            n += 1.0;
        }
    }
    s.map(|v| (v / n).sqrt())
}

#[test]
fn adaptation_absorbs_a_payload_change() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = Config::default();
    cfg.sim.payload_kg = 0.02;
    cfg.sim.payload_at_s = 10.0;
    let mut after = Vec::new();
    for (name, controller, frozen) in [
        ("nnidc", ControllerKind::Nnidc, false),
        ("nnidc-frozen", ControllerKind::Nnidc, true),
        ("ct", ControllerKind::Ct, false),
    ] {
        let mut c = cfg.clone();
        c.identifier.adapt = !frozen;
        let log = dir.path().join(format!("{name}.csv"));
        run(
            &c,
            controller,
            Trajectory::Sine,
            30.0,
            &log,
            None,
            DeviceSpec::Sim,
        );
        let (before, late) = (window_rms(&log, 2.0, 10.0), window_rms(&log, 20.0, 30.0));
        eprintln!("{name}: tracking RMS 2–10 s {before:?}, 20–30 s {late:?}");
        if name == "nnidc" {
            // The payload costs the frozen networks ~14 mrad on joints 2–3 (below); adapting,
            // the error stays within a few times the pre-payload one. That one is at the
            // oracle's floor (~0.1 mrad), finer than the encoders resolve: below their own
            // quantisation noise (one count/√12, 0.12 mrad RMS) the bar is a few times that,
            // so a better pre-payload tracking does not tighten it past what the arm can see.
            let quantisation = c.device.rad_per_count() / 12f64.sqrt();
            for j in 0..3 {
                assert!(
                    late[j] <= 3.0 * before[j].max(quantisation),
                    "joint {}: {} vs {} (quantisation {})",
                    j + 1,
                    late[j],
                    before[j],
                    quantisation
                );
            }
        }
        after.push(late);
    }
    for j in 0..3 {
        assert!(
            after[1][j] > after[0][j],
            "frozen must be worse on joint {}",
            j + 1
        );
        // On the joints the payload loads, adaptation takes away nearly all of its error.
        if j > 0 {
            assert!(
                after[0][j] < 0.05 * after[1][j],
                "joint {}: adapting {} vs frozen {}",
                j + 1,
                after[0][j],
                after[1][j]
            );
        }
        assert!(
            after[2][j] > after[0][j],
            "CT with the old model must be worse on joint {}",
            j + 1
        );
    }
}

#[test]
fn adapting_nnidc_stays_stable_over_long_runs() {
    // With too little σ-modification the online weights drift and, after ~50 s of the sine,
    // the arm went unstable (a velocity fault). Two minutes must stay as good as the first ten
    // seconds.
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("long.csv");
    let out = run(
        &Config::default(),
        ControllerKind::Nnidc,
        Trajectory::Sine,
        120.0,
        &log,
        None,
        DeviceSpec::Sim,
    );
    assert_eq!(out.end, omnid::servo::EndReason::Completed);
    let (early, late) = (window_rms(&log, 2.0, 10.0), window_rms(&log, 100.0, 120.0));
    eprintln!("long run: tracking RMS 2–10 s {early:?}, 100–120 s {late:?}");
    for j in 0..3 {
        assert!(
            late[j] <= 1.5 * early[j],
            "joint {}: {} vs {}",
            j + 1,
            late[j],
            early[j]
        );
    }
}

/// Centre 5 of `omnid experiment workspace` (docs/IDENTIFIER.md, "Across the workspace"): with
/// the default controller, identifier settings and shipped weights, the blend out of the inkwell
/// tripped the safety layer (joint 3 past 10 rad/s at 0.53 s) while the identifier learnt from
/// the arm's jump as the inkwell let go. It completes, and no joint's speed in the blend comes
/// near the limit (the oracle's peak there is 1.6 rad/s).
#[test]
fn the_default_controller_blends_out_of_the_inkwell_at_workspace_centre_5() {
    let centre = omnid::experiment::workspace::WORKSPACE_CENTRES[4];
    let mut cfg = Config::default();
    cfg.reference.center = centre;
    assert!(cfg.sim.docked, "the run starts in the inkwell");
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("centre5.csv");
    let out = run(
        &cfg,
        ControllerKind::Nnidc,
        Trajectory::Sine,
        2.0,
        &log,
        None,
        DeviceSpec::Sim,
    );
    assert_eq!(out.end, omnid::servo::EndReason::Completed);
    let text = std::fs::read_to_string(&log).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n).unwrap();
    let (t, ink, qd) = (
        col("t"),
        col("inkwell"),
        [col("qd1"), col("qd2"), col("qd3")],
    );
    let (mut left, mut peak) = (false, [0.0f64; 3]);
    for line in lines {
        let f: Vec<&str> = line.split(',').collect();
        if f[t].parse::<f64>().unwrap() >= cfg.reference.blend_s {
            break;
        }
        left |= f[ink] == "0";
        for j in 0..3 {
            peak[j] = peak[j].max(f[qd[j]].parse::<f64>().unwrap().abs());
        }
    }
    assert!(left, "the blend never left the inkwell");
    eprintln!("centre 5: peak speed in the blend {peak:?} rad/s");
    for (j, p) in peak.iter().enumerate() {
        assert!(*p < 4.0, "joint {}: {p} rad/s in the blend", j + 1);
    }
}

/// The paper's law as written: e1 = τ − τ̂ (no lag match) and every network's rate 50, the
/// defaults before the lag match became one (docs/IDENTIFIER.md, "Fourth round"), no
/// velocity-reversal mask (the fifth round's).
fn paper_law() -> Config {
    let mut cfg = Config::default();
    cfg.identifier.lag_match = false;
    cfg.identifier.rate_g = [50.0, 50.0];
    cfg.identifier.rate_f = [50.0, 50.0];
    cfg.identifier.reversal_speed = 0.0;
    cfg
}

/// The lag-matched e1 (docs/IDENTIFIER.md): alone it halves joint 1's tracking on the README's
/// sine against the paper's e1; the preset `mock/nnidc-lagmatch.toml` and the defaults (both
/// lag-matched) track every joint better than the paper's e1, the defaults by a fifth at least.
#[test]
fn the_lag_matched_error_tracks_the_sine_closer_to_the_oracle() {
    let dir = tempfile::tempdir().unwrap();
    let rms = |cfg: &Config, name: &str| {
        let log = dir.path().join(format!("{name}.csv"));
        let out = run(
            cfg,
            ControllerKind::Nnidc,
            Trajectory::Sine,
            10.0,
            &log,
            None,
            DeviceSpec::Sim,
        );
        out.summary.tracking_rms_rad.unwrap()
    };
    let paper = rms(&paper_law(), "paper");
    let mut lag = paper_law();
    lag.identifier.lag_match = true;
    let lag_only = rms(&lag, "lag");
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("mock/nnidc-lagmatch.toml"),
    )
    .unwrap();
    let preset: Config = toml::from_str(&text).unwrap();
    assert!(preset.identifier.lag_match);
    let tuned = rms(&preset, "preset");
    let defaults = rms(&Config::default(), "defaults");
    assert!(
        lag_only[0] < 0.6 * paper[0],
        "joint 1: lag-matched {lag_only:?} vs the paper's e1 {paper:?}"
    );
    for j in 0..3 {
        assert!(
            tuned[j] < paper[j],
            "joint {}: preset {tuned:?} vs the paper's e1 {paper:?}",
            j + 1
        );
        assert!(
            defaults[j] < 0.8 * paper[j],
            "joint {}: defaults {defaults:?} vs the paper's e1 {paper:?}",
            j + 1
        );
    }
}

/// `mock/nnidc-lagmatch.toml` follows a payload as the defaults do (docs/IDENTIFIER.md, "Third
/// round"): with Γ twenty times the defaults' its leakage σ is a twentieth of theirs, so the
/// pull back toward the pre-payload weights (σΓ) is the same. 20 g at the tip from t = 5 s;
/// tracking RMS over 10–15 s. The old preset (Γ = 500 with the defaults' σ, the leakage ten
/// times stronger) left joint 2 near 1.3 mrad against the defaults' 0.33, and failed this.
#[test]
fn the_lag_matched_preset_follows_a_payload() {
    let dir = tempfile::tempdir().unwrap();
    let after = |cfg: &Config, name: &str| {
        let mut cfg = cfg.clone();
        cfg.sim.payload_kg = 0.02;
        cfg.sim.payload_at_s = 5.0;
        let log = dir.path().join(format!("{name}.csv"));
        let out = run(
            &cfg,
            ControllerKind::Nnidc,
            Trajectory::Sine,
            15.0,
            &log,
            None,
            DeviceSpec::Sim,
        );
        assert_eq!(out.end, omnid::servo::EndReason::Completed, "{name}");
        window_rms(&log, 10.0, 15.0)
    };
    let defaults = after(&Config::default(), "defaults");
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("mock/nnidc-lagmatch.toml"),
    )
    .unwrap();
    let preset: Config = toml::from_str(&text).unwrap();
    let tuned = after(&preset, "preset");
    eprintln!("after the payload: preset {tuned:?}, defaults {defaults:?}");
    for j in 0..3 {
        assert!(
            tuned[j] < 1.5 * defaults[j],
            "joint {}: preset {tuned:?} vs defaults {defaults:?}",
            j + 1
        );
    }
}

/// docs/IDENTIFIER.md "Pre-tuning on smoothed states": the same log pre-tuned on its smoothed
/// states and on the live filter's gives two models; frozen under NNIDC, the one from smoothed
/// states tracks better on every joint (the filter's lag biases a fit, and the law applies M̂
/// to an acceleration that does not lag), and it fits its training data better.
#[test]
fn pretuning_on_smoothed_states_gives_the_model_the_law_needs() {
    use omnid::cmd::identify::{identify, States};
    use omnid::identifier::PretuneConfig;
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("ms.csv");
    let mut cfg = seeded(11);
    cfg.sim.docked = false;
    run(
        &cfg,
        ControllerKind::Pd,
        Trajectory::Multisine,
        30.0,
        &log,
        None,
        DeviceSpec::Sim,
    );
    let pcfg = PretuneConfig {
        epochs: 6,
        ..PretuneConfig::default()
    };
    let mut tracked = Vec::new();
    let mut fitted = Vec::new();
    for (name, states) in [
        ("smoothed", States::Smoothed),
        ("filtered", States::Filtered),
    ] {
        let weights = dir.path().join(format!("{name}.json"));
        let report = identify(
            std::slice::from_ref(&log),
            &weights,
            &Config::default(),
            &pcfg,
            states,
            None,
            |_| {},
        )
        .unwrap();
        fitted.push(report.epochs[report.kept_epoch - 1].train_nrmse);
        let mut frozen = Config::default();
        frozen.identifier.adapt = false;
        let out = run(
            &frozen,
            ControllerKind::Nnidc,
            Trajectory::Sine,
            6.0,
            &dir.path().join(format!("{name}-nnidc.csv")),
            Some(weights),
            DeviceSpec::Sim,
        );
        tracked.push(out.summary.tracking_rms_rad.unwrap());
    }
    eprintln!("frozen NNIDC, smoothed vs filtered: {tracked:?} rad; training NRMSE {fitted:?}");
    for j in 0..3 {
        assert!(
            tracked[0][j] < tracked[1][j],
            "joint {}: smoothed {:?} vs filtered {:?}",
            j + 1,
            tracked[0],
            tracked[1]
        );
        assert!(fitted[0][j] < fitted[1][j], "joint {}: {fitted:?}", j + 1);
    }
}
