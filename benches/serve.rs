//! `omnid serve` on the simulated Omni, against the real binary:
//!
//! (a) round trip: a client streams state at 1 kHz in `servo_jp` mode and answers every state
//!     k with a command `seq = k`; on time when state k + 1 carries `cmd_seq = k`. Beside it,
//!     the floor of a bare Unix SOCK_SEQPACKET ping-pong (400 bytes out, 64 back, 1 kHz), in
//!     Rust and, when `cc` is there, in C (`benches/uds_pingpong.c`);
//! (b) fan-out: the servo's lateness p99 with 0, 10 and 50 reader clients streaming at 1 kHz
//!     (a fresh daemon per count, the arm in `hold`).
//!
//! `cargo bench --bench serve -- SECONDS` (each phase's length, default 10 s). Prints a table
//! and writes the numbers to `target/serve-bench.json`. Timing on a shared machine is noisy:
//! this prints, it never fails on numbers.

use omnid::transport::client::{Client, ClientError, Message};
use serde_json::{json, Value};
use std::fs::File;
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant};

/// The pose the round-trip client's setpoint moves to (inside the soft walls).
const TARGET: [f64; 3] = [0.0, 0.5, 0.3];
/// Seconds over which the setpoint glides from the start pose to `TARGET`.
const RAMP_S: f64 = 2.0;
/// Unmeasured seconds after the ramp before the round trip is measured.
const SETTLE_S: f64 = 0.5;
/// Seconds a fan-out daemon runs in `hold` before its readers connect.
const WARMUP_S: f64 = 1.0;
/// A state arriving sooner than this after the one before came in a catch-up burst, µs.
const SPACED_US: f64 = 500.0;
const READER_COUNTS: [usize; 3] = [0, 10, 50];

/// p50, p99, p99.9 and max of `v` (indexed like `uds_pingpong.c`), µs.
#[derive(Clone, Copy, Debug)]
struct Pct {
    n: usize,
    p50: f64,
    p99: f64,
    p999: f64,
    max: f64,
}

impl Pct {
    fn of(v: &mut [f64]) -> Option<Pct> {
        if v.is_empty() {
            return None;
        }
        v.sort_by(f64::total_cmp);
        let n = v.len();
        let at = |q: f64| v[((n as f64 * q) as usize).min(n - 1)];
        Some(Pct {
            n,
            p50: at(0.5),
            p99: at(0.99),
            p999: at(0.999),
            max: v[n - 1],
        })
    }

    fn line(p: Option<Pct>) -> String {
        match p {
            Some(p) => format!(
                "p50 {:.1} p99 {:.1} p99.9 {:.1} max {:.1} µs",
                p.p50, p.p99, p.p999, p.max
            ),
            None => "no samples".to_string(),
        }
    }

    fn json(p: Option<Pct>) -> Value {
        match p {
            Some(p) => json!({"n": p.n, "p50": p.p50, "p99": p.p99, "p999": p.p999, "max": p.max}),
            None => Value::Null,
        }
    }
}

/// A running `omnid serve --device sim`; killed if still running when dropped (a panic).
struct Daemon {
    child: Option<Child>,
    socket: PathBuf,
    log: PathBuf,
}

impl Daemon {
    fn start(root: &Path, label: &str) -> Daemon {
        let dir = root.join(label);
        let state = dir.join("state");
        std::fs::create_dir_all(&state).expect("daemon temp dir");
        let socket = dir.join("sim.sock");
        let log = dir.join("daemon.log");
        let out = File::create(&log).expect("daemon log");
        let err = out.try_clone().expect("daemon log");
        let child = Command::new(env!("CARGO_BIN_EXE_omnid"))
            .args(["serve", "--device", "sim", "--socket"])
            .arg(&socket)
            .env("OMNID_STATE_DIR", &state)
            .stdin(Stdio::null())
            .stdout(out)
            .stderr(err)
            .spawn()
            .expect("spawning omnid serve");
        let mut d = Daemon {
            child: Some(child),
            socket,
            log,
        };
        let deadline = Instant::now() + Duration::from_secs(20);
        loop {
            if let Some(status) = d.child.as_mut().and_then(|c| c.try_wait().ok().flatten()) {
                panic!(
                    "omnid serve ({label}) exited at start: {status}\n{}",
                    d.log_text()
                );
            }
            if d.socket.exists() && Client::connect(&d.socket, "bench-probe").is_ok() {
                return d;
            }
            if Instant::now() > deadline {
                panic!(
                    "omnid serve ({label}): no socket after 20 s\n{}",
                    d.log_text()
                );
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Each thread of the daemon with its scheduling class (`omnid-servo FIFO 80`).
    fn threads(&self) -> Vec<String> {
        let Some(pid) = self.child.as_ref().map(Child::id) else {
            return Vec::new();
        };
        let mut out = Vec::new();
        let tasks = std::fs::read_dir(format!("/proc/{pid}/task"));
        for task in tasks.into_iter().flatten().flatten() {
            let comm = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
            let stat = std::fs::read_to_string(task.path().join("stat")).unwrap_or_default();
            // The fields after `(comm)` start at field 3; rt_priority is 40, policy 41.
            let fields: Vec<&str> = stat
                .rsplit_once(')')
                .map(|(_, rest)| rest.split_whitespace().collect())
                .unwrap_or_default();
            let (prio, policy) = (fields.get(37), fields.get(38));
            let class = match policy.copied() {
                Some("0") => "TS".to_string(),
                Some("1") => format!("FIFO {}", prio.unwrap_or(&"?")),
                Some("2") => format!("RR {}", prio.unwrap_or(&"?")),
                Some(p) => format!("policy {p}"),
                None => "?".to_string(),
            };
            out.push(format!("{} {class}", comm.trim()));
        }
        out.sort();
        out
    }

    fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    fn connect(&self, name: &str) -> Client {
        Client::connect(&self.socket, name)
            .unwrap_or_else(|e| panic!("connecting to {}: {e}", self.socket.display()))
    }

    /// `shutdown` through `ctl` (the lease holder); the daemon's exit, as text.
    fn shutdown(mut self, ctl: &mut Client) -> String {
        match ctl.request(json!({"op": "shutdown"})) {
            Ok(_) | Err(ClientError::Closed) => {}
            Err(e) => eprintln!("serve bench: shutdown refused: {e}"),
        }
        let mut child = self.child.take().expect("daemon running");
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            match child.try_wait() {
                Ok(Some(status)) if status.success() => return "exit 0".to_string(),
                Ok(Some(status)) => {
                    return format!("{status}; log:\n{}", self.log_text());
                }
                Ok(None) if Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_millis(20))
                }
                _ => {
                    let _ = child.kill();
                    let _ = child.wait();
                    return "did not stop within 10 s of `shutdown`: killed".to_string();
                }
            }
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            if let Ok(None) = child.try_wait() {
                let _ = child.kill();
            }
            let _ = child.wait();
        }
    }
}

fn loadavg() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|l| l.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

fn lost_count(v: &Value) -> u64 {
    v["count"].as_u64().unwrap_or(0)
}

/// The daemon's `timing_us.lateness` and overruns from a `status` reply.
fn lateness(status: &Value) -> Value {
    json!({
        "lateness": status["timing_us"]["lateness"],
        "overruns": status["timing_us"]["overruns"],
    })
}

fn num(v: &Value) -> String {
    v.as_f64()
        .map(|x| format!("{x:.0}"))
        .unwrap_or_else(|| "–".to_string())
}

// ----------------------------------------------------------------------------------------
// (a) Round trip

struct RoundTrip {
    /// Transitions k → k + 1 both received and judged.
    judged: u64,
    on_time: u64,
    /// The same, counting only transitions where state k + 1 arrived at least
    /// `SPACED_US` after state k (not a catch-up burst after a late servo tick).
    judged_spaced: u64,
    on_time_spaced: u64,
    /// Of the late ones: how many ticks behind `cmd_seq` was (1 = applied one tick late).
    late_by: Vec<u64>,
    /// Of the late ones: receipt of state k to receipt of state k + 1, µs (a small gap means
    /// the two came back to back, the servo catching up after a late tick).
    late_gap: Option<Pct>,
    /// States that never arrived (gaps in `seq`) during the measurement.
    gaps: u64,
    lost: u64,
    errors: Vec<String>,
    events: Vec<String>,
    commands: u64,
    /// Receipt of state k to receipt of state k + 1 carrying `cmd_seq = k`, µs.
    rt: Option<Pct>,
    /// Receipt of state k to the command sent, µs.
    proc: Option<Pct>,
    /// Receipt time against the device's schedule (`t`), above its minimum, µs.
    delivery: Option<Pct>,
    status: Value,
    /// The daemon's threads and their scheduling classes.
    threads: Vec<String>,
    exit: String,
}

fn setpoint(q0: [f64; 3], ts: f64) -> [f64; 3] {
    let a = 0.5 - 0.5 * (std::f64::consts::PI * (ts / RAMP_S).clamp(0.0, 1.0)).cos();
    std::array::from_fn(|j| q0[j] + a * (TARGET[j] - q0[j]))
}

fn round_trip(root: &Path, secs: f64) -> RoundTrip {
    let daemon = Daemon::start(root, "roundtrip");
    let mut c = daemon.connect("bench-servo");
    c.request(json!({"op": "lease"})).expect("lease");
    let reply = c
        .request(json!({"op": "stream", "rate_hz": 1000.0}))
        .expect("stream");
    assert_eq!(reply["every"], json!(1), "stream reply: {reply}");
    let first = c.next_state(2000).expect("first state");
    let q0 = first.q;
    let base = Instant::now();
    let mut r = RoundTrip {
        judged: 0,
        on_time: 0,
        judged_spaced: 0,
        on_time_spaced: 0,
        late_by: Vec::new(),
        late_gap: None,
        gaps: 0,
        lost: 0,
        errors: Vec::new(),
        events: Vec::new(),
        commands: 0,
        rt: None,
        proc: None,
        delivery: None,
        status: Value::Null,
        threads: daemon.threads(),
        exit: String::new(),
    };
    let cap = (secs * 1000.0) as usize + 100;
    let mut late_gap = Vec::new();
    let (mut rt, mut proc, mut lag) = (
        Vec::with_capacity(cap),
        Vec::with_capacity(cap),
        Vec::with_capacity(cap),
    );
    let start = RAMP_S + SETTLE_S;
    let mut prev: Option<(u64, Instant)> = None;
    loop {
        let msg = match c.recv(1000) {
            Ok(m) => m,
            Err(e) => panic!(
                "round trip: {e} after {} states\n{}",
                r.judged,
                daemon.log_text()
            ),
        };
        let t = Instant::now();
        let s = match msg {
            Message::State(s) => s,
            Message::Other(v) => {
                match v["type"].as_str() {
                    Some("lost") => r.lost += lost_count(&v),
                    Some("error") => r.errors.push(v.to_string()),
                    Some("event") => r.events.push(v.to_string()),
                    _ => {}
                }
                continue;
            }
        };
        let ts = (s.seq - first.seq) as f64 / 1000.0;
        let measuring = ts >= start;
        if measuring {
            if let Some((k, tk)) = prev {
                if s.seq == k + 1 {
                    let gap = (t - tk).as_secs_f64() * 1e6;
                    let spaced = gap >= SPACED_US;
                    r.judged += 1;
                    r.judged_spaced += u64::from(spaced);
                    if s.cmd_seq == k {
                        r.on_time_spaced += u64::from(spaced);
                        r.on_time += 1;
                        rt.push(gap);
                    } else {
                        r.late_by.push(k.saturating_sub(s.cmd_seq));
                        late_gap.push(gap);
                    }
                } else if s.seq > k + 1 {
                    r.gaps += s.seq - k - 1;
                }
            }
        }
        if ts >= start + secs {
            break;
        }
        let q = setpoint(q0, ts);
        c.send(&json!({"op": "servo_jp", "seq": s.seq, "q": q, "ttl_ms": 50}))
            .expect("servo_jp");
        let done = Instant::now();
        if measuring {
            r.commands += 1;
            proc.push((done - t).as_secs_f64() * 1e6);
            lag.push(((t - base).as_secs_f64() - s.t) * 1e6);
        }
        prev = Some((s.seq, t));
    }
    let lag_min = lag.iter().copied().fold(f64::INFINITY, f64::min);
    for x in &mut lag {
        *x -= lag_min;
    }
    r.rt = Pct::of(&mut rt);
    r.late_gap = Pct::of(&mut late_gap);
    r.proc = Pct::of(&mut proc);
    r.delivery = Pct::of(&mut lag);
    r.status = c
        .request(json!({"op": "status"}))
        .map(|v| v["status"].clone())
        .unwrap_or(Value::Null);
    r.exit = daemon.shutdown(&mut c);
    r
}

// ----------------------------------------------------------------------------------------
// The bare Unix-socket floor

fn socketpair() -> (OwnedFd, OwnedFd) {
    let mut sv = [0 as libc::c_int; 2];
    // SAFETY: sv has room for the two descriptors socketpair writes.
    let rc = unsafe { libc::socketpair(libc::AF_UNIX, libc::SOCK_SEQPACKET, 0, sv.as_mut_ptr()) };
    assert_eq!(rc, 0, "socketpair: {}", std::io::Error::last_os_error());
    // SAFETY: both descriptors are fresh and owned by nothing else.
    unsafe { (OwnedFd::from_raw_fd(sv[0]), OwnedFd::from_raw_fd(sv[1])) }
}

fn send_bytes(fd: &OwnedFd, buf: &[u8]) -> isize {
    // SAFETY: buf is valid for its length.
    unsafe {
        libc::send(
            fd.as_raw_fd(),
            buf.as_ptr().cast(),
            buf.len(),
            libc::MSG_NOSIGNAL,
        )
    }
}

fn recv_bytes(fd: &OwnedFd, buf: &mut [u8]) -> isize {
    // SAFETY: buf is valid for its length.
    unsafe { libc::recv(fd.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len(), 0) }
}

/// `n` round trips over a SOCK_SEQPACKET socketpair to an echo thread at a 1 kHz pace
/// (absolute-deadline sleeps), µs.
fn uds_floor(n: usize) -> Option<Pct> {
    let (near, far) = socketpair();
    let echo = std::thread::spawn(move || {
        let mut buf = [0u8; 512];
        let cmd = [0u8; 64];
        while recv_bytes(&far, &mut buf) > 0 {
            if send_bytes(&far, &cmd) < 0 {
                break;
            }
        }
    });
    let state = [0u8; 400];
    let mut back = [0u8; 64];
    let mut rt = Vec::with_capacity(n);
    let mut next = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: next is a valid timespec.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut next) };
    for _ in 0..n {
        next.tv_nsec += 1_000_000;
        if next.tv_nsec >= 1_000_000_000 {
            next.tv_sec += 1;
            next.tv_nsec -= 1_000_000_000;
        }
        // SAFETY: next is a valid timespec; the remainder is not used with TIMER_ABSTIME.
        while unsafe {
            libc::clock_nanosleep(
                libc::CLOCK_MONOTONIC,
                libc::TIMER_ABSTIME,
                &next,
                std::ptr::null_mut(),
            )
        } == libc::EINTR
        {}
        let t0 = Instant::now();
        assert_eq!(send_bytes(&near, &state), 400, "floor: send");
        assert_eq!(recv_bytes(&near, &mut back), 64, "floor: recv");
        rt.push(t0.elapsed().as_secs_f64() * 1e6);
    }
    drop(near);
    echo.join().expect("echo thread");
    Pct::of(&mut rt)
}

/// `benches/uds_pingpong.c` compiled and run for `n` iterations: its line, or why not.
fn c_floor(root: &Path, n: usize) -> Result<String, String> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/uds_pingpong.c");
    if !src.is_file() {
        return Err(format!("skipped: {} not found", src.display()));
    }
    let exe = root.join("pp");
    let cc = Command::new("cc")
        .arg("-O2")
        .arg(&src)
        .arg("-o")
        .arg(&exe)
        .output()
        .map_err(|e| format!("skipped: no C compiler (`cc`: {e})"))?;
    if !cc.status.success() {
        return Err(format!(
            "skipped: cc failed: {}",
            String::from_utf8_lossy(&cc.stderr).trim()
        ));
    }
    let out = Command::new(&exe)
        .arg(n.to_string())
        .output()
        .map_err(|e| format!("cannot run {}: {e}", exe.display()))?;
    if !out.status.success() {
        return Err(format!("uds_pingpong failed: {}", out.status));
    }
    Ok(String::from_utf8_lossy(&out.stdout).trim().to_string())
}

// ----------------------------------------------------------------------------------------
// (b) Fan-out

struct FanOut {
    readers: usize,
    status: Value,
    /// States each reader received during the phase.
    received: Vec<u64>,
    /// Samples each reader was told it lost during the phase.
    lost: Vec<u64>,
    /// Readers that ended with an error.
    failures: Vec<String>,
    exit: String,
}

fn reader(
    socket: PathBuf,
    i: usize,
    ready: mpsc::Sender<Result<(), String>>,
    measuring: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
) -> Result<(u64, u64), String> {
    let setup = Client::connect(&socket, &format!("bench-reader-{i}")).and_then(|mut c| {
        c.request(json!({"op": "stream", "rate_hz": 1000.0}))?;
        Ok(c)
    });
    let mut c = match setup {
        Ok(c) => {
            let _ = ready.send(Ok(()));
            c
        }
        Err(e) => {
            let _ = ready.send(Err(e.to_string()));
            return Err(e.to_string());
        }
    };
    let (mut received, mut lost) = (0u64, 0u64);
    while !stop.load(Ordering::Relaxed) {
        match c.recv(100) {
            Ok(Message::State(_)) => {
                if measuring.load(Ordering::Relaxed) {
                    received += 1;
                }
            }
            Ok(Message::Other(v)) => {
                if v["type"] == "lost" && measuring.load(Ordering::Relaxed) {
                    lost += lost_count(&v);
                }
            }
            Err(ClientError::Timeout(_)) => {}
            Err(e) => return Err(format!("reader {i}: {e}")),
        }
    }
    Ok((received, lost))
}

fn fan_out(root: &Path, readers: usize, secs: f64) -> FanOut {
    let daemon = Daemon::start(root, &format!("fanout-{readers}"));
    let mut ctl = daemon.connect("bench-ctl");
    ctl.request(json!({"op": "lease"})).expect("lease");
    ctl.request(json!({"op": "mode", "mode": "hold"}))
        .expect("mode hold");
    std::thread::sleep(Duration::from_secs_f64(WARMUP_S));
    let measuring = Arc::new(AtomicBool::new(false));
    let stop = Arc::new(AtomicBool::new(false));
    let (ready_tx, ready) = mpsc::channel();
    let handles: Vec<_> = (0..readers)
        .map(|i| {
            let (socket, ready_tx) = (daemon.socket.clone(), ready_tx.clone());
            let (measuring, stop) = (measuring.clone(), stop.clone());
            std::thread::Builder::new()
                .name(format!("reader-{i}"))
                .spawn(move || reader(socket, i, ready_tx, measuring, stop))
                .expect("reader thread")
        })
        .collect();
    let mut failures = Vec::new();
    for _ in 0..readers {
        match ready.recv_timeout(Duration::from_secs(20)) {
            Ok(Ok(())) => {}
            Ok(Err(e)) => failures.push(e),
            Err(_) => {
                failures.push("a reader did not connect within 20 s".to_string());
                break;
            }
        }
    }
    measuring.store(true, Ordering::Relaxed);
    std::thread::sleep(Duration::from_secs_f64(secs));
    measuring.store(false, Ordering::Relaxed);
    let status = ctl
        .request(json!({"op": "status"}))
        .map(|v| v["status"].clone())
        .unwrap_or_else(|e| {
            failures.push(format!("status: {e}"));
            Value::Null
        });
    stop.store(true, Ordering::Relaxed);
    let (mut received, mut lost) = (Vec::new(), Vec::new());
    for h in handles {
        match h.join() {
            Ok(Ok((r, l))) => {
                received.push(r);
                lost.push(l);
            }
            Ok(Err(e)) => failures.push(e),
            Err(_) => failures.push("a reader panicked".to_string()),
        }
    }
    let exit = daemon.shutdown(&mut ctl);
    FanOut {
        readers,
        status,
        received,
        lost,
        failures,
        exit,
    }
}

// ----------------------------------------------------------------------------------------

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let secs: f64 = args
        .first()
        .and_then(|a| a.parse().ok())
        .filter(|s: &f64| *s > 0.0)
        .unwrap_or(10.0);
    let n_floor = (secs * 1000.0).round() as usize;
    let load_start = loadavg();
    let tmp = tempfile::tempdir().expect("temp dir");
    let root = tmp.path();
    eprintln!(
        "serve bench: {secs} s per phase, daemon {}",
        env!("CARGO_BIN_EXE_omnid")
    );

    eprintln!("serve bench: round trip ({secs} s after a {RAMP_S} s ramp)…");
    let rt = round_trip(root, secs);
    eprintln!("serve bench: uds floor, Rust ({n_floor} round trips)…");
    let floor = uds_floor(n_floor);
    eprintln!("serve bench: uds floor, C…");
    let c_line = c_floor(root, n_floor);
    let mut fan = Vec::new();
    for &n in &READER_COUNTS {
        eprintln!("serve bench: fan-out, {n} readers ({secs} s)…");
        fan.push(fan_out(root, n, secs));
    }

    let load_end = loadavg();

    // The table.
    let on_time_pct = if rt.judged > 0 {
        100.0 * rt.on_time as f64 / rt.judged as f64
    } else {
        f64::NAN
    };
    let mut late_hist = std::collections::BTreeMap::<u64, u64>::new();
    for &l in &rt.late_by {
        *late_hist.entry(l).or_default() += 1;
    }
    println!();
    println!(
        "machine: {} CPUs, load average {load_start} at start, {load_end} at end; daemon threads: {}",
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        rt.threads.join(", ")
    );
    println!(
        "serve round trip ({} states at 1 kHz, sim): on time {on_time_pct:.3} % ({} of {}, floor 99.9 %)  rt {}",
        rt.judged,
        rt.on_time,
        rt.judged,
        Pct::line(rt.rt)
    );
    println!(
        "  (rt = receipt of state k to receipt of state k+1 carrying cmd_seq = k: one 1 ms tick plus delivery jitter)"
    );
    println!(
        "  client processing (recv → servo_jp sent):  {}",
        Pct::line(rt.proc)
    );
    println!(
        "  state delivery vs device schedule (above min): {}",
        Pct::line(rt.delivery)
    );
    println!(
        "  late {} (ticks behind: {late_hist:?}), states missing {}, lost {}, errors {}, daemon lateness {}, exit: {}",
        rt.late_by.len(),
        rt.gaps,
        rt.lost,
        rt.errors.len(),
        lateness(&rt.status),
        rt.exit
    );
    println!(
        "  on time when state k+1 came ≥ {SPACED_US} µs after state k: {} of {}",
        rt.on_time_spaced, rt.judged_spaced
    );
    if rt.late_gap.is_some() {
        println!(
            "  late ones, receipt of state k to state k+1: {}",
            Pct::line(rt.late_gap)
        );
    }
    for e in rt.errors.iter().take(3) {
        println!("  error: {e}");
    }
    for e in rt
        .events
        .iter()
        .filter(|e| !e.contains("\"lease\""))
        .take(5)
    {
        println!("  event: {e}");
    }
    println!(
        "uds floor (socketpair, Rust, {n_floor} at 1 kHz):  {}",
        Pct::line(floor)
    );
    match &c_line {
        Ok(l) => println!("uds floor (benches/uds_pingpong.c):  {l}"),
        Err(e) => println!("uds floor (benches/uds_pingpong.c):  {e}"),
    }
    let p99 = |f: &FanOut| f.status["timing_us"]["lateness"]["p99"].as_f64();
    println!(
        "fan-out lateness p99: {}",
        fan.iter()
            .map(|f| format!(
                "{} readers {} µs",
                f.readers,
                p99(f).map(|x| format!("{x:.0}")).unwrap_or("–".into())
            ))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let base = fan.first().and_then(p99);
    let ratio = match (base, fan.last().and_then(p99)) {
        (Some(a), Some(b)) if a > 0.0 => Some(b / a),
        _ => None,
    };
    println!(
        "  ratio {}/{} = {}  (floor ≤ 1.2)",
        READER_COUNTS[2],
        READER_COUNTS[0],
        ratio
            .map(|r| format!("{r:.2}"))
            .unwrap_or_else(|| "–".to_string())
    );
    let expected = (secs * 1000.0).round() as u64;
    for f in &fan {
        let l = &f.status["timing_us"]["lateness"];
        let readers = if f.received.is_empty() {
            "no readers".to_string()
        } else {
            let sum: u64 = f.received.iter().sum();
            format!(
                "readers received min {} mean {:.0} of ~{expected}, lost {}",
                f.received.iter().min().copied().unwrap_or(0),
                sum as f64 / f.received.len() as f64,
                f.lost.iter().sum::<u64>()
            )
        };
        let failures = if f.failures.is_empty() {
            String::new()
        } else {
            format!("failures {:?}; ", f.failures)
        };
        println!(
            "  {:>2} readers: lateness p50 {} p99 {} p99.9 {} max {} µs, overruns {}; {readers}; {failures}exit: {}",
            f.readers,
            num(&l["p50"]),
            num(&l["p99"]),
            num(&l["p999"]),
            num(&l["max"]),
            num(&f.status["timing_us"]["overruns"]),
            f.exit
        );
    }

    // The record.
    let record = json!({
        "seconds_per_phase": secs,
        "loadavg_start": load_start,
        "loadavg_end": load_end,
        "daemon_threads": rt.threads,
        "round_trip": {
            "judged": rt.judged,
            "on_time": rt.on_time,
            "on_time_pct": on_time_pct,
            "judged_spaced": rt.judged_spaced,
            "on_time_spaced": rt.on_time_spaced,
            "spaced_us": SPACED_US,
            "late": rt.late_by.len(),
            "late_gap_us": Pct::json(rt.late_gap),
            "late_by_ticks": late_hist.iter().map(|(k, v)| (k.to_string(), json!(v))).collect::<serde_json::Map<_, _>>(),
            "missing_states": rt.gaps,
            "lost": rt.lost,
            "errors": rt.errors,
            "commands": rt.commands,
            "rt_us": Pct::json(rt.rt),
            "client_processing_us": Pct::json(rt.proc),
            "delivery_above_min_us": Pct::json(rt.delivery),
            "daemon": lateness(&rt.status),
            "exit": rt.exit,
        },
        "uds_floor_rust_us": Pct::json(floor),
        "uds_floor_c": match &c_line { Ok(l) => json!(l), Err(e) => json!({"skipped": e}) },
        "fan_out": fan.iter().map(|f| json!({
            "readers": f.readers,
            "lateness_us": f.status["timing_us"]["lateness"],
            "overruns": f.status["timing_us"]["overruns"],
            "clients": f.status["clients"],
            "received": f.received,
            "lost": f.lost,
            "failures": f.failures,
            "exit": f.exit,
        })).collect::<Vec<_>>(),
        "fan_out_ratio_p99_50_over_0": ratio,
    });
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("target"));
    let path = target.join("serve-bench.json");
    match std::fs::write(
        &path,
        serde_json::to_string_pretty(&record).unwrap_or_default() + "\n",
    ) {
        Ok(()) => println!("written {}", path.display()),
        Err(e) => eprintln!("serve bench: cannot write {}: {e}", path.display()),
    }
}
