//! What went wrong is said where the user looks (issue 16, class 9): a gap in a replay's
//! device time restarts the estimator instead of tripping on its extrapolation (and a trip
//! just after a gap names it); faults scheduled past the end of a run are reported.

use crate::common;
use common::omnid;

/// Joint 1 moving at `speed` rad/s for 0.1 s, a `gap` with no data, then `after(t)` for 0.5 s.
fn log_with_gap(dir: &std::path::Path, speed: f64, gap: f64, after: impl Fn(f64) -> f64) -> String {
    let mut text = String::from("t,q1,q2,q3,tau1,tau2,tau3\n");
    for k in 0..100 {
        let t = k as f64 * 1e-3;
        text += &format!("{t:.4},{:.6},0.6,0.3,0,0,0\n", speed * t);
    }
    let t_end = 0.099;
    for k in 0..500 {
        let dt = k as f64 * 1e-3;
        text += &format!(
            "{:.4},{:.6},0.6,0.3,0,0,0\n",
            t_end + gap + dt,
            speed * t_end + after(dt)
        );
    }
    let path = dir.join("gap.csv");
    std::fs::write(&path, text).unwrap();
    format!("replay:{}", path.display())
}

fn replay(dir: &std::path::Path, device: &str) -> (Option<i32>, String, serde_json::Value) {
    let summary = dir.join("s.json");
    let out = omnid()
        .args([
            "run",
            "--fast",
            "--controller",
            "off",
            "--device",
            device,
            "--log",
        ])
        .arg(dir.join("run.csv"))
        .arg("--summary-json")
        .arg(&summary)
        .env("OMNID_STATE_DIR", dir)
        .output()
        .unwrap();
    let json = serde_json::from_str(&std::fs::read_to_string(&summary).unwrap_or_default())
        .unwrap_or_default();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr),
        json,
    )
}

#[test]
fn a_gap_in_the_data_restarts_the_estimator_instead_of_tripping() {
    let dir = tempfile::tempdir().unwrap();
    // 9 rad/s, then 0.1 s without data, then the arm at rest where it was: extrapolating
    // through the gap made the estimate swing to -10.75 rad/s and trip the speed limit.
    let device = log_with_gap(dir.path(), 9.0, 0.1, |_| 0.0);
    let (code, text, json) = replay(dir.path(), &device);
    assert_eq!(code, Some(0), "{text}");
    assert_eq!(json["estimator_restarts"], 1);
    assert!(text.contains("restarted 1 time(s)"), "{text}");

    // A real overspeed just after a gap: the trip names the gap.
    let device = log_with_gap(dir.path(), 1.0, 0.1, |dt| 15.0 * dt);
    let (code, text, _) = replay(dir.path(), &device);
    assert_eq!(code, Some(4), "{text}");
    assert!(text.contains("gap in the device time"), "{text}");
}

#[test]
fn faults_scheduled_past_the_end_are_reported() {
    let dir = tempfile::tempdir().unwrap();
    let summary = dir.path().join("s.json");
    let out = omnid()
        .args([
            "run",
            "--fast",
            "--duration",
            "1",
            "--inject",
            "stall@5:30",
            "--log",
        ])
        .arg(dir.path().join("run.csv"))
        .arg("--summary-json")
        .arg(&summary)
        .env("OMNID_STATE_DIR", dir.path())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(0), "{err}");
    assert!(
        err.contains("stall@5:30") && err.contains("never acted"),
        "{err}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    assert!(json["warnings"][0].as_str().unwrap().contains("stall@5:30"));
}
