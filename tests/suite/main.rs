//! omnid's integration tests, one binary (each file a module), so the crate and its
//! dependencies are linked once. Two tiers (README, "Development"): `cargo test` runs the
//! fast, deterministic tests; those marked `#[ignore = "paced"]` run daemons ticking in real
//! time, C/C++ compiles, PyPI checkers or paper experiments, and run with
//! `cargo test -- --include-ignored` (as `.ci/run` does). Tests that need a global allocator
//! of their own are in `tests/alloc.rs`; `crates/omnid-core/tests/replay_memory.rs` measures the process's peak
//! memory, so it has a process to itself.

mod common;
mod hd;

mod arms;
mod cli_config;
mod cli_hardware;
mod cli_human;
mod cli_input;
mod cli_run;
mod config_fuzz_smoke;
mod ecosystem;
mod experiment;
mod faults;
mod haptics;
mod hdapi;
mod hdapi_python;
mod identifier;
mod identifier_paper;
mod interrupt;
mod kinematics_data;
mod layers;
mod live_view;
mod mcap_log;
mod outputs;
mod plot;
mod protocol_fuzz_smoke;
mod python_client;
mod reader_errors;
mod readme;
mod readme_numbers;
mod replay;
mod ros_touch;
mod safety_estimator;
mod safety_flow;
mod say_where;
mod serve;
mod serve_safety;
mod stderr_stall;
mod teleop;
mod zenoh_peers;
