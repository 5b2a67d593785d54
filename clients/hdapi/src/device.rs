//! One device: a connection to `omnid serve` (its [`Link`] keeps the latest state sample, so
//! reads outside a frame and before the scheduler starts are fresh, and our requests'
//! answers) and the frame (snapshot in, force out). docs/HDAPI.md, Devices and Frames.

use crate::consts::{
    HD_EXCEEDED_MAX_FORCE, HD_EXCEEDED_MAX_VELOCITY, HD_TIMER_ERROR, HD_WARM_MOTORS,
};
use crate::error::Internal;
use crate::kin;
use crate::link::{Link, WaitEnd};
use omnid_client::protocol::{Hello, State, MAX_MESSAGE, PROTOCOL_VERSION};
use omnid_client::socket::Conn;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use thiserror::Error;

/// How long a stream command stays in effect at the daemon: a client that stops sending
/// (crash, stopped scheduler) loses its force within this (docs/HDAPI.md, Safety).
pub const FORCE_TTL_MS: f64 = 20.0;

/// The longest a committed force is kept between frames: a program whose callback is slower
/// (its frames come less often) gets a time to live of 2.5 frames, up to this, so its force
/// does not lapse (and the amplifiers do not cycle) between its frames.
pub const MAX_FORCE_TTL_MS: f64 = 100.0;

/// The time to live of a force committed `interval_ms` after the previous frame's. The first
/// frame's pace is unknown: the longest, so that a slow program's first force does not lapse
/// before its second frame (from the second on it follows the program's pace).
pub fn force_ttl_ms(interval_ms: Option<f64>) -> f64 {
    interval_ms.map_or(MAX_FORCE_TTL_MS, |i| {
        (2.5 * i).clamp(FORCE_TTL_MS, MAX_FORCE_TTL_MS)
    })
}

/// How long we wait for the daemon's first sample or a reply.
const ANSWER_TIMEOUT: Duration = Duration::from_secs(5);

#[derive(Debug, Error)]
pub enum DeviceError {
    #[error("no omnid daemon: {0}")]
    NoDaemon(String),
    #[error("the daemon refused: {0}")]
    Refused(String),
    #[error("the daemon did not answer in time")]
    Timeout,
    #[error("the connection to the daemon is closed")]
    Closed,
}

/// The frame in progress and what the last one committed.
#[derive(Default, Clone)]
pub struct Frame {
    pub depth: u32,
    /// The thread that began the outermost frame: the scheduler closes only frames its own
    /// callbacks left open, never one a program's main thread has in progress.
    pub opened_by: Option<std::thread::ThreadId>,
    /// The sample of the scheduler's tick in progress: what reads outside a frame see while
    /// the scheduler runs, so a callback without a frame (VRPN) reads one sample throughout.
    pub tick: Option<State>,
    /// The sample this frame reads (`CURRENT_…`); the last frame's is `LAST_…`.
    pub current: Option<State>,
    pub last: Option<State>,
    /// Cartesian force, N; joint torque, mN·m (docs/HDAPI.md, Units).
    pub force: [f64; 3],
    pub joint_torque: [f64; 3],
    pub gimbal_torque: [f64; 3],
    pub torque: [f64; 3],
    pub last_force: [f64; 3],
    pub last_joint_torque: [f64; 3],
    pub last_gimbal_torque: [f64; 3],
    pub last_torque: [f64; 3],
    /// When the last frame was committed (its force's time to live follows the interval).
    pub committed_at: Option<Instant>,
    /// Frames that push come further apart than [`MAX_FORCE_TTL_MS`]: the interval, ms, to be
    /// reported once (`slow` holds while the episode lasts).
    pub too_slow: Option<f64>,
    pub slow: bool,
    /// The daemon's limit flags at the last committed frame, and those that began acting
    /// since (to be raised as HD errors once per episode: [`limit_errors`]).
    pub limit_flags: u32,
    pub new_limits: u32,
    /// When each limit of [`LIMITS`] was last raised: a limit that comes and goes with the
    /// force (a program pushing at the limit) is raised at most once a second.
    pub limit_raised_at: [Option<Instant>; LIMITS.len()],
}

impl Frame {
    /// Note the daemon's limit flags at a committed frame (`pushes`: it sends a force or a
    /// torque): the limits that began acting are raised once (at most once a second each). The
    /// limits on a program's force (the force limit, a warm motor) concern only frames that
    /// push: a program that pushes nothing (force output disabled, a read-only loop) is not
    /// stopped by the daemon's own holding of the arm, and one that starts pushing while such a
    /// limit acts is told at its first pushing frame.
    pub fn note_limits(&mut self, flags: u32, one_tick: u32, pushes: bool, now: Instant) {
        let watched = LIMITS.iter().fold(0, |m, (bit, _, _)| m | bit)
            & if pushes { !0 } else { !FORCE_LIMITS };
        let began = (flags & !self.limit_flags & watched) | one_tick;
        self.limit_flags = flags & watched & !crate::link::ONE_TICK;
        for (k, (bit, _, _)) in LIMITS.iter().enumerate() {
            let quiet = self.limit_raised_at[k].is_none_or(|t| now - t >= LIMIT_HOLD_OFF);
            if began & bit != 0 && quiet {
                self.new_limits |= bit;
                self.limit_raised_at[k] = Some(now);
            }
        }
    }

    /// Begin a frame on the calling thread; the outermost takes `latest` and clears the
    /// forces.
    pub fn begin(&mut self, latest: Option<State>) {
        self.depth += 1;
        if self.depth == 1 {
            self.opened_by = Some(std::thread::current().id());
            self.current = latest;
            self.force = [0.0; 3];
            self.joint_torque = [0.0; 3];
            self.gimbal_torque = [0.0; 3];
            self.torque = [0.0; 3];
        }
    }

    /// The scheduler's tick is over (`scheduler` is its thread): a frame its callbacks left
    /// open is closed without committing, so the next tick starts clean. A frame another
    /// thread has open (a program framing its own reads between ticks) is that thread's to end.
    pub fn close_left_open(&mut self, scheduler: std::thread::ThreadId) {
        if self.opened_by == Some(scheduler) {
            self.depth = 0;
        }
    }
}

/// The least time between two raises of the same limit.
const LIMIT_HOLD_OFF: Duration = Duration::from_secs(1);

/// The daemon's `flags` bits a program is told about (docs/HDAPI.md, Errors), with the HD
/// error each raises and its internal code: the tip force held to the force limit or the
/// continuous force, a hot motor held to its continuous torque, the safety layer's speed trip
/// (one tick), and the daemon's servo loop stalled (one tick). The kick (torque-rate) limit is
/// not among them: it shapes most force onsets, and programs stop on any error.
const LIMITS: [(u32, u32, Internal); 4] = [
    (1 << 9, HD_EXCEEDED_MAX_FORCE, Internal::DaemonLimit),
    (1 << 6, HD_WARM_MOTORS, Internal::DaemonLimit),
    (1 << 11, HD_EXCEEDED_MAX_VELOCITY, Internal::DaemonLimit),
    (1 << 12, HD_TIMER_ERROR, Internal::ServoStall),
];

/// The limits of [`LIMITS`] on a program's own force: the force limit and a warm motor.
const FORCE_LIMITS: u32 = (1 << 9) | (1 << 6);

/// The HD errors (code, internal code) for the limits that began acting between two samples'
/// `flags`.
pub fn limit_errors(before: u32, now: u32) -> impl Iterator<Item = (u32, Internal)> {
    let began = now & !before;
    LIMITS
        .into_iter()
        .filter(move |(bit, _, _)| began & bit != 0)
        .map(|(_, code, internal)| (code, internal))
}

pub struct Device {
    pub hhd: u32,
    link: Arc<Link>,
    pub hello: Hello,
    pub socket: PathBuf,
    rx: Mutex<Option<JoinHandle<()>>>,
    next_id: AtomicU64,
    pub frame: Mutex<Frame>,
    /// We hold the daemon's command lease (taken when the scheduler starts).
    pub commanding: AtomicBool,
    /// `hdUpdateCalibration` was called after the inkwell was seen.
    pub calibrated: AtomicBool,
    /// The daemon offers `servo_cf` (Cartesian force); else forces go as `servo_jf`.
    servo_cf: bool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic elsewhere never poisons the library for good: the data are plain values.
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// The socket for a device name: NULL or "Default Device" → `$OMNID_SOCKET` or the only
/// socket in the default directories (as `omnid ctl` finds it); a path (has a `/`) → that
/// socket; another name → `<dir>/<name>.sock` in the default directories.
pub fn socket_for(name: Option<&str>) -> Result<PathBuf, String> {
    match name.map(str::trim) {
        None | Some("") => omnid_client::find_socket().map_err(|e| e.to_string()),
        Some(n)
            if n.eq_ignore_ascii_case("Default Device") || n.eq_ignore_ascii_case("default") =>
        {
            omnid_client::find_socket().map_err(|e| e.to_string())
        }
        Some(n) if n.contains('/') => Ok(PathBuf::from(n)),
        // An arm by name or alias (`[[arm]] aliases = ["PHANToM 1"]`): `<dir>/<name>.sock`,
        // else the daemon socket whose hello names it.
        Some(n) => omnid_client::find_arm_socket(n),
    }
}

impl Device {
    /// Connect, greet, start the state stream at the device's rate and wait for a sample.
    pub fn open(hhd: u32, socket: &Path) -> Result<Device, DeviceError> {
        let conn = Conn::connect(socket)
            .map_err(|e| DeviceError::NoDaemon(format!("{}: {e}", socket.display())))?;
        let hello = greet(&conn)?;
        let link = Arc::new(Link::new(conn));
        let rx = link
            .spawn_receiver()
            .map_err(|e| DeviceError::Refused(format!("cannot start a thread: {e}")))?;
        let servo_cf = hello.modes.iter().any(|m| m == "servo_cf");
        let d = Device {
            hhd,
            link,
            hello,
            socket: socket.to_path_buf(),
            rx: Mutex::new(Some(rx)),
            next_id: AtomicU64::new(1),
            frame: Mutex::new(Frame::default()),
            commanding: AtomicBool::new(false),
            calibrated: AtomicBool::new(false),
            servo_cf,
        };
        let rate = d.hello.rate_hz;
        d.request(json!({"op": "stream", "rate_hz": rate}))?;
        d.wait_sample(0, ANSWER_TIMEOUT)
            .ok_or(DeviceError::Timeout)?;
        Ok(d)
    }

    /// Send a request and wait for its reply (the receiving thread hands it over).
    pub fn request(&self, mut req: Value) -> Result<Value, DeviceError> {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        req["id"] = json!(id);
        self.send(&req)?;
        let v = self
            .link
            .wait_for(ANSWER_TIMEOUT, |i| i.replies.remove(&id))
            .map_err(|e| match e {
                WaitEnd::Closed => DeviceError::Closed,
                WaitEnd::Timeout => DeviceError::Timeout,
            })?;
        if v["type"] == "error" {
            Err(DeviceError::Refused(
                v["message"].as_str().unwrap_or("refused").to_string(),
            ))
        } else {
            Ok(v)
        }
    }

    pub fn send(&self, msg: &Value) -> Result<(), DeviceError> {
        let bytes = serde_json::to_vec(msg).map_err(|_| DeviceError::Closed)?;
        self.link.conn.send(&bytes).map_err(|_| DeviceError::Closed)
    }

    /// The latest sample (None before the first).
    pub fn latest(&self) -> Option<State> {
        self.link.inbox().latest.clone()
    }

    /// Samples received so far.
    pub fn samples(&self) -> u64 {
        self.link.inbox().samples
    }

    pub fn inkwell_seen(&self) -> bool {
        self.link.inbox().inkwell_seen
    }

    /// The daemon closed the connection (or said goodbye).
    pub fn is_closed(&self) -> bool {
        self.link.inbox().closed
    }

    /// The device's rate as measured over the last two samples, Hz.
    pub fn instantaneous_rate(&self) -> f64 {
        let dt = self.link.inbox().dt;
        if dt > 0.0 {
            1.0 / dt
        } else {
            self.hello.rate_hz
        }
    }

    /// Wait until more than `seen` samples have arrived: the new count, or None on time-out
    /// or when the connection closed.
    pub fn wait_sample(&self, seen: u64, timeout: Duration) -> Option<u64> {
        self.link
            .wait_for(timeout, |i| (i.samples > seen).then_some(i.samples))
            .ok()
    }

    /// The calling thread (the scheduler's) reads this device's socket from now on, so a
    /// sample wakes it directly; [`Device::give_back_reading`] ends that.
    pub fn take_reading(&self) {
        self.link.take_reading();
    }

    pub fn give_back_reading(&self) {
        self.link.give_back_reading();
    }

    /// The scheduler begins a tick (`Some`: its sample) or stopped (`None`).
    pub fn set_tick(&self, tick: bool) {
        let latest = if tick { self.latest() } else { None };
        lock(&self.frame).tick = latest;
    }

    /// `hdBeginFrame`: the outermost begin snapshots the latest sample and clears the forces
    /// (a force not set in a frame is zero, never carried over). False when the daemon is
    /// gone (the frame still opens, on the last sample).
    pub fn begin_frame(&self) -> bool {
        let latest = self.latest();
        lock(&self.frame).begin(latest);
        !self.is_closed()
    }

    /// `hdEndFrame`: the outermost end commits the frame's force (when `force_output`).
    /// False when no frame was begun.
    pub fn end_frame(&self, force_output: bool) -> Result<bool, DeviceError> {
        let mut f = lock(&self.frame);
        if f.depth == 0 {
            return Ok(false);
        }
        f.depth -= 1;
        if f.depth > 0 {
            return Ok(true);
        }
        f.last = f.current.clone();
        f.last_force = f.force;
        f.last_joint_torque = f.joint_torque;
        f.last_gimbal_torque = f.gimbal_torque;
        f.last_torque = f.torque;
        let Some(state) = f.current.clone() else {
            return Ok(true);
        };
        let (force, joint_torque) = if force_output {
            (f.force, f.joint_torque)
        } else {
            ([0.0; 3], [0.0; 3])
        };
        let pushes = force != [0.0; 3] || joint_torque != [0.0; 3];
        // One-tick bits (a trip, a stall) from every sample since the last frame, so a frame
        // that runs on a later sample still sees them; the others from this frame's sample.
        let one_tick = std::mem::take(&mut self.link.inbox().one_tick_flags);
        let now = Instant::now();
        f.note_limits(state.flags, one_tick, pushes, now);
        let interval_ms = f
            .committed_at
            .replace(now)
            .map(|t| (now - t).as_secs_f64() * 1e3);
        match interval_ms {
            Some(i) if pushes && i > MAX_FORCE_TTL_MS => {
                if !f.slow {
                    f.slow = true;
                    f.too_slow = Some(i);
                }
            }
            _ => f.slow = false,
        }
        drop(f);
        // A frame that pushes nothing, from a program whose frames are occasional (a
        // calibration loop committing once a second), commands nothing: the arm stays as the
        // daemon holds it, instead of its amplifiers toggling on for each frame and off when
        // the command lapses. A servo loop's zero-force frames still go (they keep its stream,
        // and the amplifiers, steady between contacts).
        let occasional = interval_ms.is_none_or(|i| i > MAX_FORCE_TTL_MS);
        if self.commanding.load(Ordering::Relaxed) && (pushes || !occasional) {
            let ttl = force_ttl_ms(interval_ms);
            self.send(&self.command(&state, force, joint_torque, ttl))?;
        }
        Ok(true)
    }

    /// The stream command for a frame: the force as `servo_cf` when the daemon offers it and
    /// no joint torque was set, else everything as one joint torque `servo_jf` (τ = Jᵀ F +
    /// joint torque). `seq` is the sample's tick, so the state stream's `cmd_seq` tells when
    /// it was applied.
    fn command(
        &self,
        state: &State,
        force: [f64; 3],
        joint_torque_mnm: [f64; 3],
        ttl_ms: f64,
    ) -> Value {
        let force = kin::clamp_force(force);
        if self.servo_cf && joint_torque_mnm == [0.0; 3] {
            return json!({"op": "servo_cf", "seq": state.seq, "force": force,
                          "ttl_ms": ttl_ms});
        }
        let jt = kin::joint_torque(&state.q, &force);
        let tau: [f64; 3] = std::array::from_fn(|j| jt[j] + joint_torque_mnm[j] * 1e-3);
        json!({"op": "servo_jf", "seq": state.seq, "tau": tau, "ttl_ms": ttl_ms})
    }

    /// Once per episode: the interval, ms, of frames that push but come further apart than
    /// the longest time to live (their force lapses between them).
    pub fn take_too_slow(&self) -> Option<f64> {
        lock(&self.frame).too_slow.take()
    }

    /// The HD errors (code, internal code) for limits that began acting since the last call.
    pub fn take_limit_errors(&self) -> Vec<(u32, Internal)> {
        let bits = std::mem::take(&mut lock(&self.frame).new_limits);
        limit_errors(0, bits).collect()
    }

    /// Take the command lease (the scheduler starts).
    pub fn take_lease(&self) -> Result<(), DeviceError> {
        // A program that dies must leave no force of its own: its stream falls back to idle
        // (amplifiers off, zero torque) whatever the daemon's `serve.stale_fallback`.
        self.request(json!({"op": "lease", "fallback": "idle"}))?;
        self.commanding.store(true, Ordering::Relaxed);
        Ok(())
    }

    /// Leave the arm with the amplifiers off (as the daemon started) and give the lease back:
    /// a stopped program leaves zero force.
    pub fn stand_down(&self) {
        if self.commanding.swap(false, Ordering::Relaxed) {
            let _ = self.request(json!({"op": "mode", "mode": "idle"}));
            let _ = self.request(json!({"op": "release"}));
        }
    }

    /// Close the connection and join the receiving thread.
    pub fn close(&self) {
        self.stand_down();
        self.link.shut();
        if let Some(h) = lock(&self.rx).take() {
            let _ = h.join();
        }
    }
}

/// Say hello; the daemon's hello.
fn greet(conn: &Conn) -> Result<Hello, DeviceError> {
    let hello = json!({"op": "hello", "protocol": PROTOCOL_VERSION, "name": "libHD"});
    let sent = conn.send(hello.to_string().as_bytes());
    let mut buf = vec![0u8; MAX_MESSAGE + 1];
    loop {
        if !conn.wait_readable(5000).unwrap_or(false) {
            return Err(DeviceError::Timeout);
        }
        let n = match conn.recv(&mut buf) {
            Ok(0) | Err(_) => return Err(DeviceError::Closed),
            Ok(n) => n.min(buf.len()),
        };
        let v: Value = serde_json::from_slice(&buf[..n]).unwrap_or(Value::Null);
        match v["type"].as_str() {
            Some("hello") => {
                return serde_json::from_value(v)
                    .map_err(|e| DeviceError::Refused(format!("unreadable hello: {e}")))
            }
            Some("error") => {
                return Err(DeviceError::Refused(
                    v["message"].as_str().unwrap_or("refused").into(),
                ))
            }
            _ if sent.is_err() => return Err(DeviceError::Closed),
            _ => {}
        }
    }
}

#[cfg(test)]
mod frame_tests {
    use super::Frame;

    /// A program's main thread frames a read while the scheduler ticks: the tick's end must
    /// not close that frame under it (it did, and the program's `hdEndFrame` failed with
    /// HD_ILLEGAL_END about one run in a hundred under load).
    #[test]
    fn a_tick_closes_only_the_frames_its_own_thread_left_open() {
        let scheduler = std::thread::spawn(|| std::thread::current().id())
            .join()
            .unwrap();
        let mut f = Frame::default();
        f.begin(None);
        f.close_left_open(scheduler);
        assert_eq!(f.depth, 1, "the main thread's frame was closed by the tick");
        // The scheduler's own callback left one open: closed.
        f.close_left_open(std::thread::current().id());
        assert_eq!(f.depth, 0);
        // Nested begins on the same thread are closed together.
        f.begin(None);
        f.begin(None);
        f.close_left_open(std::thread::current().id());
        assert_eq!(f.depth, 0);
    }
}

#[cfg(test)]
mod limit_tests {
    use super::*;

    #[test]
    fn a_limit_is_an_error_when_it_begins_not_while_it_lasts() {
        let force = 1 << 9;
        let warm = 1 << 6;
        let kick = 1 << 3;
        let codes = |before, now| limit_errors(before, now).map(|e| e.0).collect::<Vec<_>>();
        assert_eq!(codes(0, force), [HD_EXCEEDED_MAX_FORCE]);
        assert_eq!(limit_errors(force, force).count(), 0);
        assert_eq!(codes(force, force | warm | kick), [HD_WARM_MOTORS]);
        // The speed trip and a stall: the velocity error and the scheduler's timer error,
        // the stall with its own internal code.
        let (speed, stall) = (1 << 11, 1 << 12);
        assert_eq!(codes(0, speed), [HD_EXCEEDED_MAX_VELOCITY]);
        assert_eq!(
            limit_errors(0, stall).collect::<Vec<_>>(),
            [(HD_TIMER_ERROR, Internal::ServoStall)]
        );
        // Bits the library does not raise (a clamp, the kick limit, the ramp, a wall) raise
        // nothing.
        assert_eq!(limit_errors(0, 1 | kick | 16 | 32).count(), 0);
    }

    /// ServoLoopRate with force output disabled was stopped by HD_WARM_MOTORS: the daemon's
    /// own gravity compensation had warmed the motors, and the program pushed nothing.
    #[test]
    fn force_limits_reach_only_frames_that_push_and_a_first_push_is_told() {
        let (force, warm, speed) = (1 << 9, 1 << 6, 1 << 11);
        let t0 = Instant::now();
        let mut f = Frame::default();
        let raised = |f: &mut Frame| {
            let bits = std::mem::take(&mut f.new_limits);
            limit_errors(0, bits).map(|e| e.0).collect::<Vec<_>>()
        };
        // Warm motors and the force limit while the program pushes nothing: no error; the
        // speed trip (the arm's, not the program's force) still is one.
        f.note_limits(warm | force | speed, 0, false, t0);
        assert_eq!(raised(&mut f), [HD_EXCEEDED_MAX_VELOCITY]);
        f.note_limits(warm, 0, false, t0 + Duration::from_millis(1));
        assert!(raised(&mut f).is_empty());
        // The first frame that pushes while the motors are still warm is told, once.
        f.note_limits(warm, 0, true, t0 + Duration::from_millis(2));
        assert_eq!(raised(&mut f), [HD_WARM_MOTORS]);
        f.note_limits(warm, 0, true, t0 + Duration::from_millis(3));
        assert!(raised(&mut f).is_empty());
        // A pushing frame at the force limit is told too.
        f.note_limits(warm | force, 0, true, t0 + Duration::from_millis(4));
        assert_eq!(raised(&mut f), [HD_EXCEEDED_MAX_FORCE]);
    }
}
