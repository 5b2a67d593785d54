//! The transports of `omnid serve` (docs/PROTOCOL.md, docs/ZENOH.md): the station's `host`
//! (the loop that owns an arm's station) and its ports — the Unix SOCK_SEQPACKET socket
//! (`unix`) and zenoh (`zenoh`) — with the JSON handling they share (`json`), the protocol,
//! access rules, the socket and its default place, the live view, and a Rust client. The
//! daemon itself (assembling the servo and starting the host) is `crate::cmd::serve`.

pub(crate) mod access;
/// The Rust client (`omnid_client::client`), used by `omnid watch`, `omnid ctl`, the tests
/// and the benchmarks.
pub use omnid_client::client;
pub(crate) use omnid_core::config::serve as config;
pub mod foxglove;
pub mod host;
pub mod json;
pub mod protocol;
pub mod socket;
pub mod unix;
pub mod zenoh;

pub use config::{ServeConfig, StaleFallback};
pub use omnid_client::find::{default_socket_dirs, find_arm_socket, find_socket, FindError};
use std::path::PathBuf;

/// Where the daemon serves arm `name` unless told otherwise.
pub(crate) fn default_socket(name: &str) -> PathBuf {
    // SAFETY: geteuid has no arguments and cannot fail.
    let root = unsafe { libc::geteuid() } == 0;
    let dirs = default_socket_dirs();
    let dir = dirs
        .iter()
        .find(|d| !d.ends_with("run/omnid") || root || d.is_dir())
        .cloned()
        .unwrap_or_else(|| PathBuf::from("/run/omnid"));
    dir.join(format!("{name}.sock"))
}
