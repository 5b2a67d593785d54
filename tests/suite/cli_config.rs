//! Bad configuration files: one line naming the field and the allowed range, exit 2, no panic.

use crate::common;
use common::{omnid, run_ok};

/// Run 0.1 s with this config: (exit code, stderr, whether a log was written).
fn with_config(text: &str) -> (i32, String, bool) {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("c.toml");
    std::fs::write(&cfg, text).unwrap();
    let log = dir.path().join("x.csv");
    let out = omnid()
        .env("OMNID_STATE_DIR", dir.path())
        .args(["run", "--fast", "--duration", "0.1"])
        .args([
            "--config",
            cfg.to_str().unwrap(),
            "--log",
            log.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    (
        out.status.code().unwrap(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
        log.exists(),
    )
}

fn assert_bad(text: &str, must_contain: &[&str]) {
    let (code, err, logged) = with_config(text);
    assert!(!logged, "nothing may run with a bad config");
    assert_eq!(code, 2, "exit code for {text:?}: {err}");
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err}");
    assert!(!err.contains("panicked"), "{err}");
    for m in must_contain {
        assert!(err.contains(m), "{err:?} should mention {m:?}");
    }
}

#[test]
fn too_few_simulator_substeps_for_the_model() {
    assert_bad(
        "[model]\ncoulomb_velocity = 0.001\n",
        &["model.coulomb_velocity", "sim.substeps ≥ 11"],
    );
}

#[test]
fn unknown_key() {
    assert_bad("[kalman]\njerk_pds = 10.0\n", &["jerk_pds", "line 2"]);
}

#[test]
fn unknown_section() {
    assert_bad("[kalmann]\njerk_psd = 10.0\n", &["kalmann"]);
}

#[test]
fn wrong_type() {
    assert_bad("[control]\nomega_n = \"fast\"\n", &["omega_n", "line 2"]);
}

#[test]
fn negative_gain() {
    assert_bad(
        "[control]\nomega_n = -25.0\n",
        &["control.omega_n", "0.1 ..= 200"],
    );
}

#[test]
fn non_finite_value() {
    assert_bad(
        "[kalman]\nmeasurement_var = nan\n",
        &["kalman.measurement_var", "finite"],
    );
}

#[test]
fn torque_limit_not_positive() {
    assert_bad(
        "[safety]\nmax_torque_nm = [0.45, 0.0, 0.45]\n",
        &["safety.max_torque_nm[1]", "> 0"],
    );
    assert_bad(
        "[safety]\nmax_torque_nm = [-0.1, 0.4, 0.45]\n",
        &["safety.max_torque_nm[0]"],
    );
}

#[test]
fn unreadable_file() {
    let out = omnid()
        .args(["run", "--fast", "--config", "/no/such/omnid.toml"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/no/such/omnid.toml"));
}

#[test]
fn printed_default_config_is_accepted() {
    let out = run_ok(&["config", "--print-default"]);
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(text.contains("jerk_psd = 100.0") && text.contains("max_torque_nm"));
    let (code, err, logged) = with_config(&text);
    assert_eq!(code, 0, "{err}");
    assert!(logged);
}

#[test]
fn quoted_bad_values_are_cut_to_a_readable_length() {
    let dir = tempfile::tempdir().unwrap();
    let huge = "9".repeat(100_000);
    // A fault spec, a config value and a log field, each 100 kB long.
    let spec = format!("stall@{huge}x:5");
    let config = dir.path().join("c.toml");
    std::fs::write(&config, format!("[serve]\nread_group = \"g{huge}\"\n")).unwrap();
    let log = dir.path().join("l.csv");
    std::fs::write(
        &log,
        format!("t,q1,q2,q3,tau1,tau2,tau3\n0,1,2,3,4,5,x{huge}\n"),
    )
    .unwrap();
    let replay = format!("replay:{}", log.display());
    for (case, args) in ["fault spec", "config value", "log field"]
        .into_iter()
        .zip([
            vec!["run", "--fast", "--inject", &spec],
            vec!["run", "--fast", "--config", config.to_str().unwrap()],
            vec!["run", "--fast", "--device", &replay],
        ])
    {
        let out = omnid()
            .args(&args)
            .env("OMNID_STATE_DIR", dir.path())
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        let head: String = err.chars().take(300).collect();
        assert_eq!(out.status.code(), Some(2), "{case}: {head}");
        assert!(
            err.len() < 1500 && err.contains("…"),
            "{case}: {} bytes: {head}",
            err.len()
        );
    }
}

/// A simulated hand whose grip the simulator cannot resolve is refused, naming the field and
/// the remedy, instead of tripping the safety layer a tick into the run; one it can is fine.
#[test]
fn a_simulated_hand_the_simulator_cannot_resolve_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    for (damping, substeps, ok) in [(200, 2, true), (400, 2, false), (400, 4, true)] {
        let cfg = dir.path().join(format!("hand-{damping}-{substeps}.toml"));
        std::fs::write(
            &cfg,
            format!(
                "[sim]\nsubsteps = {substeps}\n[haptics.hand]\npattern = \"hold\"\n\
                 damping_n_s_per_m = {damping}\n"
            ),
        )
        .unwrap();
        let log = dir.path().join(format!("hand-{damping}-{substeps}.csv"));
        let out = omnid()
            .args([
                "run",
                "--fast",
                "--duration",
                "1",
                "--mode",
                "free",
                "--config",
            ])
            .arg(&cfg)
            .arg("--log")
            .arg(&log)
            .env("OMNID_STATE_DIR", dir.path())
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        if ok {
            assert_eq!(
                out.status.code(),
                Some(0),
                "b = {damping}, {substeps} substeps: {err}"
            );
        } else {
            assert_eq!(out.status.code(), Some(2), "b = {damping}: {err}");
            assert!(
                err.contains("haptics.hand.damping_n_s_per_m") && err.contains("sim.substeps"),
                "{err}"
            );
        }
    }
}

/// One list of experiments: what `--help` offers, the README's Options block and DESIGN §2's
/// command table all name every experiment the library has (none forgotten in one place).
#[test]
fn every_experiment_is_listed_where_users_look() {
    let names = omnid::experiment::Experiment::ALL.map(|e| e.as_str());
    let help = omnid().args(["experiment", "--help"]).output().unwrap();
    let help = String::from_utf8_lossy(&help.stdout);
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let design = std::fs::read_to_string(root.join("docs/DESIGN.md")).unwrap();
    assert!(
        help.contains(&format!("[possible values: {}]", names.join(", "))),
        "{help}"
    );
    assert!(
        readme.contains(&format!("omnid experiment {} --out DIR", names.join("|"))),
        "README's Options block"
    );
    assert!(
        design.contains(&format!("`{}`", names.join("\\|"))),
        "DESIGN §2's command table"
    );
    // A wrong name is refused with the whole list.
    let out = omnid()
        .args(["experiment", "fly", "--out", "x"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(names.iter().all(|n| err.contains(n)), "{err}");
}

/// Errors at their true place (issue 33, item 2): the file, line and column, and the key.
#[test]
fn config_errors_name_the_file_line_column_and_key() {
    // Out of range in the fifth line, after a blank one and another section.
    assert_bad(
        "[sim]\nsubsteps = 3\n\n[haptics]\nmax_force_n = -1\n",
        &[
            "c.toml: line 5, column 15 (`max_force_n = -1`)",
            "`haptics.max_force_n` = -1",
        ],
    );
    // A type error names its dotted key, at the value.
    assert_bad(
        "[sim]\nsubsteps = 3\n\n[control]\nomega_n = \"fast\"\n",
        &[
            "c.toml: line 5, column 11",
            "`control.omega_n`: invalid type",
        ],
    );
    // A misspelled key at the key.
    assert_bad(
        "[haptics]\nmax_force_n = 1\n  max_forse = 2\n",
        &[
            "line 3, column 3 (`max_forse = 2`)",
            "unknown field `max_forse`",
        ],
    );
}

/// `omnid run --mode free --scene` on this scene text: (exit code, stderr).
fn with_scene(text: &str) -> (i32, String) {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("s.toml");
    std::fs::write(&scene, text).unwrap();
    let out = omnid()
        .env("OMNID_STATE_DIR", dir.path())
        .args([
            "run",
            "--fast",
            "--duration",
            "0.1",
            "--mode",
            "free",
            "--scene",
        ])
        .arg(&scene)
        .arg("--log")
        .arg(dir.path().join("x.csv"))
        .output()
        .unwrap();
    (
        out.status.code().unwrap(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

const TWO_EFFECTS: &str = "[[effect]]\ntype = \"damper\"\ndamping_n_s_per_m = 1.5\n\n[[effect]]\ntype = \"plane\"\npoint_mm = [0, -20, 0]\nnormal = [0, 1, 0]\n";

#[test]
fn scene_errors_name_the_file_line_column_and_key() {
    for (last, want) in [
        // A misspelled key (was: line 1).
        (
            "stifness_n_per_mm = 1.0",
            "s.toml: line 9, column 1 (`stifness_n_per_mm = 1.0`): effect[1].stifness_n_per_mm: \
             unknown field `stifness_n_per_mm`",
        ),
        // Out of range in the second effect (was: no line).
        (
            "stiffness_n_per_mm = -3.0",
            "s.toml: line 9, column 22 (`stiffness_n_per_mm = -3.0`): \
             effect[1].stiffness_n_per_mm = -3 is out of range",
        ),
        // A type error in the second effect (was: the first effect's header, line 1).
        (
            "stiffness_n_per_mm = \"stiff\"",
            "s.toml: line 9, column 22 (`stiffness_n_per_mm = \"stiff\"`): \
             effect[1].stiffness_n_per_mm: invalid type: string \"stiff\", expected f64",
        ),
    ] {
        let (code, err) = with_scene(&format!("{TWO_EFFECTS}{last}\n"));
        assert_eq!(code, 2, "{err}");
        assert!(err.contains(want), "{want:?} not in {err:?}");
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    }
    // A user's long value is cut with its length; the list of valid types is whole.
    let long = "w".repeat(300);
    let (code, err) = with_scene(&format!("[[effect]]\ntype = \"{long}\"\n"));
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("line 2, column 8"), "{err}");
    assert!(err.contains("(300 bytes)") && !err.contains(&long), "{err}");
    assert!(
        err.contains("expected one of `spring`, `damper`, `plane`, `box`, `constant`"),
        "{err}"
    );
}
