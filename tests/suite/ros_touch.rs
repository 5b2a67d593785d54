//! The real Geomagic Touch recording (shipped in `data/`, ROS joint convention): converted with
//! `omnid convert --from ros-touch`, checked against the recorded tip, and replayed end to end.

use crate::common;
use common::{run_ok, Log};
use omnid::omni::{tip_position_mm, Geometry, Joint3};
use omnid::telemetry::reader::LogReader;

const RECORDING: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/data/touch-2016-joint-and-tip.csv"
);

/// Convert the recording into a temporary directory.
fn converted() -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("touch.csv");
    let o = run_ok(&[
        "convert",
        "--from",
        "ros-touch",
        RECORDING,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("2743 rows"));
    (dir, out)
}

#[test]
fn converted_angles_reproduce_the_recorded_tip() {
    let (_dir, out) = converted();
    let l = Log::read(&out);
    assert_eq!(
        &l.header[..7],
        &["t", "q1", "q2", "q3", "tau1", "tau2", "tau3"]
    );
    assert!(l.f64s("tau1").iter().all(|&v| v == 0.0), "nothing recorded");
    let (q1, q2, q3) = (l.f64s("q1"), l.f64s("q2"), l.f64s("q3"));
    let tip = [l.f64s("x_mm"), l.f64s("y_mm"), l.f64s("z_mm")];
    let g = Geometry::default();
    let mut sq = [0.0f64; 3];
    for k in 0..l.rows.len() {
        let p = tip_position_mm(&g, &Joint3::new(q1[k], q2[k], q3[k]));
        for a in 0..3 {
            sq[a] += (p[a] - tip[a][k]).powi(2);
        }
    }
    let rms = sq.map(|s| (s / l.rows.len() as f64).sqrt());
    eprintln!("tip RMS per axis from the converted angles (mm): {rms:?}");
    for (axis, r) in ["x", "y", "z"].iter().zip(rms) {
        assert!(r <= 0.05, "{axis}: {r} mm RMS");
    }
    // The file is a valid replayable log for the strict reader as well.
    let rows = LogReader::open(&out, false, None)
        .unwrap()
        .collect::<Result<Vec<_>, _>>()
        .unwrap();
    assert_eq!(rows.len(), 2743);
}

#[test]
fn converted_recording_replays_end_to_end() {
    let (dir, out) = converted();
    let log = dir.path().join("replayed.csv");
    let device = format!("replay:{}", out.display());
    let o = run_ok(&[
        "run",
        "--device",
        &device,
        "--controller",
        "off",
        "--fast",
        "--log",
        log.to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("2743 ticks") && text.contains("ended: at the end of the recording"),
        "{text}"
    );
    // A person's recording replayed with no controller followed nothing: no reference named,
    // no tracking error reported against a sine it never saw.
    assert!(
        text.contains("with the controller off (--fast);") && !text.contains("following"),
        "{text}"
    );
    assert!(!text.contains("tracking"), "{text}");
    let l = Log::read(&log);
    assert_eq!(l.rows.len(), 2743 + 1, "every sample and the stop row");
    for (k, row) in l.rows.iter().enumerate() {
        for (c, v) in l.header.iter().zip(row) {
            assert!(
                !v.to_ascii_lowercase().contains("nan") && !v.contains("inf"),
                "{c} = {v} at row {k}"
            );
        }
    }
    // The recording's own, irregular time stamps reach the log unchanged (relative to the first).
    let (t_in, t_out) = (Log::read(&out).f64s("t"), l.f64s("t"));
    for k in 0..2743 {
        assert_eq!(t_out[k], t_in[k] - t_in[0]);
    }
    // A hand-moved arm: the estimator reports motion, and nothing absurd.
    let qd1 = l.f64s("qd1");
    let peak = qd1.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(peak > 0.2 && peak < 20.0, "peak |qd1| {peak} rad/s");
}
