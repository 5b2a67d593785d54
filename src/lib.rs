//! omnid: a hardware I/O daemon for the Phantom Omni haptic device.
//!
//! Data flow, one module per stage:
//! `device` (packets) → `estimate` (Kalman) → `control` (PD, …) → safety in `servo` →
//! `device`, with `telemetry` carrying each tick to the log and the summary, and `omni` the
//! geometry and physics shared by the simulator and model-based control. Off the loop: `plot`
//! draws figures from a log, `experiment` reproduces the paper's experiments, `progress` the terminal progress bars of long commands, `input` the files read from outside (never an uninterruptible wait, never an unbounded row).

/// Terminal output that never panics. `print!` and `eprintln!` panic when the stream is a
/// closed pipe or a hung-up terminal, which would lose the exit code, the summary JSON and the
/// fault path after a run; these lose only the text (README, Exit codes).
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = write!(std::io::stdout(), $($arg)*);
    }};
}

/// `println!` that never panics (see [`out!`]).
#[macro_export]
macro_rules! outln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}

/// `eprintln!` that never panics (see [`out!`]).
#[macro_export]
macro_rules! errln {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($arg)*);
    }};
}

pub mod clock;
pub mod config;
pub mod config_check;
pub mod control;
pub mod convert;
pub mod daemon;
pub mod device;
pub mod estimate;
pub mod experiment;
pub mod fast_tanh;
pub mod haptics;
pub mod identifier;
pub mod input;
pub mod log_pretune;
pub mod omni;
pub mod output;
pub mod plot;
pub mod progress;
pub mod run;
pub mod serve;
pub mod servo;
pub mod telemetry;
pub mod text;
