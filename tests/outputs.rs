//! Outputs (issue 16): writing an output never destroys what is not ours (class 3).

mod common;
use common::omnid;
use std::os::unix::fs::FileTypeExt;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

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
