//! The replay (mock) device end to end: deterministic re-runs of simulator logs, irregular time
//! steps, the recorded sessions in `mock/`, the duration limit and `--lenient` on the CLI.

use crate::common;
use common::{omnid, Log};
use omnid::cmd::run::{execute, DeviceSpec, RunOptions, RunOutcome};
use omnid::config::Config;
use omnid::control::{ControllerKind, Trajectory};
use omnid::servo::EndReason;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

fn run(
    device: DeviceSpec,
    controller: ControllerKind,
    trajectory: Trajectory,
    duration_s: f64,
    log: &Path,
    cfg: &Config,
) -> RunOutcome {
    let opts = RunOptions {
        device,
        controller,
        trajectory,
        duration_s,
        log: Some(log.to_path_buf()),
        fast: true,
        ..RunOptions::default()
    };
    // Motors start cold: no heat carried over from other runs, so every run is reproducible.
    let mut cfg = cfg.clone();
    cfg.safety.persist_heat = false;
    let out = execute(&opts, &cfg, Arc::new(AtomicBool::new(false))).expect("run starts");
    assert!(out.log_error.is_none() && out.shutdown_error.is_none());
    assert_eq!(out.summary.telemetry_dropped, 0, "rows were dropped");
    out
}

/// Columns `a` and `b` hold the same values on every row: the same f64 bits for numbers (the
/// writer's shortest round-trip form parses back exactly), the same text otherwise.
fn assert_columns_equal(a: &Log, b: &Log, columns: &[&str]) {
    assert_eq!(a.rows.len(), b.rows.len(), "row counts differ");
    for c in columns {
        let (ia, ib) = (a.col(c), b.col(c));
        for (k, (ra, rb)) in a.rows.iter().zip(&b.rows).enumerate() {
            let (va, vb) = (&ra[ia], &rb[ib]);
            match (va.parse::<f64>(), vb.parse::<f64>()) {
                (Ok(x), Ok(y)) => assert_eq!(
                    x.to_bits(),
                    y.to_bits(),
                    "column {c}, row {k} (line {}): {va} vs {vb}",
                    k + 2
                ),
                _ => assert_eq!(va, vb, "column {c}, row {k} (line {})", k + 2),
            }
        }
    }
}

const ESTIMATES: [&str; 9] = [
    "qf1", "qf2", "qf3", "qd1", "qd2", "qd3", "qdd1", "qdd2", "qdd3",
];

#[test]
fn replaying_a_sim_log_reproduces_it_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let (sim_log, replay_log, ident_log) = (
        dir.path().join("sim.csv"),
        dir.path().join("replay.csv"),
        dir.path().join("ident.csv"),
    );
    let cfg = Config::default();
    let (pd, ms) = (ControllerKind::Pd, Trajectory::Multisine);
    let sim = run(DeviceSpec::Sim, pd, ms, 3.0, &sim_log, &cfg);
    assert_eq!(sim.end, EndReason::Completed);
    let rep = run(
        DeviceSpec::Replay(sim_log.clone()),
        pd,
        ms,
        f64::INFINITY,
        &replay_log,
        &cfg,
    );
    assert_eq!(rep.end, EndReason::EndOfData);
    assert_eq!(rep.summary.device, "replay");
    assert_eq!(rep.summary.ticks, sim.summary.ticks);

    let (a, b) = (Log::read(&sim_log), Log::read(&replay_log));
    assert_eq!(a.rows.len(), 3001, "3000 ticks and the stop row");
    assert_columns_equal(&a, &b, &ESTIMATES);
    // The rest of the row is the same too: time, the encoder path, the recorded torque, and,
    // since the estimates and the reference are, the same controller output and flags.
    assert_columns_equal(
        &a,
        &b,
        &[
            "t", "q1", "q2", "q3", "enc1", "enc2", "enc3", "tau1", "tau2", "tau3", "ref1", "ref2",
            "ref3", "tau_cmd1", "tau_cmd2", "tau_cmd3", "mode", "flags",
        ],
    );
    assert_eq!(b.rows.last().unwrap()[b.col("mode")], "stop");
    // The torque did move: this compares something.
    assert!(a.f64s("tau1").iter().any(|&v| v.abs() > 1e-3));
    assert_eq!(rep.summary.torque_rms_nm, sim.summary.torque_rms_nm);

    // The pure identification pass: no controller, same estimates, `tau` still the recording's.
    let ident = run(
        DeviceSpec::Replay(sim_log.clone()),
        ControllerKind::Off,
        Trajectory::Hold,
        f64::INFINITY,
        &ident_log,
        &cfg,
    );
    assert_eq!(ident.end, EndReason::EndOfData);
    let c = Log::read(&ident_log);
    assert_columns_equal(&a, &c, &ESTIMATES);
    assert_columns_equal(&a, &c, &["tau1", "tau2", "tau3"]);
    assert!(c.f64s("tau_cmd2").iter().all(|&v| v == 0.0));
}

#[test]
fn paced_and_fast_replays_agree() {
    let dir = tempfile::tempdir().unwrap();
    let sim_log = dir.path().join("sim.csv");
    let mut cfg = Config::default();
    cfg.safety.persist_heat = false;
    run(
        DeviceSpec::Sim,
        ControllerKind::Pd,
        Trajectory::Sine,
        0.3,
        &sim_log,
        &cfg,
    );
    let mut logs = Vec::new();
    for fast in [true, false] {
        let log = dir.path().join(format!("replay-{fast}.csv"));
        let opts = RunOptions {
            device: DeviceSpec::Replay(sim_log.clone()),
            controller: ControllerKind::Pd,
            duration_s: f64::INFINITY,
            log: Some(log.clone()),
            fast,
            ..RunOptions::default()
        };
        let out = execute(&opts, &cfg, Arc::new(AtomicBool::new(false))).unwrap();
        assert_eq!(out.end, EndReason::EndOfData);
        logs.push(Log::read(&log));
    }
    assert_eq!(logs[0].rows.len(), 301);
    assert_eq!(logs[0].rows, logs[1].rows);
}

/// A 100 Hz recording with jitter, starting at t = 5 s, only the seven required columns.
fn jittered_sine(path: &Path, rows: usize) -> Vec<(f64, f64)> {
    let mut text = String::from("t,q1,q2,q3,tau1,tau2,tau3\n");
    let mut truth = Vec::new();
    let mut t = 5.0;
    let w = std::f64::consts::TAU * 0.5;
    for k in 0..rows {
        // Deterministic jitter of ±3 ms about 10 ms.
        t += 0.010 + 0.003 * ((k * 7919 % 13) as f64 / 6.0 - 1.0);
        let q2 = 0.6 + 0.3 * (w * t).sin();
        truth.push((t, 0.3 * w * (w * t).cos()));
        text += &format!("{t},0.1,{q2},0.2,0,0.01,0\n");
    }
    std::fs::write(path, text).unwrap();
    truth
}

#[test]
fn irregular_time_steps_flow_through_as_device_time() {
    let dir = tempfile::tempdir().unwrap();
    let (file, log) = (dir.path().join("jitter.csv"), dir.path().join("out.csv"));
    let truth = jittered_sine(&file, 1000);
    let mut cfg = Config::default();
    cfg.kalman.jerk_psd = 10.0; // docs/DESIGN.md §4.3: suits 0.5 Hz motion
    let out = run(
        DeviceSpec::Replay(file),
        ControllerKind::Off,
        Trajectory::Hold,
        f64::INFINITY,
        &log,
        &cfg,
    );
    assert_eq!(out.end, EndReason::EndOfData);
    let l = Log::read(&log);
    assert_eq!(l.rows.len(), 1001, "1000 rows and the stop row");
    let (t, qd2) = (l.f64s("t"), l.f64s("qd2"));
    for k in 0..1000 {
        // Logged time is relative to the first sample, computed from the file's own t.
        assert_eq!(t[k], truth[k].0 - truth[0].0, "row {k}");
    }
    // The filter saw the real, irregular steps: after it settles, the velocity is right (a
    // filter stepping 1 ms per sample would be off by a factor of ten).
    let worst = (300..1000)
        .map(|k| (qd2[k] - truth[k].1).abs())
        .fold(0.0, f64::max);
    let peak = 0.3 * std::f64::consts::TAU * 0.5;
    assert!(worst < 0.05 * peak, "velocity error {worst} rad/s");
    assert_eq!(l.f64s("tau2")[10], 0.01, "recorded torque logged as tau");
    // The stop row repeats the last sample, with nothing applied.
    let last = l.rows.last().unwrap();
    assert_eq!(last[l.col("mode")], "stop");
    assert_eq!(t[1000], t[999]);
    assert_eq!(l.f64s("tau2")[1000], 0.0);
}

#[test]
fn duration_limits_replay_in_device_time() {
    let dir = tempfile::tempdir().unwrap();
    let (file, log) = (dir.path().join("jitter.csv"), dir.path().join("out.csv"));
    let truth = jittered_sine(&file, 500);
    run(
        DeviceSpec::Replay(file),
        ControllerKind::Off,
        Trajectory::Hold,
        2.0003, // off the 0.5 ms grid the jittered stamps sit on
        &log,
        &Config::default(),
    );
    let l = Log::read(&log);
    let played = truth
        .iter()
        .filter(|(t, _)| t - truth[0].0 < 2.0003)
        .count();
    assert!(played > 150 && played < 250, "{played}");
    assert_eq!(l.rows.len(), played + 1);
}

/// Run the binary with its state (motor heat) kept in `dir`; it must succeed.
fn run_ok_in(dir: &Path, args: &[&str]) -> std::process::Output {
    let out = omnid()
        .env("OMNID_STATE_DIR", dir)
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "omnid {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn mock(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("mock")
        .join(name)
}

/// Every recorded session in `mock/`, with the config it was recorded with.
const SESSIONS: [(&str, Option<&str>); 3] = [
    ("pd-multisine.csv", Some("undocked.toml")),
    ("pd-sine-payload.csv", Some("payload.toml")),
    ("nnidc-sine.csv", Some("undocked.toml")),
];

/// mock/README.md's regeneration block (the first `sh` block under "## Regenerating"), run as
/// written with this build's binary as `$B`, in a directory of its own (a copy of `mock/`'s
/// configs, and its own `/tmp`): every session it records is byte for byte the committed one.
/// (The sessions had drifted once unnoticed: recorded before the simulator's stylus started in
/// its inkwell, under a command that no longer made them.)
#[test]
fn mock_sessions_are_what_their_documented_commands_record() {
    let readme = std::fs::read_to_string(mock("README.md")).unwrap();
    let block = readme
        .split("## Regenerating")
        .nth(1)
        .and_then(|r| r.split("```sh\n").nth(1))
        .and_then(|b| b.split("```").next())
        .expect("mock/README.md has a Regenerating section with a sh block");
    let dir = tempfile::tempdir().unwrap();
    let (work, tmp) = (dir.path().join("repo"), dir.path().join("tmp"));
    std::fs::create_dir_all(work.join("mock")).unwrap();
    std::fs::create_dir_all(&tmp).unwrap();
    for e in std::fs::read_dir(mock("")).unwrap().flatten() {
        if e.path().extension().is_some_and(|x| x == "toml") {
            std::fs::copy(e.path(), work.join("mock").join(e.file_name())).unwrap();
        }
    }
    let binary = env!("CARGO_BIN_EXE_omnid");
    let script = block
        .replace("B=target/release/omnid", &format!("B='{binary}'"))
        .replace("/tmp/", &format!("{}/", tmp.display()));
    assert!(
        script.contains(binary),
        "the block sets no `B=target/release/omnid`:\n{block}"
    );
    let out = std::process::Command::new("sh")
        .arg("-ec")
        .arg(&script)
        .current_dir(&work)
        .env("TMPDIR", &tmp)
        .env_remove("OMNID_STATE_DIR")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "mock/README.md's block failed: {}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    for (name, _) in SESSIONS {
        let made = std::fs::read_to_string(work.join("mock").join(name))
            .unwrap_or_else(|e| panic!("the block made no mock/{name}: {e}"));
        let kept = std::fs::read_to_string(mock(name)).unwrap();
        if let Some((n, (a, b))) = kept
            .lines()
            .zip(made.lines())
            .enumerate()
            .find(|(_, (a, b))| a != b)
        {
            panic!(
                "mock/{name} is not what mock/README.md's commands record: line {} is\n  {a}\n\
                 recorded now\n  {b}\n(regenerate it with those commands, or fix them)",
                n + 1
            );
        }
        assert_eq!(
            kept.len(),
            made.len(),
            "mock/{name}: as many bytes as its commands record now"
        );
    }
}

#[test]
fn mock_sessions_replay_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    for (name, config) in SESSIONS {
        let file = mock(name);
        let size = std::fs::metadata(&file).unwrap().len();
        assert!(size < 1_600_000, "{name} is {size} bytes");
        let cfg = match config {
            Some(c) => Config::load(&mock(c), None).unwrap(),
            None => Config::default(),
        };
        let log = dir.path().join(name);
        let out = run(
            DeviceSpec::Replay(file.clone()),
            ControllerKind::Off,
            Trajectory::Hold,
            f64::INFINITY,
            &log,
            &cfg,
        );
        assert_eq!(out.end, EndReason::EndOfData, "{name}");
        let (rec, rep) = (Log::read(&file), Log::read(&log));
        assert!(rec.rows.len() >= 8000, "{name}: {} rows", rec.rows.len());
        // Row for row, through the encoder path: the same time, angles, counts, torque, mode.
        assert_columns_equal(
            &rec,
            &rep,
            &[
                "t", "q1", "q2", "q3", "enc1", "enc2", "enc3", "tau1", "tau2", "tau3", "mode",
            ],
        );
        for (k, row) in rep.rows.iter().enumerate() {
            for (c, v) in rep.header.iter().zip(row) {
                let x: f64 = v.parse().unwrap_or(0.0);
                assert!(x.is_finite(), "{name}: {c} = {v} at row {k}");
            }
        }
        // The sessions move: the estimator sees real velocities.
        let qd3 = rep.f64s("qd3");
        let peak = qd3.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(peak > 0.3 && peak < 10.0, "{name}: peak |qd3| {peak}");
    }
}

#[test]
fn payload_session_shows_the_payload_in_the_recorded_torque() {
    // With 20 g more at the tip from 5 s on, holding the arm up takes more torque on joints 2
    // and 3: the recording really is of a plant that changed.
    let rec = Log::read(&mock("pd-sine-payload.csv"));
    let (t, tau2, tau3) = (rec.f64s("t"), rec.f64s("tau2"), rec.f64s("tau3"));
    let mean = |v: &[f64], lo: f64, hi: f64| {
        let sel: Vec<f64> = t
            .iter()
            .zip(v)
            .filter(|(t, _)| **t >= lo && **t < hi)
            .map(|(_, v)| *v)
            .collect();
        sel.iter().sum::<f64>() / sel.len() as f64
    };
    // Two whole periods of the 0.5 Hz sine before and after the change.
    let d2 = mean(&tau2, 6.0, 10.0) - mean(&tau2, 1.0, 5.0);
    let d3 = mean(&tau3, 6.0, 10.0) - mean(&tau3, 1.0, 5.0);
    assert!(d2.abs() > 2e-3 || d3.abs() > 2e-3, "Δτ2 {d2}, Δτ3 {d3}");
}

#[test]
fn cli_replays_a_mock_session() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("out.csv");
    let device = format!("replay:{}", mock("pd-multisine.csv").display());
    let out = run_ok_in(
        dir.path(),
        &[
            "run",
            "--device",
            &device,
            "--controller",
            "pd",
            "--trajectory",
            "multisine",
            "--fast",
            "--log",
            log.to_str().unwrap(),
        ],
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("on replay") && text.contains("ended: at the end of the recording"),
        "{text}"
    );
    let l = Log::read(&log);
    assert_eq!(
        l.rows.len(),
        Log::read(&mock("pd-multisine.csv")).rows.len()
    );
}

#[test]
fn cli_refuses_a_bad_log_and_lenient_skips_its_rows() {
    let dir = tempfile::tempdir().unwrap();
    let (file, log) = (dir.path().join("bad.csv"), dir.path().join("out.csv"));
    let mut text = String::from("t,q1,q2,q3,tau1,tau2,tau3\n");
    for k in 0..100 {
        let t = k as f64 * 1e-3;
        match k {
            10 => text += &format!("{t},0.1,oops,0.3,0,0,0\n"),
            20 => text += &format!("{t},0.1,0.2,NaN,0,0,0\n"),
            30 => text += "0.0005,0.1,0.2,0.3,0,0,0\n", // backwards
            _ => text += &format!("{t},0.1,0.2,0.3,0,0,0\n"),
        }
    }
    std::fs::write(&file, text).unwrap();
    let device = format!("replay:{}", file.display());
    let args = |lenient: bool| {
        let mut a = vec![
            "run".to_string(),
            "--device".into(),
            device.clone(),
            "--controller".into(),
            "off".into(),
            "--fast".into(),
            "--log".into(),
            log.display().to_string(),
        ];
        if lenient {
            a.push("--lenient".into());
        }
        a
    };
    let strict = omnid()
        .env("OMNID_STATE_DIR", dir.path())
        .args(args(false))
        .output()
        .unwrap();
    assert_eq!(strict.status.code(), Some(2));
    let err = String::from_utf8_lossy(&strict.stderr);
    assert!(
        err.contains("bad.csv") && err.contains("line 12") && err.contains("`q2`"),
        "{err}"
    );
    assert!(!log.exists(), "nothing runs on a refused log");

    let lenient = omnid()
        .env("OMNID_STATE_DIR", dir.path())
        .args(args(true))
        .output()
        .unwrap();
    assert!(lenient.status.success());
    let err = String::from_utf8_lossy(&lenient.stderr);
    assert!(
        err.contains("skipped 3 bad rows (lines 12, 22, 32)"),
        "{err}"
    );
    assert_eq!(Log::read(&log).rows.len(), 97 + 1);
}

#[test]
fn a_sim_log_with_the_stylus_docked_undocked_and_clicked_replays_bit_for_bit_under_every_controller(
) {
    // Issue #39: the servo acts on the stylus (a docked stylus stops the identifier learning),
    // so the log records buttons and inkwell and the replay reports them; under every
    // controller, from CSV and from MCAP, every column the replay writes is the run's.
    use omnid::device::sim::StylusEvent;
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = Config::default();
    let ev = |at_s: f64, action: &str, button: Option<u64>| StylusEvent {
        at_s,
        action: action.into(),
        button,
    };
    cfg.sim.stylus = vec![
        ev(0.3, "undock", None),
        ev(1.0, "press", Some(1)),
        ev(1.4, "release", Some(1)),
        ev(1.6, "click", Some(2)),
        ev(2.0, "dock", None),
    ];
    for controller in [
        ControllerKind::Pd,
        ControllerKind::Nnidc,
        ControllerKind::Ct,
        ControllerKind::Off,
    ] {
        let name = controller.as_str();
        let p = |f: &str| dir.path().join(format!("{name}-{f}"));
        let hold = Trajectory::Hold;
        let sine = Trajectory::Sine;
        let traj = if controller == ControllerKind::Off {
            hold
        } else {
            sine
        };
        // The simulator is deterministic: the same run logged as CSV and as MCAP.
        run(DeviceSpec::Sim, controller, traj, 3.0, &p("sim.csv"), &cfg);
        run(DeviceSpec::Sim, controller, traj, 3.0, &p("sim.mcap"), &cfg);
        let a = Log::read(&p("sim.csv"));
        let docked: Vec<&str> = a
            .rows
            .iter()
            .map(|r| r[a.col("inkwell")].as_str())
            .collect();
        assert!(
            docked.contains(&"1") && docked.contains(&"0"),
            "{name}: the stylus should be docked and undocked in the run"
        );
        for b in ["button1", "button2"] {
            assert!(
                a.rows.iter().any(|r| r[a.col(b)] == "1"),
                "{name}: {b} never pressed"
            );
        }
        for from in ["sim.csv", "sim.mcap"] {
            let out = p(&format!("re-{from}.csv"));
            let rep = run(
                DeviceSpec::Replay(p(from)),
                controller,
                traj,
                f64::INFINITY,
                &out,
                &cfg,
            );
            assert_eq!(rep.end, EndReason::EndOfData);
            let b = Log::read(&out);
            // Every column the replay writes (all but the simulator's own: tau_model, fhand).
            let columns: Vec<&str> = b.header.iter().map(String::as_str).collect();
            for c in [
                "tau_hat1", "tau_ext1", "fext1", "inkwell", "button1", "tau_cmd1",
            ] {
                assert!(columns.contains(&c), "{name}: no {c} column");
            }
            assert_columns_equal(&a, &b, &columns);
        }
    }
}
