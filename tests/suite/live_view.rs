//! The live view (`omnid serve --foxglove`), checked from outside with a headless viewer
//! (tests/mcap/check_live.py: PyPI's `websockets` speaking the Foxglove SDK's subprotocol, and
//! `mcap-ros2-support` decoding every payload against its advertised schema). Skipped, loudly,
//! only when PyPI is out of reach.

use crate::common;
use common::omnid;
use common::Served;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

fn python() -> Option<PathBuf> {
    let py = common::venv(
        "live-venv",
        &[
            "mcap==1.6.0",
            "mcap-ros2-support==0.6.0",
            "websockets==17.4",
        ],
        "websockets",
    );
    if py.is_none() {
        eprintln!("SKIPPED: PyPI is out of reach, so no independent viewer is here");
    }
    py
}

fn viewer(py: &Path, args: &[&str]) -> serde_json::Value {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/mcap/check_live.py");
    let out = Command::new(py).arg(script).args(args).output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "check_live.py {args:?}: {text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(text.trim()).expect("one JSON line")
}

fn rate(report: &serde_json::Value, topic: &str) -> f64 {
    report[topic]["hz"].as_f64().unwrap_or(0.0)
}

fn assert_all_decode(report: &serde_json::Value) {
    for (topic, r) in report.as_object().unwrap() {
        assert_eq!(r["undecodable"], 0, "{topic}: {r}");
        assert_eq!(r["encoding"], "cdr", "{topic}");
    }
}

#[test]
#[ignore = "paced"]
fn a_viewer_gets_every_arm_channel_at_the_device_rate_and_every_payload_decodes() {
    let Some(py) = python() else { return };
    let d = Served::with_live_view(&["--device", "sim"]);
    let report = viewer(&py, &[&d.url, "5"]);
    assert_all_decode(&report);
    let hz = rate(&report, "/joint_states");
    assert!(
        (950.0..=1050.0).contains(&hz),
        "/joint_states at {hz} Hz: {report}"
    );
    assert_eq!(
        report["/joint_states"]["type"],
        "sensor_msgs/msg/JointState"
    );
    let tf = rate(&report, "/tf");
    assert!((55.0..=70.0).contains(&tf), "/tf at {tf} Hz");
    // The URDF comes again every second, so a viewer that connects late still draws the arm.
    assert!(report["/robot_description"]["messages"].as_u64().unwrap() >= 3);
    // The same names as a recording's, so one layout serves both.
    let layout: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/omnid-layout.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let text = layout.to_string();
    for topic in text.split('"').filter(|s| s.starts_with('/')) {
        let topic = topic.split('.').next().unwrap();
        assert!(
            report.get(topic).is_some(),
            "the layout names {topic}, not served"
        );
    }
}

#[test]
#[ignore = "paced"]
fn a_viewer_that_never_reads_costs_the_other_viewers_nothing() {
    let Some(py) = python() else { return };
    let d = Served::with_live_view(&["--device", "sim"]);
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/mcap/check_live.py");
    let mut stuck = Command::new(&py)
        .arg(&script)
        .args(["--stuck", &d.url, "120"])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(stuck.stdout.as_mut().unwrap())
        .read_line(&mut line)
        .unwrap();
    assert_eq!(line.trim(), "subscribed");
    // Let its queue on the server fill (1024 messages: about a tenth of a second).
    std::thread::sleep(Duration::from_secs(2));
    let report = viewer(&py, &[&d.url, "5"]);
    assert_all_decode(&report);
    let hz = rate(&report, "/joint_states");
    assert!(
        (950.0..=1050.0).contains(&hz),
        "beside a stuck viewer: {hz} Hz"
    );
    // SIGTERM with the stuck viewer still connected: the daemon still ends (its viewer never
    // closes; the live view waits a second for it, no longer).
    let mut d = d;
    // SAFETY: kill with a live child's pid.
    unsafe { libc::kill(d.child.as_ref().unwrap().id() as i32, libc::SIGTERM) };
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    let status = loop {
        if let Some(s) = d.child.as_mut().unwrap().try_wait().unwrap() {
            break Some(s);
        }
        if std::time::Instant::now() > deadline {
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let _ = stuck.kill();
    let _ = stuck.wait();
    let status = status.expect("omnid serve did not end on SIGTERM beside a stuck viewer");
    // An operator's stop: its documented exit code.
    assert_eq!(status.code(), Some(130), "{status:?}");
}

#[test]
#[ignore = "paced"]
fn the_old_subprotocol_is_refused_and_bad_addresses_are_input_errors() {
    // Bad addresses need no viewer.
    for (addr, want) in [("localhost", "HOST:PORT"), ("127.0.0.1:99999", "HOST:PORT")] {
        let out = omnid()
            .args(["serve", "--device", "sim", "--foxglove", addr])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{addr}: {err}");
        assert!(err.contains(want), "{addr}: {err}");
    }
    // A port another program holds: refused before any arm starts, naming the address.
    let held = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = held.local_addr().unwrap().to_string();
    let dir = tempfile::tempdir().unwrap();
    let out = omnid()
        .args(["serve", "--device", "sim", "--foxglove", &addr])
        .env("XDG_RUNTIME_DIR", dir.path())
        .env("OMNID_STATE_DIR", dir.path())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains(&addr) && !err.contains("panicked"), "{err}");
    let Some(py) = python() else { return };
    // Clients that offer only the old `foxglove.websocket.v1` (the open-source Foxglove
    // Studio) are refused by the SDK's server: asserted, so a change is noticed.
    let d = Served::with_live_view(&["--device", "sim"]);
    let old = viewer(&py, &["--old", &d.url]);
    assert_eq!(old["status"], 400);
}
