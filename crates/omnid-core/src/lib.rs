//! omnid-core: the realtime core of omnid, the Phantom Omni (SensAble Phantom Omni / Geomagic
//! Touch) daemon — the device paths, the simulator and log replay, the servo loop, the
//! estimator, the identifier, the controllers, haptics, teleoperation's coupling, the arm's
//! station, telemetry, and the commands that need no network (`omnid run`, `omnid identify`).
//! The transports (Unix socket, zenoh, the live view), `omnid serve` and the lab tools that
//! draw or compare (`plot`, `experiment`) are the `omnid` crate's; it re-exports every module
//! here under the same path (docs/ARCHITECTURE.md, Crates).
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
//! - A loop of your own: build a [`Servo`] over any [`Device`] — [`SimOmni`] (the simulated
//!   arm), [`ReplayDevice`] (a recorded log) or, for fault drills, [`FaultyDevice`] wrapping
//!   any of them with [`Fault`]s.
//! - An arm served to clients: [`station`] (what the transports of the `omnid` crate drive).
//! - Off the loop: [`convert`] turns other recordings into omnid logs, [`cmd::identify`]
//!   pretunes the identifier from a log.
//! - Around them: [`input`] reads files from outside (no wait beyond Ctrl-C, no unbounded
//!   row), [`output`] writes files without leaving half-written ones, [`progress`] draws the
//!   progress bars of long commands.
//!
//! Terminal text goes through [`out!`], [`outln!`] and [`errln!`], which never panic on a
//! closed pipe.

#![warn(missing_docs)]

/// Terminal output that never panics. `print!` and `eprintln!` panic when the stream is a
/// closed pipe or a hung-up terminal, which would lose the exit code, the summary JSON and the
/// fault path after a run; these lose only the text (README, Exit codes). A failure other than
/// a closed pipe is kept ([`diag::stdout_failed`]): the CLI then exits non-zero.
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let mut out = std::io::stdout().lock();
        if let Err(e) = write!(out, $($arg)*).and_then(|()| out.flush()) {
            $crate::diag::stdout_error(e);
        }
    }};
}

/// `println!` that never panics (see [`out!`]).
#[macro_export]
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let mut out = std::io::stdout().lock();
        if let Err(e) = writeln!(out, $($arg)*).and_then(|()| out.flush()) {
            $crate::diag::stdout_error(e);
        }
    }};
}

/// `eprintln!` that never panics (see [`out!`]) and never blocks: the line goes to stderr
/// through its own thread ([`diag`]).
#[macro_export]
macro_rules! errln {
    ($($arg:tt)*) => {{
        let mut line = format!($($arg)*);
        line.push('\n');
        $crate::diag::line(line);
    }};
}

pub mod arm;
pub mod clock;
pub mod cmd;
pub mod config;
pub(crate) mod config_check;
pub mod control;
pub mod convert;
pub mod device;
pub mod diag;
pub mod estimate;
pub(crate) mod fast_tanh;
pub mod handoff;
pub mod haptics;
pub mod human;
pub mod identifier;
pub mod input;
pub mod omni;
pub mod output;
pub mod progress;
pub mod ros2;
pub mod servo;
pub mod station;
pub mod telemetry;
pub mod teleop;
pub mod text;
pub mod toml_place;

pub use cmd::run::{execute, DeviceSpec, RunError, RunOptions, RunOutcome};
pub use config::{Config, ConfigError};
pub use control::{ControllerKind, Trajectory};
pub use device::inject::{Fault, FaultyDevice};
pub use device::replay::ReplayDevice;
pub use device::sim::SimOmni;
pub use device::{Device, DeviceError, RawSample};
pub use omni::{Geometry, Joint3};
pub use servo::summary::RunSummary;
pub use servo::{EndReason, Servo};
