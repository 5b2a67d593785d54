//! The safety limits do not depend on the estimator's tuning (issue 16, class 1): a Kalman
//! configuration that cannot follow the arm is refused before any torque is sent, and the
//! speed limit also watches the encoders.

use crate::common;
use common::omnid;

#[test]
fn a_kalman_config_that_cannot_follow_the_arm_is_refused_before_torque() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("k.toml");
    // Accepted until now: the run "completed" with exit 0 while the encoders showed the arm
    // at 65 rad/s and a radian beyond the soft walls.
    std::fs::write(
        &config,
        "[kalman]\njerk_psd = 1e-6\nmeasurement_var = 1e-2\n",
    )
    .unwrap();
    let log = dir.path().join("run.csv");
    let out = omnid()
        .args(["run", "--fast", "--controller", "pd", "--config"])
        .arg(&config)
        .arg("--log")
        .arg(&log)
        .env("OMNID_STATE_DIR", dir.path())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("kalman.jerk_psd") && err.contains("5 Hz"),
        "{err}"
    );
    assert!(!log.exists(), "refused before the run");
}

#[test]
fn the_speed_limit_watches_the_encoders() {
    // A 20 Hz, 0.15 rad tremor on joint 1 from t = 1 s (18.8 rad/s at its steepest), replayed
    // with an estimator the config accepts but that smooths it: the encoders trip within a
    // window of ~10 ms; the estimate alone tripped 38 ms in.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tremor.csv");
    let mut text = String::from("t,q1,q2,q3,tau1,tau2,tau3\n");
    for k in 0..3000 {
        let t = k as f64 * 1e-3;
        let q1 = if t > 1.0 {
            0.15 * (std::f64::consts::TAU * 20.0 * (t - 1.0)).sin()
        } else {
            0.0
        };
        text += &format!("{t:.3},{q1:.6},0.6,0.3,0,0,0\n");
    }
    std::fs::write(&path, text).unwrap();
    let config = dir.path().join("k.toml");
    std::fs::write(&config, "[kalman]\njerk_psd = 1.0\n").unwrap();
    let summary = dir.path().join("s.json");
    let out = omnid()
        .args(["run", "--fast", "--controller", "off", "--device"])
        .arg(format!("replay:{}", path.display()))
        .arg("--config")
        .arg(&config)
        .arg("--log")
        .arg(dir.path().join("run.csv"))
        .arg("--summary-json")
        .arg(&summary)
        .env("OMNID_STATE_DIR", dir.path())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(4), "{err}");
    assert!(err.contains("by its encoders"), "{err}");
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    let t = s["faults"][0]["t"].as_f64().unwrap();
    assert!(t <= 1.015, "tripped at {t} s");
}
