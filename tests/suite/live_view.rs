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
    let d = common::shared_sim();
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

/// This process's soft descriptor limit raised to the hard one; the limit now.
fn raise_own_nofile() -> u64 {
    let mut l = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: a valid rlimit to fill and set.
    unsafe {
        libc::getrlimit(libc::RLIMIT_NOFILE, &mut l);
        l.rlim_cur = l.rlim_max;
        libc::setrlimit(libc::RLIMIT_NOFILE, &l);
        libc::getrlimit(libc::RLIMIT_NOFILE, &mut l);
    }
    l.rlim_cur
}

fn open_descriptors(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .map(|d| d.count())
        .unwrap_or(0)
}

fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap()
}

/// docs/ZENOH.md, "Ports and descriptors": 5000 connections to the live view's port that never
/// send their handshake, against a daemon started with the common soft limit of 1024
/// descriptors. The gate holds a bounded few and closes the rest; root's (here: the daemon
/// user's) `omnid ctl mode idle` still gets in; memory stays put; the held ones are closed at
/// the handshake deadline.
#[test]
#[ignore = "paced"]
fn five_thousand_half_open_viewers_leave_the_unix_socket_working_and_are_shed() {
    let limit = raise_own_nofile();
    let n = 5000usize.min(limit.saturating_sub(200) as usize);
    assert!(
        n >= 2000,
        "this test needs ~5200 descriptors (limit {limit})"
    );
    let d = Served::with_live_view_limited(&["--device", "sim"], Some(1024));
    let pid = d.child.as_ref().unwrap().id();
    let addr: std::net::SocketAddr = d.url.trim_start_matches("ws://").parse().unwrap();
    let ctl = |args: &[&str]| {
        omnid()
            .args(args)
            .env("XDG_RUNTIME_DIR", d.dir.path())
            .env_remove("RUNTIME_DIRECTORY")
            .env_remove("OMNID_SOCKET")
            .output()
            .unwrap()
    };
    let ok = ctl(&["ctl", "mode", "hold"]);
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let rss_before = rss_kib(pid);
    let mut held = Vec::with_capacity(n);
    let mut most_descriptors = 0;
    let mut failed_in_a_row = 0;
    for i in 0..n {
        // A connect the kernel cannot queue (its backlog full for a moment) fails: that is
        // the daemon not being reached, which is fine; the rest stay open and silent. A port
        // that takes nobody any more (its server out of descriptors) ends the flood.
        match std::net::TcpStream::connect_timeout(&addr, Duration::from_secs(2)) {
            Ok(s) => {
                held.push(s);
                failed_in_a_row = 0;
            }
            Err(_) => failed_in_a_row += 1,
        }
        if failed_in_a_row >= 10 {
            break;
        }
        if i % 500 == 0 {
            most_descriptors = most_descriptors.max(open_descriptors(pid));
        }
    }
    most_descriptors = most_descriptors.max(open_descriptors(pid));
    assert!(held.len() > n / 2, "only {} of {n} connected", held.len());
    // The gate's caps, not the descriptor limit, bound what the port holds.
    assert!(
        most_descriptors < 512,
        "the daemon held {most_descriptors} descriptors with {} silent connections",
        held.len()
    );
    let idle = ctl(&["ctl", "mode", "idle"]);
    assert!(
        idle.status.success(),
        "mode idle refused beside {} silent connections: {}",
        held.len(),
        String::from_utf8_lossy(&idle.stderr)
    );
    let rss_after = rss_kib(pid);
    assert!(
        rss_after < rss_before + 64 * 1024,
        "memory grew from {rss_before} KiB to {rss_after} KiB"
    );
    // Every silent connection is closed by the daemon: at once (past a cap) or at the
    // handshake deadline (5 s); a read that still waits after 20 s is one never shed.
    let until = std::time::Instant::now() + Duration::from_secs(20);
    let mut open = 0;
    for s in &mut held {
        let left = until
            .saturating_duration_since(std::time::Instant::now())
            .max(Duration::from_millis(10));
        s.set_read_timeout(Some(left)).unwrap();
        let mut b = [0u8; 64];
        match std::io::Read::read(s, &mut b) {
            Ok(0) => {}
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => {}
            Ok(_) => panic!("a silent connection was sent data"),
            Err(_) => open += 1,
        }
    }
    assert_eq!(
        open, 0,
        "{open} silent connections still open after the deadline"
    );
    let st = ctl(&["ctl", "status"]);
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
}
