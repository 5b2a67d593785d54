//! Outputs (issue 16): nothing a command writes is lost silently (class 2), writing an output
//! never destroys what is not ours (class 3), and every output path is checked before the
//! work starts (class 8).

use crate::common;
use common::{omnid, Log};
use std::os::unix::fs::{FileTypeExt, MetadataExt};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant, SystemTime};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// `omnid` with its state (motor heat) kept in `dir`.
fn omnid_in(dir: &Path) -> Command {
    let mut c = omnid();
    c.env("OMNID_STATE_DIR", dir.join("state"));
    c
}

/// Run `omnid args` (state in `dir`), which must succeed.
fn ok(dir: &Path, args: &[&str]) -> Output {
    let o = omnid_in(dir).args(args).output().unwrap();
    assert!(o.status.success(), "{args:?}: {}", stderr(&o));
    o
}

/// `cmd` with files limited to `bytes` (writes past it fail with EFBIG, as on a full disk).
fn with_file_limit(mut cmd: Command, bytes: u64) -> Command {
    // SAFETY: setrlimit and signal are async-signal-safe; nothing else runs in the child.
    unsafe {
        cmd.pre_exec(move || {
            let lim = libc::rlimit {
                rlim_cur: bytes,
                rlim_max: bytes,
            };
            // A write past the limit raises SIGXFSZ, which would kill the process: ignore it.
            libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
            if libc::setrlimit(libc::RLIMIT_FSIZE, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    cmd
}

/// The names in `dir`, sorted.
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(s(path)).unwrap();
    // SAFETY: a valid C string; mkfifo only creates the node.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
}

/// A character device like /dev/null (1, 3) at `path`, where we may make one (root).
fn mknod_null(path: &Path) -> bool {
    let c = std::ffi::CString::new(s(path)).unwrap();
    // SAFETY: a valid C string; mknod only creates the node.
    let ok = unsafe { libc::mknod(c.as_ptr(), libc::S_IFCHR | 0o666, libc::makedev(1, 3)) } == 0;
    if !ok {
        eprintln!("skipping the device case: mknod needs root");
    }
    ok
}

/// A 2 s PD multisine log to identify from.
fn training_log(dir: &Path) -> PathBuf {
    let log = dir.join("ms.csv");
    ok(
        dir,
        &["run", "--fast", "--duration", "2", "--controller", "pd"]
            .iter()
            .chain(&["--trajectory", "multisine", "--log", s(&log)])
            .copied()
            .collect::<Vec<_>>(),
    );
    log
}

// ---------------------------------------------------------------------------------------------
// Class 2: no output is lost silently.

#[test]
fn default_log_names_never_replace_another_file() {
    let dir = tempfile::tempdir().unwrap();
    let logs = dir.path().join("logs");
    std::fs::create_dir(&logs).unwrap();
    // Someone's logs under the names the next seconds' runs would take.
    let now = SystemTime::now();
    let taken: Vec<PathBuf> = (0..20)
        .map(|k| {
            let stamp = omnid::telemetry::utc_stamp(now + Duration::from_secs(k));
            let p = logs.join(format!("omnid-{stamp}.csv"));
            std::fs::write(&p, "someone's log\n").unwrap();
            p
        })
        .collect();
    // Two runs started together, in the same second.
    let start = || {
        omnid_in(dir.path())
            .current_dir(dir.path())
            .args(["run", "--fast", "--duration", "0.5", "--controller", "pd"])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let (a, b) = (start(), start());
    for child in [a, b] {
        let o = child.wait_with_output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
    }
    for p in &taken {
        assert_eq!(std::fs::read_to_string(p).unwrap(), "someone's log\n");
    }
    let new: Vec<PathBuf> = names(&logs)
        .iter()
        .map(|n| logs.join(n))
        .filter(|p| !taken.contains(p))
        .collect();
    assert_eq!(new.len(), 2, "{new:?}");
    for p in new {
        let l = Log::read(&p);
        assert_eq!(l.rows.len(), 501, "{}", p.display());
        assert_eq!(l.rows.last().unwrap()[l.col("mode")], "stop");
    }
}

#[test]
fn a_runs_inputs_and_outputs_must_be_distinct_files() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    std::fs::write(p("old.csv"), "precious\n").unwrap();
    std::fs::hard_link(p("old.csv"), p("hard.json")).unwrap();
    std::os::unix::fs::symlink("run.csv", p("link.json")).unwrap();
    let replay = p("replay.csv");
    ok(
        dir.path(),
        &["run", "--fast", "--duration", "0.3", "--log", s(&replay)],
    );
    let recorded = std::fs::read(&replay).unwrap();
    std::os::unix::fs::symlink("replay.csv", p("replay-link.csv")).unwrap();
    let cases: [(&[&str], &str, &str); 5] = [
        (
            &["--log", "run.csv", "--summary-json", "run.csv"],
            "--log",
            "--summary-json",
        ),
        (
            &["--log", "run.csv", "--summary-json", "link.json"],
            "--log",
            "--summary-json",
        ),
        (
            &["--log", "old.csv", "--summary-json", "hard.json"],
            "--log",
            "--summary-json",
        ),
        (
            &["--log", "run.csv", "--summary-json", "run-fault.csv"],
            "fault dump",
            "--summary-json",
        ),
        (
            &["--device", "replay:replay.csv", "--log", "replay-link.csv"],
            "--device replay:",
            "--log",
        ),
    ];
    for (args, a, b) in cases {
        let o = omnid_in(dir.path())
            .current_dir(dir.path())
            .args(["run", "--fast", "--duration", "0.3"])
            .args(args)
            .output()
            .unwrap();
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.contains(a) && err.contains(b) && err.contains("same file"),
            "{err}"
        );
        // Refused before the run: nothing written.
        assert!(!p("run.csv").exists(), "{args:?}");
    }
    assert_eq!(std::fs::read_to_string(p("old.csv")).unwrap(), "precious\n");
    assert_eq!(std::fs::read(&replay).unwrap(), recorded);
}

fn wait_for_rows(path: &Path, rows: usize) {
    let t0 = Instant::now();
    while std::fs::read_to_string(path).map_or(0, |t| t.lines().count()) <= rows {
        assert!(t0.elapsed() < Duration::from_secs(30), "no rows in the log");
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
#[ignore = "paced"]
fn a_log_another_omnid_writes_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("busy.csv");
    let link = dir.path().join("link.csv");
    std::os::unix::fs::symlink(&log, &link).unwrap();
    let first = omnid_in(dir.path())
        .args([
            "run",
            "--duration",
            "60",
            "--controller",
            "pd",
            "--log",
            s(&log),
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    wait_for_rows(&log, 200);
    let inode = std::fs::metadata(&log).unwrap().ino();
    for path in [&log, &link] {
        let o = omnid_in(dir.path())
            .args(["run", "--fast", "--duration", "0.3", "--log", s(path)])
            .output()
            .unwrap();
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(
            err.contains(s(path)) && err.contains("another omnid writes it"),
            "{err}"
        );
    }
    assert_eq!(std::fs::metadata(&log).unwrap().ino(), inode);
    // SAFETY: signals our own child.
    unsafe { libc::kill(first.id() as i32, libc::SIGINT) };
    let o = first.wait_with_output().unwrap();
    assert_eq!(o.status.code(), Some(130), "{}", stderr(&o));
    let l = Log::read(&log);
    assert_eq!(l.rows.last().unwrap()[l.col("mode")], "stop");
    assert!(
        l.f64s("t").windows(2).all(|w| w[1] > w[0]),
        "one run's rows"
    );

    // Once it has ended the log is free again; /dev/null takes any number of runs at once.
    ok(
        dir.path(),
        &["run", "--fast", "--duration", "0.3", "--log", s(&log)],
    );
    let null_run = |state: PathBuf| {
        move || {
            omnid_in(&state)
                .args(["run", "--fast", "--duration", "1", "--log", "/dev/null"])
                .output()
                .unwrap()
        }
    };
    let other = std::thread::spawn(null_run(dir.path().to_path_buf()));
    let o = null_run(dir.path().to_path_buf())();
    assert!(o.status.success(), "{}", stderr(&o));
    let o = other.join().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
}

/// A run whose log stops fitting on the disk: exit 1, the log ends with its last whole row,
/// and the summary (printed and JSON) gives the rows in the file and says the log is
/// incomplete.
fn assert_incomplete_log(o: &Output, log: &Path, summary: &Path) {
    let err = stderr(o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    let l = Log::read(log);
    let s = json(summary);
    assert_eq!(s["log_rows"], l.rows.len() as u64, "rows in the file");
    assert!(l.rows.len() < 5000);
    assert_eq!(s["log_complete"], false);
    let why = s["log_error"].as_str().unwrap();
    assert!(why.contains("did not reach the file"), "{why}");
    let printed = String::from_utf8_lossy(&o.stdout);
    assert!(
        printed.contains(&format!("({} rows; INCOMPLETE", l.rows.len())),
        "{printed}"
    );
    assert!(err.contains("the log is incomplete"), "{err}");
}

#[test]
fn a_full_disk_is_reported_with_the_rows_that_reached_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let (log, summary) = (dir.path().join("run.csv"), dir.path().join("s.json"));
    let o = with_file_limit(omnid_in(dir.path()), 100_000)
        .args(["run", "--fast", "--duration", "5", "--controller", "pd"])
        .args(["--log", s(&log), "--summary-json", s(&summary)])
        .output()
        .unwrap();
    assert_incomplete_log(&o, &log, &summary);
    // A complete run says so.
    let o = omnid_in(dir.path())
        .args(["run", "--fast", "--duration", "0.5", "--log", s(&log)])
        .args(["--summary-json", s(&summary)])
        .output()
        .unwrap();
    assert!(o.status.success());
    assert_eq!(json(&summary)["log_complete"], true);
    assert_eq!(json(&summary)["log_rows"], 501);

    // A disk already full: refused before the run.
    let o = omnid_in(dir.path())
        .args(["run", "--fast", "--duration", "1", "--log", "/dev/full"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(
        stderr(&o).contains("cannot create log /dev/full"),
        "{}",
        stderr(&o)
    );

    // A real full file system, where we may mount one (root).
    let mnt = dir.path().join("small");
    std::fs::create_dir(&mnt).unwrap();
    let mounted = Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=64k", "tmpfs", s(&mnt)])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|st| st.success());
    if !mounted {
        eprintln!("skipping the tmpfs case: cannot mount one here");
        return;
    }
    let log = mnt.join("run.csv");
    let o = omnid_in(dir.path())
        .args(["run", "--fast", "--duration", "5", "--controller", "pd"])
        .args(["--log", s(&log), "--summary-json", s(&summary)])
        .output()
        .unwrap();
    let result = std::panic::catch_unwind(|| assert_incomplete_log(&o, &log, &summary));
    let _ = Command::new("umount").arg(&mnt).status();
    if let Err(e) = result {
        std::panic::resume_unwind(e);
    }
}

// ---------------------------------------------------------------------------------------------
// Class 3: writing an output never destroys what is not ours.

/// `identify` and `convert` writing to `out`.
fn writers(dir: &Path, log: &Path, out: &Path) -> [Command; 2] {
    let mut identify = omnid_in(dir);
    identify.args(["identify", s(log), "--epochs", "1", "--out", s(out)]);
    let mut convert = omnid_in(dir);
    convert.args(["convert", "--from", "omnid", s(log), "--out", s(out)]);
    [identify, convert]
}

#[test]
fn identify_and_convert_replace_only_regular_files() {
    let dir = tempfile::tempdir().unwrap();
    let log = training_log(dir.path());
    let nodes = dir.path().join("nodes");
    std::fs::create_dir(&nodes).unwrap();
    let fifo = nodes.join("fifo");
    mkfifo(&fifo);
    let sub = nodes.join("sub");
    std::fs::create_dir(&sub).unwrap();
    let to_sub = nodes.join("to-sub");
    std::os::unix::fs::symlink("sub", &to_sub).unwrap();
    let mut refused = vec![
        (fifo, "a FIFO"),
        (sub, "a directory"),
        (to_sub, "a directory"),
    ];
    let device = nodes.join("null");
    if mknod_null(&device) {
        refused.push((device, "a character device"));
    }
    let before = names(&nodes);
    for (out, what) in &refused {
        let kind = std::fs::symlink_metadata(out).unwrap().file_type();
        for mut cmd in writers(dir.path(), &log, out) {
            let o = cmd.output().unwrap();
            let err = stderr(&o);
            assert_eq!(o.status.code(), Some(2), "{cmd:?}: {err}");
            assert!(err.contains(&format!("{} is {what}", s(out))), "{err}");
            assert!(!err.contains("epoch"), "refused before training: {err}");
            assert_eq!(std::fs::symlink_metadata(out).unwrap().file_type(), kind);
            // Nothing left beside it (no temporary file).
            assert_eq!(names(&nodes), before, "{cmd:?}");
            assert!(names(&nodes.join("sub")).is_empty());
        }
    }
    if let Some((dev, _)) = refused.get(3) {
        assert!(std::fs::metadata(dev).unwrap().file_type().is_char_device());
    }

    // A symlink to a file is followed, as `run --log` follows it: the file is replaced, the
    // link stays.
    let target = dir.path().join("target");
    let link = dir.path().join("link");
    std::os::unix::fs::symlink("target", &link).unwrap();
    for (i, mut cmd) in writers(dir.path(), &log, &link).into_iter().enumerate() {
        std::fs::write(&target, "old").unwrap();
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        let text = std::fs::read_to_string(&target).unwrap();
        let expected = [
            "\"format\": \"omnid-identifier-weights\"",
            "t,q1,q2,q3,tau1",
        ][i];
        assert!(text.contains(expected), "{}", &text[..80.min(text.len())]);
    }
}

#[test]
fn a_write_that_fails_part_way_leaves_the_old_file_and_no_temporary() {
    let dir = tempfile::tempdir().unwrap();
    let log = training_log(dir.path());
    let outs = dir.path().join("outs");
    std::fs::create_dir(&outs).unwrap();
    let out = outs.join("out");
    // Weights (~20 kB) and the converted log (~0.5 MB) do not fit in 8 kB.
    for cmd in writers(dir.path(), &log, &out) {
        std::fs::write(&out, "old").unwrap();
        let mut cmd = with_file_limit(cmd, 8_000);
        let o = cmd.output().unwrap();
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{cmd:?}: {err}");
        assert!(
            err.contains(s(&out)) && err.contains("File too large"),
            "{err}"
        );
        assert_eq!(std::fs::read_to_string(&out).unwrap(), "old");
        assert_eq!(names(&outs), ["out"], "{cmd:?}");
    }
}

// ---------------------------------------------------------------------------------------------
// Class 8: fail before the work, not after.

#[test]
fn bad_output_paths_are_found_before_the_work() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    std::fs::create_dir(p("adir")).unwrap();
    std::fs::write(p("afile"), "").unwrap();
    let log = p("run.csv");
    for (json, what) in [
        (p("adir"), "is a directory"),
        (p("afile/s.json"), "Not a directory"),
    ] {
        let o = omnid_in(dir.path())
            .args(["run", "--fast", "--duration", "3", "--log", s(&log)])
            .args(["--summary-json", s(&json)])
            .output()
            .unwrap();
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(
            err.contains("--summary-json") && err.contains(what),
            "{err}"
        );
        assert!(!log.exists(), "the run started");
    }

    let train = training_log(dir.path());
    let o = omnid_in(dir.path())
        .args(["identify", s(&train), "--epochs", "1"])
        .args(["--out", s(&p("afile/w.json"))])
        .output()
        .unwrap();
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("--out") && !err.contains("epoch"), "{err}");

    // A figure's file is a directory: refused before the log is read, exit 2 (bad input).
    let figs = p("figs");
    std::fs::create_dir_all(figs.join("angles.png")).unwrap();
    let o = omnid_in(dir.path())
        .args(["plot", s(&train), "--out", s(&figs)])
        .output()
        .unwrap();
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("--out") && err.contains("angles.png"), "{err}");
    assert_eq!(names(&figs), ["angles.png"]);

    // The experiment's report cannot be written: found before its first run.
    let exp = p("exp");
    std::fs::create_dir_all(exp.join("report.md")).unwrap();
    let o = omnid_in(dir.path())
        .args(["experiment", "alpha", "--quick", "--out", s(&exp)])
        .output()
        .unwrap();
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("--out") && err.contains("report.md"), "{err}");
    assert_eq!(names(&exp), ["report.md"], "no run was made");
}

#[test]
fn identify_refuses_a_joint_without_torque() {
    let dir = tempfile::tempdir().unwrap();
    let train = training_log(dir.path());
    // The same recording with joint 2's torque zeroed (as a log without torque has it).
    let text = std::fs::read_to_string(&train).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let c = header.iter().position(|h| *h == "tau2").unwrap();
    let mut out = header.join(",") + "\n";
    for line in lines {
        let mut f: Vec<&str> = line.split(',').collect();
        f[c] = "0.0";
        out += &(f.join(",") + "\n");
    }
    let flat = dir.path().join("flat.csv");
    std::fs::write(&flat, out).unwrap();
    let weights = dir.path().join("w.json");
    let o = omnid_in(dir.path())
        .args(["identify", s(&flat), "--epochs", "1", "--out", s(&weights)])
        .output()
        .unwrap();
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("joint 2") && err.contains(s(&flat)), "{err}");
    assert!(!err.contains("NaN") && !weights.exists(), "{err}");
}

/// Output lost to a full disk (`> file` on a full file system) is not a success; a closed pipe
/// (`| head`) is the reader's choice and stays quiet.
#[test]
fn stdout_on_a_full_disk_fails_the_command_and_says_so() {
    let full = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/full")
        .unwrap();
    let out = omnid()
        .args(["config", "--print-default"])
        .stdout(Stdio::from(full))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("cannot write to stdout"),
        "{}",
        stderr(&out)
    );
    // A closed pipe: quiet, and the command's own exit code.
    let mut child = omnid()
        .args(["config", "--print-default"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(!stderr(&out).contains("cannot write"), "{}", stderr(&out));
}
