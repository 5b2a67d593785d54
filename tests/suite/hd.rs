//! The libHD test kit: install the library and compile the C call-order replays against the
//! installed headers once for every test process (`HD::get`), run `omnid serve --device sim`.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// The installed library and the compiled programs.
pub struct HD {
    /// `lib/libHD.so*`, `include/HD/…` as `install.sh` lays them out (shared, read only).
    pub prefix: PathBuf,
    /// The call-order replays every test uses (shared, read only).
    bin: PathBuf,
}

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// The cdylib this test binary was built with: `omnid-hd` is a dev-dependency, so `cargo
/// test` built it (every crate type of a dependency, with this build's features) beside the
/// test executable before linking it. Else (a test executable moved away from its build)
/// `cargo build -p omnid-hd`, which compiles the library a second time.
fn build_library() -> PathBuf {
    let exe = std::env::current_exe().expect("the test executable's path");
    if let Some(lib) = exe.parent().map(|d| d.join("libomnid_hd.so")) {
        if lib.is_file() {
            return lib;
        }
    }
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let out = Command::new(cargo)
        .args(["build", "-p", "omnid-hd", "--message-format=json"])
        .current_dir(root())
        .stderr(Stdio::inherit())
        .output()
        .expect("cargo runs");
    assert!(out.status.success(), "cargo build -p omnid-hd failed");
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v["reason"] == "compiler-artifact" && v["target"]["name"] == "omnid_hd")
        .flat_map(|v| {
            v["filenames"]
                .as_array()
                .cloned()
                .unwrap_or_default()
                .into_iter()
                .filter_map(|f| f.as_str().map(PathBuf::from))
        })
        .find(|p| p.extension().is_some_and(|e| e == "so"))
        .expect("cargo reported the cdylib")
}

/// The programs of `tests/c/` every test runs: (name, source, compiler, flags).
const PROGRAMS: &[(&str, &str, &str, &[&str])] = &[
    ("abi", "abi.c", "cc", &["-std=c11"]),
    ("chai", "chai.c", "cc", &["-std=c11"]),
    ("ros", "ros.c", "cc", &["-std=c11"]),
    ("jhu", "jhu.c", "cc", &["-std=c11"]),
    ("vrpn", "vrpn.c", "cc", &["-std=c11"]),
    ("nodaemon", "nodaemon.c", "cc", &["-std=c11"]),
    ("bench", "bench.c", "cc", &["-std=c11"]),
    ("gone", "gone.c", "cc", &["-std=c11"]),
    ("two", "two.c", "cc", &["-std=c11"]),
    ("slow", "slow.c", "cc", &["-std=c11"]),
    ("temp", "temp.c", "cc", &["-std=c11"]),
    ("occasional", "occasional.c", "cc", &["-std=c11"]),
    ("query", "query.c", "cc", &["-std=c11"]),
    ("inkwell", "inkwell.c", "cc", &["-std=c11"]),
    ("speed", "speed.c", "cc", &["-std=c11"]),
    ("stall", "stall.c", "cc", &["-std=c11"]),
    ("abi_cpp", "abi.c", "c++", &["-x", "c++", "-std=c++11"]),
];

/// A digest of everything the installed fixture is made from: the library's bytes, every file
/// under `clients/hdapi/{include,hdu,tests/c}` and `install.sh` (paths and bytes), the program
/// list and the compilers' versions. A change to any of them makes a new fixture.
fn fixture_key(lib: &Path) -> String {
    fn add_tree(h: &mut xxhash_rust::xxh3::Xxh3, dir: &Path) {
        let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .collect();
        entries.sort();
        for p in entries {
            if p.is_dir() {
                add_tree(h, &p);
            } else {
                h.update(
                    p.strip_prefix(root())
                        .unwrap_or(&p)
                        .as_os_str()
                        .as_encoded_bytes(),
                );
                h.update(&std::fs::read(&p).unwrap());
            }
        }
    }
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(&std::fs::read(lib).expect("the library is readable"));
    let hd = root().join("clients/hdapi");
    for d in ["include", "hdu", "tests/c"] {
        add_tree(&mut h, &hd.join(d));
    }
    h.update(&std::fs::read(hd.join("install.sh")).unwrap());
    h.update(format!("{PROGRAMS:?}").as_bytes());
    for compiler in ["cc", "c++"] {
        if let Ok(v) = Command::new(compiler).arg("--version").output() {
            h.update(&v.stdout);
        }
    }
    format!("{:032x}", h.digest128())
}

impl HD {
    /// The library installed and the programs compiled once for every test process:
    /// in `CARGO_TARGET_TMPDIR/hd-<digest of what they are made from>`, made by the first
    /// process under a file lock (the others wait for it, then use it) and marked complete
    /// last, so half a fixture (a maker killed) is made again. Fixtures made more than an hour
    /// ago are removed then.
    pub fn get() -> &'static HD {
        static HD: OnceLock<HD> = OnceLock::new();
        HD.get_or_init(|| {
            let lib = build_library();
            let tmp = Path::new(env!("CARGO_TARGET_TMPDIR"));
            std::fs::create_dir_all(tmp).unwrap();
            let ready = tmp.join(format!("hd-{}", fixture_key(&lib)));
            let lock = std::fs::File::create(tmp.join("hd.lock")).unwrap();
            // SAFETY: a valid descriptor; the lock is released when `lock` is closed.
            let locked =
                unsafe { libc::flock(std::os::fd::AsRawFd::as_raw_fd(&lock), libc::LOCK_EX) };
            assert_eq!(locked, 0, "flock: {}", std::io::Error::last_os_error());
            let complete = ready.join("complete");
            if !complete.exists() {
                prune_fixtures(tmp);
                let _ = std::fs::remove_dir_all(&ready);
                std::fs::create_dir_all(&ready).unwrap();
                make_fixture(&lib, &ready);
                std::fs::write(&complete, "").unwrap();
            }
            drop(lock);
            HD {
                prefix: ready.join("prefix"),
                bin: ready.join("bin"),
            }
        })
    }

    /// Compile `tests/c/<src>` against the installed headers, linking `libs` from the
    /// installed `lib/` (panics with the compiler's messages if it fails): the program, in a
    /// directory the calling test owns and removes when it drops it. (Not in `HD`, which lives in
    /// a static: a static is never dropped, so a directory it held stayed in /tmp after every
    /// test process.)
    pub fn compile_with(
        &self,
        name: &str,
        src: &str,
        compiler: &str,
        flags: &[&str],
        libs: &[&str],
    ) -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let exe = dir.path().join(name);
        compile(&self.prefix, &exe, src, compiler, flags, libs);
        (dir, exe)
    }

    /// One of the shared programs (`PROGRAMS`).
    pub fn exe(&self, name: &str) -> PathBuf {
        self.bin.join(name)
    }
}

/// Remove the fixtures in `tmp` made more than an hour ago (other digests: an older library or
/// test program; each process holds its fixture's lock only while it looks for or makes it).
fn prune_fixtures(tmp: &Path) {
    let Ok(entries) = std::fs::read_dir(tmp) else {
        return;
    };
    for e in entries.flatten() {
        let old = e
            .metadata()
            .and_then(|m| m.modified())
            .ok()
            .and_then(|t| t.elapsed().ok())
            .is_some_and(|age| age > Duration::from_secs(3600));
        if old && e.file_name().to_string_lossy().starts_with("hd-") {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// Install `lib` with `install.sh` into `dir/prefix` and compile `PROGRAMS` into `dir/bin`.
fn make_fixture(lib: &Path, dir: &Path) {
    let prefix = dir.join("prefix");
    let install = Command::new("sh")
        .arg(root().join("clients/hdapi/install.sh"))
        .arg("--lib")
        .arg(lib)
        .arg(&prefix)
        .output()
        .expect("install.sh runs");
    assert!(
        install.status.success(),
        "install.sh: {}",
        String::from_utf8_lossy(&install.stderr)
    );
    let bin = dir.join("bin");
    std::fs::create_dir_all(&bin).unwrap();
    for (name, src, compiler, flags) in PROGRAMS {
        compile(
            &prefix,
            &bin.join(name),
            src,
            compiler,
            flags,
            &["-lHDU", "-lHD", "-lpthread"],
        );
    }
}

/// Compile `tests/c/<src>` against the headers and library installed in `prefix` into `exe`,
/// linking `libs` from its `lib/` (panics with the compiler's messages if it fails).
fn compile(prefix: &Path, exe: &Path, src: &str, compiler: &str, flags: &[&str], libs: &[&str]) {
    let lib = prefix.join("lib");
    let out = Command::new(compiler)
        .args(flags)
        .args(["-Wall", "-Werror", "-O1", "-D_DEFAULT_SOURCE", "-I"])
        .arg(prefix.join("include"))
        .arg(root().join("clients/hdapi/tests/c").join(src))
        .arg("-o")
        .arg(exe)
        .arg(format!("-L{}", lib.display()))
        .arg(format!("-Wl,-rpath,{}", lib.display()))
        .args(libs)
        .output()
        .unwrap_or_else(|e| panic!("{compiler}: {e} (a C/C++ compiler is needed)"));
    assert!(
        out.status.success(),
        "{compiler} {src}:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Run a program to its end (at most 60 s): its stdout; fails on a non-zero exit.
pub fn run(exe: PathBuf, args: &[&str], env: &[(&str, &str)]) -> String {
    let mut cmd = Command::new(&exe);
    cmd.args(args).env_remove("OMNID_SOCKET");
    for (k, v) in env {
        cmd.env(k, v);
    }
    let child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let out = wait_output(child, Duration::from_secs(60));
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{} failed ({}):\n{stdout}\n{}",
        exe.display(),
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

/// Kills a child that outlives `limit` (a hang fails the test instead of stalling CI);
/// disarmed when dropped, except that a test failing while the child still runs kills it
/// (else the program would outlive the test run).
pub struct Watchdog {
    pid: u32,
    done: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// `pid` is still a child of this process (running, or exited and not yet reaped).
fn is_our_child(pid: u32) -> bool {
    // Field 4 is the parent's pid.
    stat_field(std::path::Path::new(&format!("/proc/{pid}/stat")), 4)
        == Some(std::process::id().to_string())
}

/// Field `n` (1-based, as `man proc` numbers them) of a `/proc/…/stat` file. The fields after
/// the command name (which may hold spaces) start after its last ')', at field 3.
fn stat_field(path: &std::path::Path, n: usize) -> Option<String> {
    let stat = std::fs::read_to_string(path).ok()?;
    let rest = stat.rsplit_once(')')?.1;
    rest.split_whitespace()
        .nth(n.checked_sub(3)?)
        .map(str::to_string)
}

impl Watchdog {
    pub fn new(child: &Child, limit: Duration) -> Watchdog {
        let pid = child.id();
        let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let thread = {
            let done = done.clone();
            std::thread::spawn(move || {
                let until = Instant::now() + limit;
                while Instant::now() < until {
                    if done.load(std::sync::atomic::Ordering::SeqCst) {
                        return;
                    }
                    std::thread::sleep(Duration::from_millis(50));
                }
                // SAFETY: kill on the pid of our own child; its owner reaps it only when it
                // exits, so at the limit the pid is still ours (or a zombie of ours).
                unsafe { libc::kill(pid as i32, libc::SIGKILL) };
            })
        };
        Watchdog {
            pid,
            done,
            thread: Some(thread),
        }
    }
}

impl Drop for Watchdog {
    fn drop(&mut self) {
        if std::thread::panicking() && is_our_child(self.pid) {
            // SAFETY: a signal to our own child (checked just above through /proc).
            unsafe { libc::kill(self.pid as i32, libc::SIGKILL) };
        }
        self.done.store(true, std::sync::atomic::Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The child's output, killing it after `limit`.
pub fn wait_output(child: Child, limit: Duration) -> std::process::Output {
    let watchdog = Watchdog::new(&child, limit);
    let out = child.wait_with_output().unwrap();
    drop(watchdog);
    out
}

/// The scheduling policy and realtime priority of process `pid`'s thread named `name`
/// (`/proc/PID/task/TID/stat`, fields 41 and 40; policy 1 is SCHED_FIFO), if it has one.
pub fn thread_sched(pid: u32, name: &str) -> Option<(u32, u32)> {
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))
        .ok()?
        .flatten()
    {
        let comm = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
        if comm.trim_end() != name {
            continue;
        }
        let stat = task.path().join("stat");
        let field = |n| stat_field(&stat, n).and_then(|v| v.parse().ok());
        return Some((field(41)?, field(40)?));
    }
    None
}

/// This process may take SCHED_FIFO at `priority` (root, or an `rtprio` limit that allows it).
pub fn may_use_fifo(priority: u32) -> bool {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: plain libc calls; `lim` is a valid rlimit to fill.
    unsafe {
        libc::geteuid() == 0
            || (libc::getrlimit(libc::RLIMIT_RTPRIO, &mut lim) == 0
                && lim.rlim_cur >= priority as libc::rlim_t)
    }
}
