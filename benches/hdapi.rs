//! libHD's frames against `omnid serve --device sim`: the fraction of scheduler frames whose
//! force the servo applies at the next tick (the frame on state k is on time when state k + 1
//! carries `cmd_seq = k`), beside the same fraction for a plain client of the socket that
//! answers every state with a `servo_jf` (serve's own round trip, as `benches/serve.rs`
//! measures it). Both are judged by the same watching client, so the daemon streams to two
//! clients in both phases.
//!
//! `cargo bench --bench hdapi -- SECONDS` (each phase, default 10 s). Prints a table and
//! writes `target/hdapi-bench.json`. Timing on a shared machine is noisy: this prints, it
//! never fails on numbers.

#[path = "../tests/suite/common.rs"]
mod common;
#[path = "../tests/suite/hd.rs"]
mod hd;

use common::Served;
use hd::HD;
use omnid::transport::client::{Client, Message};
use serde_json::json;
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

/// On-time transitions k → k + 1 among consecutive streamed states in a stream mode.
#[derive(Default, Debug, Clone, Copy)]
struct OnTime {
    judged: u64,
    on_time: u64,
    gaps: u64,
}

impl OnTime {
    fn add(&mut self, prev: Option<(u64, bool)>, seq: u64, cmd_seq: u64, streaming: bool) {
        if let Some((k, was)) = prev {
            if seq == k + 1 && was && streaming {
                self.judged += 1;
                self.on_time += u64::from(cmd_seq == k);
            } else if seq > k + 1 {
                self.gaps += seq - k - 1;
            }
        }
    }

    fn fraction(&self) -> f64 {
        self.on_time as f64 / self.judged.max(1) as f64
    }
}

/// Watch the stream for `secs` after the program's frames began.
fn observe(watch: &mut Client, secs: f64) -> OnTime {
    let mut r = OnTime::default();
    let mut prev = None;
    let mut start = None;
    loop {
        let s = match watch.recv(2000) {
            Ok(Message::State(s)) => s,
            Ok(_) => continue,
            Err(e) => panic!("watching: {e}"),
        };
        let streaming = s.mode.starts_with("servo_");
        // Half a second to settle once the frames began.
        let t0 = match (streaming, start) {
            (true, None) => *start.insert(s.t + 0.5),
            (_, Some(t0)) => t0,
            (false, None) => continue,
        };
        if s.t >= t0 + secs {
            return r;
        }
        if s.t >= t0 {
            r.add(prev, s.seq, s.cmd_seq, streaming);
        }
        prev = Some((s.seq, streaming));
    }
}

fn libhd(hd: &HD, daemon: &Served, secs: f64) -> (OnTime, String) {
    let mut watch = daemon.connect("bench-watch");
    watch
        .request(json!({"op": "stream", "rate_hz": 1000}))
        .unwrap();
    let mut child = Command::new(hd.exe("bench"))
        .arg(format!("{}", secs + 2.0))
        .env("OMNID_SOCKET", &daemon.sock)
        .stdout(Stdio::piped())
        .spawn()
        .expect("bench program starts");
    let r = observe(&mut watch, secs);
    let mut frames = String::new();
    for line in BufReader::new(child.stdout.take().unwrap()).lines() {
        let line = line.unwrap();
        if let Some(f) = line.strip_prefix("frames ") {
            frames = f.to_string();
        }
    }
    child.wait().unwrap();
    (r, frames)
}

/// A plain client answering every state k with `servo_jf` seq = k (zero torque), judged by
/// a watching client as libHD's frames are (so the daemon streams to two clients in both).
fn plain(daemon: &Served, secs: f64) -> OnTime {
    let mut watch = daemon.connect("bench-watch");
    watch
        .request(json!({"op": "stream", "rate_hz": 1000}))
        .unwrap();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let answering = {
        let mut c = daemon.connect("bench-plain");
        let stop = stop.clone();
        std::thread::spawn(move || {
            c.request(json!({"op": "lease"})).unwrap();
            c.request(json!({"op": "stream", "rate_hz": 1000})).unwrap();
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                let s = match c.recv(2000) {
                    Ok(Message::State(s)) => s,
                    Ok(_) => continue,
                    Err(e) => panic!("plain client: {e}"),
                };
                c.send(
                    &json!({"op": "servo_jf", "seq": s.seq, "tau": [0.0, 0.0, 0.0], "ttl_ms": 10}),
                )
                .unwrap();
            }
            let _ = c.request(json!({"op": "mode", "mode": "idle"}));
            let _ = c.request(json!({"op": "release"}));
        })
    };
    let r = observe(&mut watch, secs);
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    answering.join().expect("plain client");
    r
}

fn main() {
    let secs: f64 = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(10.0);
    let hd = HD::get();
    let daemon = Served::sim(&[], None);
    let (lib, frames) = libhd(hd, &daemon, secs);
    let bare = plain(&daemon, secs);
    // The servo's own timing over both phases: a tick that starts late leaves the next one
    // (at its absolute deadline) no time for any client's round trip.
    let timing = daemon
        .connect("bench-status")
        .request(json!({"op": "status"}))
        .map(|v| v["status"]["timing_us"].clone())
        .unwrap_or_default();
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "libHD bench: {secs} s per phase on the simulator (load {})",
        load.trim()
    );
    for (name, r) in [
        ("libHD scheduler frames", lib),
        ("plain socket client", bare),
    ] {
        println!(
            "  {name:24} {:>6} of {:>6} applied at the next tick = {:.4} %  (states missed {})",
            r.on_time,
            r.judged,
            100.0 * r.fraction(),
            r.gaps
        );
    }
    println!("  frames the HD program ran: {frames}");
    let lateness = &timing["lateness"];
    println!(
        "  the servo's own lateness (both phases): p99 {} p99.9 {} max {} µs; overruns {}",
        lateness["p99"], lateness["p999"], lateness["max"], timing["overruns"]
    );
    let out = json!({
        "seconds": secs,
        "libhd": {"judged": lib.judged, "on_time": lib.on_time, "fraction": lib.fraction(), "gaps": lib.gaps, "frames": frames},
        "plain": {"judged": bare.judged, "on_time": bare.on_time, "fraction": bare.fraction(), "gaps": bare.gaps},
        "servo_timing_us": timing,
    });
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("target/hdapi-bench.json");
    let _ = std::fs::write(&path, serde_json::to_vec_pretty(&out).unwrap_or_default());
    println!("  written to {}", path.display());
}
