//! The daemon's descriptors (docs/ZENOH.md, "Ports and descriptors"): the soft limit raised to
//! the hard one at start, and every network port capped so that together they stay well below
//! it. What is left is the Unix socket's: root's and the daemon user's `mode idle` and
//! `shutdown` always find a descriptor.

/// Descriptors the daemon uses besides its ports: standard streams, logs, the device, eventfds,
/// zenoh's and tokio's own, per arm and in all.
const BASE: u64 = 128;
const PER_ARM: u64 = 32;

/// The soft limit raised to the hard one: (the soft limit before, the one now).
pub(crate) fn raise_limit() -> (u64, u64) {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: `lim` is a valid rlimit to fill.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) } != 0 {
        return (0, 0);
    }
    let before = lim.rlim_cur;
    if lim.rlim_cur < lim.rlim_max {
        let raised = libc::rlimit {
            rlim_cur: lim.rlim_max,
            rlim_max: lim.rlim_max,
        };
        // SAFETY: as above; raising the soft limit to the hard one needs no privilege.
        if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
            return (before, lim.rlim_max);
        }
    }
    (before, before)
}

/// The most descriptors the daemon's ports can hold together with what it uses anyway.
pub(crate) struct Budget {
    /// Every arm's Unix socket: `serve.max_clients` plus the slots kept for root and the
    /// daemon's user, and the connections not greeted yet.
    pub socket_clients: u64,
    /// zenoh: sessions times links, and handshakes in progress.
    pub zenoh: u64,
    /// The live view's gate: three per viewer (its connection and the relay's two ends).
    pub live_view: u64,
    /// Arms served.
    pub arms: u64,
}

impl Budget {
    /// The whole, with the daemon's own.
    pub(crate) fn total(&self) -> u64 {
        BASE + PER_ARM * self.arms + self.socket_clients + self.zenoh + self.live_view
    }

    /// A warning when the limit `limit` leaves less than a quarter of it in reserve.
    pub(crate) fn warning(&self, limit: u64) -> Option<String> {
        let total = self.total();
        (total.saturating_mul(4) > limit.saturating_mul(3)).then(|| {
            format!(
                "the ports could hold {total} descriptors together (sockets {}, zenoh {}, live \
                 view {}) and the limit is {limit}: a flood could leave the Unix socket none; \
                 raise the limit (systemd LimitNOFILE=, `ulimit -n`) or lower serve.max_clients \
                 / [zenoh] max_sessions (docs/ZENOH.md)",
                self.socket_clients, self.zenoh, self.live_view
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_soft_limit_is_raised_to_the_hard_one_and_a_tight_limit_is_warned_of() {
        let (before, now) = raise_limit();
        assert!(now >= before);
        let b = Budget {
            socket_clients: 128 + 8 + 32,
            zenoh: 256 + 32,
            live_view: 96,
            arms: 1,
        };
        assert!(b.warning(65536).is_none());
        let w = b.warning(512).expect("a tight limit is warned of");
        assert!(w.contains("512") && w.contains("LimitNOFILE"), "{w}");
    }
}
