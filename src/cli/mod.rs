//! One module per command of the `omnid` binary; what they share is in `main.rs`.

pub(crate) mod convert;
pub(crate) mod ctl;
pub(crate) mod identify;
pub(crate) mod plot;
pub(crate) mod probe;
pub(crate) mod run;
pub(crate) mod serve;
pub(crate) mod watch;
