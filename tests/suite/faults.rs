//! Fault injection end to end: each fault on the simulated Omni ends (or survives) as the
//! safety contract says — exit code per class, complete log ending in the stop packet, a
//! 500-tick dump beside it, the fault in the summary — and the device itself sees zero torque
//! with the amplifiers off within one exchange of detection.

use crate::common;
use common::{omnid, Log};
use omnid::config::Config;
use omnid::control::{ControllerKind, ControllerSet, Reference, Trajectory};
use omnid::device::codec::{decode_command, MotorCommand};
use omnid::device::inject::{Fault, FaultyDevice};
use omnid::device::sim::SimOmni;
use omnid::device::{Device, DeviceError, RawSample, COMMAND_LEN};
use omnid::servo::{EndReason, Servo};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};

struct Case {
    spec: &'static str,
    exit: i32,
    class: Option<&'static str>,
}

const CASES: &[Case] = &[
    Case {
        spec: "disconnect@3",
        exit: 3,
        class: Some("device-fault"),
    },
    Case {
        spec: "stall@3:200",
        exit: 3,
        class: Some("device-fault"),
    },
    Case {
        spec: "stall@3:5",
        exit: 0,
        class: None,
    },
    Case {
        spec: "corrupt:0.01",
        exit: 0,
        class: None,
    },
    Case {
        spec: "encoder-jump@3:800",
        exit: 4,
        class: Some("safety-fault"),
    },
    Case {
        spec: "nan@3",
        exit: 4,
        class: Some("safety-fault"),
    },
    Case {
        spec: "slow@3:20",
        exit: 0,
        class: None,
    },
];

fn run_case(case: &Case, controller: &str) {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("run.csv");
    let json = dir.path().join("s.json");
    let out = omnid()
        .args([
            "run",
            "--fast",
            "--duration",
            "5",
            "--controller",
            controller,
        ])
        .args(["--inject", case.spec, "--log", log.to_str().unwrap()])
        .args(["--summary-json", json.to_str().unwrap()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        out.status.code(),
        Some(case.exit),
        "{}: {stderr}",
        case.spec
    );
    assert!(!stderr.contains("panicked"));

    let l = Log::read(&log);
    let last = l.rows.last().unwrap();
    assert_eq!(last[l.col("mode")], "stop", "{}", case.spec);
    assert_eq!(last[l.col("amps")], "0");
    for c in ["tau1", "tau2", "tau3"] {
        assert_eq!(last[l.col(c)].parse::<f64>().unwrap(), 0.0);
    }
    let t = l.f64s("t");
    assert!(
        t.windows(2).all(|w| w[1] > w[0]),
        "{}: time must increase",
        case.spec
    );

    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let faults = s["faults"].as_array().unwrap();
    let dump = dir.path().join("run-fault.csv");
    match case.class {
        Some(class) => {
            assert_eq!(faults.len(), 1, "{}", case.spec);
            assert_eq!(faults[0]["class"], class);
            let tick = faults[0]["tick"].as_u64().unwrap();
            assert!(
                (2990..=3010).contains(&tick),
                "{}: fault at tick {tick}",
                case.spec
            );
            let d = Log::read(&dump);
            assert_eq!(d.header, l.header);
            assert_eq!(d.rows.len(), 500, "{}: dump rows", case.spec);
            // The dump is the log's last 500 rows.
            assert_eq!(d.rows.last(), l.rows.last());
        }
        None => {
            assert!(faults.is_empty(), "{}: {faults:?}", case.spec);
            assert!(!dump.exists());
            assert_eq!(s["ticks"], 5000);
        }
    }
    if case.spec.starts_with("corrupt") {
        let missed = s["missed_packets"].as_u64().unwrap();
        assert!(
            (20..=100).contains(&missed),
            "1 % of 5000 packets: {missed}"
        );
    }
}

#[test]
fn every_injected_fault_with_pd() {
    for case in CASES {
        run_case(case, "pd");
    }
}

#[test]
fn every_injected_fault_with_ct() {
    for case in CASES {
        run_case(case, "ct");
    }
}

/// Records every command the plant receives.
struct Recorder {
    inner: SimOmni,
    seen: Arc<Mutex<Vec<MotorCommand>>>,
}

impl Device for Recorder {
    fn kind(&self) -> &'static str {
        "sim"
    }
    fn exchange(&mut self, c: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError> {
        self.seen.lock().unwrap().push(decode_command(c).unwrap());
        self.inner.exchange(c)
    }
}

fn plant_commands(fault: &str) -> (EndReason, u64, Vec<MotorCommand>) {
    let cfg = Config::default();
    let seen = Arc::new(Mutex::new(Vec::new()));
    let plant = Recorder {
        inner: SimOmni::new(&cfg, false),
        seen: seen.clone(),
    };
    let f: Fault = fault.parse().unwrap();
    let device = FaultyDevice::new(Box::new(plant), &[f], 1, Arc::default());
    let (tx, rx) = crossbeam_channel::bounded(1 << 16);
    let servo = Servo::new(
        &cfg,
        Box::new(device),
        ControllerSet::new(&cfg, ControllerKind::Pd, 0.0),
        Reference::new(Trajectory::Sine, &cfg.reference, 1),
        tx,
        Arc::new(AtomicBool::new(false)),
        Some(6000),
        false,
    );
    let report = servo.run();
    drop(rx);
    let tick = report.faults.first().map(|f| f.tick).unwrap_or(0);
    let seen = seen.lock().unwrap().clone();
    (report.end, tick, seen)
}

#[test]
fn the_plant_gets_zero_torque_and_amps_off_right_after_detection() {
    for fault in ["stall@3:200", "encoder-jump@3:800"] {
        let (end, tick, seen) = plant_commands(fault);
        assert!(
            matches!(end, EndReason::DeviceFault(_) | EndReason::SafetyFault(_)),
            "{fault}"
        );
        let last = seen.last().unwrap();
        assert!(last.is_safe(), "{fault}: last command {last:?}");
        // Before the fault the amplifiers were on; the command after detection is the safe one.
        let on = seen.iter().rposition(|c| c.amps_on).unwrap();
        assert_eq!(
            on + 2,
            seen.len(),
            "{fault}: one safe packet follows the last live one"
        );
        assert!(tick > 2900, "{fault}: detected at tick {tick}");
    }
}

#[test]
fn the_first_packet_has_the_amplifiers_off() {
    let (_, _, seen) = plant_commands("slow@100:1");
    assert!(!seen[0].amps_on && seen[0].is_safe());
    assert!(seen[1].amps_on);
}

#[test]
fn hot_motors_are_held_to_continuous_torque_and_heat_carries_over() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("hot.toml");
    std::fs::write(
        &cfg,
        "[safety]\ncontinuous_torque_nm = [0.004, 0.004, 0.004]\nthermal_time_constant_s = 1.0\n",
    )
    .unwrap();
    let log = dir.path().join("hot.csv");
    let state = dir.path().join("state");
    let out = omnid()
        .env("OMNID_STATE_DIR", &state)
        .args([
            "run",
            "--fast",
            "--duration",
            "4",
            "--config",
            cfg.to_str().unwrap(),
        ])
        .args(["--log", log.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("thermal warning level"), "{stderr}");
    let l = Log::read(&log);
    let flags = l.f64s("flags");
    let tau3 = l.f64s("tau3");
    let thermal = omnid::telemetry::record::flags::THERMAL as u64;
    let hot: Vec<usize> = (0..flags.len())
        .filter(|&i| flags[i] as u64 & thermal != 0)
        .collect();
    assert!(
        hot.len() > 100,
        "the thermal clamp must act ({} ticks)",
        hot.len()
    );
    for &i in &hot {
        assert!(tau3[i].abs() <= 0.004 + 2.2e-4, "tick {i}: {}", tau3[i]);
    }
    let saved = std::fs::read_to_string(state.join("thermal-sim.json")).unwrap();
    assert!(saved.contains("heat"));
}
