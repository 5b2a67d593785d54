//! What recording costs the servo loop: paced simulator runs logging CSV and MCAP, rounds
//! interleaved, each round's lateness and compute percentiles, then the median over rounds.
//! `cargo bench --bench recording -- [SECONDS] [ROUNDS]` (default 20 s, 3 rounds).

mod support;

use omnid::cmd::run::{execute, RunOptions};
use omnid::config::Config;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

fn main() {
    let (secs, rounds) = support::seconds_and_rounds(20.0, 3);
    let dir = tempfile::tempdir().expect("temp dir");
    let mut cfg = Config::default();
    cfg.safety.persist_heat = false;
    let formats = ["csv", "mcap"];
    let mut results: Vec<Vec<[f64; 4]>> = vec![Vec::new(); formats.len()];
    for round in 0..rounds {
        for (i, ext) in formats.iter().enumerate() {
            let log = dir.path().join(format!("run-{round}.{ext}"));
            let opts = RunOptions {
                duration_s: secs,
                log: Some(log.clone()),
                ..RunOptions::default()
            };
            let o = execute(&opts, &cfg, Arc::new(AtomicBool::new(false))).expect("run");
            let t = &o.summary.timing_us;
            let (late, compute) = (t.lateness.expect("paced"), t.compute.expect("ticks"));
            let size = std::fs::metadata(&log).map(|m| m.len()).unwrap_or(0);
            println!(
                "round {round} {ext:4}: lateness p50 {:.1} p99 {:.1} p99.9 {:.1} µs, compute p99 \
                 {:.1} µs, dropped {}, {:.0} B/tick",
                late.p50,
                late.p99,
                late.p999,
                compute.p99,
                o.summary.telemetry_dropped,
                size as f64 / (secs * 1000.0)
            );
            results[i].push([late.p50, late.p99, late.p999, compute.p99]);
            std::fs::remove_file(&log).ok();
        }
    }
    for (i, ext) in formats.iter().enumerate() {
        let col = |k: usize| support::median(&results[i].iter().map(|r| r[k]).collect::<Vec<_>>());
        println!(
            "median {ext:4}: lateness p50 {:.1} p99 {:.1} p99.9 {:.1} µs, compute p99 {:.1} µs",
            col(0),
            col(1),
            col(2),
            col(3)
        );
    }
    let p99 = |i: usize| support::median(&results[i].iter().map(|r| r[1]).collect::<Vec<_>>());
    println!("lateness p99 mcap / csv: {:.3}", p99(1) / p99(0));
}
