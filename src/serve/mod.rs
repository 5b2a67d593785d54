//! The client interface of `omnid serve` (docs/PROTOCOL.md): the hub that serves clients on a
//! Unix SOCK_SEQPACKET socket, the protocol, access rules, the socket and its default place,
//! and a Rust client. The daemon itself (assembling the servo and starting the hub) is
//! `crate::daemon`.

pub(crate) mod access;
pub mod client;
pub(crate) mod config;
pub mod hub;
pub mod protocol;
pub mod socket;

pub use config::{ServeConfig, StaleFallback};

use std::path::PathBuf;

/// The directories a daemon's socket goes in by default, in order of preference:
/// `$RUNTIME_DIRECTORY` (systemd's `RuntimeDirectory=`), `$XDG_RUNTIME_DIR/omnid`, and
/// `/run/omnid` for root.
pub fn default_socket_dirs() -> Vec<PathBuf> {
    let mut dirs = Vec::new();
    if let Some(d) = std::env::var_os("RUNTIME_DIRECTORY").filter(|d| !d.is_empty()) {
        dirs.push(PathBuf::from(d));
    }
    if let Some(d) = std::env::var_os("XDG_RUNTIME_DIR").filter(|d| !d.is_empty()) {
        dirs.push(PathBuf::from(d).join("omnid"));
    }
    dirs.push(PathBuf::from("/run/omnid"));
    dirs
}

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

/// The socket a client connects to when given none: `$OMNID_SOCKET`, else the one socket in
/// the default directories (an error lists them when there are several or none).
pub fn find_socket() -> Result<PathBuf, String> {
    if let Some(p) = std::env::var_os("OMNID_SOCKET").filter(|p| !p.is_empty()) {
        return Ok(PathBuf::from(p));
    }
    let dirs = default_socket_dirs();
    for dir in &dirs {
        let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|e| e == "sock"))
            .collect();
        found.sort();
        match found.len() {
            0 => continue,
            1 => return Ok(found.remove(0)),
            _ => {
                return Err(format!(
                    "several omnid sockets in {}: {}; pass --socket PATH",
                    dir.display(),
                    found
                        .iter()
                        .map(|p| p.display().to_string())
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            }
        }
    }
    Err(format!(
        "no omnid socket found in {}: is `omnid serve` running? (or pass --socket PATH, or set \
         OMNID_SOCKET)",
        dirs.iter()
            .map(|d| d.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    ))
}

/// The socket of arm `name` (its name or an alias): `<dir>/<name>.sock` in the default
/// directories, else the daemon whose hello names it (`arm` or `aliases`).
pub fn find_arm_socket(name: &str) -> Result<PathBuf, String> {
    let dirs = default_socket_dirs();
    if crate::arm::check_name(name).is_ok() {
        if let Some(p) = dirs
            .iter()
            .map(|d| d.join(format!("{name}.sock")))
            .find(|p| p.exists())
        {
            return Ok(p);
        }
    }
    let mut served = Vec::new();
    for dir in &dirs {
        let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
            .into_iter()
            .flatten()
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|e| e == "sock"))
            .collect();
        found.sort();
        for p in found {
            let Ok(c) = client::Client::connect(&p, "omnid (looking for an arm)") else {
                continue;
            };
            let hello = c.hello();
            if hello.arm == name || hello.aliases.iter().any(|a| a == name) {
                return Ok(p);
            }
            served.push(hello.arm.clone());
        }
    }
    Err(format!(
        "no arm named `{}` is served in {} (arms served: {}); is `omnid serve` running with it?",
        crate::text::cut(name),
        dirs.iter()
            .map(|d| d.display().to_string())
            .collect::<Vec<_>>()
            .join(", "),
        if served.is_empty() {
            "none".to_string()
        } else {
            served.join(", ")
        }
    ))
}
