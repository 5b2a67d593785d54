//! An arm's station: what a served arm is, with no transport in it. It holds the servo's
//! mailbox (commands in, records and replies back), the sessions that clients of any transport
//! open on it, the command lease and its checks, and the taps every tick record flows to: the
//! fault ring, a recording, subscribers' state views, events, and any [`Tap`] added.
//!
//! A transport (the Unix socket in `transport::hub`) turns its messages into [`Op`]s, calls
//! [`Station::request`], and forwards what [`Station::pump`] hands out. Nothing here knows JSON
//! or sockets; a test can drive a station directly.
//!
//! Everything that allocates happens here or in a transport, never on the servo thread. What
//! the servo must never miss (who owns the force, the emergency stop) is state it reads every
//! tick (`servo::ArmSignals`), not a message a full mailbox could drop.

pub mod device_info;
pub mod files;
pub mod ops;
mod saver;
mod taps;
mod view;

pub use files::FileRights;
pub use ops::{
    ModeRequest, Op, OpError, Reply, SessionId, SessionInfo, Status, TeleopReply, TeleopRequest,
};
pub use saver::Writer as WeightsWriter;
pub use taps::Tap;
pub use view::ArmState;

use crate::arm::ArmIdentity;
use crate::control::ControllerKind;
use crate::handoff::{Inlet, Outlet};
use crate::identifier::{Identifier, IdentifierConfig};
use crate::omni::kinematics::Geometry;
use crate::servo::summary::{FaultEntry, IdentifierState, RunSummary, SummaryLabels};
use crate::servo::{
    Activity, ArmSignals, ServoCommand, ServoEvent, ServoReply, Snapshot, Stamped, Wake,
};
use crate::telemetry::mcap_log::LogFormat;
use crate::telemetry::record::{LogSchema, Mode, TickRecord};
use crate::telemetry::{LogError, LogFile};
use crossbeam_channel::{Receiver, TryRecvError};
use ops::{LeaseHolder, RecordingStatus};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use taps::{FaultRing, Recording};

/// What a station is built from (`daemon::prepare` assembles it with the arm's pipeline).
pub struct StationSetup {
    /// Who the arm is.
    pub arm: ArmIdentity,
    /// The servo's wake-up signal (a tick some subscriber wants, a reply, an event).
    pub wake: Arc<Wake>,
    /// Every tick's record from the servo.
    pub records: Receiver<TickRecord>,
    /// The servo's mailbox.
    pub commands: Inlet<Stamped>,
    /// What the servo hands back.
    pub replies: Outlet<ServoReply>,
    /// Ownership, fallback and stop requests, read by the servo every tick.
    pub signals: Arc<ArmSignals>,
    /// Ends the daemon (`shutdown`).
    pub stop: Arc<AtomicBool>,
    /// Time to live, fallback, fault ring and dumps (from `[serve]`).
    pub limits: StationLimits,
    /// The servo rate, Hz.
    pub rate_hz: f64,
    /// The servo period, ns.
    pub period_ns: u64,
    /// The log columns this arm's device feeds.
    pub schema: LogSchema,
    /// Link lengths, for the tip in the state view.
    pub geometry: Geometry,
    /// The identifier's configuration (for weights loaded at run time).
    pub identifier_cfg: IdentifierConfig,
    /// The identifier as the servo started with it (shape for weight snapshots).
    pub identifier: Identifier,
    /// The law the servo started with.
    pub controller: ControllerKind,
    /// Where the starting weights came from.
    pub weights_label: String,
    /// The simulator's seed (in the summary).
    pub seed: u64,
    /// Where the arm's learned weights are kept (`[identifier] persist`), its name and serial
    /// (docs/IDENTIFIER.md).
    pub weights_store: Option<(PathBuf, String, Option<String>)>,
    /// How often they are saved while the daemon runs, s.
    pub weights_every_s: f64,
    /// Where recordings without a path and fault dumps go.
    pub state_dir: PathBuf,
    /// The realtime steps the servo thread took (set before its first tick).
    pub realtime: Arc<std::sync::OnceLock<crate::servo::realtime::RealtimeReport>>,
    /// `[teleop]`: a pair's settings unless its `teleop` op changes them.
    pub teleop: crate::teleop::TeleopConfig,
    /// Where this arm meets the other side of a pair (shared by the daemon's arms).
    pub rendezvous: crate::teleop::Rendezvous,
}

/// The station's share of `[serve]` (the rest is the transports').
#[derive(Debug, Clone, PartialEq)]
pub struct StationLimits {
    /// A stream command's default time to live, ms.
    pub stream_ttl_ms: f64,
    /// Where a stream falls back unless its owner chose: hold or idle.
    pub stale_fallback: Activity,
    /// Seconds of ticks kept for a fault dump.
    pub ring_s: f64,
    /// At most one fault dump this often, s.
    pub dump_interval_s: f64,
    /// Fault dumps kept per arm.
    pub max_dumps: usize,
    /// Format of fault dumps and of recordings started without a path.
    pub log_format: crate::telemetry::mcap_log::LogKind,
}

/// An event kind's line on stderr is said at most this often (safety trips always).
const SAY_EVERY: std::time::Duration = std::time::Duration::from_secs(1);

/// What [`Station::pump`] hands a transport.
#[derive(Debug)]
pub enum Output<'a> {
    /// A tick that at least one session streams (see [`Station::streams`]).
    State(&'a ArmState),
    /// Something every session is told.
    Event(&'a Event),
    /// The answer to an op that [`Station::request`] accepted as [`Answer::Later`].
    Done {
        /// The ticket it returned.
        ticket: u64,
        /// The session that asked.
        session: SessionId,
        /// The op's name.
        op: &'static str,
        /// The answer.
        result: Result<Reply, OpError>,
    },
}

/// An event for every session (docs/PROTOCOL.md, Events).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Event {
    /// Its name: `mode`, `controller`, `lease`, `weights`, `stream-stale`, `stream-ended`,
    /// `safety-trip`, `stopped`, `recording-failed`, `identifier-fault`.
    pub event: &'static str,
    /// The mode after it, where it concerns the mode.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mode: Option<&'static str>,
    /// The tick it happened at.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seq: Option<u64>,
    /// Device time, s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub t: Option<f64>,
    /// The law in effect (`controller` events).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub controller: Option<Option<&'static str>>,
    /// The lease holder (`lease` events; `null` when free).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub holder: Option<Option<SessionId>>,
    /// What happened, for people.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
}

impl Event {
    fn named(event: &'static str) -> Event {
        Event {
            event,
            mode: None,
            seq: None,
            t: None,
            controller: None,
            holder: None,
            message: None,
        }
    }

    fn lease(holder: Option<SessionId>, message: String) -> Event {
        Event {
            holder: Some(holder),
            message: Some(message),
            ..Event::named("lease")
        }
    }
}

/// How [`Station::request`] answers.
#[derive(Debug)]
pub enum Answer {
    /// Now.
    Now(Reply),
    /// Later, as [`Output::Done`] with this ticket (the servo has to answer first).
    Later(u64),
}

/// What the station saw, for the daemon's exit.
pub struct StationReport {
    /// A session asked for the shutdown.
    pub shutdown_requested: bool,
    /// Safety trips the arm survived (it went idle).
    pub faults: Vec<FaultEntry>,
    /// Fault dumps written.
    pub dumps: Vec<PathBuf>,
    /// The fault ring (for a dump at the end).
    pub(crate) ring: FaultRing,
    /// An error of the recording in progress at the end, if any.
    pub recording_error: Option<String>,
}

impl StationReport {
    /// Write the fault ring as a dump (a device fault ended the arm).
    pub fn dump_device_fault(&mut self, dir: &std::path::Path, arm: &str) {
        self.dumps.extend(self.ring.dump(dir, arm, "device"));
    }
}

struct Session {
    id: SessionId,
    info: SessionInfo,
    /// Every `every`-th tick is streamed (0: not streaming).
    every: u64,
    /// Someone else stopped the arm while this session held the lease: its streams are
    /// refused until it asks for a mode again.
    stopped_by: Option<String>,
}

/// A request waiting for the servo's snapshot.
enum Waiting {
    Status {
        ticket: u64,
        session: SessionId,
    },
    Save {
        ticket: u64,
        session: SessionId,
        path: PathBuf,
        rights: FileRights,
    },
    /// The periodic save of what the arm learned.
    Persist,
}

/// An arm's station (see the module's documentation).
pub struct Station {
    s: StationSetup,
    sessions: Vec<Session>,
    next_session: SessionId,
    next_ticket: u64,
    lease: Option<SessionId>,
    /// The stream fallback the holder chose (`lease` with `fallback`), if it did.
    lease_fallback: Option<Activity>,
    /// The owner epoch commands are stamped with (it grows when the lease ends).
    epoch: u64,
    /// Stop requests issued (commands are stamped with it).
    halts: u64,
    /// One snapshot box circulates: here when `Some`, at the servo otherwise.
    spare: Option<Box<Snapshot>>,
    /// A snapshot back before the record of its tick: answered once that record is here.
    held: Option<Box<Snapshot>>,
    waiting: Vec<Waiting>,
    /// Weight loads sent to the servo, answered when the old identifier comes back (`None`:
    /// a reset to the shipped weights).
    loads: std::collections::VecDeque<(u64, SessionId, Option<PathBuf>)>,
    adapt: bool,
    /// The time to live of the last stream command sent, ms (named when the stream goes
    /// stale).
    stream_ttl_ms: f64,
    last: Option<TickRecord>,
    ring: FaultRing,
    recording: Option<Recording>,
    taps: Vec<Box<dyn Tap>>,
    faults: Vec<FaultEntry>,
    dumps: Vec<PathBuf>,
    shutdown_requested: bool,
    /// When the last fault dump was written, and trips since that wrote none.
    last_dump: Option<std::time::Instant>,
    dumps_skipped: u64,
    /// Event lines said on stderr: when each kind was last said, and how many since were not
    /// (a peer's stream with a 2 ms time to live goes stale hundreds of times a second).
    said: std::collections::BTreeMap<&'static str, (std::time::Instant, u64)>,
    /// A safety trip latched the arm: streams are refused until a mode is asked for.
    latched: Option<String>,
    /// Events and answers produced by requests, handed out at the next pump.
    pending: Vec<PendingOut>,
    /// This arm's side of a pair as started, and its token at the rendezvous (kept while
    /// the side is on the line).
    teleop: Option<(TeleopReply, crate::teleop::OnTheLine)>,
    /// When the learned weights are next saved (with a store).
    persist_due: Option<std::time::Instant>,
    /// The thread that writes them, off the host (with a store).
    saver: Option<saver::Saver>,
}

enum PendingOut {
    Event(Event),
    Done {
        ticket: u64,
        session: SessionId,
        op: &'static str,
        result: Result<Reply, OpError>,
    },
}

impl Station {
    /// A station over the servo mailbox of `s`.
    pub fn new(s: StationSetup) -> Station {
        let spare = Some(Box::new(Snapshot::new(
            s.period_ns,
            Some(s.identifier.clone()),
        )));
        let adapt = s.identifier.config().adapt;
        let ring = FaultRing::new(
            (s.limits.ring_s * s.rate_hz).round().max(1.0) as usize,
            s.schema,
            s.limits.log_format.format(s.geometry),
        );
        let epoch = s.signals.owner().0;
        Station {
            sessions: Vec::new(),
            next_session: 1,
            next_ticket: 1,
            lease: None,
            lease_fallback: None,
            epoch,
            halts: s.signals.halts(),
            spare,
            held: None,
            waiting: Vec::new(),
            loads: Default::default(),
            adapt,
            stream_ttl_ms: s.limits.stream_ttl_ms,
            last: None,
            ring,
            recording: None,
            taps: Vec::new(),
            faults: Vec::new(),
            teleop: None,
            dumps: Vec::new(),
            shutdown_requested: false,
            last_dump: None,
            said: std::collections::BTreeMap::new(),
            dumps_skipped: 0,
            latched: None,
            pending: Vec::new(),
            persist_due: s.weights_store.as_ref().map(|_| {
                std::time::Instant::now()
                    + std::time::Duration::from_secs_f64(s.weights_every_s.max(0.0))
            }),
            saver: s.weights_store.as_ref().and_then(|(path, arm, serial)| {
                saver::Saver::spawn(path.clone(), arm.clone(), serial.clone(), s.wake.clone())
                    .map_err(|e| {
                        crate::errln!(
                            "omnid: warning: arm {arm}: no thread for saving the learned \
                             weights ({e}): they are kept only when the daemon ends"
                        )
                    })
                    .ok()
            }),
            s,
        }
    }

    /// The kept weights are written by `writer` instead of the store (a test's writer that
    /// blocks, to show the host serving meanwhile); without a store, nothing changes.
    #[doc(hidden)]
    pub fn set_weights_writer(&mut self, writer: WeightsWriter) {
        let Some((path, arm, serial)) = &self.s.weights_store else {
            return;
        };
        if let Some(mut old) = self.saver.take() {
            old.finish();
        }
        self.saver = saver::Saver::spawn_with(
            path.clone(),
            arm.clone(),
            serial.clone(),
            self.s.wake.clone(),
            writer,
        )
        .ok();
    }

    /// Who the arm is.
    pub fn arm(&self) -> &ArmIdentity {
        &self.s.arm
    }

    /// The servo rate, Hz.
    pub fn rate_hz(&self) -> f64 {
        self.s.rate_hz
    }

    /// The default stream time to live, ms.
    pub fn stream_ttl_ms(&self) -> f64 {
        self.s.limits.stream_ttl_ms
    }

    /// The servo's wake-up signal (a transport polls it).
    pub fn wake(&self) -> &Wake {
        &self.s.wake
    }

    /// Add a consumer of every tick and event (a recorder, a remote transport's feed).
    pub fn add_tap(&mut self, tap: Box<dyn Tap>) {
        self.taps.push(tap);
        self.publish_every();
    }

    /// A client arrived: its session number.
    pub fn open_session(&mut self, info: SessionInfo) -> SessionId {
        let id = self.next_session;
        self.next_session += 1;
        self.sessions.push(Session {
            id,
            info,
            every: 0,
            stopped_by: None,
        });
        id
    }

    /// The client left, whichever way: its lease ends and everything it set up that makes
    /// force ends with it.
    pub fn close_session(&mut self, id: SessionId) {
        self.sessions.retain(|s| s.id != id);
        if self.lease == Some(id) {
            self.end_lease();
            self.announce(Event::lease(
                None,
                format!("client {id} left; the command lease is free"),
            ));
        }
        self.publish_every();
    }

    /// The lease of a holder that stopped reading lapses (the transport decides when).
    pub fn lapse_lease(&mut self, id: SessionId, why: &str) {
        if self.lease == Some(id) {
            self.end_lease();
            self.announce(Event::lease(
                None,
                format!("client {id} {why}; its command lease lapsed"),
            ));
        }
    }

    /// Whether session `id` streams tick `seq`.
    pub fn streams(&self, id: SessionId, seq: u64) -> bool {
        self.sessions
            .iter()
            .any(|s| s.id == id && s.every > 0 && seq.is_multiple_of(s.every))
    }

    /// The lease holder, if any.
    pub fn lease_holder(&self) -> Option<SessionId> {
        self.lease
    }

    /// Ask the arm for `op` on behalf of session `id`.
    pub fn request(&mut self, id: SessionId, op: Op) -> Result<Answer, OpError> {
        let Some(k) = self.sessions.iter().position(|s| s.id == id) else {
            return Err(OpError::Failed("no such session".into()));
        };
        if op.commands() {
            let info = &self.sessions[k].info;
            if !info.control {
                return Err(OpError::ReadOnly(info.read_only_reason.clone()));
            }
            if op.is_stop() {
                return self.stop(k, op);
            }
            if op.is_hand() {
                return self.apply(k, op);
            }
            if op.is_stream() {
                if let Some(why) = &self.latched {
                    return Err(OpError::Stopped(format!(
                        "{why}: a stream does not re-arm it; ask for a mode (hold, track, free) \
                         to command it again"
                    )));
                }
                if let Some(by) = &self.sessions[k].stopped_by {
                    return Err(OpError::Stopped(format!(
                        "{by}: a stream does not re-arm it; ask for a mode (hold, track, free) \
                         to command it again"
                    )));
                }
            }
            self.take_lease(k)?;
        }
        self.apply(k, op)
    }

    /// One op, access and lease already granted: the whole interface in one table, by op
    /// family; what an op does beyond a line is its own function below.
    fn apply(&mut self, k: usize, op: Op) -> Result<Answer, OpError> {
        let id = self.sessions[k].id;
        match op {
            // The session's own: its stream, the status, the lease.
            Op::Stream { rate_hz } => self.subscribe(k, rate_hz).map(Answer::Now),
            Op::Status => Ok(self.status_later(id)),
            Op::Lease { fallback } => Ok(self.lease_fallback_to(id, fallback)),
            Op::Release => Ok(self.release(id)),
            // What the arm does: a mode, or a stream of setpoints.
            Op::Mode(m) => self.mode(k, m),
            Op::ServoJp { seq, q, ttl_ms } => {
                self.stream(&q, ttl_ms, |ttl_s| ServoCommand::ServoJp { seq, q, ttl_s })
            }
            Op::ServoJf { seq, tau, ttl_ms } => self.stream(&tau, ttl_ms, |ttl_s| {
                ServoCommand::ServoJf { seq, tau, ttl_s }
            }),
            Op::ServoCf { seq, force, ttl_ms } => self.stream(&force, ttl_ms, |ttl_s| {
                ServoCommand::ServoCf { seq, force, ttl_s }
            }),
            // The servo's settings.
            Op::Effect { slot, effect } => {
                effect_check(slot, effect.as_ref())?;
                self.command(
                    ServoCommand::Effect { slot, effect },
                    Reply::Effect { slot, effect },
                )
            }
            Op::Passivity(on) => self.command(
                ServoCommand::Passivity(on),
                Reply::Passivity { passivity: on },
            ),
            Op::Controller(kind) => self.command(
                ServoCommand::Controller(kind),
                Reply::Controller {
                    controller: kind.as_str(),
                },
            ),
            Op::Adapt(on) => {
                self.adapt = on;
                self.command(ServoCommand::Adapt(on), Reply::Adapt { adapt: on })
            }
            Op::Stylus(action) => self.stylus(action),
            // Files, opened with the session's rights.
            Op::WeightsSave(path) => self.weights_save(k, path),
            Op::WeightsLoad(path) => {
                absolute(&path)?;
                let rights = self.rights(k);
                self.weights_load(id, path, &rights)
            }
            Op::WeightsReset => self.weights_reset(id),
            Op::RecordStart(path) => {
                if let Some(p) = &path {
                    absolute(p)?;
                }
                let rights = self.rights(k);
                self.record_start(path, &rights).map(Answer::Now)
            }
            Op::RecordStop => self
                .record_stop()
                .map(|(path, rows, error)| Answer::Now(Reply::RecordStop { path, rows, error }))
                .ok_or_else(|| OpError::Failed("not recording".into())),
            // Teleoperation.
            Op::Teleop(request) => self.teleop_start(k, &request).map(Answer::Now),
            Op::TeleopStop => self.teleop_stop(),
            Op::TeleopScale(scale) => self.teleop_scale(scale),
            Op::Shutdown => unreachable!("a stop is handled by Station::stop"),
        }
    }

    /// Hand the servo `command`; once it is in the mailbox the answer is `reply`.
    fn command(&mut self, command: ServoCommand, reply: Reply) -> Result<Answer, OpError> {
        self.send(command)?;
        Ok(Answer::Now(reply))
    }

    /// Whose rights open the files session `k` names.
    fn rights(&self, k: usize) -> FileRights {
        self.sessions[k].info.files.clone()
    }

    /// `status`: answered once the servo's snapshot is back.
    fn status_later(&mut self, session: SessionId) -> Answer {
        let ticket = self.ticket();
        self.ask_snapshot(Waiting::Status { ticket, session });
        Answer::Later(ticket)
    }

    /// `lease`: the holder's stream fallback, if it names one.
    fn lease_fallback_to(&mut self, holder: SessionId, fallback: Option<Activity>) -> Answer {
        if let Some(to) = fallback {
            self.lease_fallback = Some(to);
            self.s.signals.set_fallback(to);
        }
        Answer::Now(Reply::Lease {
            holder,
            fallback: self.current_fallback().mode().as_str(),
        })
    }

    /// `release`: the lease is free, and every session hears it.
    fn release(&mut self, id: SessionId) -> Answer {
        self.end_lease();
        self.announce(Event::lease(
            None,
            format!("client {id} released the command lease"),
        ));
        Answer::Now(Reply::Done {})
    }

    /// `mode`: re-arms an arm a trip or a stop left idle.
    fn mode(&mut self, k: usize, m: ModeRequest) -> Result<Answer, OpError> {
        self.sessions[k].stopped_by = None;
        self.latched = None;
        let command = match m {
            ModeRequest::Idle => ServoCommand::Idle,
            ModeRequest::Hold => ServoCommand::Hold,
            ModeRequest::Free => ServoCommand::Free,
            ModeRequest::Track(t) => ServoCommand::Track(t),
        };
        self.command(command, Reply::Mode { mode: m.as_str() })
    }

    /// `servo_jp`, `servo_jf`, `servo_cf`: checked, then `command` with the time to live in
    /// seconds; a stream is not answered.
    fn stream(
        &mut self,
        values: &[f64; 3],
        ttl_ms: Option<f64>,
        command: impl FnOnce(f64) -> ServoCommand,
    ) -> Result<Answer, OpError> {
        let ttl_s = self.stream_check(values, ttl_ms)?;
        self.command(command(ttl_s), Reply::Silent)
    }

    /// `stylus`: only the simulator's stylus is worked from here.
    fn stylus(&mut self, action: crate::device::StylusAction) -> Result<Answer, OpError> {
        if self.s.arm.kind != "sim" {
            return Err(OpError::Invalid(format!(
                "stylus {}: only the simulator's stylus can be worked from here; this \
                 arm's device is {} (press its buttons, dock it, with your hand)",
                action.name(),
                self.s.arm.kind
            )));
        }
        self.command(
            ServoCommand::Stylus(action),
            Reply::Stylus {
                stylus: action.name(),
                button: action.button(),
            },
        )
    }

    /// `weights_save`: written once the servo's snapshot (with the weights) is back.
    fn weights_save(&mut self, k: usize, path: PathBuf) -> Result<Answer, OpError> {
        absolute(&path)?;
        let ticket = self.ticket();
        let rights = self.rights(k);
        self.ask_snapshot(Waiting::Save {
            ticket,
            session: self.sessions[k].id,
            path,
            rights,
        });
        Ok(Answer::Later(ticket))
    }

    /// `teleop_stop`: the servo leaves the pair (if this arm is in one).
    fn teleop_stop(&mut self) -> Result<Answer, OpError> {
        if self.teleop.take().is_some() {
            self.send(ServoCommand::TeleopEnd)?;
        }
        Ok(Answer::Now(Reply::Done {}))
    }

    /// `teleop_scale`: the leader's motion scale.
    fn teleop_scale(&mut self, scale: f64) -> Result<Answer, OpError> {
        let Some((side, _)) = self.teleop.as_mut() else {
            return Err(OpError::Invalid(
                "teleop_scale: this arm is not in a pair (`teleop` first)".into(),
            ));
        };
        if side.role != crate::teleop::Role::Leader {
            return Err(OpError::Invalid(format!(
                "teleop_scale: the motion scale is the leader's; ask `{}`",
                side.peer
            )));
        }
        if !(0.05..=20.0).contains(&scale) {
            return Err(OpError::Invalid(format!(
                "teleop_scale: motion_scale = {} is out of range: allowed 0.05 ..= 20",
                crate::text::number(&scale.to_string())
            )));
        }
        side.motion_scale = scale;
        self.command(
            ServoCommand::TeleopScale(scale),
            Reply::TeleopScale {
                motion_scale: scale,
            },
        )
    }

    /// `mode idle` and `shutdown`: never refused by a lease. Idle goes through the signals
    /// (it cannot be lost in a full mailbox); a stop by someone other than the holder ends
    /// the holder's lease, and the holder is told who stopped the arm.
    fn stop(&mut self, k: usize, op: Op) -> Result<Answer, OpError> {
        let me = self.sessions[k].id;
        let who = describe(me, &self.sessions[k].info);
        self.halts = self.s.signals.halt();
        self.sessions[k].stopped_by = None;
        if let Some(holder) = self.lease.filter(|h| *h != me) {
            let what = if op == Op::Shutdown {
                "shut the daemon down"
            } else {
                "stopped the arm (mode idle)"
            };
            let message = format!("{who} {what}; the command lease of client {holder} ended");
            self.end_lease();
            if let Some(h) = self.sessions.iter_mut().find(|s| s.id == holder) {
                h.stopped_by = Some(format!("the arm was stopped by {who}"));
            }
            self.announce(Event {
                holder: Some(None),
                message: Some(message),
                ..Event::named("stopped")
            });
        } else if self.lease.is_none() && op != Op::Shutdown {
            // A free lease is taken as by any command.
            self.take_lease(k)?;
        }
        if op == Op::Shutdown {
            self.shutdown_requested = true;
            self.s.stop.store(true, Ordering::SeqCst);
            return Ok(Answer::Now(Reply::Done {}));
        }
        Ok(Answer::Now(Reply::Mode { mode: "idle" }))
    }

    fn ticket(&mut self) -> u64 {
        self.next_ticket += 1;
        self.next_ticket
    }

    /// Start (every `rate / rate_hz`-th tick) or stop (0) a session's state stream.
    fn subscribe(&mut self, k: usize, rate_hz: f64) -> Result<Reply, OpError> {
        // A stream slower than one state a second would look like a dead one.
        if !(rate_hz.is_finite() && (rate_hz == 0.0 || rate_hz >= 1.0)) {
            return Err(OpError::Invalid(format!(
                "rate_hz {rate_hz}: allowed 0 (stop) or ≥ 1"
            )));
        }
        let every = if rate_hz == 0.0 {
            0
        } else {
            (self.s.rate_hz / rate_hz).round().max(1.0) as u64
        };
        self.sessions[k].every = every;
        self.publish_every();
        let actual = if every == 0 {
            0.0
        } else {
            self.s.rate_hz / every as f64
        };
        Ok(Reply::Stream {
            rate_hz: actual,
            every,
        })
    }

    /// Tell the servo which ticks to wake us for: the gcd of the sessions' intervals.
    fn publish_every(&self) {
        fn gcd(a: u64, b: u64) -> u64 {
            if b == 0 {
                a
            } else {
                gcd(b, a % b)
            }
        }
        let every = self
            .sessions
            .iter()
            .filter(|s| s.every > 0)
            .fold(0, |g, s| gcd(g, s.every));
        // A prompt tap wants every tick.
        let every = if self.taps.iter().any(|t| t.prompt()) {
            1
        } else {
            every
        };
        self.s.wake.set_every(every);
    }

    /// The fallback in force: the holder's choice, else the config's.
    fn current_fallback(&self) -> Activity {
        self.lease_fallback.unwrap_or(self.s.limits.stale_fallback)
    }

    /// The lease is free again: the owner's streams, effects and free mode end at its
    /// fallback (the servo reads it as state), then the config's fallback is back for the
    /// next holder.
    fn end_lease(&mut self) {
        if self.lease.take().is_none() {
            return;
        }
        // The pair was the holder's: the servo ends its side itself (it sees the owner go).
        self.teleop = None;
        self.epoch = self.s.signals.end_owner();
        self.lease_fallback = None;
    }

    /// `teleop`: join the pair at the rendezvous and couple the servo (the mode becomes
    /// `teleop`). Like a mode, it re-arms an arm a trip or a stop left idle.
    fn teleop_start(&mut self, k: usize, request: &TeleopRequest) -> Result<Reply, OpError> {
        let cfg = request.settings(&self.s.teleop)?;
        let role = request.role.unwrap_or(crate::teleop::Role::Leader);
        let seed = self.s.seed ^ u64::from(role == crate::teleop::Role::Follower);
        let (endpoint, line) = self
            .s
            .rendezvous
            .join(&self.s.arm.name, &request.peer, role, &cfg, seed)
            .map_err(|e| OpError::Invalid(e.to_string()))?;
        // `auto` chooses by the channel: waves to another daemon's arm (docs/TELEOP.md §5).
        let cfg = cfg.on_channel(line.channel() == "zenoh");
        let dt = self.s.period_ns as f64 * 1e-9;
        let coupling = Box::new(crate::teleop::Coupling::new(role, &cfg, endpoint, dt));
        self.sessions[k].stopped_by = None;
        self.latched = None;
        self.send(ServoCommand::Teleop(coupling))?;
        let side = TeleopReply {
            role,
            peer: request.peer.clone(),
            architecture: cfg.architecture.as_str(),
            motion_scale: cfg.motion_scale,
            force_scale: cfg.force_scale,
            operator: cfg.operator,
            passivity: cfg.passivity,
            delay_control: cfg.delay_control.as_str(),
            state: None,
            round_trip_ms: None,
            channel: line.channel(),
            network: None,
        };
        self.teleop = Some((side.clone(), line));
        Ok(Reply::Teleop { teleop: side })
    }

    /// Any command takes the lease while it is free; another session's lease refuses it.
    fn take_lease(&mut self, k: usize) -> Result<(), OpError> {
        let me = self.sessions[k].id;
        match self.lease {
            Some(holder) if holder == me => Ok(()),
            Some(holder) => {
                let who = self
                    .sessions
                    .iter()
                    .find(|s| s.id == holder)
                    .map(|s| describe(holder, &s.info))
                    .unwrap_or_else(|| format!("client {holder}"));
                Err(OpError::LeaseHeld(format!(
                    "the command lease is held by {who}; it is free when that client releases \
                     it or disconnects (`mode idle` and `shutdown` are never refused)"
                )))
            }
            None => {
                self.lease = Some(me);
                // A new owner starts with the config's fallback (its own once it asks).
                self.s.signals.set_fallback(self.s.limits.stale_fallback);
                let name = crate::text::cut(&self.sessions[k].info.name);
                self.announce(Event::lease(
                    Some(me),
                    format!("client {me} `{name}` holds the command lease"),
                ));
                Ok(())
            }
        }
    }

    /// A stream command's values; its time to live in seconds.
    fn stream_check(&mut self, values: &[f64; 3], ttl_ms: Option<f64>) -> Result<f64, OpError> {
        if let Some(j) = values.iter().position(|v| !v.is_finite()) {
            return Err(OpError::Invalid(format!(
                "value {} is not a finite number",
                j + 1
            )));
        }
        let ttl = ttl_ms.unwrap_or(self.s.limits.stream_ttl_ms);
        if !(ttl.is_finite() && ttl > 0.0 && ttl <= 10_000.0) {
            return Err(OpError::Invalid(format!(
                "ttl_ms {ttl}: allowed > 0 and ≤ 10000"
            )));
        }
        self.stream_ttl_ms = ttl;
        Ok(ttl * 1e-3)
    }

    /// Hand a command to the servo, stamped with the owner epoch.
    fn send(&mut self, command: ServoCommand) -> Result<(), OpError> {
        let stamped = self.stamp(command);
        self.s
            .commands
            .push(stamped)
            .map_err(|_| OpError::ServoBusy)
    }

    /// `command` stamped with the owner epoch and the stop count.
    fn stamp(&self, command: ServoCommand) -> Stamped {
        Stamped {
            epoch: self.epoch,
            halts: self.halts,
            command,
        }
    }

    /// Read a weights file here, off the servo thread, and hand the servo a ready identifier.
    fn weights_load(
        &mut self,
        session: SessionId,
        path: PathBuf,
        rights: &FileRights,
    ) -> Result<Answer, OpError> {
        // No stop flag: the station never waits on a client's pipe (it is refused).
        let mut loaded = files::with_rights_for("weights_load", rights, || {
            Identifier::from_weights_file(&self.s.identifier_cfg, &path, None)
        })
        .map_err(OpError::Failed)?
        .map_err(|e| OpError::Failed(files::quoting_nothing(e)))?;
        loaded.set_adapt(self.adapt);
        self.send(ServoCommand::LoadIdentifier(Box::new(loaded)))?;
        let ticket = self.ticket();
        self.loads.push_back((ticket, session, Some(path)));
        Ok(Answer::Later(ticket))
    }

    /// Hand the servo an identifier on the shipped weights; once it has swapped them in, the
    /// arm's saved weights are removed (a periodic save asked before the swap is written
    /// before it: the file does not come back with the old weights).
    fn weights_reset(&mut self, session: SessionId) -> Result<Answer, OpError> {
        let mut shipped =
            crate::identifier::store::shipped(&self.s.identifier_cfg).map_err(OpError::Failed)?;
        shipped.set_adapt(self.adapt);
        self.send(ServoCommand::LoadIdentifier(Box::new(shipped)))?;
        let ticket = self.ticket();
        self.loads.push_back((ticket, session, None));
        Ok(Answer::Later(ticket))
    }

    /// The shipped weights are in: remove the arm's saved ones, on the saver thread after the
    /// saves asked before (the answer comes when it is done), or here without one.
    fn weights_reset_done(&mut self, ticket: u64, session: SessionId) {
        if let Some(saver) = &mut self.saver {
            saver.ask(saver::Job::Remove { ticket, session });
            return;
        }
        let result = match &self.s.weights_store {
            Some((path, _, _)) => saver::remove_kept(path),
            None => Ok(false),
        };
        self.weights_reset_answer(ticket, session, result);
    }

    /// The reset's answer once the arm's file is removed (`Ok(true)`), was not there, or could
    /// not be removed.
    fn weights_reset_answer(
        &mut self,
        ticket: u64,
        session: SessionId,
        removed: Result<bool, String>,
    ) {
        let weights = crate::identifier::store::SHIPPED_WEIGHTS_NAME;
        let path = self.s.weights_store.as_ref().map(|(p, _, _)| p.clone());
        let result = match (removed, path) {
            (Ok(true), Some(path)) => Ok(Reply::WeightsReset {
                weights,
                removed: Some(path),
            }),
            (Ok(_), _) => Ok(Reply::WeightsReset {
                weights,
                removed: None,
            }),
            (Err(e), path) => Err(OpError::Failed(format!(
                "the identifier is back on the shipped weights, but {} could not be removed: \
                 {e} (the next start would load it)",
                path.map(|p| p.display().to_string()).unwrap_or_default()
            ))),
        };
        self.pending.push(PendingOut::Done {
            ticket,
            session,
            op: "weights_reset",
            result,
        });
    }

    fn ask_snapshot(&mut self, w: Waiting) {
        self.waiting.push(w);
        if let Some(spare) = self.spare.take() {
            let stamped = self.stamp(ServoCommand::Snapshot(spare));
            if let Err(stamped) = self.s.commands.push_or_return(stamped) {
                if let ServoCommand::Snapshot(b) = stamped.command {
                    self.spare = Some(b);
                }
            }
        }
    }

    fn record_start(
        &mut self,
        path: Option<PathBuf>,
        rights: &FileRights,
    ) -> Result<Reply, OpError> {
        if let Some(r) = &self.recording {
            return Err(OpError::Failed(format!(
                "already recording to {}",
                r.path().display()
            )));
        }
        let failed = |e: LogError| OpError::Failed(e.to_string());
        let log = match path {
            // A client's path: opened with its rights, and only ever a new file.
            Some(p) => files::with_rights_for("record_start", rights, || LogFile::create_new(&p))
                .map_err(OpError::Failed)?
                .map_err(failed)?,
            None => {
                let dir = self.s.state_dir.join("recordings");
                let stem = format!("omnid-{}-{}", self.s.arm.file_stem(), utc_stamp());
                let ext = self.s.limits.log_format.format(self.s.geometry).extension();
                LogFile::create_unique(&dir, &stem, ext).map_err(failed)?
            }
        };
        let format = LogFormat::for_path(&log.path, self.s.geometry);
        let r = Recording::start(log, self.s.schema, format).map_err(failed)?;
        let path = r.path().to_path_buf();
        self.recording = Some(r);
        Ok(Reply::Path { path })
    }

    /// End the recording: (path, rows written, error).
    fn record_stop(&mut self) -> Option<(PathBuf, u64, Option<String>)> {
        self.recording.take().map(Recording::stop)
    }

    /// Take what the servo has sent since the last call, update the taps, and hand the
    /// transport each state some session streams, each event and each late answer. True
    /// once the servo has ended.
    pub fn pump(&mut self, out: &mut dyn FnMut(Output<'_>)) -> bool {
        let ended = loop {
            match self.s.records.try_recv() {
                Ok(r) => self.on_record(r, out),
                Err(TryRecvError::Empty) => break false,
                Err(TryRecvError::Disconnected) => break true,
            }
        };
        while let Some(reply) = self.s.replies.pop() {
            match reply {
                ServoReply::Snapshot(snap) => self.held = Some(snap),
                ServoReply::Identifier(_old) => match self.loads.pop_front() {
                    Some((ticket, session, Some(path))) => {
                        self.pending.push(PendingOut::Done {
                            ticket,
                            session,
                            op: "weights_load",
                            result: Ok(Reply::Path { path: path.clone() }),
                        });
                        self.announce(Event {
                            message: Some(format!("weights loaded from {}", path.display())),
                            ..Event::named("weights")
                        });
                    }
                    Some((ticket, session, None)) => {
                        // A snapshot still held was taken before the swap (replies come in
                        // the servo's order): its weights are the forgotten ones, not saved.
                        if self.held.is_some() {
                            self.waiting.retain(|w| !matches!(w, Waiting::Persist));
                        }
                        self.weights_reset_done(ticket, session);
                        self.announce(Event {
                            message: Some(format!(
                                "weights reset to the shipped ones ({})",
                                crate::identifier::store::SHIPPED_WEIGHTS_NAME
                            )),
                            ..Event::named("weights")
                        });
                    }
                    None => {}
                },
                // A coupling that ended: freed here, off the servo thread.
                ServoReply::Teleop(_old) => {}
            }
        }
        // A status names the mode of the tick its snapshot was taken in, so it shows every
        // command sent before it (the record comes after the reply; its emit wakes the host).
        if let Some(snap) = self.held.take() {
            if ended || self.last.as_ref().is_some_and(|r| r.live.seq >= snap.seq) {
                self.answer_snapshot(snap);
            } else {
                self.held = Some(snap);
            }
        }
        if let Some(due) = self.persist_due {
            let now = std::time::Instant::now();
            if now >= due && !ended {
                self.persist_due =
                    Some(now + std::time::Duration::from_secs_f64(self.s.weights_every_s.max(0.0)));
                self.ask_snapshot(Waiting::Persist);
            }
        }
        if let Some(saver) = &mut self.saver {
            saver.hand_on();
        }
        while let Some(r) = self.saver.as_mut().and_then(|s| s.removed()) {
            self.weights_reset_answer(r.ticket, r.session, r.result);
        }
        self.flush_pending(out);
        ended
    }

    fn flush_pending(&mut self, out: &mut dyn FnMut(Output<'_>)) {
        for p in std::mem::take(&mut self.pending) {
            match p {
                PendingOut::Event(e) => {
                    for tap in &mut self.taps {
                        tap.on_event(&e);
                    }
                    out(Output::Event(&e))
                }
                PendingOut::Done {
                    ticket,
                    session,
                    op,
                    result,
                } => out(Output::Done {
                    ticket,
                    session,
                    op,
                    result,
                }),
            }
        }
    }

    fn announce(&mut self, e: Event) {
        self.pending.push(PendingOut::Event(e));
    }

    fn on_record(&mut self, r: TickRecord, out: &mut dyn FnMut(Output<'_>)) {
        self.ring.push(r);
        if let Some(rec) = &mut self.recording {
            rec.push(r);
            if let Some(why) = rec.newly_failed() {
                let message = format!(
                    "the recording to {} stopped taking rows ({why}); what follows is lost \
                     until record_stop, which says how many rows reached the file",
                    rec.path().display()
                );
                crate::errln!("omnid serve: {}: {message}", self.s.arm.name);
                self.announce(Event {
                    seq: Some(r.live.seq),
                    message: Some(message),
                    ..Event::named("recording-failed")
                });
            }
        }
        for tap in &mut self.taps {
            tap.on_tick(&r);
        }
        // Changes are against the state the servo started in (idle, the configured law), so
        // one applied at the very first tick is announced too.
        let (mode_before, controller_before, flags_before) = match self.last.replace(r) {
            Some(b) => (b.mode, b.live.controller, b.flags),
            None => (Mode::Idle, Some(self.s.controller), 0),
        };
        let ident_fault = crate::telemetry::record::flags::IDENT_FAULT;
        if r.flags & ident_fault != 0 && flags_before & ident_fault == 0 {
            let message = "the identifier stopped on a non-finite value: it no longer learns, \
                           and NNIDC runs on its PD fallback (load weights or restart to resume)"
                .to_string();
            crate::errln!("omnid serve: {}: {message}", self.s.arm.name);
            self.announce(Event {
                seq: Some(r.live.seq),
                t: Some(r.t),
                message: Some(message),
                ..Event::named("identifier-fault")
            });
        }
        if let Some(ev) = r.live.event {
            self.on_servo_event(&r, ev);
        }
        if mode_before != r.mode && !(mode_before == Mode::Blend && r.mode == Mode::Track) {
            self.announce(Event {
                mode: Some(r.mode.as_str()),
                seq: Some(r.live.seq),
                t: Some(r.t),
                ..Event::named("mode")
            });
        }
        if controller_before != r.live.controller {
            self.announce(Event {
                controller: Some(r.live.controller.map(|k| k.as_str())),
                seq: Some(r.live.seq),
                ..Event::named("controller")
            });
        }
        // Events before the state they came with, as a client reads them.
        self.flush_pending(out);
        let seq = r.live.seq;
        if self
            .sessions
            .iter()
            .any(|s| s.every > 0 && seq.is_multiple_of(s.every))
        {
            out(Output::State(&view::arm_state(&r, &self.s.geometry)));
        }
    }

    fn on_servo_event(&mut self, r: &TickRecord, ev: ServoEvent) {
        let ttl = self.stream_ttl_ms;
        let (name, message) = match ev {
            ServoEvent::StreamStale { fallback } => (
                "stream-stale",
                format!(
                    "no servo_jp/servo_jf/servo_cf command within its time to live ({ttl} ms): \
                     now {}",
                    fallback.as_str()
                ),
            ),
            ServoEvent::StreamEnded { fallback } => (
                "stream-ended",
                format!(
                    "the stream's owner left or released the lease: now {}",
                    fallback.as_str()
                ),
            ),
            ServoEvent::Limit { flags: bits } => {
                use crate::telemetry::record::flags;
                let mut what = Vec::new();
                if bits & flags::FORCE_LIMIT != 0 {
                    what.push("the tip force is held to the force limit (haptics.max_force_n, or the continuous force after a sustained push)");
                }
                if bits & flags::THERMAL != 0 {
                    what.push("a hot motor is held to its continuous torque (safety.continuous_torque_nm)");
                }
                if bits & flags::EFFECT_SKIPPED != 0 {
                    what.push("an effect whose force is not finite here is left out");
                }
                ("limit", what.join("; "))
            }
            ServoEvent::SafetyTrip(trip) => {
                let message = format!("safety: {trip}; zero torque, amplifiers off, mode idle");
                self.faults.push(FaultEntry {
                    tick: r.live.seq,
                    t: r.t,
                    class: "safety-fault".into(),
                    message: message.clone(),
                });
                self.latched = Some(format!("the arm tripped the safety layer ({trip})"));
                self.dump_safety();
                ("safety-trip", message)
            }
        };
        self.say(name, &message);
        self.announce(Event {
            mode: Some(r.mode.as_str()),
            seq: Some(r.live.seq),
            t: Some(r.t),
            message: Some(message),
            ..Event::named(name)
        });
    }

    /// An event's line on stderr: a safety trip always, any other kind at most once a second,
    /// saying how many of its kind were left unsaid since (every client still gets each
    /// event).
    fn say(&mut self, name: &'static str, message: &str) {
        let now = std::time::Instant::now();
        let arm = &self.s.arm.name;
        match self.said.get_mut(name) {
            Some((last, held)) if name != "safety-trip" && now - *last < SAY_EVERY => {
                *held += 1;
            }
            Some((last, held)) => {
                let more = match *held {
                    0 => String::new(),
                    n => format!(
                        " ({n} more since the last said, {:.1} s ago)",
                        (now - *last).as_secs_f64()
                    ),
                };
                crate::errln!("omnid serve: {arm}: {message}{more}");
                (*last, *held) = (now, 0);
            }
            None => {
                crate::errln!("omnid serve: {arm}: {message}");
                self.said.insert(name, (now, 0));
            }
        }
    }

    /// A trip's dump: at most one every `serve.dump_interval_s` (the others are counted), and
    /// the arm's oldest dumps removed past `serve.max_dumps`.
    fn dump_safety(&mut self) {
        let now = std::time::Instant::now();
        let interval = std::time::Duration::from_secs_f64(self.s.limits.dump_interval_s);
        if self.last_dump.is_some_and(|t| now - t < interval) {
            self.dumps_skipped += 1;
            return;
        }
        self.last_dump = Some(now);
        let arm = self.s.arm.file_stem().to_string();
        let dump = self.ring.dump(&self.s.state_dir, &arm, "safety");
        if dump.is_some() {
            taps::prune_dumps(&self.s.state_dir, &arm, self.s.limits.max_dumps);
        }
        self.dumps.extend(dump);
    }

    fn status(&self, snap: &Snapshot) -> Status {
        let last = self.last.as_ref();
        let mut summary = RunSummary::from_results(
            &SummaryLabels {
                device: self.s.arm.kind,
                controller: last
                    .and_then(|r| r.live.controller)
                    .unwrap_or(self.s.controller)
                    .as_str(),
                trajectory: "serve".into(),
                weights: self.s.weights_label.clone(),
                seed: self.s.seed,
                fast: false,
            },
            &snap.stats,
            &snap.timing,
            IdentifierState {
                adapt: snap.adapt,
                fault: snap.ident_fault,
            },
            snap.telemetry_dropped,
            snap.missed_packets,
        );
        summary.faults = self.faults.clone();
        summary.realtime = self.s.realtime.get().cloned();
        let lease = self.lease.and_then(|h| {
            self.sessions
                .iter()
                .find(|s| s.id == h)
                .map(|s| LeaseHolder {
                    client: h,
                    name: s.info.name.clone(),
                    pid: s.info.pid,
                    uid: s.info.uid,
                })
        });
        Status {
            summary,
            arm: self.s.arm.name.clone(),
            mode: last.map(|r| r.mode.as_str()),
            lease,
            clients: self.sessions.len(),
            recording: self.recording.as_ref().map(|r| RecordingStatus {
                path: r.path().to_path_buf(),
                dropped: r.dropped(),
            }),
            heat: snap.heat,
            teleop: self.teleop.as_ref().map(|(side, line)| TeleopReply {
                state: last.and_then(|r| r.live.teleop),
                round_trip_ms: last.map(|r| r.live.teleop_round_trip_s * 1e3),
                network: line.network().map(Box::new),
                ..side.clone()
            }),
        }
    }

    fn answer_snapshot(&mut self, snap: Box<Snapshot>) {
        let waiting = std::mem::take(&mut self.waiting);
        let status = Box::new(self.status(&snap));
        for w in waiting {
            let done = match w {
                Waiting::Persist => {
                    self.persist(&snap);
                    continue;
                }
                Waiting::Status { ticket, session } => PendingOut::Done {
                    ticket,
                    session,
                    op: "status",
                    result: Ok(Reply::Status {
                        status: status.clone(),
                    }),
                },
                // Written here, on the host, unlike the periodic save (docs/DESIGN.md §4.7):
                // its answer says the file is there, so it comes once the file is written.
                Waiting::Save {
                    ticket,
                    session,
                    path,
                    rights,
                } => {
                    let result = match (&snap.weights, snap.weights_copied) {
                        (Some(w), true) => files::with_rights_for("weights_save", &rights, || {
                            crate::identifier::weights::save(w, &path)
                        })
                        .map_err(OpError::Failed)
                        .and_then(|saved| {
                            saved
                                .map(|()| Reply::Path { path })
                                .map_err(|e| OpError::Failed(e.to_string()))
                        }),
                        _ => Err(OpError::Failed(
                            "the servo has no identifier of the configured sizes".into(),
                        )),
                    };
                    PendingOut::Done {
                        ticket,
                        session,
                        op: "weights_save",
                        result,
                    }
                }
            };
            self.pending.push(done);
        }
        self.spare = Some(snap);
    }

    /// Save what the arm has learned (a healthy identifier only): a copy goes to the saver
    /// thread, which writes it whole and says a failure (the host does not wait on the disk).
    fn persist(&mut self, snap: &Snapshot) {
        let (Some(saver), Some(w), true, None) = (
            &mut self.saver,
            &snap.weights,
            snap.weights_copied,
            snap.ident_fault,
        ) else {
            return;
        };
        saver.ask(saver::Job::Save(Box::new(w.clone())));
    }

    /// The servo has ended: finish the recording and the taps, hand back the report.
    pub fn finish(mut self) -> StationReport {
        // The saves asked for are written (and a reset's removal done) before the daemon's
        // last save, which comes after this.
        if let Some(saver) = &mut self.saver {
            saver.finish();
        }
        let recording_error = self.record_stop().and_then(|(_, _, e)| e);
        for tap in &mut self.taps {
            tap.finish();
        }
        StationReport {
            shutdown_requested: self.shutdown_requested,
            faults: self.faults,
            dumps: self.dumps,
            ring: self.ring,
            recording_error,
        }
    }
}

/// A session as a lease message names it.
/// A path a client names must be absolute: the daemon's working directory is not the client's.
fn absolute(path: &std::path::Path) -> Result<(), OpError> {
    if path.is_absolute() {
        Ok(())
    } else {
        Err(OpError::Invalid(format!(
            "path `{}` is relative: give an absolute path (the daemon's working directory is not \
             yours)",
            crate::text::cut(&path.to_string_lossy())
        )))
    }
}

fn describe(id: SessionId, info: &SessionInfo) -> String {
    format!(
        "client {id} `{}` (pid {}, uid {})",
        crate::text::cut(&info.name),
        info.pid,
        info.uid
    )
}

/// Check an effect and its slot here, so the servo gets only valid ones.
fn effect_check(slot: usize, effect: Option<&crate::haptics::Effect>) -> Result<(), OpError> {
    if slot >= crate::haptics::MAX_EFFECTS {
        let max = crate::haptics::MAX_EFFECTS - 1;
        return Err(OpError::Invalid(format!(
            "slot {slot}: allowed 0 ..= {max}"
        )));
    }
    if let Some(Err(why)) = effect.map(|e| e.validate("effect.")) {
        return Err(OpError::Invalid(why));
    }
    Ok(())
}

pub(crate) fn utc_stamp() -> String {
    crate::telemetry::utc_stamp(std::time::SystemTime::now())
}
