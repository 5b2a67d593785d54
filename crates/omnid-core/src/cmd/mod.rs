//! The commands that run arms without a network: `omnid run` ([`run`]), `omnid identify`
//! ([`identify`]), and the arm's assembly both `run` and `serve` build ([`assembly`]: device,
//! controllers, identifier, heat, on the servo's own thread). `omnid serve` is the `omnid`
//! crate's (it adds the transports).

pub mod assembly;
pub mod identify;
pub mod run;
