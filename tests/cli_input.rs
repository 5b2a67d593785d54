//! Hostile input through the binary (issue 16): what a user can hand omnid — a config, a log,
//! stored state — is taken exactly as written or refused naming where, never cut, ignored or
//! guessed at.

mod common;
use common::{omnid, Log};
use std::path::Path;
use std::process::Output;

fn run(args: &[&str], state_dir: &Path) -> Output {
    omnid()
        .args(args)
        .env("OMNID_STATE_DIR", state_dir)
        .output()
        .expect("omnid starts")
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn a_config_array_with_a_value_too_many_is_refused_on_its_line() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("four.toml");
    // Read as [0.4, 0.4, 0.4] before: the fourth value was dropped without a word.
    std::fs::write(&config, "[safety]\nmax_torque_nm = [0.4, 0.4, 0.4, 99]\n").unwrap();
    let log = dir.path().join("run.csv");
    let out = run(
        &[
            "run",
            "--fast",
            "--duration",
            "0.05",
            "--config",
            config.to_str().unwrap(),
            "--log",
            log.to_str().unwrap(),
        ],
        dir.path(),
    );
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("four.toml")
            && err.contains("line 2")
            && err.contains("max_torque_nm")
            && err.contains("exactly 3 values"),
        "{err}"
    );
    assert!(!log.exists(), "nothing ran");
}

#[test]
fn replay_convert_and_plot_refuse_a_mode_omnid_does_not_write() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("modes.csv");
    std::fs::write(
        &input,
        "t,q1,q2,q3,tau1,tau2,tau3,mode\n0,0,0.27,-0.37,0,0,0,blend\n\
         0.001,0,0.27,-0.37,0,0,0,pause\n0.002,0,0.27,-0.37,0,0,0,track\n",
    )
    .unwrap();
    let replay = format!("replay:{}", input.display());
    let log = dir.path().join("replayed.csv");
    let converted = dir.path().join("converted.csv");
    let figures = dir.path().join("figures");
    let input = input.to_str().unwrap();
    for args in [
        vec![
            "run",
            "--device",
            &replay,
            "--fast",
            "--controller",
            "off",
            "--log",
            log.to_str().unwrap(),
        ],
        vec![
            "convert",
            "--from",
            "omnid",
            input,
            "--out",
            converted.to_str().unwrap(),
        ],
        vec!["plot", input, "--out", figures.to_str().unwrap()],
    ] {
        let out = run(&args, dir.path());
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.contains("modes.csv")
                && err.contains("line 3")
                && err.contains("`mode`")
                && err.contains("`pause`"),
            "{args:?}: {err}"
        );
    }
    assert!(!log.exists() && !converted.exists() && !figures.exists());
}

#[test]
fn an_absurd_motor_heat_file_is_ignored_naming_file_and_value() {
    let dir = tempfile::tempdir().unwrap();
    let heat = dir.path().join("thermal-sim.json");
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    std::fs::write(
        &heat,
        format!("{{\"heat\":[1e300,0,0],\"unix_time_s\":{now}}}\n"),
    )
    .unwrap();
    let log = dir.path().join("run.csv");
    let out = run(
        &[
            "run",
            "--fast",
            "--duration",
            "1",
            "--log",
            log.to_str().unwrap(),
        ],
        dir.path(),
    );
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(0), "{err}");
    assert!(
        err.contains("thermal-sim.json")
            && err.contains("`heat[0]` = 1e300")
            && err.contains("out of range")
            && err.contains("starting with cold motors"),
        "{err}"
    );
    // Cold motors: no tick was held to the continuous torque (flag 64) or warned about (128).
    let l = Log::read(&log);
    let flags = l.col("flags");
    let hot = l
        .rows
        .iter()
        .filter(|r| r[flags].parse::<u32>().unwrap() & (64 | 128) != 0)
        .count();
    assert_eq!(hot, 0, "ticks with thermal flags");
    // And what is carried to the next run is this run's heat, not the absurd value.
    let saved: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&heat).unwrap()).unwrap();
    assert!(saved["heat"][0].as_f64().unwrap() < 1.0, "{saved}");
}
