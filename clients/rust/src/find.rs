//! Where a client finds the daemon: the directories a daemon's sockets go in, the one socket
//! there, or the socket of an arm by its name or an alias (docs/PROTOCOL.md).

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

/// Check an arm's name: it names files, sockets and a systemd instance, so it is kept to
/// letters, digits, `-` and `_`, 1 to 32 characters.
pub fn check_arm_name(name: &str) -> Result<(), String> {
    let ok = !name.is_empty()
        && name.len() <= 32
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
    if ok {
        Ok(())
    } else {
        Err(format!(
            "arm name `{}`: allowed 1 to 32 letters, digits, `-` or `_` (it names the socket, \
             the heat file and the fault dumps)",
            quoted(name)
        ))
    }
}

/// A name as it is quoted back in a message: at most 64 characters.
fn quoted(name: &str) -> String {
    match name.char_indices().nth(64) {
        None => name.to_string(),
        Some((end, _)) => format!("{}… ({} bytes)", &name[..end], name.len()),
    }
}

/// Why no one socket was found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FindError {
    /// Several arms are served there: the caller must say which.
    #[error(
        "several arms are served in {}: {}; name one with --arm NAME (or --socket PATH)",
        dir.display(),
        arms.join(", ")
    )]
    Several {
        /// The directory.
        dir: PathBuf,
        /// The arms, by their sockets' names.
        arms: Vec<String>,
    },
    /// No daemon there.
    #[error(
        "no omnid socket found in {}: is `omnid serve` running? (or pass --socket PATH, or \
         set OMNID_SOCKET)",
        dirs.iter().map(|d| d.display().to_string()).collect::<Vec<_>>().join(", ")
    )]
    None {
        /// Where it looked.
        dirs: Vec<PathBuf>,
    },
}

/// The socket a client connects to when given none: `$OMNID_SOCKET`, else the one live
/// socket in the default directories (an error lists them when there are several or none).
pub fn find_socket() -> Result<PathBuf, FindError> {
    if let Some(p) = std::env::var_os("OMNID_SOCKET").filter(|p| !p.is_empty()) {
        return Ok(PathBuf::from(p));
    }
    find_socket_in(&default_socket_dirs())
}

/// The `*.sock` files in `dir`, sorted (none when it cannot be read).
fn sockets_in(dir: &std::path::Path) -> Vec<PathBuf> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "sock"))
        .collect();
    found.sort();
    found
}

/// The one live socket in the first of `dirs` that has any; sockets left by a daemon that
/// died are passed over.
pub fn find_socket_in(dirs: &[PathBuf]) -> Result<PathBuf, FindError> {
    for dir in dirs {
        // A daemon that crashed left its socket: not one to choose between.
        let mut found = sockets_in(dir);
        found.retain(|p| crate::socket::is_live(p));
        match found.len() {
            0 => continue,
            1 => return Ok(found.remove(0)),
            _ => {
                return Err(FindError::Several {
                    dir: dir.clone(),
                    arms: found
                        .iter()
                        .filter_map(|p| p.file_stem())
                        .map(|s| s.to_string_lossy().into_owned())
                        .collect(),
                })
            }
        }
    }
    Err(FindError::None {
        dirs: dirs.to_vec(),
    })
}

/// The socket of arm `name` (its name or an alias): `<dir>/<name>.sock` in the default
/// directories, else the daemon whose hello names it (`arm` or `aliases`).
pub fn find_arm_socket(name: &str) -> Result<PathBuf, String> {
    let dirs = default_socket_dirs();
    if check_arm_name(name).is_ok() {
        if let Some(p) = dirs
            .iter()
            .map(|d| d.join(format!("{name}.sock")))
            .find(|p| crate::socket::is_live(p))
        {
            return Ok(p);
        }
    }
    let mut served = Vec::new();
    for dir in &dirs {
        for p in sockets_in(dir) {
            let Ok(c) = crate::client::Client::connect(&p, "omnid (looking for an arm)") else {
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
        quoted(name),
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::net::UnixListener;

    #[test]
    fn a_socket_left_by_a_dead_daemon_is_passed_over() {
        let dir = tempfile::tempdir().unwrap();
        // A daemon that died: its socket file stays, nobody listens.
        drop(UnixListener::bind(dir.path().join("a.sock")).unwrap());
        assert!(dir.path().join("a.sock").exists());
        let dirs = [dir.path().to_path_buf()];
        let e = find_socket_in(&dirs).unwrap_err();
        assert!(e.to_string().contains("no omnid socket"), "{e}");
        let _live = UnixListener::bind(dir.path().join("b.sock")).unwrap();
        assert_eq!(find_socket_in(&dirs).unwrap(), dir.path().join("b.sock"));
        // Two arms: named, and how to choose.
        let _other = UnixListener::bind(dir.path().join("c.sock")).unwrap();
        let e = find_socket_in(&dirs).unwrap_err();
        assert_eq!(
            e,
            FindError::Several {
                dir: dir.path().to_path_buf(),
                arms: vec!["b".into(), "c".into()]
            }
        );
        assert!(
            e.to_string().contains("b, c; name one with --arm NAME"),
            "{e}"
        );
    }
}
