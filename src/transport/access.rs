//! Who may do what (SO_PEERCRED): the daemon's own user and root may command; members of
//! `serve.control_group` may command; members of `serve.read_group` may read; everyone else
//! is refused with a message saying which group would let them in.

use super::socket::Peer;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    Read,
    Control,
}

impl Access {
    pub fn as_str(self) -> &'static str {
        match self {
            Access::Read => "read",
            Access::Control => "control",
        }
    }
}

/// The configured groups, resolved to ids at start.
#[derive(Debug, Clone, Default)]
pub struct Policy {
    /// The daemon's effective uid.
    pub own_uid: u32,
    pub read_group: Option<(String, u32)>,
    pub control_group: Option<(String, u32)>,
}

impl Policy {
    /// What `peer` may do, or why it is refused.
    pub fn decide(&self, peer: &Peer) -> Result<Access, String> {
        if peer.uid == 0 || peer.uid == self.own_uid {
            return Ok(Access::Control);
        }
        if let Some((_, gid)) = &self.control_group {
            if peer.in_group(*gid) {
                return Ok(Access::Control);
            }
        }
        if let Some((_, gid)) = &self.read_group {
            if peer.in_group(*gid) {
                return Ok(Access::Read);
            }
        }
        let groups: Vec<String> = [&self.read_group, &self.control_group]
            .into_iter()
            .flatten()
            .map(|(name, _)| format!("`{name}`"))
            .collect();
        Err(if groups.is_empty() {
            format!(
                "access refused: uid {} is not the daemon's user (uid {}); set serve.read_group \
                 / serve.control_group in the daemon's config to admit a group",
                peer.uid, self.own_uid
            )
        } else {
            format!(
                "access refused: uid {} is in none of the groups admitted ({}); ask for membership \
                 (`usermod -aG GROUP USER`, then log in again)",
                peer.uid,
                groups.join(", ")
            )
        })
    }

    /// Why `peer`, admitted to read, may not command.
    pub fn read_only_reason(&self, peer: &Peer) -> String {
        match &self.control_group {
            Some((name, _)) => format!(
                "read-only access: uid {} is not in the control group `{name}` (serve.control_group)",
                peer.uid
            ),
            None => format!(
                "read-only access: only the daemon's user (uid {}) and root may command; set \
                 serve.control_group to admit a group",
                self.own_uid
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn peer(uid: u32, gid: u32, groups: &[u32]) -> Peer {
        Peer {
            pid: 1,
            uid,
            gid,
            groups: groups.to_vec(),
        }
    }

    #[test]
    fn owner_and_root_command_groups_read_or_command_others_are_refused() {
        let p = Policy {
            own_uid: 500,
            read_group: Some(("lab".into(), 20)),
            control_group: Some(("omnid".into(), 30)),
        };
        assert_eq!(p.decide(&peer(500, 500, &[])), Ok(Access::Control));
        assert_eq!(p.decide(&peer(0, 0, &[])), Ok(Access::Control));
        assert_eq!(p.decide(&peer(7, 7, &[30])), Ok(Access::Control));
        assert_eq!(p.decide(&peer(7, 30, &[])), Ok(Access::Control));
        assert_eq!(p.decide(&peer(8, 8, &[20, 99])), Ok(Access::Read));
        let e = p.decide(&peer(9, 9, &[99])).unwrap_err();
        assert!(
            e.contains("uid 9") && e.contains("`lab`") && e.contains("`omnid`"),
            "{e}"
        );
        assert!(p.read_only_reason(&peer(8, 8, &[20])).contains("`omnid`"));
    }

    #[test]
    fn without_groups_only_the_owner_and_root_get_in() {
        let p = Policy {
            own_uid: 500,
            ..Policy::default()
        };
        let e = p.decide(&peer(9, 9, &[])).unwrap_err();
        assert!(e.contains("serve.read_group"), "{e}");
    }
}
