//! What zenoh costs and how fast it is: `omnid serve` on the simulator with zenoh off, and on
//! with a ROS 2 subscriber of `measured_js` in this process (a peer on loopback), rounds
//! interleaved. Reported: the servo's lateness percentiles (from the daemon's summary) off vs
//! on, and the state → subscriber latency (a sample's receipt minus its tick's time: the
//! header stamp, device time on the system clock) beside a bare zenoh put → subscriber floor
//! measured in the same run between two sessions of this process; samples received vs ticks
//! and sequence gaps. `cargo bench --bench zenoh -- [SECONDS] [ROUNDS]` (default 10 s, 2).

#[path = "../tests/suite/common.rs"]
mod common;
mod support;

use omnid::ros2::{msgs, rmw_zenoh as rmw};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use zenoh::Wait;

fn now_ns() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as i64
}

fn main() {
    let (secs, rounds) = support::seconds_and_rounds(10.0, 2);
    let mut p99 = [Vec::new(), Vec::new()];
    for round in 0..rounds {
        for on in [false, true] {
            let port = common::free_port();
            let daemon = support::SimServe::start(|cfg, opts| {
                if on {
                    support::zenoh_on_loopback(cfg, opts, port, true)
                }
            });
            let mut report = String::new();
            if on {
                let sub_session = common::zenoh_peer(&format!("tcp/127.0.0.1:{port}"));
                let key =
                    rmw::data_key(0, "/sim/measured_js", &rmw::JOINT_STATE, Default::default());
                let got: Arc<Mutex<Vec<(i64, i64)>>> = Arc::default();
                let g = got.clone();
                let _sub = sub_session
                    .declare_subscriber(key)
                    .callback(move |s| {
                        let recv = now_ns();
                        let bytes = s.payload().to_bytes();
                        let stamp = msgs::read_joint_state(&bytes).map_or(0, |m| {
                            m.header.stamp.sec as i64 * 1_000_000_000
                                + m.header.stamp.nanosec as i64
                        });
                        let seq = s
                            .attachment()
                            .and_then(|a| rmw::read_attachment(&a.to_bytes()).ok())
                            .map_or(0, |a| a.0);
                        g.lock().unwrap().push((recv - stamp, seq));
                    })
                    .wait()
                    .unwrap();
                // The floor: a bare put from a second session of this process to the first.
                let floor_port = common::free_port();
                let mut c = zenoh::Config::default();
                for (k, v) in [
                    ("mode", "\"peer\"".to_string()),
                    (
                        "listen/endpoints",
                        format!("[\"tcp/127.0.0.1:{floor_port}\"]"),
                    ),
                    ("scouting/multicast/enabled", "false".into()),
                ] {
                    c.insert_json5(k, &v).unwrap();
                }
                let floor_sub_session = zenoh::open(c).wait().unwrap();
                let floor: Arc<Mutex<Vec<f64>>> = Arc::default();
                let f = floor.clone();
                let _fsub = floor_sub_session
                    .declare_subscriber("bench/floor")
                    .callback(move |s| {
                        let b = s.payload().to_bytes();
                        let sent = i64::from_le_bytes(b[..8].try_into().unwrap());
                        f.lock().unwrap().push((now_ns() - sent) as f64 * 1e-3);
                    })
                    .wait()
                    .unwrap();
                let pub_session = common::zenoh_peer(&format!("tcp/127.0.0.1:{floor_port}"));
                let publisher = pub_session.declare_publisher("bench/floor").wait().unwrap();
                std::thread::sleep(Duration::from_millis(500));
                got.lock().unwrap().clear();
                let t0 = std::time::Instant::now();
                let mut next = t0;
                while t0.elapsed().as_secs_f64() < secs {
                    let mut payload = now_ns().to_le_bytes().to_vec();
                    payload.resize(120, 0);
                    publisher.put(payload).wait().unwrap();
                    next += Duration::from_millis(1);
                    if let Some(d) = next.checked_duration_since(std::time::Instant::now()) {
                        std::thread::sleep(d);
                    }
                }
                let elapsed = t0.elapsed().as_secs_f64();
                let got = std::mem::take(&mut *got.lock().unwrap());
                let mut lat: Vec<f64> = got.iter().map(|g| g.0 as f64 * 1e-3).collect();
                let gaps = got.windows(2).filter(|w| w[1].1 != w[0].1 + 1).count();
                let mut fl = std::mem::take(&mut *floor.lock().unwrap());
                let (l50, l99) = (
                    support::percentile(&mut lat, 0.5),
                    support::percentile(&mut lat, 0.99),
                );
                let (f50, f99) = (
                    support::percentile(&mut fl, 0.5),
                    support::percentile(&mut fl, 0.99),
                );
                report = format!(
                    "\n    measured_js: {} samples in {elapsed:.1} s ({:.0} Hz), {gaps} sequence \
                     gaps; latency p50 {l50:.0} p99 {l99:.0} µs | floor put→sub p50 {f50:.0} \
                     p99 {f99:.0} µs | p99 ratio {:.2}",
                    got.len(),
                    got.len() as f64 / elapsed,
                    l99 / f99
                );
            } else {
                std::thread::sleep(Duration::from_secs_f64(secs + 0.5));
            }
            let outcome = daemon.finish();
            let t = &outcome.arms[0].summary.timing_us;
            let late = t.lateness.expect("paced");
            println!(
                "round {round} zenoh {:3}: lateness p50 {:.1} p99 {:.1} p99.9 {:.1} max {:.0} µs, \
                 overruns {}{report}",
                if on { "on" } else { "off" },
                late.p50,
                late.p99,
                late.p999,
                late.max,
                t.overruns
            );
            p99[on as usize].push(late.p99);
        }
    }
    let (off, on) = (support::median(&p99[0]), support::median(&p99[1]));
    println!(
        "median lateness p99: off {off:.1} µs, on {on:.1} µs, on / off {:.3}",
        on / off
    );
}
