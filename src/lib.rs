//! omnid: a hardware I/O daemon for the Phantom Omni haptic device.
//!
//! Data flow, one module per stage:
//! `device` (packets) → `estimate` (Kalman) → `control` (PD, …) → safety in `servo` →
//! `device`, with `telemetry` carrying each tick to the log and the summary, and `omni` the
//! geometry and physics shared by the simulator and model-based control. Off the loop: `plot`
//! draws figures from a log, `experiment` reproduces the paper's experiments, `progress` the terminal progress bars of long commands.

pub mod config;
pub mod control;
pub mod device;
pub mod estimate;
pub mod experiment;
pub mod fastmath;
pub mod ident;
pub mod identify;
pub mod omni;
pub mod plot;
pub mod progress;
pub mod run;
pub mod serve;
pub mod servo;
pub mod telemetry;
