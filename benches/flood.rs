//! The servo beside a network flood (issue #40, docs/ZENOH.md "Budgets"): `omnid serve` on the
//! simulator with zenoh on, each round once quiet and once with a remote client (a zenoh
//! peer in this process, bound to its key as any client is) asking for `status` as fast as
//! zenoh takes it, rounds interleaved. Reported: the servo's lateness percentiles from the
//! daemon's summary with and without the flood, the flood's requests sent and throttled, and
//! the median p99 with / without (the goal: at most 1.1).
//! `cargo bench --bench flood -- [SECONDS] [ROUNDS]` (default 10 s, 3).

#[path = "../tests/suite/common.rs"]
mod common;
mod support;

use omnid::transport::zenoh::bind::ClientKey;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::{Duration, Instant};
use zenoh::Wait;

/// A remote client on arm `sim` that says hello (with its key) and then puts sealed `status`
/// requests until `stop`; returns how many it put.
fn flood(port: u16, stop: Arc<AtomicBool>, greeted: mpsc::Sender<()>) -> u64 {
    let s = common::zenoh_peer(&format!("tcp/127.0.0.1:{port}"));
    let key = ClientKey::new().unwrap();
    let cid = key.cid("flood-");
    let replies = s
        .declare_subscriber(format!("omnid/sim/out/{cid}"))
        .wait()
        .unwrap();
    let _token = s
        .liveliness()
        .declare_token(format!("omnid/sim/client/{cid}"))
        .wait()
        .unwrap();
    let hello = serde_json::json!({"op": "hello", "protocol": 1, "key": key.public_base64()});
    let until = Instant::now() + Duration::from_secs(20);
    let answer = loop {
        assert!(Instant::now() < until, "the flooding client got no hello");
        s.put(format!("omnid/sim/in/{cid}"), hello.to_string())
            .wait()
            .unwrap();
        if let Ok(Some(r)) = replies.recv_timeout(Duration::from_millis(1000)) {
            break serde_json::from_slice::<serde_json::Value>(&r.payload().to_bytes()).unwrap();
        }
    };
    let mut sealer = key
        .finish(&cid, answer["key"].as_str().expect("the daemon's key"))
        .unwrap();
    let _ = greeted.send(());
    let p = s
        .declare_publisher(format!("omnid/sim/in/{cid}"))
        .wait()
        .unwrap();
    let body = br#"{"op":"status"}"#;
    let mut sent = 0;
    while !stop.load(Ordering::Relaxed) {
        p.put(&body[..])
            .attachment(sealer.seal(body).to_vec())
            .wait()
            .unwrap();
        sent += 1;
    }
    drop(replies);
    let _ = s.close().wait();
    sent
}

fn main() {
    let (secs, rounds) = support::seconds_and_rounds(10.0, 3);
    let mut p99 = [Vec::new(), Vec::new()];
    for round in 0..rounds {
        for flooded in [false, true] {
            let port = common::free_port();
            let daemon = support::SimServe::start(|cfg, opts| {
                support::zenoh_on_loopback(cfg, opts, port, false)
            });
            let flood_stop = Arc::new(AtomicBool::new(false));
            let sent = Arc::new(AtomicU64::new(0));
            let flooder = flooded.then(|| {
                let (tx, rx) = mpsc::channel();
                let (s, st) = (flood_stop.clone(), sent.clone());
                let h = std::thread::spawn(move || st.store(flood(port, s, tx), Ordering::SeqCst));
                rx.recv_timeout(Duration::from_secs(30))
                    .expect("the flood started");
                h
            });
            std::thread::sleep(Duration::from_secs_f64(secs));
            flood_stop.store(true, Ordering::SeqCst);
            if let Some(h) = flooder {
                h.join().unwrap();
            }
            let outcome = daemon.finish();
            let t = &outcome.arms[0].summary.timing_us;
            let late = t.lateness.expect("paced");
            let flood_line = if flooded {
                format!(
                    ", {} status requests put ({:.0}/s)",
                    sent.load(Ordering::SeqCst),
                    sent.load(Ordering::SeqCst) as f64 / secs
                )
            } else {
                String::new()
            };
            println!(
                "round {round} flood {:3}: lateness p50 {:.1} p99 {:.1} p99.9 {:.1} max {:.0} µs, \
                 overruns {}{flood_line}",
                if flooded { "on" } else { "off" },
                late.p50,
                late.p99,
                late.p999,
                late.max,
                t.overruns
            );
            p99[flooded as usize].push(late.p99);
        }
    }
    let (quiet, flooded) = (support::median(&p99[0]), support::median(&p99[1]));
    println!(
        "median lateness p99: without a flood {quiet:.1} µs, with {flooded:.1} µs, \
         with / without {:.3} (goal <= 1.1)",
        flooded / quiet
    );
}
