//! Files a client names (`record_start PATH`, `weights_save`, `weights_load`) are opened with
//! that client's own rights, never the daemon's: a root daemon takes the client's file-system
//! identity (fsuid, fsgid and groups, on this thread only) for the open alone, so a client
//! reaches exactly the files it could reach itself and a file it creates is its own. A daemon
//! that is not root cannot take another user's identity: it opens files only for its own
//! user (and root's default places stay open to everyone: a recording without a path).

/// Whose rights open the files a session names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FileRights {
    /// The daemon's own: the session is the daemon's user.
    Daemon,
    /// The client's: its user, primary group and supplementary groups.
    Peer {
        /// User id.
        uid: u32,
        /// Primary group id.
        gid: u32,
        /// Supplementary group ids.
        groups: Vec<u32>,
    },
    /// None: why files cannot be opened for this session.
    Refused(String),
}

impl FileRights {
    /// The rights a peer (`uid`, `gid`, `groups`) gets from a daemon running as `daemon_uid`.
    pub fn for_peer(daemon_uid: u32, uid: u32, gid: u32, groups: &[u32]) -> FileRights {
        if uid == daemon_uid {
            FileRights::Daemon
        } else if daemon_uid == 0 {
            FileRights::Peer {
                uid,
                gid,
                groups: groups.to_vec(),
            }
        } else {
            FileRights::Refused(format!(
                "this daemon runs as uid {daemon_uid}, not root, so it cannot open files with \
                 your rights (uid {uid})"
            ))
        }
    }
}

/// What a session whose files are refused can do instead, per op.
pub(crate) fn instead(op: &str) -> &'static str {
    match op {
        "record_start" => "record without a path (into the daemon's recordings directory)",
        _ => {
            "the daemon keeps each arm's learned weights itself ([identifier] persist); a \
             weights file is saved or loaded by a client on the daemon's PC, as its user"
        }
    }
}

/// `with_rights`, its refusal followed by what to do instead of `op`.
pub(crate) fn with_rights_for<T>(
    op: &str,
    rights: &FileRights,
    f: impl FnOnce() -> T,
) -> Result<T, String> {
    with_rights(rights, f).map_err(|why| match rights {
        FileRights::Refused(_) => format!("{why}: {}", instead(op)),
        _ => why,
    })
}

/// Run `f` (an open, a save) with `rights`; the daemon's identity is back before this returns.
pub(crate) fn with_rights<T>(rights: &FileRights, f: impl FnOnce() -> T) -> Result<T, String> {
    match rights {
        FileRights::Daemon => Ok(f()),
        FileRights::Refused(why) => Err(why.clone()),
        FileRights::Peer { uid, gid, groups } => {
            let _as_peer = AsPeer::take(*uid, *gid, groups)?;
            Ok(f())
        }
    }
}

/// The calling thread's file-system identity switched to a client's; switched back on drop.
/// Raw system calls: glibc's `setgroups` would change every thread of the process.
struct AsPeer {
    fsuid: u32,
    fsgid: u32,
    groups: Vec<libc::gid_t>,
}

fn set_groups(groups: &[libc::gid_t]) -> bool {
    // SAFETY: the pointer and length describe a live slice of gid_t.
    unsafe { libc::syscall(libc::SYS_setgroups, groups.len(), groups.as_ptr()) == 0 }
}

fn set_fsuid(uid: u32) -> u32 {
    // SAFETY: no pointers; returns the previous fsuid.
    unsafe { libc::syscall(libc::SYS_setfsuid, uid) as u32 }
}

fn set_fsgid(gid: u32) -> u32 {
    // SAFETY: no pointers; returns the previous fsgid.
    unsafe { libc::syscall(libc::SYS_setfsgid, gid) as u32 }
}

impl AsPeer {
    fn take(uid: u32, gid: u32, groups: &[u32]) -> Result<AsPeer, String> {
        let refused = || "the daemon cannot take your identity to open the file".to_string();
        // SAFETY: a null list with size 0 asks for the count only.
        let n = unsafe { libc::getgroups(0, std::ptr::null_mut()) };
        let mut saved = vec![0 as libc::gid_t; n.max(0) as usize];
        // SAFETY: `saved` has room for `n` entries.
        let n = unsafe { libc::getgroups(n, saved.as_mut_ptr()) };
        if n < 0 {
            return Err(refused());
        }
        saved.truncate(n as usize);
        if !set_groups(groups) {
            return Err(refused());
        }
        // Made before the checks below, so that a failed switch is undone too.
        let mut back = AsPeer {
            fsuid: u32::MAX,
            fsgid: set_fsgid(gid),
            groups: saved,
        };
        back.fsuid = set_fsuid(uid);
        // An invalid id changes nothing and reports the current one.
        if set_fsgid(u32::MAX) != gid || set_fsuid(u32::MAX) != uid {
            return Err(refused());
        }
        Ok(back)
    }
}

impl Drop for AsPeer {
    fn drop(&mut self) {
        if self.fsuid != u32::MAX {
            set_fsuid(self.fsuid);
        }
        set_fsgid(self.fsgid);
        set_groups(&self.groups);
    }
}

/// A weights file's error as a client hears it: where and what kind of problem, never a value
/// out of the file (a client must not read a file through the daemon's error messages).
pub(crate) fn quoting_nothing(e: crate::identifier::WeightsError) -> String {
    use crate::identifier::WeightsError as E;
    match e {
        E::Parse { path, message } => {
            // serde_json ends its messages with "at line L column C".
            let at = message
                .rfind(" at line ")
                .map_or(String::new(), |i| format!(" ({})", message[i + 1..].trim()));
            format!("weights file {path} is not valid weights JSON{at}")
        }
        E::Format { path, .. } => {
            format!("weights file {path} is not a weights file of this build's format and version")
        }
        other => other.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::{MetadataExt, PermissionsExt};

    #[test]
    fn a_refusal_says_what_to_do_instead_for_its_op() {
        let remote = FileRights::Refused("a client over the network names no files".into());
        let record = with_rights_for("record_start", &remote, || ()).unwrap_err();
        assert!(record.contains("record without a path"), "{record}");
        for op in ["weights_save", "weights_load"] {
            let e = with_rights_for(op, &remote, || ()).unwrap_err();
            assert!(!e.contains("record"), "{op}: {e}");
            assert!(e.contains("[identifier] persist"), "{op}: {e}");
        }
        assert_eq!(
            with_rights_for("weights_save", &FileRights::Daemon, || 5),
            Ok(5)
        );
    }

    #[test]
    fn who_gets_which_rights() {
        assert_eq!(FileRights::for_peer(500, 500, 500, &[]), FileRights::Daemon);
        assert_eq!(FileRights::for_peer(0, 0, 0, &[]), FileRights::Daemon);
        assert_eq!(
            FileRights::for_peer(0, 7, 8, &[9]),
            FileRights::Peer {
                uid: 7,
                gid: 8,
                groups: vec![9]
            }
        );
        let FileRights::Refused(why) = FileRights::for_peer(500, 7, 7, &[]) else {
            panic!("a non-root daemon opened files for another user");
        };
        assert!(why.contains("uid 500"), "{why}");
        let refused = FileRights::Refused(why);
        let e = with_rights_for("record_start", &refused, || ()).unwrap_err();
        assert!(e.contains("without a path"), "{e}");
    }

    /// Needs root (CI runs as root): a client reaches what it could reach itself, and the
    /// daemon is itself again afterwards.
    #[test]
    fn a_client_opens_only_what_it_could_open_itself() {
        // SAFETY: no arguments.
        if unsafe { libc::geteuid() } != 0 {
            eprintln!("skipped: taking another user's identity needs root");
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
        let private = dir.path().join("private");
        let open = dir.path().join("open");
        let team = dir.path().join("team");
        for (d, mode) in [(&private, 0o700), (&open, 0o777), (&team, 0o770)] {
            std::fs::create_dir(d).unwrap();
            std::fs::set_permissions(d, std::fs::Permissions::from_mode(mode)).unwrap();
        }
        let team_gid = 4242;
        // SAFETY: a valid NUL-terminated path.
        let c = std::ffi::CString::new(team.as_os_str().as_encoded_bytes()).unwrap();
        assert_eq!(unsafe { libc::chown(c.as_ptr(), 0, team_gid) }, 0);
        let secret = private.join("secret");
        std::fs::write(&secret, "root only").unwrap();

        let nobody = FileRights::for_peer(0, 65534, 65534, &[]);
        let e = with_rights(&nobody, || std::fs::File::create(private.join("x")))
            .unwrap()
            .unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::PermissionDenied);
        assert!(with_rights(&nobody, || std::fs::read(&secret))
            .unwrap()
            .is_err());
        assert!(
            with_rights(&nobody, || std::fs::File::create(team.join("x")))
                .unwrap()
                .is_err()
        );
        with_rights(&nobody, || std::fs::File::create(open.join("mine")))
            .unwrap()
            .unwrap();
        assert_eq!(std::fs::metadata(open.join("mine")).unwrap().uid(), 65534);
        // A member of the directory's group gets in through the group.
        let member = FileRights::for_peer(0, 65534, 65534, &[team_gid]);
        with_rights(&member, || std::fs::File::create(team.join("ours")))
            .unwrap()
            .unwrap();
        // The daemon is root again on this thread.
        std::fs::File::create(private.join("root")).unwrap();
        assert_eq!(std::fs::metadata(private.join("root")).unwrap().uid(), 0);
        assert_eq!(std::fs::read_to_string(&secret).unwrap(), "root only");
    }
}
