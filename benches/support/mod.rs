//! What the daemon benches share: their `[SECONDS] [ROUNDS]` arguments, the median over
//! rounds, and `omnid serve` on the simulator run in a thread of the bench (so its own
//! summary gives the servo's lateness).
#![allow(dead_code)]

use omnid::cmd::serve::{serve, ServeOptions, ServeOutcome};
use omnid::config::Config;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;

/// `[SECONDS] [ROUNDS]` from the command line (cargo's own `--bench` dropped), or the defaults.
pub fn seconds_and_rounds(secs: f64, rounds: usize) -> (f64, usize) {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    (
        args.first().and_then(|a| a.parse().ok()).unwrap_or(secs),
        args.get(1).and_then(|a| a.parse().ok()).unwrap_or(rounds),
    )
}

/// The middle value (the upper one of an even count).
pub fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The `p` quantile (0..=1) by nearest rank; sorts `v`.
pub fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// `omnid serve --device sim` (nnidc, the shipped weights, nothing kept, dumps and socket in its own directory),
/// running in a thread until `finish`.
pub struct SimServe {
    stop: Arc<AtomicBool>,
    daemon: JoinHandle<Result<ServeOutcome, omnid::cmd::run::RunError>>,
    _dir: tempfile::TempDir,
}

impl SimServe {
    /// Start it, after `adjust` has had its say on the config and options (zenoh, live view…).
    pub fn start(adjust: impl FnOnce(&mut Config, &mut ServeOptions)) -> SimServe {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = Config::default();
        // Nothing kept from or for another run: no heat, no learned weights.
        cfg.safety.persist_heat = false;
        cfg.identifier.persist = false;
        cfg.serve.dump_dir = dir.path().display().to_string();
        let mut opts = ServeOptions {
            devices: vec![omnid::cmd::run::DeviceSpec::Sim],
            socket: Some(dir.path().join("bench.sock")),
            ..ServeOptions::default()
        };
        adjust(&mut cfg, &mut opts);
        let stop = Arc::new(AtomicBool::new(false));
        let daemon = {
            let stop = stop.clone();
            std::thread::spawn(move || serve(&opts, &cfg, stop))
        };
        SimServe {
            stop,
            daemon,
            _dir: dir,
        }
    }

    /// Stop it as Ctrl-C would and return what it reports.
    pub fn finish(self) -> ServeOutcome {
        self.stop.store(true, Ordering::SeqCst);
        self.daemon.join().unwrap().expect("serve ran")
    }
}

/// Zenoh listening on loopback `port` only (no ROS 2 unless asked).
pub fn zenoh_on_loopback(cfg: &mut Config, opts: &mut ServeOptions, port: u16, ros2: bool) {
    cfg.zenoh.listen = vec![format!("tcp/127.0.0.1:{port}")];
    cfg.zenoh.connect = vec![];
    cfg.zenoh.ros2 = ros2;
    opts.zenoh = true;
}
