//! zenoh: every arm past this PC (docs/ZENOH.md). One zenoh session per daemon, and per arm:
//! - the ROS 2 topics of CRTK's arm under `/<arm>/`, in rmw_zenoh's format (`ros`), so a ROS 2
//!   graph on rmw_zenoh sees omnid as a node with no ROS build here;
//! - omnid's own protocol for remote clients under `omnid/<arm>/` (`remote`): the socket's JSON
//!   messages, one stream each way per client;
//! - a teleoperation channel per pair with another daemon's arm (`teleop`).
//!
//! Nothing here runs on the servo thread: ticks arrive through the station's taps, commands go
//! to the arm's hub through a bounded inbox (`door`) and become the same station ops, lease
//! checks and stream time to live as a socket client's.

pub mod config;
pub(crate) mod door;
mod remote;
mod ros;
mod teleop;

pub use config::{ZenohConfig, ZenohMode};
pub use door::ZenohStats;

use crate::ros2::rmw_zenoh::Node;
use crate::station::Tap;
use std::sync::atomic::AtomicU64;
use std::sync::Arc;
use thiserror::Error;
use zenoh::Wait;

/// Why the zenoh transport could not start.
#[derive(Debug, Error)]
pub enum ZenohError {
    /// The session's configuration was refused.
    #[error("zenoh: configuration `{key}` = {value}: {why}")]
    Config {
        /// The zenoh key (or `config_file`).
        key: &'static str,
        /// Its value.
        value: String,
        /// What zenoh said.
        why: String,
    },
    /// The session could not open (an endpoint in use, a router that cannot be reached in
    /// client mode).
    #[error("zenoh: cannot open the session: {0}")]
    Open(String),
    /// A declaration (publisher, subscriber, token) failed.
    #[error("zenoh: cannot declare {what}: {why}")]
    Declare {
        /// The key or token.
        what: String,
        /// What zenoh said.
        why: String,
    },
    /// `ROS_DOMAIN_ID` is not a domain.
    #[error("zenoh: {0}")]
    Domain(String),
}

/// The daemon's zenoh session and its ROS 2 node.
pub struct ZenohNet {
    session: zenoh::Session,
    /// The endpoints the session listens on (a default port: the one it got).
    listening: Vec<String>,
    cfg: ZenohConfig,
    node: Node,
    /// rmw_zenoh numbers the node and its endpoints from one counter.
    next_entity: Arc<AtomicU64>,
    /// One for the session: its teleop frames' counter is never reused while it lives.
    teleop: Arc<teleop::TeleopNet>,
    _node_token: Option<zenoh::liveliness::LivelinessToken>,
}

/// Where a peer listens when `[zenoh] listen` is empty: loopback, the first of these ports
/// that is free (docs/ZENOH.md). 7448 is the next after ROS 2's router (7447), so a remote
/// client on this PC reaches the first daemon at `tcp/127.0.0.1:7448`.
pub const DEFAULT_PORTS: std::ops::RangeInclusive<u16> = 7448..=7457;

fn set(zc: &mut zenoh::Config, key: &'static str, value: String) -> Result<(), ZenohError> {
    zc.insert_json5(key, &value)
        .map_err(|e| ZenohError::Config {
            key,
            value,
            why: e.to_string(),
        })
}

/// Open a peer on the first free default port (a second daemon on this PC takes the next).
fn open_on_a_default_port(zc: zenoh::Config) -> Result<(zenoh::Session, Vec<String>), ZenohError> {
    let mut last = String::new();
    for port in DEFAULT_PORTS {
        // A port another program holds is free again as soon as it lets go: ask the OS
        // first, which is cheaper than a session that fails to open.
        if std::net::TcpListener::bind(("127.0.0.1", port)).is_err() {
            last = format!("tcp/127.0.0.1:{port} is taken");
            continue;
        }
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let mut attempt = zc.clone();
        set(
            &mut attempt,
            "listen/endpoints",
            json_list(std::slice::from_ref(&endpoint)),
        )?;
        match zenoh::open(attempt).wait() {
            Ok(session) => return Ok((session, vec![endpoint])),
            Err(e) => last = format!("{endpoint}: {e}"),
        }
    }
    Err(ZenohError::Open(format!(
        "no default port free on loopback ({}..={}; last: {last}); name one in [zenoh] listen",
        DEFAULT_PORTS.start(),
        DEFAULT_PORTS.end()
    )))
}

fn json_list(v: &[String]) -> String {
    serde_json::to_string(v).unwrap_or_else(|_| "[]".into())
}

impl ZenohNet {
    /// Open the session as `[zenoh]` says (loopback and no multicast unless configured) and
    /// declare the ROS 2 node.
    pub fn start(cfg: &ZenohConfig) -> Result<ZenohNet, ZenohError> {
        let domain = cfg.domain().map_err(ZenohError::Domain)?;
        let mut zc = if cfg.config_file.is_empty() {
            zenoh::Config::default()
        } else {
            zenoh::Config::from_file(&cfg.config_file).map_err(|e| ZenohError::Config {
                key: "config_file",
                value: cfg.config_file.clone(),
                why: e.to_string(),
            })?
        };
        let connect = if cfg.connect.is_empty() && cfg.mode == ZenohMode::Peer {
            // ROS 2's router on this PC, if there is one; tried again in the background.
            vec!["tcp/127.0.0.1:7447".to_string()]
        } else {
            cfg.connect.clone()
        };
        let mode = match cfg.mode {
            ZenohMode::Peer => "\"peer\"",
            ZenohMode::Client => "\"client\"",
        };
        let mut settings: Vec<(&'static str, String)> = vec![
            ("mode", mode.into()),
            ("connect/endpoints", json_list(&connect)),
            (
                "scouting/multicast/enabled",
                cfg.multicast_scouting.to_string(),
            ),
        ];
        if cfg.mode == ZenohMode::Peer {
            // A router that is not there yet is not an error: ROS 2 starts in any order.
            settings.push(("connect/exit_on_failure", "false".into()));
        }
        for (key, value) in settings {
            set(&mut zc, key, value)?;
        }
        let (session, listening) = if cfg.mode != ZenohMode::Peer {
            let session = zenoh::open(zc)
                .wait()
                .map_err(|e| ZenohError::Open(e.to_string()))?;
            (session, Vec::new())
        } else if !cfg.listen.is_empty() {
            let listen = cfg.listen.clone();
            set(&mut zc, "listen/endpoints", json_list(&listen))?;
            let session = zenoh::open(zc)
                .wait()
                .map_err(|e| ZenohError::Open(e.to_string()))?;
            (session, listen)
        } else {
            open_on_a_default_port(zc)?
        };
        let node = Node {
            domain,
            zid: session.zid().to_string(),
            id: 0,
            enclave: String::new(),
            namespace: cfg.namespace.clone(),
            name: cfg.node_name.clone(),
        };
        let node_token = if cfg.ros2 {
            Some(
                session
                    .liveliness()
                    .declare_token(node.token())
                    .wait()
                    .map_err(|e| ZenohError::Declare {
                        what: node.token(),
                        why: e.to_string(),
                    })?,
            )
        } else {
            None
        };
        Ok(ZenohNet {
            teleop: Arc::new(teleop::TeleopNet::new(session.clone(), cfg)),
            session,
            listening,
            cfg: cfg.clone(),
            node,
            next_entity: Arc::new(AtomicU64::new(1)),
            _node_token: node_token,
        })
    }

    /// What opens teleoperation channels to other daemons' arms on this session.
    pub fn teleop(&self) -> std::sync::Arc<dyn crate::teleop::RemoteChannels> {
        self.teleop.clone()
    }

    /// Close the session now (its peers see it go at once, as when the daemon ends).
    pub fn close(self) {
        let _ = self.session.close().wait();
    }

    /// This session's id (32 hex digits), as peers and ROS 2's graph name it.
    pub fn zid(&self) -> String {
        self.node.zid.clone()
    }

    /// The endpoints this session listens on: as configured, or the default port it got
    /// (empty in client mode).
    pub fn listening(&self) -> Vec<String> {
        self.listening.clone()
    }

    /// Serve the arm a hub serves: the tap that feeds its ROS 2 topics and remote clients, and
    /// the door its hub takes requests through.
    pub fn arm(
        &self,
        hub: &crate::transport::hub::HubSetup,
    ) -> Result<(Box<dyn Tap>, door::Door), ZenohError> {
        let s = &hub.station;
        let (hub_side, mut net_side) = door::Door::pair(
            self.cfg.inbox,
            self.cfg.allow_commands,
            hub.serve.lease_lapse_ms,
        )
        .map_err(|e| ZenohError::Declare {
            what: "the hub's wake-up".into(),
            why: e.to_string(),
        })?;
        net_side.max_sample_bytes = self.cfg.max_sample_bytes;
        let ros = if self.cfg.ros2 || self.cfg.bridge {
            Some(ros::RosArm::declare(
                &self.session,
                &self.cfg,
                &self.node,
                &self.next_entity,
                &s.arm.name,
                s.rate_hz,
                s.geometry,
                net_side.clone(),
            )?)
        } else {
            None
        };
        let remote = if self.cfg.protocol {
            Some(remote::RemoteArm::declare(
                &self.session,
                &self.cfg,
                &s.arm.name,
                net_side.clone(),
            )?)
        } else {
            None
        };
        let tap = ros::NetTap::start(&s.arm.name, ros, remote, net_side);
        Ok((tap, hub_side))
    }
}
