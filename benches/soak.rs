//! Soak: a long paced run on the simulated Omni, reporting memory at start and end, faults and
//! telemetry drops. `cargo bench --bench soak -- SECONDS [CONTROLLER]` (default 600 s, nnidc).

use omnid::cmd::run::{execute, RunOptions};
use omnid::config::Config;
use omnid::control::ControllerKind;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

/// (VmRSS, VmHWM) of this process in KiB.
fn memory_kib() -> (u64, u64) {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let secs: f64 = args.first().and_then(|a| a.parse().ok()).unwrap_or(600.0);
    let controller = match args.get(1).map(String::as_str) {
        Some("pd") => ControllerKind::Pd,
        Some("ct") => ControllerKind::Ct,
        Some("off") => ControllerKind::Off,
        _ => ControllerKind::Nnidc,
    };
    let dir = tempfile::tempdir().expect("temp dir");
    let opts = RunOptions {
        controller,
        duration_s: secs,
        log: Some(dir.path().join("soak.csv")),
        ..RunOptions::default()
    };
    let stop = Arc::new(AtomicBool::new(false));
    let sampler_stop = stop.clone();
    let sampler = std::thread::spawn(move || {
        let mut samples = vec![memory_kib()];
        while !sampler_stop.load(Ordering::Relaxed) {
            std::thread::sleep(Duration::from_secs(1));
            samples.push(memory_kib());
        }
        samples
    });
    let start = memory_kib();
    let outcome = execute(&opts, &Config::default(), Arc::new(AtomicBool::new(false)));
    stop.store(true, Ordering::Relaxed);
    let samples = sampler.join().expect("sampler");
    let end = memory_kib();
    match outcome {
        Ok(o) => {
            print!("{}", o.summary.human());
            let early = samples.get(10).copied().unwrap_or(start);
            println!(
                "soak {secs} s {}: RSS start {} KiB, after 10 s {} KiB, end {} KiB, peak {} KiB; faults {}; telemetry dropped {}",
                controller.as_str(),
                start.0,
                early.0,
                end.0,
                end.1,
                o.summary.faults.len(),
                o.summary.telemetry_dropped
            );
        }
        Err(e) => {
            eprintln!("soak failed to start: {e}");
            std::process::exit(1);
        }
    }
}
