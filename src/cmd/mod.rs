//! The commands that run arms: `omnid run` ([`run`]), `omnid serve` ([`serve`]) and
//! `omnid identify` ([`identify`]), and the arm's assembly both `run` and `serve` build
//! ([`assembly`]: device, controllers, identifier, heat, on the servo's own thread). The
//! lab tools that only read logs (`plot`, `convert`, `experiment`) have their own modules.
//! All but `serve` live in the core crate (`omnid-core`, docs/ARCHITECTURE.md, Crates).

pub use omnid_core::cmd::{assembly, identify, run};
pub mod serve;
