//! Hostile input through the binary (issue 16): what a user can hand omnid — a config, a log,
//! stored state — is taken exactly as written or refused naming where, never cut, ignored or
//! guessed at; and however long a line or a file goes on, reading it takes bounded memory.

use crate::common;
use common::{omnid, Log};
use std::io::Write;
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
    assert!(!log.exists(), "log");
    assert!(!converted.exists(), "converted");
    assert!(!figures.exists(), "figures");
}

#[test]
fn an_absurd_motor_heat_file_fails_closed_naming_file_and_value() {
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
            && err.contains("assuming the motors at the thermal limit"),
        "{err}"
    );
    // A file that lies does not make the motors cold: the run starts warned (flag 128).
    let l = Log::read(&log);
    let flags = l.col("flags");
    let first = l.rows[0][flags].parse::<u32>().unwrap();
    assert_ne!(first & 128, 0, "first tick's flags {first}");
    // And what is carried to the next run is this run's heat, not the absurd value.
    let saved: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&heat).unwrap()).unwrap();
    assert!(saved["heat"][0].as_f64().unwrap() <= 1.0, "{saved}");
}

/// How a bounded run ended.
struct Bounded {
    code: Option<i32>,
    stderr: String,
    /// The child's peak resident set, kB (getrusage of that child, from wait4).
    max_rss_kb: i64,
}

/// Run omnid under a 1 GiB address-space limit (a reader that tried to hold a gigabyte fails
/// instead of taking the machine) and at most 60 s, measuring its peak memory.
// The child is reaped by `wait4` (for its resource usage), which clippy cannot see.
#[allow(clippy::zombie_processes)]
fn run_bounded(args: &[&str], dir: &Path) -> Bounded {
    use std::os::unix::process::CommandExt;
    let stderr_path = dir.join("stderr.txt");
    let mut cmd = omnid();
    cmd.args(args)
        .env("OMNID_STATE_DIR", dir)
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(&stderr_path).unwrap());
    // SAFETY: only setrlimit, async-signal-safe, between fork and exec.
    unsafe {
        cmd.pre_exec(|| {
            let limit = libc::rlimit {
                rlim_cur: 1 << 30,
                rlim_max: 1 << 30,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &limit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let child = cmd.spawn().expect("omnid starts");
    let pid = child.id() as libc::pid_t;
    let t0 = std::time::Instant::now();
    let mut status = 0;
    // SAFETY: a zeroed rusage is a valid value for wait4 to fill.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    loop {
        // SAFETY: wait4 on our own child, with valid pointers.
        let rc = unsafe { libc::wait4(pid, &mut status, libc::WNOHANG, &mut usage) };
        assert!(rc >= 0, "wait4: {}", std::io::Error::last_os_error());
        if rc == pid {
            break;
        }
        if t0.elapsed() > std::time::Duration::from_secs(60) {
            // SAFETY: our own child.
            unsafe { libc::kill(pid, libc::SIGKILL) };
            panic!("omnid {args:?} still running after a minute");
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    Bounded {
        code: libc::WIFEXITED(status).then(|| libc::WEXITSTATUS(status)),
        stderr: std::fs::read_to_string(&stderr_path).unwrap(),
        max_rss_kb: usage.ru_maxrss,
    }
}

/// An omnid reading a log keeps well under this (a row buffer of 1 MiB at most, the rest is
/// the program).
const SMALL_RSS_KB: i64 = 64 * 1024;

/// Every command that reads a log, on `input`.
fn readers_of(input: &Path, dir: &Path) -> Vec<Vec<String>> {
    let input = input.to_str().unwrap().to_string();
    let d = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let s = |v: &[&str]| v.iter().map(|a| a.to_string()).collect::<Vec<_>>();
    vec![
        s(&["run", "--device", &format!("replay:{input}"), "--fast"])
            .into_iter()
            .chain([
                "--controller".into(),
                "off".into(),
                "--log".into(),
                d("r.csv"),
            ])
            .collect(),
        s(&["plot", &input, "--out", &d("figures")]),
        s(&["convert", "--from", "omnid", &input, "--out", &d("c.csv")]),
        s(&[
            "convert",
            "--from",
            "ros-touch",
            &input,
            "--out",
            &d("t.csv"),
        ]),
        s(&["identify", &input, "--out", &d("w.json")]),
    ]
}

#[test]
fn a_gigabyte_line_is_refused_naming_where_in_bounded_memory() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("one-line.csv");
    // A header, then one "line" of a gigabyte without an end (sparse: no disk space is used).
    let f = std::fs::File::create(&input).unwrap();
    (&f).write_all(b"t,q1,q2,q3,tau1,tau2,tau3\n").unwrap();
    f.set_len(1 << 30).unwrap();
    // (`convert --from ros-touch` reads through the same reader; its header is another.)
    let readers = readers_of(&input, dir.path());
    for args in readers
        .iter()
        .filter(|a| !a.contains(&"ros-touch".to_string()))
    {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let b = run_bounded(&args, dir.path());
        assert_eq!(b.code, Some(2), "{args:?}: {}", b.stderr);
        assert!(
            b.stderr.contains("one-line.csv")
                && b.stderr.contains("line 2")
                && b.stderr.contains("1048576 bytes"),
            "{args:?}: {}",
            b.stderr
        );
        assert!(
            b.max_rss_kb < SMALL_RSS_KB,
            "{args:?}: peak RSS {} kB",
            b.max_rss_kb
        );
    }
}

#[test]
fn special_files_that_never_end_are_refused_in_bounded_memory() {
    let dir = tempfile::tempdir().unwrap();
    for device in ["/dev/zero", "/dev/urandom"] {
        for args in readers_of(Path::new(device), dir.path()) {
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            let b = run_bounded(&args, dir.path());
            assert_eq!(b.code, Some(2), "{args:?}: {}", b.stderr);
            assert!(b.stderr.contains(device), "{args:?}: {}", b.stderr);
            if args[0] == "run" {
                // Read twice (checked, then played): refused before it is opened.
                assert!(b.stderr.contains("character device"), "{}", b.stderr);
            } else if device == "/dev/zero" {
                assert!(
                    b.stderr.contains("line 1") && b.stderr.contains("1048576 bytes"),
                    "{args:?}: {}",
                    b.stderr
                );
            }
            assert!(
                b.max_rss_kb < SMALL_RSS_KB,
                "{args:?}: peak RSS {} kB",
                b.max_rss_kb
            );
        }
    }
}

#[test]
fn config_and_weights_files_are_read_up_to_a_size() {
    let dir = tempfile::tempdir().unwrap();
    // A comment line of 2 MiB: valid TOML, but no config is that big.
    let config = dir.path().join("big.toml");
    let f = std::fs::File::create(&config).unwrap();
    (&f).write_all(b"# ").unwrap();
    f.set_len(2 << 20).unwrap();
    let b = run_bounded(
        &["run", "--fast", "--config", config.to_str().unwrap()],
        dir.path(),
    );
    assert_eq!(b.code, Some(2), "{}", b.stderr);
    assert!(
        b.stderr.contains("big.toml") && b.stderr.contains("larger than 1 MiB"),
        "{}",
        b.stderr
    );
    let b = run_bounded(
        &[
            "run",
            "--fast",
            "--weights",
            "/dev/zero",
            "--duration",
            "0.1",
        ],
        dir.path(),
    );
    assert_eq!(b.code, Some(2), "{}", b.stderr);
    assert!(
        b.stderr.contains("/dev/zero") && b.stderr.contains("larger than 16 MiB"),
        "{}",
        b.stderr
    );
    assert!(b.max_rss_kb < SMALL_RSS_KB, "peak RSS {} kB", b.max_rss_kb);
}

/// One reader, one set of checks: replay, convert, plot and identify refuse the same rows,
/// naming the file, the line and the column — a non-integer `flags`, a time that goes
/// backwards, repeats or jumps further than a device ever pauses, an empty `mode`.
#[test]
fn every_log_reader_refuses_the_same_bad_rows() {
    let cases: [(&str, &str, &str); 5] = [
        ("flags", "0.002,0,0.27,-0.37,0.01,0,0,NaN,track", "`flags`"),
        (
            "backwards",
            "0.0005,0,0.27,-0.37,0.01,0,0,0,track",
            "time goes backwards",
        ),
        (
            "repeats",
            "0.001,0,0.27,-0.37,0.01,0,0,0,track",
            "time repeats",
        ),
        (
            "jump",
            "1e12,0,0.27,-0.37,0.01,0,0,0,track",
            "time jumps 1e12 s",
        ),
        ("empty_mode", "0.002,0,0.27,-0.37,0.01,0,0,0,", "`mode`"),
    ];
    for (name, bad_row, says) in cases {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join(format!("{name}.csv"));
        std::fs::write(
            &input,
            format!(
                "t,q1,q2,q3,tau1,tau2,tau3,flags,mode\n0,0,0.27,-0.37,0.01,0,0,0,track\n\
                 0.001,0,0.27,-0.37,0.01,0,0,0,track\n{bad_row}\n"
            ),
        )
        .unwrap();
        let input_s = input.to_str().unwrap();
        let d = |f: &str| dir.path().join(f).to_str().unwrap().to_string();
        let (log, converted, figures, weights) = (d("r.csv"), d("c.csv"), d("fig"), d("w.json"));
        let replay = format!("replay:{input_s}");
        let commands: [Vec<&str>; 4] = [
            vec![
                "run",
                "--device",
                &replay,
                "--fast",
                "--controller",
                "off",
                "--log",
                &log,
            ],
            vec!["convert", "--from", "omnid", input_s, "--out", &converted],
            vec!["plot", input_s, "--out", &figures],
            vec!["identify", input_s, "--out", &weights],
        ];
        for args in commands {
            let out = run(&args, dir.path());
            let err = stderr(&out);
            assert_eq!(out.status.code(), Some(2), "{name}: {args:?}: {err}");
            assert!(
                err.contains(&format!("{name}.csv"))
                    && err.contains("line 4")
                    && err.contains(says),
                "{name}: {args:?}: {err}"
            );
        }
    }
}
