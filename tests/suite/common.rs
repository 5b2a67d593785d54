//! Helpers shared by the integration tests: run the `omnid` binary, read its CSV logs.
#![allow(dead_code)]

use std::path::Path;
use std::process::{Command, Output};

/// The binary under test, with a state directory of its own ([`fresh_state_dir`]; a test that
/// wants another sets `OMNID_STATE_DIR` after): a run's motor heat and learned weights are
/// neither read from nor written to the user's, nor carried from one test to another.
pub fn omnid() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_omnid"));
    c.env("OMNID_STATE_DIR", fresh_state_dir());
    c
}

/// A new directory path for one run's state, inside one directory of this test process that is
/// removed when the process exits.
pub fn fresh_state_dir() -> std::path::PathBuf {
    static ROOT: std::sync::OnceLock<tempfile::TempDir> = std::sync::OnceLock::new();
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    extern "C" fn remove_root() {
        if let Some(root) = ROOT.get() {
            let _ = std::fs::remove_dir_all(root.path());
        }
    }
    let root = ROOT.get_or_init(|| {
        // SAFETY: registering a plain extern "C" function.
        unsafe { libc::atexit(remove_root) };
        tempfile::tempdir().unwrap()
    });
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    root.path().join(format!("state-{n}"))
}

pub fn run_ok(args: &[&str]) -> Output {
    let out = omnid().args(args).output().expect("omnid starts");
    assert!(
        out.status.success(),
        "omnid {args:?} failed: {}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// A parsed log: header and rows of fields.
pub struct Log {
    pub header: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

impl Log {
    pub fn read(path: &Path) -> Log {
        let text = std::fs::read_to_string(path).expect("log readable");
        let mut lines = text.lines();
        let header: Vec<String> = lines
            .next()
            .expect("header")
            .split(',')
            .map(String::from)
            .collect();
        let rows: Vec<Vec<String>> = lines
            .map(|l| l.split(',').map(String::from).collect::<Vec<_>>())
            .collect();
        for (i, r) in rows.iter().enumerate() {
            assert_eq!(
                r.len(),
                header.len(),
                "row {} has {} fields",
                i + 2,
                r.len()
            );
        }
        Log { header, rows }
    }

    pub fn col(&self, name: &str) -> usize {
        self.header
            .iter()
            .position(|h| h == name)
            .unwrap_or_else(|| panic!("no column {name}"))
    }

    pub fn f64s(&self, name: &str) -> Vec<f64> {
        let c = self.col(name);
        self.rows
            .iter()
            .map(|r| r[c].parse::<f64>().expect("numeric"))
            .collect()
    }
}

/// The one daemon fixture: `omnid serve ARGS` in its own directory (its runtime directory,
/// with the default sockets, and its state directory are in there); killed if a test fails.
pub struct Served {
    pub child: Option<std::process::Child>,
    pub dir: tempfile::TempDir,
    /// The simulated arm's socket, given as `--socket` ([`Served::sim`]).
    pub sock: std::path::PathBuf,
    /// The live view's address (`ws://…`), when started with one ([`Served::with_live_view`]).
    pub url: String,
}

impl Served {
    /// Start `omnid serve` with `args` (and `config` as its --config), and wait until every
    /// socket in `sockets` (names in the runtime directory, `<arm>.sock`) answers.
    pub fn start(args: &[&str], config: Option<&str>, sockets: &[&str]) -> Served {
        let served = Served::spawn(args, config);
        for s in sockets {
            served.wait_for(&served.socket(s));
        }
        served
    }

    /// [`Served::start`] in `dir` (its runtime directory, prepared by the test).
    pub fn start_in(
        dir: tempfile::TempDir,
        args: &[&str],
        config: Option<&str>,
        sockets: &[&str],
    ) -> Served {
        let served = Served::spawn_in(dir, args, config, None);
        for s in sockets {
            served.wait_for(&served.socket(s));
        }
        served
    }

    /// `omnid serve --device sim --socket <dir>/sim.sock EXTRA` (with `config`), once its
    /// socket answers.
    pub fn sim(extra: &[&str], config: Option<&str>) -> Served {
        let dir = tempfile::tempdir().unwrap();
        let sock = dir.path().join("sim.sock");
        let mut args = vec!["--device", "sim", "--socket", sock.to_str().unwrap()];
        args.extend_from_slice(extra);
        let mut served = Served::spawn_in(dir, &args, config, None);
        served.sock = sock;
        served.wait_for(&served.sock);
        served
    }

    /// `omnid serve ARGS --foxglove 127.0.0.1:0`, once it says where the live view is
    /// ([`Served::url`]); its stderr is read to the end by a thread of its own.
    pub fn with_live_view(args: &[&str]) -> Served {
        Served::with_live_view_limited(args, None)
    }

    /// As [`Served::with_live_view`], the daemon started with a soft descriptor limit of
    /// `nofile` if given.
    pub fn with_live_view_limited(args: &[&str], nofile: Option<u64>) -> Served {
        let mut all = args.to_vec();
        all.extend_from_slice(&["--foxglove", "127.0.0.1:0"]);
        let mut served = Served::spawn_in(tempfile::tempdir().unwrap(), &all, None, nofile);
        served.url = served.read_live_view_address();
        served
    }

    /// Read the daemon's stderr to the end in a thread of its own (so the pipe never fills)
    /// and return the live view's address once it says it.
    fn read_live_view_address(&mut self) -> String {
        use std::io::BufRead;
        let stderr = self.child.as_mut().unwrap().stderr.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stderr)
                .lines()
                .map_while(Result::ok)
            {
                if let Some(rest) = line.split("live view on ").nth(1) {
                    let url = rest.split_whitespace().next().unwrap_or("").to_string();
                    let _ = tx.send(url);
                }
            }
        });
        rx.recv_timeout(std::time::Duration::from_secs(60))
            .expect("omnid serve says where the live view is")
    }

    fn spawn(args: &[&str], config: Option<&str>) -> Served {
        Served::spawn_in(tempfile::tempdir().unwrap(), args, config, None)
    }

    /// `omnid serve ARGS` in `dir`. The daemon gets SIGTERM when the thread that started it
    /// ends (Linux's parent-death signal): a test's own daemon when its test's thread ends,
    /// even when the test process is killed outright (no `Drop` runs then, and a daemon left
    /// running went on ticking at 1 kHz for as long as nobody stopped it).
    fn spawn_in(
        dir: tempfile::TempDir,
        args: &[&str],
        config: Option<&str>,
        nofile: Option<u64>,
    ) -> Served {
        let mut cmd = omnid();
        let parent = std::process::id() as libc::pid_t;
        // SAFETY: only async-signal-safe calls between fork and exec.
        unsafe {
            std::os::unix::process::CommandExt::pre_exec(&mut cmd, move || {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                // The parent may have died before the signal was asked for (no allocation here).
                if libc::getppid() != parent {
                    return Err(std::io::Error::from_raw_os_error(libc::ESRCH));
                }
                Ok(())
            });
        }
        if let Some(n) = nofile {
            // SAFETY: only async-signal-safe calls between fork and exec.
            unsafe {
                std::os::unix::process::CommandExt::pre_exec(&mut cmd, move || {
                    let mut l = libc::rlimit {
                        rlim_cur: 0,
                        rlim_max: 0,
                    };
                    libc::getrlimit(libc::RLIMIT_NOFILE, &mut l);
                    l.rlim_cur = n.min(l.rlim_max);
                    libc::setrlimit(libc::RLIMIT_NOFILE, &l);
                    Ok(())
                });
            }
        }
        cmd.arg("serve")
            .args(args)
            .env("XDG_RUNTIME_DIR", dir.path())
            .env_remove("RUNTIME_DIRECTORY")
            .env_remove("OMNID_SOCKET")
            .env("OMNID_STATE_DIR", dir.path().join("state"))
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped());
        if let Some(text) = config {
            let path = dir.path().join("omnid.toml");
            std::fs::write(&path, text).unwrap();
            cmd.arg("--config").arg(path);
        }
        Served {
            child: Some(cmd.spawn().expect("omnid serve starts")),
            dir,
            sock: std::path::PathBuf::new(),
            url: String::new(),
        }
    }

    /// A daemon started by hand (`child`, with resource limits or a shared state directory of
    /// the test's own), once its socket `sock` answers.
    pub fn adopt(
        child: std::process::Child,
        dir: tempfile::TempDir,
        sock: std::path::PathBuf,
    ) -> Served {
        let served = Served {
            child: Some(child),
            dir,
            sock,
            url: String::new(),
        };
        served.wait_for(&served.sock);
        served
    }

    /// A client of the simulated arm's socket ([`Served::sim`]).
    pub fn connect(&self, who: &str) -> omnid::transport::client::Client {
        omnid::transport::client::Client::connect(&self.sock, who).expect("connects")
    }

    /// A file in the daemon's directory.
    pub fn path(&self, name: &str) -> std::path::PathBuf {
        self.dir.path().join(name)
    }

    /// Wait for the daemon to exit by itself: exit code and stderr.
    pub fn wait(&mut self) -> (Option<i32>, String) {
        let child = self.child.take().unwrap();
        let out = child.wait_with_output().unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    }

    /// The default socket of arm `name`.
    pub fn socket(&self, name: &str) -> std::path::PathBuf {
        self.dir.path().join("omnid").join(format!("{name}.sock"))
    }

    fn wait_for(&self, socket: &Path) {
        let until = std::time::Instant::now() + std::time::Duration::from_secs(30);
        while std::time::Instant::now() < until {
            if omnid::transport::client::Client::connect(socket, "probe").is_ok() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        panic!("omnid serve did not open {}", socket.display());
    }

    /// A client of arm `name`.
    pub fn client(&self, name: &str, who: &str) -> omnid::transport::client::Client {
        omnid::transport::client::Client::connect(&self.socket(name), who).expect("connects")
    }

    /// `omnid ARGS` with this daemon's runtime directory.
    pub fn omnid(&self, args: &[&str]) -> Output {
        omnid()
            .args(args)
            .env("XDG_RUNTIME_DIR", self.dir.path())
            .env_remove("RUNTIME_DIRECTORY")
            .env_remove("OMNID_SOCKET")
            .output()
            .unwrap()
    }

    /// `omnid ctl teleop start --leader L --follower F --seconds S` with this daemon's runtime
    /// directory (as on its PC: it finds this daemon's arms).
    pub fn teleop_console(&self, leader: &str, follower: &str, seconds: &str) -> Command {
        let mut c = omnid();
        c.env("XDG_RUNTIME_DIR", self.dir.path())
            .env_remove("RUNTIME_DIRECTORY")
            .env_remove("OMNID_SOCKET")
            .args(["ctl", "teleop", "start", "--leader", leader])
            .args(["--follower", follower, "--seconds", seconds]);
        c
    }

    pub fn pid(&self) -> i32 {
        self.child.as_ref().unwrap().id() as i32
    }

    /// Stop it (SIGTERM) and wait: exit code and stderr.
    pub fn stop(&mut self) -> (Option<i32>, String) {
        let child = self.child.take().unwrap();
        // SAFETY: kill with a live child's pid.
        unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
        let out = child.wait_with_output().unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    }
}

/// The daemon the read-only tests share: `omnid serve --device sim --socket <dir>/sim.sock
/// --foxglove 127.0.0.1:0`, started by the first test that asks and stopped (SIGTERM, waited
/// for, its directory removed) when the test process exits. A test on it may connect, read
/// states and status, watch the live view and try things that are refused; it never takes
/// the lease, commands, changes a mode or stops it: those tests start a daemon of their own.
pub fn shared_sim() -> &'static Served {
    static SHARED: std::sync::OnceLock<Served> = std::sync::OnceLock::new();
    extern "C" fn stop_at_exit() {
        if let Some(d) = SHARED.get() {
            let pid = d.pid();
            // SAFETY: signal and reap our own child.
            unsafe {
                libc::kill(pid, libc::SIGTERM);
                libc::waitpid(pid, std::ptr::null_mut(), 0);
            }
            let _ = std::fs::remove_dir_all(d.dir.path());
        }
    }
    SHARED.get_or_init(|| {
        // Started from a thread that lives as long as the process, so the daemon's parent-death
        // signal fires only when the test process ends, even killed outright.
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let dir = tempfile::tempdir().unwrap();
            let sock = dir.path().join("sim.sock");
            let args = [
                "--device",
                "sim",
                "--socket",
                sock.to_str().unwrap(),
                "--foxglove",
                "127.0.0.1:0",
            ];
            let mut served = Served::spawn_in(dir, &args, None, None);
            served.sock = sock;
            served.url = served.read_live_view_address();
            let _ = tx.send(served);
            loop {
                std::thread::park();
            }
        });
        let served = rx.recv().expect("the shared daemon starts");
        served.wait_for(&served.sock);
        // SAFETY: registering a plain extern "C" function.
        unsafe { libc::atexit(stop_at_exit) };
        served
    })
}

impl Drop for Served {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// A virtual environment under target/`name` (kept between runs) with `packages` from PyPI
/// installed; `probe` is a module whose presence means they are. None when PyPI is out of
/// reach (the caller skips, loudly); a failed install for any other reason fails the test.
pub fn venv(name: &str, packages: &[&str], probe: &str) -> Option<std::path::PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("target")
        .join(name);
    let python = dir.join("bin/python");
    // One maker at a time (tests run in parallel, and in several processes): the others wait
    // here and then find it made.
    std::fs::create_dir_all(dir.parent().unwrap()).unwrap();
    let lock = std::fs::File::create(dir.with_extension("lock")).unwrap();
    // SAFETY: a valid descriptor; the lock is released when `lock` is dropped (closed).
    assert_eq!(
        unsafe { libc::flock(std::os::fd::AsRawFd::as_raw_fd(&lock), libc::LOCK_EX) },
        0
    );
    if !python.exists() {
        let made = Command::new("python3")
            .args(["-m", "venv"])
            .arg(&dir)
            .output()
            .expect("python3 runs");
        assert!(
            made.status.success(),
            "python3 -m venv failed (install python3-venv; .ci/run does): {}",
            String::from_utf8_lossy(&made.stderr)
        );
    }
    let check = format!("import importlib.util as u; print(u.find_spec('{probe}') is not None)");
    let site = Command::new(&python)
        .args(["-c", &check])
        .output()
        .expect("venv python runs");
    if String::from_utf8_lossy(&site.stdout).trim() == "True" {
        return Some(python);
    }
    let pip = Command::new(&python)
        .args(["-m", "pip", "install", "--disable-pip-version-check", "-q"])
        .args(packages)
        .output()
        .expect("pip runs");
    if pip.status.success() {
        return Some(python);
    }
    let err = String::from_utf8_lossy(&pip.stderr);
    let unreachable = [
        "Could not fetch",
        "NewConnectionError",
        "Temporary failure in name resolution",
        "Network is unreachable",
        "No matching distribution found",
        "ConnectTimeout",
        "Failed to establish",
    ];
    if unreachable.iter().any(|s| err.contains(s)) {
        return None;
    }
    panic!("pip install {packages:?} failed:\n{err}");
}

/// A pair's link has just been cut: tick `ticks` times (`next` ticks and gives the leader's
/// force, N) from its force `f0` when the link went. The tick at which the force first reached
/// zero; on the way, no step larger than the fade's slope (the force over `fade_ms`) per tick,
/// plus the change the force had anyway while the link was still thought up.
pub fn ticks_to_fade(
    f0: [f64; 3],
    fade_ms: f64,
    ticks: usize,
    mut next: impl FnMut() -> [f64; 3],
) -> Option<usize> {
    let f0 = nalgebra::Vector3::from(f0);
    let mut prev = f0;
    let mut zero_at = None;
    for k in 1..=ticks {
        let f = nalgebra::Vector3::from(next());
        assert!(
            (f - prev).norm() <= f0.norm() * 1e-3 / (fade_ms * 1e-3) + 0.05,
            "a step of {} N at tick {k}",
            (f - prev).norm()
        );
        prev = f;
        if f.norm() == 0.0 && zero_at.is_none() {
            zero_at = Some(k);
        }
    }
    zero_at
}

/// A port free on loopback now (taken and let go: the daemon binds it next).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A zenoh peer of this process connected to `connect` only: it listens on a loopback port of
/// its own and does not scout, so it meets nobody else's daemon on the machine.
pub fn zenoh_peer(connect: &str) -> zenoh::Session {
    use zenoh::Wait;
    let mut c = zenoh::Config::default();
    for (k, v) in [
        ("mode", "\"peer\"".to_string()),
        ("connect/endpoints", format!("[\"{connect}\"]")),
        ("listen/endpoints", "[\"tcp/127.0.0.1:0\"]".into()),
        ("scouting/multicast/enabled", "false".into()),
    ] {
        c.insert_json5(k, &v).unwrap();
    }
    zenoh::open(c).wait().unwrap()
}
