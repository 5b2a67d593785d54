//! One arm against two in one daemon: the servo's lateness p99 (from each arm's `status`)
//! with each arm streamed at 1 kHz by its own client that answers every state with a
//! setpoint (a commander holding the lease), and whether any client lost a sample.
//!
//!     cargo bench --bench arms -- [SECONDS]      (default 20 s per configuration)
//!
//! Both configurations run in one invocation, interleaved over three rounds, so the machine's
//! load falls on both alike; the median round is compared.

use omnid::transport::client::{Client, Message};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A daemon serving `arms` simulated arms, its runtime directory in `dir`.
fn start(dir: &Path, arms: usize) -> Child {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_omnid"));
    cmd.arg("serve");
    for _ in 0..arms {
        cmd.args(["--device", "sim"]);
    }
    cmd.env("XDG_RUNTIME_DIR", dir)
        .env("OMNID_STATE_DIR", dir.join("state"))
        .env_remove("RUNTIME_DIRECTORY")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("omnid serve starts")
}

fn socket(dir: &Path, name: &str) -> PathBuf {
    dir.join("omnid").join(format!("{name}.sock"))
}

fn connect(path: &Path) -> Client {
    let until = Instant::now() + Duration::from_secs(30);
    loop {
        if let Ok(c) = Client::connect(path, "bench-arms") {
            return c;
        }
        assert!(Instant::now() < until, "no daemon at {}", path.display());
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Command one arm until `stop`: states received, and samples the daemon reported lost.
fn commander(path: PathBuf, stop: Arc<AtomicBool>) -> (u64, u64) {
    let mut c = connect(&path);
    c.request(json!({"op": "mode", "mode": "hold"})).unwrap();
    c.request(json!({"op": "stream", "rate_hz": 1000})).unwrap();
    let (mut n, mut lost) = (0, 0);
    while !stop.load(Ordering::Relaxed) {
        match c.recv(1000) {
            Ok(Message::State(s)) => {
                n += 1;
                let _ = c.send(&json!({"op": "servo_jp", "seq": s.seq, "q": [0.0, 0.6, 0.3]}));
            }
            Ok(Message::Other(v)) if v["type"] == "lost" => lost = v["total"].as_u64().unwrap_or(0),
            Ok(_) => {}
            Err(_) => break,
        }
    }
    (n, lost)
}

/// Lateness p99 of each arm, µs, and losses, over `secs` with `arms` arms.
fn measure(arms: usize, secs: f64) -> Vec<(String, f64, u64, u64)> {
    let dir = tempfile::tempdir().unwrap();
    let mut daemon = start(dir.path(), arms);
    let names: Vec<String> = (0..arms)
        .map(|k| {
            if k == 0 {
                "sim".into()
            } else {
                format!("sim-{}", k + 1)
            }
        })
        .collect();
    let stop = Arc::new(AtomicBool::new(false));
    let workers: Vec<_> = names
        .iter()
        .map(|n| {
            let (p, s) = (socket(dir.path(), n), stop.clone());
            std::thread::spawn(move || commander(p, s))
        })
        .collect();
    std::thread::sleep(Duration::from_secs_f64(secs));
    let mut out = Vec::new();
    let statuses: Vec<_> = names
        .iter()
        .map(|n| {
            let mut c = connect(&socket(dir.path(), n));
            c.request(json!({"op": "status"})).unwrap()["status"].clone()
        })
        .collect();
    stop.store(true, Ordering::Relaxed);
    for ((name, w), status) in names.iter().zip(workers).zip(statuses) {
        let (n, lost) = w.join().unwrap();
        let p99 = status["timing_us"]["lateness"]["p99"]
            .as_f64()
            .unwrap_or(f64::NAN);
        out.push((name.clone(), p99, n, lost));
    }
    // SAFETY: kill with our live child's pid.
    unsafe { libc::kill(daemon.id() as i32, libc::SIGTERM) };
    let _ = daemon.wait();
    out
}

fn main() {
    let secs: f64 = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .and_then(|a| a.parse().ok())
        .unwrap_or(20.0);
    // Interleaved rounds, so a burst of load elsewhere on the machine falls on both.
    let (mut one, mut two) = (Vec::new(), Vec::new());
    for round in 1..=3 {
        for (arms, into) in [(1, &mut one), (2, &mut two)] {
            let rows = measure(arms, secs);
            for (name, p99, n, lost) in &rows {
                println!(
                    "round {round}, {arms} arm(s): {name:<6} lateness p99 {p99:>7.1} µs   \
                     states {n}   lost {lost}"
                );
            }
            into.push(rows.iter().map(|r| r.1).fold(f64::NAN, f64::max));
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let (m1, m2) = (median(&mut one), median(&mut two));
    println!(
        "lateness p99 (median of 3 rounds, the worse arm): one arm {m1:.1} µs, two arms \
         {m2:.1} µs, ratio {:.2} (goal ≤ 1.2)",
        m2 / m1
    );
}
