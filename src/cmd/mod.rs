//! The commands that run arms: `omnid run` ([`run`]), `omnid serve` ([`serve`]) and
//! `omnid identify` ([`identify`]), and the arm's assembly both `run` and `serve` build
//! ([`assembly`]: device, controllers, identifier, heat, on the servo's own thread). The
//! lab tools that only read logs (`plot`, `convert`, `experiment`) have their own modules.

pub mod assembly;
pub mod identify;
pub mod run;
pub mod serve;
