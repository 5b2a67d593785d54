//! `[zenoh]`: serving the arms past this PC through zenoh (docs/ZENOH.md).

use crate::config_check::{self as check, ConfigError};
use serde::{Deserialize, Serialize};

/// How the daemon's zenoh session joins the network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum ZenohMode {
    /// Talk to peers directly and to a router if one is configured (rmw_zenoh's own mode).
    Peer,
    /// Go through a router (`connect` names it).
    Client,
}

/// A password or key from the config: read like a string, never shown. Its `Debug` and its
/// serialised form (a config written back, the commented default) say `(hidden)`, or nothing
/// when empty, so no status line, dump or log ever prints it.
#[derive(Clone, PartialEq, Eq, Default, Deserialize, schemars::JsonSchema)]
#[serde(transparent)]
pub struct Secret(String);

impl Secret {
    /// The secret itself, for the one place that uses it.
    pub fn expose(&self) -> &str {
        &self.0
    }

    /// Nothing set.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    fn shown(&self) -> &'static str {
        if self.0.is_empty() {
            ""
        } else {
            "(hidden)"
        }
    }
}

impl From<&str> for Secret {
    fn from(s: &str) -> Secret {
        Secret(s.to_string())
    }
}

impl From<String> for Secret {
    fn from(s: String) -> Secret {
        Secret(s)
    }
}

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.shown())
    }
}

impl Serialize for Secret {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.shown())
    }
}

/// The `[zenoh]` section (docs/ZENOH.md). Off unless `enabled` or `omnid serve --zenoh`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohConfig {
    /// Serve every arm over zenoh beside its Unix socket.
    pub enabled: bool,
    /// `peer` or `client`.
    pub mode: ZenohMode,
    /// Endpoints to connect to, e.g. `tcp/192.168.1.10:7447` (a router: `rmw_zenohd` or
    /// `zenohd`). Empty: ROS 2's router on this PC, `tcp/127.0.0.1:7447`, tried in the
    /// background.
    pub connect: Vec<String>,
    /// Endpoints to listen on. Empty: loopback only, `tcp/127.0.0.1:7448` (or the next free
    /// port up to 7457: a second daemon on this PC); other PCs reach the daemon through a
    /// router, or list an address here.
    pub listen: Vec<String>,
    /// Find peers by UDP multicast (off: only the endpoints above).
    pub multicast_scouting: bool,
    /// Accept commands from the network (ROS 2 `servo_cf`, `servo_jp`, `state_command`, and
    /// remote clients' control requests). Off: everything over zenoh is read-only.
    pub allow_commands: bool,
    /// ROS 2 domain; -1: `ROS_DOMAIN_ID` from the environment, else 0.
    pub domain_id: i64,
    /// ROS 2 namespace put before every arm's topics (e.g. `/lab1`); empty: none.
    pub namespace: String,
    /// The ROS 2 node's name.
    pub node_name: String,
    /// Publish the ROS 2 topics in rmw_zenoh's form (what `ros2` with rmw_zenoh sees).
    pub ros2: bool,
    /// Also publish them for Humble's rmw_zenoh (`TypeHashNotSupported` keys).
    pub humble: bool,
    /// Also publish under zenoh-bridge-ros2dds's keys (bare topic names, no attachment).
    pub bridge: bool,
    /// `measured_js` rate, Hz; 0: every tick (the device rate).
    pub joint_rate_hz: f64,
    /// `measured_cp` and `measured_cv` rate, Hz; 0: every tick.
    pub cartesian_rate_hz: f64,
    /// Serve omnid's own protocol (`omnid/<arm>/...`) to remote clients.
    pub protocol: bool,
    /// Requests taken from the network per arm before new ones are dropped (and counted).
    pub inbox: usize,
    /// Largest sample accepted from the network, bytes.
    pub max_sample_bytes: usize,
    /// A zenoh configuration file (JSON5) to start from: TLS certificates
    /// (`transport.link.tls`), access control (`access_control`), anything zenoh knows. The
    /// keys above are set on top of it. Empty: zenoh's defaults.
    pub config_file: String,
    /// Pre-shared keys of teleop pairs across daemons, `"<leader>/<follower>" = "<base64>"`
    /// (at least 16 bytes; make one with `head -c32 /dev/urandom | base64`). Both daemons of a
    /// pair list the same key; a pair without one is refused (docs/TELEOP.md §9).
    pub teleop_keys: std::collections::BTreeMap<String, Secret>,
    /// Allow commands over endpoints other machines reach with no zenoh authentication
    /// (anyone who reaches them could move the arms). Off: `omnid serve` refuses such a
    /// configuration (docs/ZENOH.md).
    pub insecure: bool,
    /// Sessions with other zenoh peers and clients held at once (zenoh's
    /// `transport.unicast.max_sessions`): each holds a descriptor, and the daemon keeps
    /// descriptors in reserve for its Unix socket.
    pub max_sessions: usize,
    /// Incoming connections in their handshake at once (zenoh's `accept_pending`); more wait
    /// in the kernel's queue.
    pub max_handshakes: usize,
    /// An incoming connection that has not finished its handshake within this is closed, ms
    /// (zenoh's `accept_timeout`).
    pub handshake_timeout_ms: u64,
    /// zenoh user/password authentication: who may connect. A file of `user:password` lines,
    /// one per principal (zenoh's `transport.auth.usrpwd.dictionary_file`); a peer or client
    /// that is not in it cannot open a session with this daemon. Empty: no check.
    pub users_file: String,
    /// This daemon's own user name, for peers and routers that check (zenoh's
    /// `transport.auth.usrpwd.user`; set with `password`).
    pub user: String,
    /// This daemon's own password (never shown: status and dumps say `(hidden)`).
    pub password: Secret,
    /// The principals (zenoh user names, or TLS certificate common names) that may command:
    /// put on the arms' command keys (remote clients' requests `omnid/<arm>/in/*`, their
    /// liveliness tokens, ROS 2 command topics) and teleop keys `omnid/teleop/**`. Non-empty:
    /// zenoh's access control is set up so that everyone else can only read (docs/ZENOH.md).
    /// Empty: no access control from omnid (a `config_file` may bring its own).
    pub commanders: Vec<String>,
    /// TLS for `tls/` endpoints: this daemon's certificate (PEM), zenoh's
    /// `transport.link.tls.listen_certificate` and `connect_certificate`.
    pub tls_certificate: String,
    /// Its private key (PEM file).
    pub tls_private_key: String,
    /// The lab's certificate authority (PEM file) that peers' certificates are checked against.
    pub tls_root_ca: String,
    /// Mutual TLS: a peer must show a certificate signed by `tls_root_ca` (its common name is
    /// its principal, for `commanders`).
    pub tls_mutual: bool,
}

impl Default for ZenohConfig {
    fn default() -> Self {
        ZenohConfig {
            enabled: false,
            mode: ZenohMode::Peer,
            connect: Vec::new(),
            listen: Vec::new(),
            multicast_scouting: false,
            allow_commands: false,
            domain_id: -1,
            namespace: String::new(),
            node_name: "omnid".into(),
            ros2: true,
            humble: false,
            bridge: false,
            joint_rate_hz: 0.0,
            cartesian_rate_hz: 250.0,
            protocol: true,
            inbox: 1024,
            max_sample_bytes: 64 * 1024,
            config_file: String::new(),
            teleop_keys: Default::default(),
            insecure: false,
            max_sessions: 256,
            max_handshakes: 32,
            handshake_timeout_ms: 5000,
            users_file: String::new(),
            user: String::new(),
            password: Secret::default(),
            commanders: Vec::new(),
            tls_certificate: String::new(),
            tls_private_key: String::new(),
            tls_root_ca: String::new(),
            tls_mutual: false,
        }
    }
}

/// A pair's key from its base64 text.
fn pair_key(text: &Secret) -> Result<crate::teleop::wire::PairKey, String> {
    use base64::Engine;
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(text.expose().trim())
        .map_err(|_| {
            "base64 of at least 16 random bytes (make one with `head -c32 /dev/urandom | base64`)"
                .to_string()
        })?;
    crate::teleop::wire::PairKey::new(&bytes).map_err(|e| e.to_string())
}

/// A ROS name: letters, digits and '_', not starting with a digit.
fn ros_token_ok(s: &str) -> bool {
    !s.is_empty()
        && !s.starts_with(|c: char| c.is_ascii_digit())
        && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
}

impl ZenohConfig {
    /// Check every value; the first problem names its field (`zenoh.…`).
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.check_ros_names()?;
        self.check_endpoints()?;
        self.check_limits()?;
        self.check_access()?;
        self.check_teleop_keys()
    }

    /// The ROS 2 domain, namespace and node name.
    fn check_ros_names(&self) -> Result<(), ConfigError> {
        if !(-1..=232).contains(&self.domain_id) {
            return Err(check::invalid(
                "zenoh.domain_id",
                self.domain_id.to_string(),
                "0 ..= 232, or -1 for ROS_DOMAIN_ID",
            ));
        }
        let namespace_ok = self.namespace.is_empty()
            || (self.namespace.starts_with('/')
                && self.namespace[1..].split('/').all(ros_token_ok));
        if !namespace_ok {
            return Err(check::invalid(
                "zenoh.namespace",
                crate::text::cut(&self.namespace),
                "empty, or /name[/name...] of letters, digits and _",
            ));
        }
        if !ros_token_ok(&self.node_name) {
            return Err(check::invalid(
                "zenoh.node_name",
                crate::text::cut(&self.node_name),
                "letters, digits and _, not starting with a digit",
            ));
        }
        Ok(())
    }

    /// Where the session connects and listens.
    fn check_endpoints(&self) -> Result<(), ConfigError> {
        for (field, list) in [
            ("zenoh.connect", &self.connect),
            ("zenoh.listen", &self.listen),
        ] {
            for e in list {
                if !endpoint_shape_ok(e) {
                    return Err(check::invalid(
                        field,
                        crate::text::cut(e),
                        "zenoh endpoints such as tcp/192.168.1.10:7447 or tls/host:7447",
                    ));
                }
            }
        }
        Ok(())
    }

    /// Publishing rates, the inbox and sample sizes, sessions and handshakes.
    fn check_limits(&self) -> Result<(), ConfigError> {
        check::in_range(
            "zenoh.joint_rate_hz",
            self.joint_rate_hz,
            0.0,
            100_000.0,
            "0 (every tick) ..= 100000 Hz",
        )?;
        check::in_range(
            "zenoh.cartesian_rate_hz",
            self.cartesian_rate_hz,
            0.0,
            100_000.0,
            "0 (every tick) ..= 100000 Hz",
        )?;
        check::int_in("zenoh.inbox", self.inbox, 16, 1 << 20, "16 ..= 1048576")?;
        check::int_in(
            "zenoh.max_sample_bytes",
            self.max_sample_bytes,
            1024,
            16 << 20,
            "1024 ..= 16777216",
        )?;
        for (field, value, range) in [
            ("zenoh.max_sessions", self.max_sessions as u64, 1..=65536),
            ("zenoh.max_handshakes", self.max_handshakes as u64, 1..=4096),
            (
                "zenoh.handshake_timeout_ms",
                self.handshake_timeout_ms,
                100..=600_000,
            ),
        ] {
            if !range.contains(&value) {
                return Err(check::invalid(
                    field,
                    value.to_string(),
                    format!("{} ..= {}", range.start(), range.end()),
                ));
            }
        }
        Ok(())
    }

    /// Who may connect and command: user and password, commanders, mutual TLS.
    fn check_access(&self) -> Result<(), ConfigError> {
        if self.user.is_empty() != self.password.is_empty() {
            return Err(check::invalid(
                "zenoh.user",
                crate::text::cut(&self.user),
                "set together with zenoh.password (or neither)",
            ));
        }
        if self.user.contains(':') {
            return Err(check::invalid(
                "zenoh.user",
                crate::text::cut(&self.user),
                "a user name without ':'",
            ));
        }
        for c in &self.commanders {
            if c.is_empty() || c.contains(':') || c.chars().any(char::is_whitespace) {
                return Err(check::invalid(
                    "zenoh.commanders",
                    crate::text::cut(c),
                    "zenoh user names or certificate common names (no ':', no spaces)",
                ));
            }
        }
        if !self.commanders.is_empty() && self.users_file.is_empty() && !self.tls_mutual {
            return Err(check::invalid(
                "zenoh.commanders",
                format!("{:?}", self.commanders),
                "who connects must be authenticated to be told apart: set zenoh.users_file \
                 (user/password) or zenoh.tls_mutual (certificates)",
            ));
        }
        let tls = [
            &self.tls_certificate,
            &self.tls_private_key,
            &self.tls_root_ca,
        ];
        if self.tls_mutual && tls.iter().any(|s| s.is_empty()) {
            return Err(check::invalid(
                "zenoh.tls_mutual",
                "true",
                "needs zenoh.tls_certificate, zenoh.tls_private_key and zenoh.tls_root_ca",
            ));
        }
        Ok(())
    }

    /// Each teleoperation pair's name and pre-shared key.
    fn check_teleop_keys(&self) -> Result<(), ConfigError> {
        for (pair, key) in &self.teleop_keys {
            let names_ok = pair.split_once('/').is_some_and(|(l, f)| {
                omnid_client::find::check_arm_name(l).is_ok()
                    && omnid_client::find::check_arm_name(f).is_ok()
                    && l != f
            });
            if !names_ok {
                return Err(check::invalid(
                    "zenoh.teleop_keys",
                    crate::text::cut(pair),
                    "\"<leader>/<follower>\", two arm names",
                ));
            }
            if let Err(e) = pair_key(key) {
                return Err(check::invalid(
                    "zenoh.teleop_keys",
                    format!("{:?} (the key not shown)", crate::text::cut(pair)),
                    e,
                ));
            }
        }
        Ok(())
    }

    /// The pre-shared key of the pair `leader`→`follower`: none configured, or the key (an
    /// unreadable one is an error naming the setting).
    pub fn teleop_key(
        &self,
        leader: &str,
        follower: &str,
    ) -> Option<Result<crate::teleop::wire::PairKey, String>> {
        self.teleop_keys
            .get(&format!("{leader}/{follower}"))
            .map(pair_key)
    }

    /// The most descriptors zenoh's sessions and handshakes can hold (one link a session,
    /// zenoh's default), and a few of its own.
    pub fn descriptors(&self) -> u64 {
        self.max_sessions as u64 + self.max_handshakes as u64 + 32
    }

    /// The ROS 2 domain: `domain_id`, else `ROS_DOMAIN_ID`, else 0 (an unreadable variable is
    /// an error naming it).
    pub fn domain(&self) -> Result<u32, String> {
        if self.domain_id >= 0 {
            return Ok(self.domain_id as u32);
        }
        match std::env::var("ROS_DOMAIN_ID") {
            Err(_) => Ok(0),
            Ok(v) if v.trim().is_empty() => Ok(0),
            Ok(v) => v
                .trim()
                .parse::<u32>()
                .ok()
                .filter(|d| *d <= 232)
                .ok_or_else(|| {
                    format!(
                        "ROS_DOMAIN_ID={:?} is not a domain (0 ..= 232); set it, or \
                         [zenoh] domain_id",
                        crate::text::cut(&v)
                    )
                }),
        }
    }
}

/// Whether `e` has the shape of a zenoh endpoint, `<protocol>/<address>[?<metadata>][#<config>]`
/// (docs/ZENOH.md): protocol and address not empty; metadata and config, where present, one or
/// more `key[=value]` entries split by `;`, no key empty. The core links no zenoh, so this is
/// checked here by shape; `transport::zenoh` has a test that it agrees with zenoh's own parser.
pub fn endpoint_shape_ok(e: &str) -> bool {
    let Some((protocol, rest)) = e.split_once('/') else {
        return false;
    };
    let (rest, config) = match rest.split_once('#') {
        Some((r, c)) => (r, Some(c)),
        None => (rest, None),
    };
    let (address, metadata) = match rest.split_once('?') {
        Some((a, m)) => (a, Some(m)),
        None => (rest, None),
    };
    let params_ok = |p: &str| {
        let mut entries = p.split(';').filter(|kv| !kv.is_empty()).peekable();
        entries.peek().is_some() && entries.all(|kv| !kv.split('=').next().unwrap_or("").is_empty())
    };
    !protocol.is_empty()
        && !address.is_empty()
        && metadata.is_none_or(params_ok)
        && config.is_none_or(params_ok)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_key(pair: &str, key: &str) -> ZenohConfig {
        ZenohConfig {
            teleop_keys: [(pair.to_string(), Secret::from(key))].into(),
            ..ZenohConfig::default()
        }
    }

    #[test]
    fn passwords_and_keys_are_never_shown() {
        let cfg = ZenohConfig {
            user: "omnid".into(),
            password: "hunter2-password".into(),
            teleop_keys: [(
                "left/right".to_string(),
                Secret::from("2dEoOzyuZk8W2mWRzN0kqxUJ1NQ3gHc6kBzYw3h0n3U="),
            )]
            .into(),
            ..ZenohConfig::default()
        };
        let shown = [
            format!("{cfg:?}"),
            format!("{cfg:#?}"),
            toml::to_string(&cfg).unwrap(),
            serde_json::to_string(&cfg).unwrap(),
        ];
        for text in shown {
            assert!(
                !text.contains("hunter2") && !text.contains("2dEoOzyuZk8W"),
                "{text}"
            );
            assert!(text.contains("(hidden)"), "{text}");
        }
        // Read as written, used as written.
        let read: ZenohConfig = toml::from_str("password = \"pw-1234\"\nuser = \"u\"").unwrap();
        assert_eq!(read.password.expose(), "pw-1234");
        assert_eq!(format!("{:?}", ZenohConfig::default().password), "");
    }

    #[test]
    fn a_teleop_key_names_two_arms_and_is_base64_of_16_bytes_or_more() {
        let good = "2dEoOzyuZk8W2mWRzN0kqxUJ1NQ3gHc6kBzYw3h0n3U=";
        let cfg = with_key("left/right", good);
        assert!(cfg.validate().is_ok());
        assert!(matches!(cfg.teleop_key("left", "right"), Some(Ok(_))));
        assert!(cfg.teleop_key("right", "left").is_none());
        for pair in ["left", "left/", "/right", "a/b/c", "l*/r", "same/same"] {
            let e = with_key(pair, good).validate().unwrap_err().to_string();
            assert!(e.contains("zenoh.teleop_keys"), "{pair}: {e}");
        }
        // Not base64; too short (8 bytes): refused naming how to make one, never showing it.
        for key in ["not base64!", "c2hvcnRrZXk="] {
            let e = with_key("left/right", key)
                .validate()
                .unwrap_err()
                .to_string();
            assert!(e.contains("head -c32 /dev/urandom | base64"), "{e}");
            assert!(!e.contains(key), "{e}");
        }
    }
}
