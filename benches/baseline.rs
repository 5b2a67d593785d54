//! The machine's own timing floor: an absolute-deadline 1 kHz sleep loop with the same
//! realtime set-up as the servo thread and nothing else in it. Run it right before a paced
//! `omnid run` to report the daemon's lateness as a ratio to this floor:
//!
//! ```sh
//! cargo bench --bench baseline -- 60     # seconds (default 10)
//! ```

use omnid::clock;
use omnid::config::RealtimeConfig;
use omnid::servo::realtime;
use omnid::servo::timing::Histogram;

fn main() {
    // `cargo bench` passes `--bench`; the first number on the command line is the duration.
    let secs: f64 = std::env::args()
        .skip(1)
        .find_map(|a| a.parse().ok())
        .unwrap_or(10.0);
    let ticks = (secs * 1000.0) as u64;
    let handle = std::thread::Builder::new()
        .name("baseline".into())
        .stack_size(2 << 20)
        .spawn(move || {
            let rt = realtime::apply(&RealtimeConfig::default());
            for w in &rt.warnings {
                eprintln!("warning: {w}");
            }
            let mut lateness = Histogram::new(1_000, 20_000_000);
            let period = 1_000_000u64;
            let start = clock::now_ns() + period;
            for k in 0..ticks {
                let deadline = start + k * period;
                clock::sleep_until_ns(deadline);
                lateness.record(clock::now_ns().saturating_sub(deadline));
            }
            (lateness, rt)
        })
        .expect("spawn baseline thread");
    let (h, rt) = handle.join().expect("baseline thread");
    let p = h.percentiles_us().expect("ticks recorded");
    println!(
        "baseline 1 kHz sleep loop, {ticks} ticks (SCHED_FIFO {:?}, memory locked {}): lateness p50 {:.1} p99 {:.1} p99.9 {:.1} max {:.1} µs",
        rt.fifo_priority, rt.memory_locked, p.p50, p.p99, p.p999, p.max
    );
}
