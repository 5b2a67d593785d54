//! Where the two sides of a pair meet in one daemon (docs/TELEOP.md §8): each arm's station
//! takes up its side on its own client's request (so each side passes its own arm's lease and
//! checks), and the first side to come opens the channel and leaves the other end here for the
//! second. A peer that is not an arm of this daemon is served by another: with zenoh up, the
//! side opens a network channel to it instead ([`RemoteChannels`], docs/TELEOP.md §9). Off
//! the servo threads (the stations' hub threads), so a lock is fine.

use super::channel::{pair, Endpoint};
use super::{Role, TeleopConfig};
use serde::Serialize;
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
    #[error(
        "no arm `{peer}` in this daemon (its arms: {arms}); an arm of another daemon is reached \
         when both serve over zenoh (`omnid serve --zenoh`, docs/TELEOP.md §9)"
    )]
    UnknownPeer {
        /// The name asked for.
        peer: String,
        /// The daemon's arms.
        arms: String,
    },
    /// The peer is served by another daemon, and the network channel could not open.
    #[error("{0}")]
    Remote(String),
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

/// Opens a channel to a peer arm served by another daemon (zenoh: src/transport/zenoh/teleop.rs).
pub trait RemoteChannels: Send + Sync {
    /// Arm `me`'s end of a channel to `peer` (another daemon's arm) as `role`, with `config`;
    /// and what keeps the network side open (dropped when the side ends).
    fn open(
        &self,
        me: &str,
        peer: &str,
        role: Role,
        config: &TeleopConfig,
        seed: u64,
    ) -> Result<(Endpoint, Box<dyn RemoteLine>), String>;
}

/// The network side of a channel to another daemon's arm, kept open while it lives.
pub trait RemoteLine: Send {
    /// What it has carried so far.
    fn stats(&self) -> LineStats;
}

/// What a network channel has carried (in `status`).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct LineStats {
    /// The zenoh session the peer's packets come from, once one has been heard.
    pub peer_session: Option<String>,
    /// Frames sent to the peer.
    pub sent: u64,
    /// Well-formed frames received from the peer.
    pub received: u64,
    /// Frames refused (malformed, other settings, another sender, a full queue).
    pub refused: u64,
    /// Why the last refused frame was refused.
    pub last_refusal: Option<String>,
}

/// What a side keeps while it is on the line: its token at the rendezvous, and for a peer of
/// another daemon the network side of its channel.
pub struct OnTheLine {
    _token: Arc<()>,
    remote: Option<Box<dyn RemoteLine>>,
}

impl OnTheLine {
    /// The channel's kind: `in_process` or `zenoh`.
    pub fn channel(&self) -> &'static str {
        if self.remote.is_some() {
            "zenoh"
        } else {
            "in_process"
        }
    }

    /// What the network channel has carried (none in process).
    pub fn network(&self) -> Option<LineStats> {
        self.remote.as_ref().map(|r| r.stats())
    }
}

/// The daemon's meeting point; cheap to clone (every station holds one).
#[derive(Clone, Default)]
pub struct Rendezvous {
    arms: Arc<Vec<String>>,
    waiting: Arc<Mutex<HashMap<(String, String), Waiting>>>,
    remote: Option<Arc<dyn RemoteChannels>>,
}

impl Rendezvous {
    /// For a daemon serving `arms` (their names).
    pub fn new(arms: Vec<String>) -> Rendezvous {
        Rendezvous {
            arms: Arc::new(arms),
            waiting: Arc::default(),
            remote: None,
        }
    }

    /// Peers that are not this daemon's arms are reached through `remote`.
    pub fn with_remote(mut self, remote: Arc<dyn RemoteChannels>) -> Rendezvous {
        self.remote = Some(remote);
        self
    }

    /// Arm `me` joins the pair with `peer` as `role`, with `config` (the pair's settings
    /// and channel impairments): its end of the channel, and a token to keep while it is on
    /// the line. The first side opens the channel; the second takes the other end, if the
    /// opener is still on the line (else it opens a fresh one). A peer of another daemon is
    /// reached over the network, when this daemon has one.
    pub fn join(
        &self,
        me: &str,
        peer: &str,
        role: Role,
        config: &TeleopConfig,
        seed: u64,
    ) -> Result<(Endpoint, OnTheLine), RendezvousError> {
        if me != peer && !self.arms.iter().any(|a| a == peer) {
            if let Some(remote) = &self.remote {
                let (endpoint, net) = remote
                    .open(me, peer, role, config, seed)
                    .map_err(RendezvousError::Remote)?;
                return Ok((
                    endpoint,
                    OnTheLine {
                        _token: Arc::new(()),
                        remote: Some(net),
                    },
                ));
            }
        }
        let (endpoint, token) = self.join_here(me, peer, role, config, seed)?;
        Ok((
            endpoint,
            OnTheLine {
                _token: token,
                remote: None,
            },
        ))
    }

    fn join_here(
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

    /// Another daemon's arms, as a network would reach them: records who asked.
    struct FakeNet(Mutex<Vec<(String, String, Role)>>);

    struct FakeLine;
    impl RemoteLine for FakeLine {
        fn stats(&self) -> LineStats {
            LineStats {
                received: 42,
                ..LineStats::default()
            }
        }
    }

    impl RemoteChannels for FakeNet {
        fn open(
            &self,
            me: &str,
            peer: &str,
            role: Role,
            config: &TeleopConfig,
            seed: u64,
        ) -> Result<(Endpoint, Box<dyn RemoteLine>), String> {
            if peer == "unreachable" {
                return Err("the network says no".into());
            }
            self.0.lock().unwrap().push((me.into(), peer.into(), role));
            let (end, _) = pair(config.to_leader, config.to_follower, seed);
            Ok((end, Box::new(FakeLine)))
        }
    }

    #[test]
    fn a_peer_of_another_daemon_goes_over_the_network_and_one_of_this_daemon_does_not() {
        let net = Arc::new(FakeNet(Mutex::default()));
        let r = arms().with_remote(net.clone());
        let cfg = TeleopConfig::default();
        let (_e, line) = r.join("left", "far", Role::Leader, &cfg, 1).unwrap();
        assert_eq!(line.channel(), "zenoh");
        assert_eq!(line.network().map(|s| s.received), Some(42));
        let (_e, line) = r.join("right", "left", Role::Follower, &cfg, 1).unwrap();
        assert_eq!(line.channel(), "in_process");
        assert_eq!(line.network(), None);
        assert_eq!(
            *net.0.lock().unwrap(),
            vec![("left".to_string(), "far".to_string(), Role::Leader)]
        );
        let e = r
            .join("left", "unreachable", Role::Leader, &cfg, 1)
            .err()
            .unwrap();
        assert_eq!(e.to_string(), "the network says no");
        // Itself is never a remote peer.
        let e = r.join("left", "left", Role::Leader, &cfg, 1).err().unwrap();
        assert_eq!(e, RendezvousError::SelfPeer("follower"));
    }

    #[test]
    fn a_peer_that_is_not_an_arm_here_or_is_itself_or_disagrees_is_refused() {
        let r = arms();
        let cfg = TeleopConfig::default();
        let e = r
            .join("left", "nobody", Role::Leader, &cfg, 1)
            .err()
            .unwrap();
        assert!(
            e.to_string()
                .starts_with("no arm `nobody` in this daemon (its arms: left, right, third); "),
            "{e}"
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
