//! Where the two sides of a pair meet in one daemon (docs/TELEOP.md §8): each arm's station
//! takes up its side on its own client's request (so each side passes its own arm's lease and
//! checks), and the first side to come opens the channel and leaves the other end here for the
//! second. Off the servo threads (the stations' hub threads), so a lock is fine.

use super::channel::{pair, Endpoint};
use super::{Role, TeleopConfig};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, Weak};
use thiserror::Error;

/// Why a side cannot join.
#[derive(Debug, Error, PartialEq)]
pub enum RendezvousError {
    /// The peer is this arm.
    #[error("an arm cannot be its own {0}")]
    SelfPeer(&'static str),
    /// The peer is not an arm of this daemon.
    #[error("no arm `{peer}` in this daemon (its arms: {arms})")]
    UnknownPeer {
        /// The name asked for.
        peer: String,
        /// The daemon's arms.
        arms: String,
    },
    /// The other side started with other settings.
    #[error(
        "`{other}` started its side of this pair with other [teleop] settings \
         (architecture {architecture}); start both sides with the same ones"
    )]
    Mismatch {
        /// The other side's arm.
        other: String,
        /// The other side's architecture.
        architecture: &'static str,
    },
}

/// The far end of an opened channel, waiting for its side.
struct Waiting {
    /// The role of the side that will take it.
    role: Role,
    endpoint: Endpoint,
    config: TeleopConfig,
    /// The opener's end: while it lives, the opener is still on the line.
    opener: Weak<()>,
}

/// The daemon's meeting point; cheap to clone (every station holds one).
#[derive(Clone, Default)]
pub struct Rendezvous {
    arms: Arc<Vec<String>>,
    waiting: Arc<Mutex<HashMap<(String, String), Waiting>>>,
}

impl Rendezvous {
    /// For a daemon serving `arms` (their names).
    pub fn new(arms: Vec<String>) -> Rendezvous {
        Rendezvous {
            arms: Arc::new(arms),
            waiting: Arc::default(),
        }
    }

    /// Arm `me` joins the pair with `peer` as `role`, with `config` (the pair's settings
    /// and channel impairments): its end of the channel, and a token to keep while it is on
    /// the line. The first side opens the channel; the second takes the other end, if the
    /// opener is still on the line (else it opens a fresh one).
    pub fn join(
        &self,
        me: &str,
        peer: &str,
        role: Role,
        config: &TeleopConfig,
        seed: u64,
    ) -> Result<(Endpoint, Arc<()>), RendezvousError> {
        let role_name = match role {
            Role::Leader => "follower",
            Role::Follower => "leader",
        };
        if me == peer {
            return Err(RendezvousError::SelfPeer(role_name));
        }
        if !self.arms.iter().any(|a| a == peer) {
            return Err(RendezvousError::UnknownPeer {
                peer: crate::text::cut(peer),
                arms: self.arms.join(", "),
            });
        }
        let key = match role {
            Role::Leader => (me.to_string(), peer.to_string()),
            Role::Follower => (peer.to_string(), me.to_string()),
        };
        let mut waiting = self.waiting.lock().unwrap_or_else(|e| e.into_inner());
        let token = Arc::new(());
        if let Some(w) = waiting.get(&key) {
            let usable = w.role == role && w.opener.strong_count() > 0;
            if usable && &w.config != config {
                return Err(RendezvousError::Mismatch {
                    other: peer.to_string(),
                    architecture: w.config.architecture.as_str(),
                });
            }
            if usable {
                let w = waiting.remove(&key).expect("looked up above");
                return Ok((w.endpoint, token));
            }
        }
        let (leader, follower) = pair(config.to_leader, config.to_follower, seed);
        let (mine, theirs, their_role) = match role {
            Role::Leader => (leader, follower, Role::Follower),
            Role::Follower => (follower, leader, Role::Leader),
        };
        waiting.insert(
            key,
            Waiting {
                role: their_role,
                endpoint: theirs,
                config: config.clone(),
                opener: Arc::downgrade(&token),
            },
        );
        Ok((mine, token))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::teleop::{Architecture, Packet};

    fn arms() -> Rendezvous {
        Rendezvous::new(vec!["left".into(), "right".into(), "third".into()])
    }

    /// A packet sent from one end arrives at the other (no impairment: due at once).
    fn joined(a: &mut Endpoint, b: &mut Endpoint) -> bool {
        a.send(Packet {
            seq: 7,
            ..Packet::default()
        });
        b.receive(0.0).map(|p| p.seq) == Some(7)
    }

    #[test]
    fn the_second_side_takes_the_other_end_of_the_first_sides_channel() {
        let r = arms();
        let cfg = TeleopConfig::default();
        let (mut l, _lt) = r.join("left", "right", Role::Leader, &cfg, 1).unwrap();
        let (mut f, _ft) = r.join("right", "left", Role::Follower, &cfg, 1).unwrap();
        assert!(joined(&mut l, &mut f) && joined(&mut f, &mut l));
        // Either order.
        let (mut f, _ft) = r.join("third", "left", Role::Follower, &cfg, 1).unwrap();
        let (mut l, _lt) = r.join("left", "third", Role::Leader, &cfg, 1).unwrap();
        assert!(joined(&mut l, &mut f) && joined(&mut f, &mut l));
    }

    #[test]
    fn a_side_that_left_before_its_peer_came_is_not_joined() {
        let r = arms();
        let cfg = TeleopConfig::default();
        let (old, token) = r.join("left", "right", Role::Leader, &cfg, 1).unwrap();
        drop((old, token));
        // The follower opens a fresh channel; the leader that comes next joins that one.
        let (mut f, _ft) = r.join("right", "left", Role::Follower, &cfg, 1).unwrap();
        let (mut l, _lt) = r.join("left", "right", Role::Leader, &cfg, 1).unwrap();
        assert!(joined(&mut l, &mut f));
        // A side starting again while its first start waits replaces it.
        let (_a, _at) = r.join("left", "third", Role::Leader, &cfg, 1).unwrap();
        let (mut b, _bt) = r.join("left", "third", Role::Leader, &cfg, 1).unwrap();
        let (mut f, _ft) = r.join("third", "left", Role::Follower, &cfg, 1).unwrap();
        assert!(joined(&mut b, &mut f));
    }

    #[test]
    fn a_peer_that_is_not_an_arm_here_or_is_itself_or_disagrees_is_refused() {
        let r = arms();
        let cfg = TeleopConfig::default();
        let e = r
            .join("left", "nobody", Role::Leader, &cfg, 1)
            .err()
            .unwrap();
        assert_eq!(
            e.to_string(),
            "no arm `nobody` in this daemon (its arms: left, right, third)"
        );
        let e = r.join("left", "left", Role::Leader, &cfg, 1).err().unwrap();
        assert_eq!(e, RendezvousError::SelfPeer("follower"));
        let (_l, _lt) = r.join("left", "right", Role::Leader, &cfg, 1).unwrap();
        let pf = TeleopConfig {
            architecture: Architecture::Pf,
            ..cfg
        };
        let e = r
            .join("right", "left", Role::Follower, &pf, 1)
            .err()
            .unwrap();
        assert!(e.to_string().contains("architecture pp"), "{e}");
    }
}
