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

pub mod bind;
pub use omnid_core::config::zenoh as config;
pub(crate) mod door;
pub mod port;
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
    /// Commands allowed where other machines reach the session, and zenoh asks no one who
    /// they are.
    #[error(
        "zenoh: `[zenoh] allow_commands = true` on {reach}, which other machines can reach, and \
         zenoh authenticates no one: anyone who reaches it could move the arms. Configure \
         zenoh's authentication in `[zenoh] config_file` (user/password \
         `transport.auth.usrpwd`, or mutual TLS `transport.link.tls.enable_mtls` on tls/ \
         endpoints) with its access control (docs/ZENOH.md), or set `[zenoh] insecure = true` \
         to run so anyway"
    )]
    Insecure {
        /// The endpoints (and scouting) other machines reach.
        reach: String,
    },
}

/// Who can reach a session and whether zenoh authenticates them (docs/ZENOH.md).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Exposure {
    /// Endpoints other machines reach (not loopback), and multicast scouting if on.
    pub reach: Vec<String>,
    /// How zenoh authenticates peers, if it does.
    pub auth: Option<&'static str>,
}

/// Whether `endpoint` (`proto/host:port[?…][#…]`) is on this PC's loopback only.
fn loopback(endpoint: &str) -> bool {
    let address = endpoint.split(['?', '#']).next().unwrap_or("");
    let Some((_, address)) = address.split_once('/') else {
        return false;
    };
    let host = address.rsplit_once(':').map_or(address, |(h, _)| h);
    let host = host.trim_start_matches('[').trim_end_matches(']');
    host == "localhost"
        || host
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

/// Who can reach a session on `listen` and `connect` as `zc` configures it.
fn exposure(
    cfg: &ZenohConfig,
    zc: &zenoh::Config,
    listen: &[String],
    connect: &[String],
) -> Exposure {
    let mut reach: Vec<String> = listen
        .iter()
        .chain(connect)
        .filter(|e| !loopback(e))
        .cloned()
        .collect();
    if cfg.multicast_scouting {
        reach.push("multicast scouting".into());
    }
    let set = |key: &str| {
        zc.get_json(key)
            .is_ok_and(|v| !matches!(v.trim(), "" | "null" | "\"\""))
    };
    let usrpwd = (set("transport/auth/usrpwd/user") && set("transport/auth/usrpwd/password"))
        || set("transport/auth/usrpwd/dictionary_file");
    let mtls = zc
        .get_json("transport/link/tls/enable_mtls")
        .is_ok_and(|v| v.trim() == "true")
        && reach
            .iter()
            .all(|e| e.starts_with("tls/") || e.starts_with("quic/"))
        && !cfg.multicast_scouting;
    let auth = if usrpwd {
        Some("user/password")
    } else if mtls {
        Some("mutual TLS")
    } else {
        None
    };
    Exposure { reach, auth }
}

/// The daemon's zenoh session and its ROS 2 node.
pub struct ZenohNet {
    session: zenoh::Session,
    /// The endpoints the session listens on (a default port: the one it got).
    listening: Vec<String>,
    cfg: ZenohConfig,
    node: Node,
    exposure: Exposure,
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

/// The keys an arm's commands arrive on (docs/ZENOH.md): remote clients' requests, the ROS 2
/// command topics (rmw_zenoh's and the bridge's forms), teleop frames.
pub const COMMAND_KEYS: [&str; 5] = [
    "omnid/*/in/**",
    "omnid/teleop/**",
    "**/servo_cf/**",
    "**/servo_jp/**",
    "**/state_command/**",
];

/// The liveliness tokens a remote client takes a slot with.
pub const CLIENT_TOKENS: &str = "omnid/*/client/**";

/// zenoh's settings for `[zenoh]`'s caps, authentication, TLS and access control, as
/// (key, JSON value) pairs laid over `config_file`.
fn security_settings(cfg: &ZenohConfig) -> Vec<(&'static str, String)> {
    let text = |s: &str| serde_json::to_string(s).unwrap_or_else(|_| "\"\"".into());
    let mut out = vec![
        (
            "transport/unicast/max_sessions",
            cfg.max_sessions.to_string(),
        ),
        (
            "transport/unicast/accept_pending",
            cfg.max_handshakes.to_string(),
        ),
        (
            "transport/unicast/accept_timeout",
            cfg.handshake_timeout_ms.to_string(),
        ),
    ];
    if !cfg.users_file.is_empty() {
        out.push((
            "transport/auth/usrpwd/dictionary_file",
            text(&cfg.users_file),
        ));
    }
    if !cfg.user.is_empty() {
        out.push(("transport/auth/usrpwd/user", text(&cfg.user)));
        out.push((
            "transport/auth/usrpwd/password",
            text(cfg.password.expose()),
        ));
    }
    let tls = [
        ("transport/link/tls/root_ca_certificate", &cfg.tls_root_ca),
        (
            "transport/link/tls/listen_certificate",
            &cfg.tls_certificate,
        ),
        (
            "transport/link/tls/listen_private_key",
            &cfg.tls_private_key,
        ),
    ];
    for (key, path) in tls {
        if !path.is_empty() {
            out.push((key, text(path)));
        }
    }
    if cfg.tls_mutual {
        out.push(("transport/link/tls/enable_mtls", "true".into()));
        out.push((
            "transport/link/tls/connect_certificate",
            text(&cfg.tls_certificate),
        ));
        out.push((
            "transport/link/tls/connect_private_key",
            text(&cfg.tls_private_key),
        ));
    }
    if !cfg.commanders.is_empty() {
        out.push(("access_control", access_control(cfg).to_string()));
    }
    out
}

/// zenoh's access control under which only `commanders` may put on the command keys and take
/// a remote client's slot; everything else stays allowed (docs/ZENOH.md). zenoh lets a
/// message through when any subject the sender matches allows it, so the deny is tied to a
/// subject everyone matches and the commanders match one with nothing denied.
fn access_control(cfg: &ZenohConfig) -> serde_json::Value {
    use serde_json::json;
    let mut subjects = vec![json!({ "id": "omnid_anyone" })];
    let mut named = Vec::new();
    if !cfg.users_file.is_empty() {
        subjects.push(json!({ "id": "omnid_commander_users", "usernames": cfg.commanders }));
        named.push("omnid_commander_users");
    }
    if cfg.tls_mutual {
        subjects.push(json!({
            "id": "omnid_commander_certificates",
            "cert_common_names": cfg.commanders,
        }));
        named.push("omnid_commander_certificates");
    }
    json!({
        "enabled": true,
        "default_permission": "allow",
        "rules": [
            { "id": "omnid_no_commands", "permission": "deny", "flows": ["ingress"],
              "messages": ["put", "delete"], "key_exprs": COMMAND_KEYS },
            { "id": "omnid_no_client_slots", "permission": "deny", "flows": ["ingress"],
              "messages": ["liveliness_token"], "key_exprs": [CLIENT_TOKENS] },
            { "id": "omnid_commands", "permission": "allow", "flows": ["ingress"],
              "messages": ["put", "delete", "liveliness_token"],
              "key_exprs": COMMAND_KEYS.iter().copied().chain([CLIENT_TOKENS]).collect::<Vec<_>>() },
        ],
        "subjects": subjects,
        "policies": [
            { "rules": ["omnid_no_commands", "omnid_no_client_slots"], "subjects": ["omnid_anyone"] },
            { "rules": ["omnid_commands"], "subjects": named },
        ],
    })
}

fn json_list(v: &[String]) -> String {
    serde_json::to_string(v).unwrap_or_else(|_| "[]".into())
}

/// Zenoh's defaults, or `[zenoh] config_file`'s.
fn base_config(cfg: &ZenohConfig) -> Result<zenoh::Config, ZenohError> {
    if cfg.config_file.is_empty() {
        return Ok(zenoh::Config::default());
    }
    zenoh::Config::from_file(&cfg.config_file).map_err(|e| ZenohError::Config {
        key: "config_file",
        value: cfg.config_file.clone(),
        why: e.to_string(),
    })
}

/// Where the session connects: `[zenoh] connect`, or a peer's try at ROS 2's router on this PC.
fn connect_endpoints(cfg: &ZenohConfig) -> Vec<String> {
    if cfg.connect.is_empty() && cfg.mode == ZenohMode::Peer {
        // ROS 2's router on this PC, if there is one; tried again in the background.
        vec!["tcp/127.0.0.1:7447".to_string()]
    } else {
        cfg.connect.clone()
    }
}

/// Who can reach the session; refused when commands would be open to them unauthenticated
/// (unless `[zenoh] insecure`).
fn judge_exposure(
    cfg: &ZenohConfig,
    zc: &zenoh::Config,
    connect: &[String],
) -> Result<Exposure, ZenohError> {
    let exposure = exposure(
        cfg,
        zc,
        // Empty: the default ports, all on loopback.
        if cfg.mode == ZenohMode::Peer {
            &cfg.listen
        } else {
            &[]
        },
        connect,
    );
    if cfg.allow_commands && !exposure.reach.is_empty() && exposure.auth.is_none() && !cfg.insecure
    {
        return Err(ZenohError::Insecure {
            reach: exposure.reach.join(", "),
        });
    }
    Ok(exposure)
}

/// The session's mode, endpoints and scouting.
fn session_settings(cfg: &ZenohConfig, connect: &[String]) -> Vec<(&'static str, String)> {
    let mode = match cfg.mode {
        ZenohMode::Peer => "\"peer\"",
        ZenohMode::Client => "\"client\"",
    };
    let mut settings: Vec<(&'static str, String)> = vec![
        ("mode", mode.into()),
        ("connect/endpoints", json_list(connect)),
        (
            "scouting/multicast/enabled",
            cfg.multicast_scouting.to_string(),
        ),
    ];
    if cfg.mode == ZenohMode::Peer {
        // A router that is not there yet is not an error: ROS 2 starts in any order.
        settings.push(("connect/exit_on_failure", "false".into()));
    }
    settings
}

/// Open the session: a client as configured, a peer on `[zenoh] listen` or else on a default
/// port. Returns it with the endpoints it listens on.
fn open_session(
    cfg: &ZenohConfig,
    mut zc: zenoh::Config,
) -> Result<(zenoh::Session, Vec<String>), ZenohError> {
    if cfg.mode != ZenohMode::Peer {
        let session = zenoh::open(zc)
            .wait()
            .map_err(|e| ZenohError::Open(e.to_string()))?;
        Ok((session, Vec::new()))
    } else if !cfg.listen.is_empty() {
        let listen = cfg.listen.clone();
        set(&mut zc, "listen/endpoints", json_list(&listen))?;
        let session = zenoh::open(zc)
            .wait()
            .map_err(|e| ZenohError::Open(e.to_string()))?;
        Ok((session, listen))
    } else {
        open_on_a_default_port(zc)
    }
}

/// The ROS 2 node this session is, and its liveliness token when `[zenoh] ros2` declares it.
fn declare_node(
    cfg: &ZenohConfig,
    domain: u32,
    session: &zenoh::Session,
) -> Result<(Node, Option<zenoh::liveliness::LivelinessToken>), ZenohError> {
    let node = Node {
        domain,
        zid: session.zid().to_string(),
        id: 0,
        enclave: String::new(),
        namespace: cfg.namespace.clone(),
        name: cfg.node_name.clone(),
    };
    if !cfg.ros2 {
        return Ok((node, None));
    }
    let token = session
        .liveliness()
        .declare_token(node.token())
        .wait()
        .map_err(|e| ZenohError::Declare {
            what: node.token(),
            why: e.to_string(),
        })?;
    Ok((node, Some(token)))
}

impl ZenohNet {
    /// Open the session as `[zenoh]` says (loopback and no multicast unless configured) and
    /// declare the ROS 2 node.
    pub fn start(cfg: &ZenohConfig) -> Result<ZenohNet, ZenohError> {
        let domain = cfg.domain().map_err(ZenohError::Domain)?;
        let mut zc = base_config(cfg)?;
        let connect = connect_endpoints(cfg);
        // Authentication, TLS and access control from `[zenoh]`'s own keys, before the
        // exposure is judged (docs/ZENOH.md, "A lab network").
        for (key, value) in security_settings(cfg) {
            set(&mut zc, key, value)?;
        }
        let exposure = judge_exposure(cfg, &zc, &connect)?;
        for (key, value) in session_settings(cfg, &connect) {
            set(&mut zc, key, value)?;
        }
        let (session, listening) = open_session(cfg, zc)?;
        let (node, node_token) = declare_node(cfg, domain, &session)?;
        Ok(ZenohNet {
            teleop: Arc::new(teleop::TeleopNet::new(session.clone(), cfg)),
            session,
            listening,
            cfg: cfg.clone(),
            node,
            exposure,
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

    /// Who can reach this session and whether zenoh authenticates them.
    pub fn exposure(&self) -> &Exposure {
        &self.exposure
    }

    /// What this session lets the network do, in a sentence for the start-up line.
    pub fn allows(&self) -> String {
        let e = &self.exposure;
        let keys = self.cfg.teleop_keys.len();
        let pairs = if keys == 0 {
            "no teleop pair with another daemon ([zenoh.teleop_keys] empty)".to_string()
        } else {
            format!("teleop with another daemon for {keys} keyed pair(s)")
        };
        if !self.cfg.allow_commands {
            return "read-only: commands refused ([zenoh] allow_commands = false)".into();
        }
        let who = if self.cfg.commanders.is_empty() {
            String::new()
        } else {
            format!(
                ", and of them only {} (zenoh access control, [zenoh] commanders)",
                self.cfg.commanders.join(", ")
            )
        };
        let pairs = format!("{who}; {pairs}");
        match (e.reach.is_empty(), e.auth) {
            (true, None) => format!("commands from this PC only (loopback){pairs}"),
            (true, Some(how)) => format!(
                "commands from this PC only (loopback), from peers zenoh authenticates \
                 ({how}){pairs}"
            ),
            (false, Some(how)) => format!(
                "commands from peers zenoh authenticates ({how}) on {}{pairs}",
                e.reach.join(", ")
            ),
            (false, None) => format!(
                "commands from ANYONE who reaches {} ([zenoh] insecure = true){pairs}",
                e.reach.join(", ")
            ),
        }
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

    /// Serve an arm over zenoh: the tap that feeds its ROS 2 topics and remote clients, and
    /// the door its host's port (`port::ZenohPort`) takes requests through.
    pub fn arm(
        &self,
        s: &crate::station::StationSetup,
        serve: &crate::transport::ServeConfig,
    ) -> Result<(Box<dyn Tap>, door::Door), ZenohError> {
        let (host_side, mut net_side, outbox) = door::Door::pair(
            self.cfg.inbox,
            self.cfg.allow_commands,
            serve.lease_lapse_ms,
        )
        .map_err(|e| ZenohError::Declare {
            what: "the host's wake-up".into(),
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
        let tap = ros::NetTap::start(&s.arm.name, ros, remote, net_side, outbox);
        Ok((tap, host_side))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with(cfg: ZenohConfig) -> Result<ZenohNet, ZenohError> {
        ZenohNet::start(&cfg)
    }

    /// The core checks `[zenoh] connect`/`listen` by shape (it links no zenoh): it refuses what
    /// zenoh's own parser refuses, so a config it passes does not fail later at start.
    #[test]
    fn the_cores_endpoint_shape_check_agrees_with_zenohs_parser() {
        let cases = [
            "tcp/127.0.0.1:7447",
            "tls/lab-pc:7447",
            "udp/[::1]:7447",
            "tcp/host:1?rel=1",
            "tcp/host:1#iface=eth0",
            "tcp/host:1?rel=1;prio=2#iface=eth0",
            "tcp/host:1?",
            "tcp/host:1#",
            "tcp/host:1?=1",
            "tcp/host:1#=x",
            "tcp/",
            "/host:1",
            "tcp",
            "",
            "tcp/host:1?a=1#",
            "tcp/host:1?;;",
            "tcp/host:1?a;b",
        ];
        for e in cases {
            let ours = crate::config::zenoh::endpoint_shape_ok(e);
            let theirs = e.parse::<zenoh::config::EndPoint>().is_ok();
            assert_eq!(ours, theirs, "{e:?}: ours {ours}, zenoh's {theirs}");
        }
    }

    #[test]
    fn commands_on_a_reachable_endpoint_without_authentication_are_refused_saying_how() {
        // Refused before the session opens: nothing listens.
        for (listen, connect, scouting) in [
            ("tcp/0.0.0.0:0", vec![], false),
            ("tcp/192.168.1.10:7447", vec![], false),
            (
                "tcp/127.0.0.1:0",
                vec!["tcp/10.0.0.2:7447".to_string()],
                false,
            ),
            ("tcp/127.0.0.1:0", vec![], true),
        ] {
            let cfg = ZenohConfig {
                allow_commands: true,
                listen: vec![listen.into()],
                connect,
                multicast_scouting: scouting,
                ..ZenohConfig::default()
            };
            let e = with(cfg).err().expect("refused").to_string();
            assert!(
                e.contains("allow_commands = true")
                    && e.contains("insecure = true")
                    && e.contains("transport.auth.usrpwd"),
                "{listen}: {e}"
            );
        }
    }

    #[test]
    fn users_tls_and_commanders_become_zenohs_authentication_and_access_control() {
        let dir = tempfile::tempdir().unwrap();
        let users = dir.path().join("users");
        std::fs::write(&users, "lab:lab-secret\nviewer:viewer-secret\n").unwrap();
        let cfg = ZenohConfig {
            allow_commands: true,
            listen: vec!["tcp/0.0.0.0:0".into()],
            connect: vec!["tcp/127.0.0.1:1".into()],
            users_file: users.display().to_string(),
            user: "omnid".into(),
            password: "daemon-secret".into(),
            commanders: vec!["lab".into()],
            ..ZenohConfig::default()
        };
        cfg.validate().unwrap();
        let settings = security_settings(&cfg);
        let value = |k: &str| {
            settings
                .iter()
                .find(|(key, _)| *key == k)
                .map(|(_, v)| v.clone())
        };
        assert_eq!(
            value("transport/unicast/max_sessions").as_deref(),
            Some("256")
        );
        assert_eq!(
            value("transport/unicast/accept_timeout").as_deref(),
            Some("5000")
        );
        let acl: serde_json::Value =
            serde_json::from_str(&value("access_control").unwrap()).unwrap();
        assert_eq!(acl["default_permission"], "allow");
        assert_eq!(acl["subjects"][1]["usernames"][0], "lab");
        // zenoh takes all of it: the session opens with the ACL and authentication, and the
        // daemon says who may command.
        let net = with(cfg).expect("opens");
        assert_eq!(net.exposure().auth, Some("user/password"));
        let said = net.allows();
        assert!(
            said.contains("only lab") && said.contains("user/password"),
            "{said}"
        );
        net.close();
    }

    #[test]
    fn commanders_need_a_way_to_tell_peers_apart() {
        let cfg = ZenohConfig {
            commanders: vec!["lab".into()],
            ..ZenohConfig::default()
        };
        let e = cfg.validate().unwrap_err().to_string();
        assert!(
            e.contains("zenoh.users_file") && e.contains("zenoh.tls_mutual"),
            "{e}"
        );
        let cfg = ZenohConfig {
            user: "omnid".into(),
            ..ZenohConfig::default()
        };
        assert!(cfg
            .validate()
            .unwrap_err()
            .to_string()
            .contains("zenoh.password"));
    }

    #[test]
    fn what_a_session_lets_in_is_told_from_its_endpoints_and_zenohs_authentication() {
        let cfg = ZenohConfig::default();
        let local = |l: &[&str]| l.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let plain = zenoh::Config::default();
        let e = exposure(
            &cfg,
            &plain,
            &local(&["tcp/127.0.0.1:0", "tcp/[::1]:7447"]),
            &local(&["tcp/localhost:7447"]),
        );
        assert_eq!(
            e,
            Exposure {
                reach: vec![],
                auth: None
            }
        );
        let e = exposure(&cfg, &plain, &local(&["tcp/0.0.0.0:7447"]), &[]);
        assert_eq!(e.reach, vec!["tcp/0.0.0.0:7447".to_string()]);
        assert_eq!(e.auth, None);
        let mut pw = zenoh::Config::default();
        pw.insert_json5(
            "transport/auth/usrpwd/dictionary_file",
            "\"/etc/omnid/users\"",
        )
        .unwrap();
        assert_eq!(
            exposure(&cfg, &pw, &local(&["tcp/0.0.0.0:7447"]), &[]).auth,
            Some("user/password")
        );
        let mut mtls = zenoh::Config::default();
        mtls.insert_json5("transport/link/tls/enable_mtls", "true")
            .unwrap();
        assert_eq!(
            exposure(&cfg, &mtls, &local(&["tls/0.0.0.0:7447"]), &[]).auth,
            Some("mutual TLS")
        );
        // A plain tcp endpoint beside the TLS one is not authenticated by TLS.
        assert_eq!(
            exposure(
                &cfg,
                &mtls,
                &local(&["tls/0.0.0.0:7447", "tcp/0.0.0.0:7448"]),
                &[]
            )
            .auth,
            None
        );
    }
}
