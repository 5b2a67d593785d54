//! The libHD test kit: build and install the library once per test binary, compile the C
//! call-order replays against the installed headers, run `omnid serve --device sim`.
#![allow(dead_code)]

use omnid::serve::client::Client;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

/// The installed library and the compiled programs.
pub struct HD {
    _dir: tempfile::TempDir,
    /// `lib/libHD.so*`, `include/HD/…` as `install.sh` lays them out.
    pub prefix: PathBuf,
    bin: PathBuf,
}

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// `cargo build -p omnid-hd`: the path of the cdylib it made.
fn build_library() -> PathBuf {
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

impl HD {
    pub fn get() -> &'static HD {
        static HD: OnceLock<HD> = OnceLock::new();
        HD.get_or_init(|| {
            let lib = build_library();
            let dir = tempfile::tempdir().unwrap();
            let prefix = dir.path().join("prefix");
            let install = Command::new("sh")
                .arg(root().join("clients/hdapi/install.sh"))
                .arg("--lib")
                .arg(&lib)
                .arg(&prefix)
                .output()
                .expect("install.sh runs");
            assert!(
                install.status.success(),
                "install.sh: {}",
                String::from_utf8_lossy(&install.stderr)
            );
            let bin = dir.path().join("bin");
            std::fs::create_dir_all(&bin).unwrap();
            let hd = HD {
                _dir: dir,
                prefix,
                bin,
            };
            for name in [
                "abi",
                "chai",
                "ros",
                "jhu",
                "vrpn",
                "nodaemon",
                "bench",
                "gone",
                "two",
                "slow",
                "temp",
                "occasional",
                "query",
                "inkwell",
                "speed",
                "stall",
            ] {
                hd.compile(name, &format!("{name}.c"), "cc", &["-std=c11"]);
            }
            hd.compile("abi_cpp", "abi.c", "c++", &["-x", "c++", "-std=c++11"]);
            hd
        })
    }

    /// Compile `tests/c/<src>` against the installed headers and library.
    fn compile(&self, name: &str, src: &str, compiler: &str, flags: &[&str]) {
        self.compile_with(name, src, compiler, flags, &["-lHDU", "-lHD", "-lpthread"]);
    }

    /// Compile `tests/c/<src>` against the installed headers, linking `libs` from the
    /// installed `lib/` (panics with the compiler's messages if it fails).
    pub fn compile_with(
        &self,
        name: &str,
        src: &str,
        compiler: &str,
        flags: &[&str],
        libs: &[&str],
    ) {
        let lib = self.prefix.join("lib");
        let out = Command::new(compiler)
            .args(flags)
            .args(["-Wall", "-Werror", "-O1", "-D_DEFAULT_SOURCE", "-I"])
            .arg(self.prefix.join("include"))
            .arg(root().join("clients/hdapi/tests/c").join(src))
            .arg("-o")
            .arg(self.exe(name))
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

    pub fn exe(&self, name: &str) -> PathBuf {
        self.bin.join(name)
    }
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

/// `omnid serve --device sim` in its own directory, killed when dropped.
pub struct Daemon {
    child: Option<Child>,
    _dir: tempfile::TempDir,
    pub socket: PathBuf,
}

impl Daemon {
    pub fn start(extra: &[&str]) -> Daemon {
        Daemon::start_with_config(extra, "")
    }

    /// With `config` (TOML) as its config file.
    pub fn start_with_config(extra: &[&str], config: &str) -> Daemon {
        let dir = tempfile::tempdir().unwrap();
        let socket = dir.path().join("sim.sock");
        let config_path = dir.path().join("omnid.toml");
        std::fs::write(&config_path, config).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_omnid"))
            .args(["serve", "--device", "sim", "--socket"])
            .arg(&socket)
            .arg("--config")
            .arg(&config_path)
            .args(extra)
            .env("OMNID_STATE_DIR", dir.path().join("state"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("omnid serve starts");
        let d = Daemon {
            child: Some(child),
            _dir: dir,
            socket,
        };
        let until = Instant::now() + Duration::from_secs(20);
        while Client::connect(&d.socket, "probe").is_err() {
            assert!(Instant::now() < until, "omnid serve did not start");
            std::thread::sleep(Duration::from_millis(20));
        }
        d
    }

    /// The daemon's process id.
    pub fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, |c| c.id())
    }

    /// Stop the daemon (SIGTERM: zero torque, goodbye to every client) and wait for it.
    pub fn stop(&mut self) {
        if let Some(mut c) = self.child.take() {
            // SAFETY: kill on our own child's pid, not yet reaped.
            unsafe { libc::kill(c.id() as i32, libc::SIGTERM) };
            let _ = c.wait();
        }
    }

    pub fn client(&self, name: &str) -> Client {
        Client::connect(&self.socket, name).expect("connects")
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
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
