//! omnid: a hardware I/O daemon for the Phantom Omni (SensAble Phantom Omni / Geomagic Touch)
//! haptic device, with the simulator, log replay, the identifier and the tools around them.
//!
//! # Data flow
//!
//! Once per device packet (1 kHz), the [`Servo`] runs one tick:
//!
//! ```text
//!  Device ──state packet──▶ decode ──▶ estimate (Kalman) ──▶ control (PD, CT, NNIDC, …)
//!    ▲                                                              │
//!    └──────── encode ◀── safety (walls, ramp, heat, clamp) ◀───────┘
//!                   │
//!                   └──▶ telemetry: the CSV log and the run summary
//! ```
//!
//! One module per stage: [`device`] (packets and the [`Device`] trait), [`estimate`],
//! [`control`], [`servo`] (the loop and its safety layer), [`telemetry`]; [`omni`] holds the
//! geometry and physics shared by the simulator and model-based control, [`identifier`] the
//! online model identifier. Everything the loop touches is allocated before its first tick.
//!
//! # Entry points
//!
//! - A run (`omnid run`): fill a [`Config`] and [`RunOptions`], call [`execute`], read the
//!   [`RunOutcome`] (its [`RunSummary`] and [`EndReason`]).
//! - The daemon (`omnid serve`): [`cmd::serve::serve`] with [`ServeOptions`]; lab software talks to
//!   it through [`Client`] (the protocol is in `docs/PROTOCOL.md`).
//! - A loop of your own: build a [`Servo`] over any [`Device`] — [`SimOmni`] (the simulated
//!   arm), [`ReplayDevice`] (a recorded log) or, for fault drills, [`FaultyDevice`] wrapping
//!   any of them with [`Fault`]s.
//! - Off the loop: [`plot`] draws figures from a log, [`convert`] turns other recordings into
//!   omnid logs, [`experiment`] reproduces the paper's experiments, [`cmd::identify`] pretunes the
//!   identifier from a log.
//! - Around them: [`input`] reads files from outside (no wait beyond Ctrl-C, no unbounded
//!   row), [`output`] writes files without leaving half-written ones, [`progress`] draws the
//!   progress bars of long commands.
//!
//! Terminal text goes through [`out!`], [`outln!`] and [`errln!`], which never panic on a
//! closed pipe.
//!
//! # Crates
//!
//! The realtime core (everything up to the arm's station, and `run`/`identify`) is the
//! `omnid-core` crate, which links neither zenoh nor the Foxglove SDK nor plotters; this crate
//! adds the transports, `omnid serve`, [`plot`] and [`experiment`], and re-exports the core's
//! modules under the same paths (docs/ARCHITECTURE.md, Crates).

#![warn(missing_docs)]

pub use omnid_core::{
    arm, clock, config, control, convert, device, diag, estimate, handoff, haptics, human,
    identifier, input, omni, output, progress, ros2, servo, station, telemetry, teleop, text,
    toml_place,
};
pub use omnid_core::{errln, out, outln};

pub mod cmd;
pub mod experiment;
pub mod plot;
pub mod transport;

pub use cmd::run::{execute, DeviceSpec, RunError, RunOptions, RunOutcome};
pub use cmd::serve::{ArmOutcome, ServeOptions, ServeOutcome};
pub use config::{Config, ConfigError};
pub use control::{ControllerKind, Trajectory};
pub use device::inject::{Fault, FaultyDevice};
pub use device::replay::ReplayDevice;
pub use device::sim::SimOmni;
pub use device::{Device, DeviceError, RawSample};
pub use omni::{Geometry, Joint3};
pub use servo::summary::RunSummary;
pub use servo::{EndReason, Servo};
pub use transport::client::{Client, ClientError, Message};
