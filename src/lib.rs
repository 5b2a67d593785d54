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
pub mod experiment;
pub(crate) mod fast_tanh;
pub mod haptics;
pub mod human;
pub mod identifier;
pub mod input;
pub mod omni;
pub mod output;
pub mod plot;
pub mod progress;
pub mod ros2;
pub mod servo;
pub mod station;
pub mod telemetry;
pub mod teleop;
pub mod text;
pub mod toml_place;
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
