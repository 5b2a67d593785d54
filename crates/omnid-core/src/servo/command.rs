//! What other threads may ask of the servo loop (`omnid serve`), and what it hands back. The
//! commands are plain values moved through a bounded channel that the loop drains once per
//! tick with `try_recv`; anything that needs memory (an identifier to swap in, a snapshot to
//! fill) arrives pre-allocated in a `Box` and goes back the same way, so the loop never
//! allocates or frees.

use super::timing::TickTiming;
use crate::control::{ControllerKind, Trajectory};
use crate::handoff::Bell;
use crate::identifier::{Fault, Identifier};
use crate::servo::summary::RunStats;
use crate::telemetry::record::Mode;
use std::sync::atomic::{AtomicU64, Ordering};

/// What the loop does with the arm (the mode a client asks for; `Track` shows as `blend`
/// then `track` in the log).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activity {
    /// Amplifiers off, zero torque, the state still streaming.
    Idle,
    /// Hold the pose where the mode began, with the active controller.
    Hold,
    /// Follow a built-in trajectory, blended in from the pose where the mode began.
    Track,
    /// Only the active controller's compensation (gravity, friction): the arm moves freely.
    Free,
    /// Follow a client's joint position setpoints (stream with a time to live).
    ServoJp,
    /// A client's joint torques on top of the compensation (stream with a time to live).
    ServoJf,
    /// A client's tip force (N, OpenHaptics frame) on top of the compensation, as τ = Jᵀ F
    /// (stream with a time to live).
    ServoCf,
    /// One side of a teleoperation pair: the coupling's tip force on top of the compensation
    /// (docs/TELEOP.md).
    Teleop,
}

impl Activity {
    /// Modes that a client must keep feeding.
    pub fn is_stream(self) -> bool {
        matches!(
            self,
            Activity::ServoJp | Activity::ServoJf | Activity::ServoCf
        )
    }

    /// Whether the identifier may learn in this mode: only where the torque it sees is all
    /// that moves the arm. Amplifiers off, the arm rests on something; in the haptic modes
    /// (free, servo_cf) a hand moves it with a force no sensor measures, and learning from
    /// that teaches the model the hand (docs/HAPTICS.md §3).
    pub fn learns(self) -> bool {
        !matches!(
            self,
            Activity::Idle | Activity::Free | Activity::ServoCf | Activity::Teleop
        )
    }

    /// The mode this activity is logged as.
    pub fn mode(self) -> Mode {
        match self {
            Activity::Idle => Mode::Idle,
            Activity::Hold => Mode::Hold,
            Activity::Track => Mode::Track,
            Activity::Free => Mode::Free,
            Activity::ServoJp => Mode::ServoJp,
            Activity::ServoJf => Mode::ServoJf,
            Activity::ServoCf => Mode::ServoCf,
            Activity::Teleop => Mode::Teleop,
        }
    }
}

/// A command as the station sent it: stamped with the owner epoch it was issued under and the
/// stop requests issued before it ([`ArmSignals`]), so a command of an owner who has since
/// left is never applied, and a stop takes effect in its place among the commands.
pub struct Stamped {
    /// The owner epoch when the station sent it.
    pub epoch: u64,
    /// Stop requests issued before it.
    pub halts: u64,
    /// The command.
    pub command: ServoCommand,
}

/// A request for the loop, applied at the first tick after it arrives.
pub enum ServoCommand {
    /// Amplifiers off: the arm rests.
    Idle,
    /// Hold where the arm is.
    Hold,
    /// Follow a trajectory.
    Track(Trajectory),
    /// Free mode: only the model's compensation (gravity, friction).
    Free,
    /// Joint position setpoint (rad), valid for `ttl_s` seconds of device time.
    ServoJp {
        /// The client's sequence number (later wins).
        seq: u64,
        /// The setpoint, rad.
        q: [f64; 3],
        /// How long it stays valid, s of device time.
        ttl_s: f64,
    },
    /// Joint torque (N·m) added to the compensation, valid for `ttl_s`.
    ServoJf {
        /// The client's sequence number (later wins).
        seq: u64,
        /// The torque, N·m.
        tau: [f64; 3],
        /// How long it stays valid, s of device time.
        ttl_s: f64,
    },
    /// Tip force (N, OpenHaptics frame) added to the compensation as Jᵀ F, valid for
    /// `ttl_s`; its norm is clamped to `[haptics] max_force_n` in the servo.
    ServoCf {
        /// The client's sequence number (later wins).
        seq: u64,
        /// The force, N.
        force: [f64; 3],
        /// How long it stays valid, s of device time.
        ttl_s: f64,
    },
    /// Put an effect in a slot of the scene (None removes it), faded in.
    Effect {
        /// The scene's slot.
        slot: usize,
        /// The effect (None removes the slot's).
        effect: Option<crate::haptics::Effect>,
    },
    /// Turn the passivity controller on or off.
    Passivity(bool),
    /// Switch the control law (bumpless).
    Controller(ControllerKind),
    /// Resume (`true`) or freeze (`false`) online adaptation.
    Adapt(bool),
    /// The simulator's hand acts on the stylus (press a button, dock, …): the station checked
    /// that the device is the simulator. Makes no force of a client's: any epoch applies it.
    Stylus(crate::device::StylusAction),
    /// Couple this arm as one side of a teleoperation pair (the arm enters `teleop`); a
    /// coupling already there comes back as [`ServoReply::Teleop`].
    Teleop(Box<crate::teleop::Coupling>),
    /// Uncouple: the coupling comes back as [`ServoReply::Teleop`], the arm holds.
    TeleopEnd,
    /// Change the coupling's motion scale now (no jump).
    TeleopScale(f64),
    /// Swap this identifier in; the old one comes back as [`ServoReply::Identifier`].
    LoadIdentifier(Box<Identifier>),
    /// Fill this in and send it back as [`ServoReply::Snapshot`].
    Snapshot(Box<Snapshot>),
}

/// What the loop hands back (never dropped on the servo thread).
pub enum ServoReply {
    /// The identifier that a `LoadIdentifier` replaced.
    Identifier(Box<Identifier>),
    /// The snapshot a `Snapshot` command asked for, filled in.
    Snapshot(Box<Snapshot>),
    /// A coupling that was replaced or ended.
    Teleop(Box<crate::teleop::Coupling>),
}

/// The loop's results so far, copied into memory the caller provided.
pub struct Snapshot {
    /// The tick it was filled in: that tick's record is the first to carry every command
    /// sent before it (the station answers with both).
    pub seq: u64,
    /// The run's statistics so far.
    pub stats: RunStats,
    /// Tick timing so far.
    pub timing: TickTiming,
    /// Receives the identifier's current weights (same network sizes) when `Some`.
    pub weights: Option<Identifier>,
    /// The weights were copied (false: no identifier, or other sizes).
    pub weights_copied: bool,
    /// Whether the identifier is learning.
    pub adapt: bool,
    /// Why the identifier stopped, if it did.
    pub ident_fault: Option<Fault>,
    /// Telemetry records dropped (the channel was full).
    pub telemetry_dropped: u64,
    /// Device packets that did not come in time.
    pub missed_packets: u64,
    /// Each motor's estimated winding temperature rise, °C.
    pub heat: [f64; 3],
}

impl Snapshot {
    /// Storage shaped like the loop's own (`period_ns` as the servo's).
    pub fn new(period_ns: u64, weights: Option<Identifier>) -> Self {
        Snapshot {
            seq: 0,
            stats: RunStats::default(),
            timing: TickTiming::new(period_ns),
            weights,
            weights_copied: false,
            adapt: false,
            ident_fault: None,
            telemetry_dropped: 0,
            missed_packets: 0,
            heat: [0.0; 3],
        }
    }
}

pub use crate::telemetry::record::ServoEvent;

/// Wakes the thread that serves clients when a tick's record is wanted at once: one
/// non-blocking `write` to an eventfd (a [`Bell`]: no lock, no allocation), so a client can
/// answer within the tick. Only ticks some client streams (every `every`-th), replies and
/// events wake it; otherwise it drains the records on its own schedule and the loop makes no
/// syscall.
#[derive(Debug)]
pub struct Wake {
    bell: Bell,
    /// The greatest common divisor of the streaming clients' sample intervals (0: none).
    every: AtomicU64,
}

impl Wake {
    /// A fresh eventfd; fails only when the process or system is out of descriptors.
    pub fn new() -> std::io::Result<Wake> {
        Ok(Wake {
            bell: Bell::new()?,
            every: AtomicU64::new(0),
        })
    }

    /// Ticks whose number is a multiple of `every` are wanted at once (0: none is).
    pub fn set_every(&self, every: u64) {
        self.every.store(every, Ordering::Relaxed);
    }

    /// Signal if tick `seq` is wanted at once.
    pub fn tick(&self, seq: u64) {
        let every = self.every.load(Ordering::Relaxed);
        if every != 0 && seq.is_multiple_of(every) {
            self.notify();
        }
    }

    /// Signal (never blocks).
    pub fn notify(&self) {
        self.bell.ring();
    }

    /// Reset the counter (the reader's side, after waking).
    pub fn clear(&self) {
        self.bell.clear();
    }

    /// The end to poll for readability.
    pub fn fd(&self) -> std::os::fd::BorrowedFd<'_> {
        self.bell.fd()
    }
}

/// What the servo must never miss, held as state it reads every tick rather than as messages
/// that a full mailbox could drop: who owns the arm's force, where its streams fall back to,
/// and stop requests.
#[derive(Debug, Default)]
pub struct ArmSignals {
    /// Owner epoch (bits 8..) and the owner's stream fallback (bits 0..8, [`Activity`] code).
    /// The epoch grows when the lease ends, whichever way: the servo then ends everything the
    /// owner set up that makes force (streams, effects, free) at the fallback.
    owner: AtomicU64,
    /// Stop requests (`mode idle`, the emergency stop): each one leaves the arm idle.
    halts: AtomicU64,
}

impl ArmSignals {
    /// Signals with this initial stream fallback.
    pub fn new(fallback: Activity) -> ArmSignals {
        let s = ArmSignals::default();
        s.owner.store(code(fallback), Ordering::SeqCst);
        s
    }

    /// The owner epoch and the fallback in force.
    pub fn owner(&self) -> (u64, Activity) {
        let v = self.owner.load(Ordering::Acquire);
        (v >> 8, activity(v & 0xFF))
    }

    /// The owner left (lease released, client gone, lease lapsed): a new epoch, keeping the
    /// leaving owner's fallback for what it leaves behind. Returns the new epoch.
    pub fn end_owner(&self) -> u64 {
        let (epoch, fallback) = self.owner();
        self.owner
            .store(((epoch + 1) << 8) | code(fallback), Ordering::Release);
        epoch + 1
    }

    /// Where streams fall back from now on (same epoch).
    pub fn set_fallback(&self, fallback: Activity) {
        let (epoch, _) = self.owner();
        self.owner
            .store((epoch << 8) | code(fallback), Ordering::Release);
    }

    /// Ask for idle; never lost, never refused by a full mailbox. Returns the stop requests
    /// issued so far.
    pub fn halt(&self) -> u64 {
        self.halts.fetch_add(1, Ordering::AcqRel) + 1
    }

    /// Stop requests so far.
    pub fn halts(&self) -> u64 {
        self.halts.load(Ordering::Acquire)
    }
}

fn code(a: Activity) -> u64 {
    match a {
        Activity::Idle => 0,
        Activity::Hold => 1,
        Activity::Free => 2,
        // Only the three above are fallbacks; anything else is held as hold.
        _ => 1,
    }
}

fn activity(code: u64) -> Activity {
    match code {
        0 => Activity::Idle,
        2 => Activity::Free,
        _ => Activity::Hold,
    }
}

/// The loop's side of `omnid serve`'s connection.
pub struct ServoLink {
    /// Commands for the servo, stamped (a `handoff` queue: the servo never waits for the
    /// station's thread, whatever its priority; docs/DESIGN.md §4.7).
    pub commands: crate::handoff::Outlet<Stamped>,
    /// What the servo hands back.
    pub replies: crate::handoff::Inlet<ServoReply>,
    /// Wakes the station's host when a reply is sent.
    pub wake: std::sync::Arc<Wake>,
    /// Ownership, fallback and stop requests, read every tick.
    pub signals: std::sync::Arc<ArmSignals>,
}

/// Most commands taken in one tick (the rest wait for the next).
pub const MAX_COMMANDS_PER_TICK: usize = 64;
