//! ROS 2's names on zenoh, as rmw_zenoh writes them (docs/ZENOH.md, The wire format): the data
//! key of a topic, the liveliness tokens that make a node and its endpoints appear in the ROS
//! graph, the QoS chunk in its default-omitted form, an endpoint's GID (XXH3-128 of its token)
//! and the 33-byte attachment every sample carries. Pure functions of strings and numbers: the
//! transport that uses them is `transport::zenoh`.

// Constants, fields and variants named for what rmw_zenoh and ROS call them (docs/ZENOH.md).
#![allow(missing_docs)]

use super::msgs::{self, MsgType};
use thiserror::Error;

/// A message type as rmw_zenoh names it: its ROS name and its RIHS01 type hash (REP-2016).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RosType {
    /// The message (name and schema).
    pub msg: MsgType,
    /// `RIHS01_<sha256 hex>` of its type description (docs/ROS2.md, Type hashes).
    pub hash: &'static str,
}

pub const JOINT_STATE: RosType = RosType {
    msg: msgs::JOINT_STATE,
    hash: "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
};
pub const POSE_STAMPED: RosType = RosType {
    msg: msgs::POSE_STAMPED,
    hash: "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
};
pub const TWIST_STAMPED: RosType = RosType {
    msg: msgs::TWIST_STAMPED,
    hash: "RIHS01_5f0fcd4f81d5d06ad9b4c4c63e3ea51b82d6ae4d0558f1d475229b1121db6f64",
};
pub const WRENCH_STAMPED: RosType = RosType {
    msg: msgs::WRENCH_STAMPED,
    hash: "RIHS01_8dc3deaf06b2ab281f9f9a742a8961c328ca7cec16e3fd6586d3a5c83fa78f77",
};
pub const JOY: RosType = RosType {
    msg: msgs::JOY,
    hash: "RIHS01_0d356c79cad3401e35ffeb75a96a96e08be3ef896b8b83841d73e890989372c5",
};
pub const STRING: RosType = RosType {
    msg: msgs::STRING,
    hash: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
};
pub const OPERATING_STATE: RosType = RosType {
    msg: msgs::OPERATING_STATE,
    hash: "RIHS01_5cc57eea589b217fe5194bf2735b91d4a7f2dd5ac1245ae657f7ea7590c2c80e",
};
pub const STRING_STAMPED: RosType = RosType {
    msg: msgs::STRING_STAMPED,
    hash: "RIHS01_83efb802e6596e03f69ac322e3231037329946f2bd13ed48874d97f5b8f5db1d",
};

/// What a key and a token carry in the type-hash field.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum HashForm {
    /// Jazzy and later: the RIHS01 hash.
    #[default]
    Rihs01,
    /// Humble's rmw_zenoh (0.1.x): the literal `TypeHashNotSupported`.
    Humble,
}

impl HashForm {
    fn of(self, t: &RosType) -> &'static str {
        match self {
            HashForm::Rihs01 => t.hash,
            HashForm::Humble => "TypeHashNotSupported",
        }
    }
}

/// The DDS name of `pkg/msg/Type`: `pkg::msg::dds_::Type_`.
pub fn dds_type_name(ros_name: &str) -> String {
    match ros_name.rsplit_once('/') {
        Some((pkg_msg, ty)) => format!("{}::dds_::{ty}_", pkg_msg.replace('/', "::")),
        None => format!("{ros_name}_"),
    }
}

/// A topic or namespace without its leading and trailing '/' (inner ones kept).
fn strip(name: &str) -> &str {
    name.trim_matches('/')
}

/// The key a topic's samples are put on: `<domain>/<topic>/<dds type>/<hash>`.
pub fn data_key(domain: u32, topic: &str, t: &RosType, form: HashForm) -> String {
    format!(
        "{domain}/{}/{}/{}",
        strip(topic),
        dds_type_name(t.msg.name),
        form.of(t)
    )
}

/// A name as a token chunk: every '/' written '%' (an empty name is "%", never empty).
pub fn mangle(name: &str) -> String {
    if name.is_empty() {
        return "%".into();
    }
    name.replace('/', "%")
}

/// A name back from a token chunk.
pub fn demangle(chunk: &str) -> String {
    chunk.replace('%', "/")
}

/// QoS reliability (rmw's numbers).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reliability {
    Reliable = 1,
    BestEffort = 2,
}

/// QoS durability (rmw's numbers).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Durability {
    TransientLocal = 1,
    Volatile = 2,
}

/// The QoS of an endpoint, as far as omnid sets it (history is always KEEP_LAST; deadline,
/// lifespan and liveliness are rmw_zenoh's defaults).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    pub reliability: Reliability,
    pub durability: Durability,
    pub depth: u32,
}

/// rmw_zenoh's default depth: written as an empty field.
const DEFAULT_DEPTH: u32 = 42;

impl Qos {
    /// CRTK's (cisst-ros) publishers and subscribers: reliable, volatile, depth 100.
    pub const CRTK: Qos = Qos {
        reliability: Reliability::Reliable,
        durability: Durability::Volatile,
        depth: 100,
    };

    /// The token chunk `R:D:H,depth:DLs,DLns:LSs,LSns:LV,LVs,LVns`, each field empty where it is
    /// rmw_zenoh's default (reliable, volatile, keep-last, 42, infinite, automatic), as rmw_zenoh
    /// rebuilds it: a receiver hashes that canonical token into the GID.
    pub fn chunk(&self) -> String {
        let r = match self.reliability {
            Reliability::Reliable => String::new(),
            other => (other as u8).to_string(),
        };
        let d = match self.durability {
            Durability::Volatile => String::new(),
            other => (other as u8).to_string(),
        };
        let depth = if self.depth == DEFAULT_DEPTH {
            String::new()
        } else {
            self.depth.to_string()
        };
        format!("{r}:{d}:,{depth}:,:,:,,")
    }

    /// A chunk back: reliability, durability and depth (`None` for what omnid does not write
    /// or a malformed chunk).
    pub fn parse(chunk: &str) -> Option<Qos> {
        let f: Vec<&str> = chunk.split(':').collect();
        if f.len() != 6 {
            return None;
        }
        let num = |s: &str, default: u32| -> Option<u32> {
            if s.is_empty() {
                Some(default)
            } else {
                s.parse().ok()
            }
        };
        let reliability = match num(f[0], 1)? {
            1 => Reliability::Reliable,
            2 => Reliability::BestEffort,
            _ => return None,
        };
        let durability = match num(f[1], 2)? {
            1 => Durability::TransientLocal,
            2 => Durability::Volatile,
            _ => return None,
        };
        let (history, depth) = f[2].split_once(',')?;
        if num(history, 1)? != 1 {
            return None;
        }
        Some(Qos {
            reliability,
            durability,
            depth: num(depth, DEFAULT_DEPTH)?,
        })
    }
}

/// A node: its namespace ("" or "/ns"), name and enclave ("" is the root, as rmw writes "/").
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Node {
    pub domain: u32,
    /// The zenoh session id, 32 lowercase hex digits.
    pub zid: String,
    /// Its id in the session (rmw_zenoh counts nodes and endpoints from 0 on one counter).
    pub id: u64,
    pub enclave: String,
    pub namespace: String,
    pub name: String,
}

/// An endpoint's kind, as its token spells it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    Publisher,
    Subscription,
}

impl Kind {
    pub fn as_str(self) -> &'static str {
        match self {
            Kind::Publisher => "MP",
            Kind::Subscription => "MS",
        }
    }
}

impl Node {
    fn prefix(&self, entity: u64, kind: &str) -> String {
        let enclave = if self.enclave.is_empty() {
            "/"
        } else {
            &self.enclave
        };
        let namespace = if self.namespace.is_empty() {
            "/"
        } else {
            &self.namespace
        };
        format!(
            "@ros2_lv/{}/{}/{}/{entity}/{kind}/{}/{}/{}",
            self.domain,
            self.zid,
            self.id,
            mangle(enclave),
            mangle(namespace),
            mangle(&self.name)
        )
    }

    /// The node's liveliness token.
    pub fn token(&self) -> String {
        self.prefix(self.id, "NN")
    }

    /// An endpoint's liveliness token (`topic` fully qualified, e.g. `/left/measured_js`).
    pub fn endpoint_token(
        &self,
        entity: u64,
        kind: Kind,
        topic: &str,
        t: &RosType,
        form: HashForm,
        qos: Qos,
    ) -> String {
        format!(
            "{}/{}/{}/{}/{}",
            self.prefix(entity, kind.as_str()),
            mangle(topic),
            mangle(&dds_type_name(t.msg.name)),
            mangle(form.of(t)),
            qos.chunk()
        )
    }
}

/// An endpoint token read back, as rmw_zenoh's graph cache parses it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Token {
    pub domain: u32,
    pub zid: String,
    pub node_id: u64,
    pub entity_id: u64,
    /// `NN`, `MP`, `MS`, `SS` or `SC`.
    pub kind: String,
    pub enclave: String,
    pub namespace: String,
    pub node_name: String,
    /// Endpoints only: topic, DDS type, hash and QoS chunk.
    pub topic: Option<String>,
    pub dds_type: Option<String>,
    pub hash: Option<String>,
    pub qos: Option<String>,
}

/// Parse a liveliness token (`None` if it is not one of rmw_zenoh's: wrong prefix, an empty or
/// missing chunk, a bad number).
pub fn parse_token(token: &str) -> Option<Token> {
    let parts: Vec<&str> = token.split('/').collect();
    if parts.first() != Some(&"@ros2_lv") || parts.iter().any(|p| p.is_empty()) {
        return None;
    }
    let (node_parts, endpoint) = match parts.len() {
        9 => (&parts[..], None),
        13 | 14 => (&parts[..9], Some(&parts[9..13])),
        _ => return None,
    };
    let kind = node_parts[5];
    if (kind == "NN") != endpoint.is_none() {
        return None;
    }
    Some(Token {
        domain: node_parts[1].parse().ok()?,
        zid: node_parts[2].into(),
        node_id: node_parts[3].parse().ok()?,
        entity_id: node_parts[4].parse().ok()?,
        kind: kind.into(),
        enclave: demangle(node_parts[6]),
        namespace: demangle(node_parts[7]),
        node_name: demangle(node_parts[8]),
        topic: endpoint.map(|e| demangle(e[0])),
        dds_type: endpoint.map(|e| demangle(e[1])),
        hash: endpoint.map(|e| demangle(e[2])),
        qos: endpoint.map(|e| e[3].into()),
    })
}

/// An endpoint's GID: XXH3-128 (seed 0) of its token, low 64 bits first, both little-endian.
pub fn gid(token: &str) -> [u8; 16] {
    xxhash_rust::xxh3::xxh3_128(token.as_bytes()).to_le_bytes()
}

/// Bytes of an attachment.
pub const ATTACHMENT_LEN: usize = 33;

/// The attachment every sample carries (rmw_zenoh's compact form): the publisher's sequence
/// number (from 1), the source time in ns since the Unix epoch, both i64 little-endian, then
/// the GID's length (16, one LEB128 byte) and the GID.
pub fn attachment(seq: i64, time_ns: i64, gid: &[u8; 16]) -> [u8; ATTACHMENT_LEN] {
    let mut a = [0u8; ATTACHMENT_LEN];
    a[..8].copy_from_slice(&seq.to_le_bytes());
    a[8..16].copy_from_slice(&time_ns.to_le_bytes());
    a[16] = 16;
    a[17..].copy_from_slice(gid);
    a
}

/// Why an attachment could not be read.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum AttachmentError {
    #[error("the attachment is {0} bytes; rmw_zenoh's is {ATTACHMENT_LEN}")]
    Length(usize),
    #[error("the attachment's GID length byte is {0}; rmw_zenoh writes 16")]
    GidLength(u8),
}

/// An attachment's sequence number, source time (ns) and GID.
pub fn read_attachment(a: &[u8]) -> Result<(i64, i64, [u8; 16]), AttachmentError> {
    let a: &[u8; ATTACHMENT_LEN] = a.try_into().map_err(|_| AttachmentError::Length(a.len()))?;
    if a[16] != 16 {
        return Err(AttachmentError::GidLength(a[16]));
    }
    let mut gid = [0u8; 16];
    gid.copy_from_slice(&a[17..]);
    let i64_at = |i: usize| i64::from_le_bytes(a[i..i + 8].try_into().unwrap_or([0; 8]));
    Ok((i64_at(0), i64_at(8), gid))
}

#[cfg(test)]
mod tests {
    use super::*;

    // rmw_zenoh's documented example (its design document): the demo talker's publisher token,
    // made again from its parts, and its GID computed by Python's xxhash (docs/ROS2.md).
    const TALKER: &str = "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/\
        %chatter/std_msgs::msg::dds_::String_/\
        RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,";

    fn talker_node() -> Node {
        Node {
            domain: 0,
            zid: "8b20917502ee955ac4476e0266340d5c".into(),
            id: 0,
            enclave: String::new(),
            namespace: String::new(),
            name: "talker".into(),
        }
    }

    fn hex(b: &[u8]) -> String {
        b.iter().map(|x| format!("{x:02x}")).collect()
    }

    #[test]
    fn the_documented_talker_token_is_made_again_with_its_gid() {
        let qos = Qos {
            depth: 7,
            ..Qos::CRTK
        };
        let token = talker_node().endpoint_token(
            10,
            Kind::Publisher,
            "/chatter",
            &STRING,
            HashForm::Rihs01,
            qos,
        );
        assert_eq!(token, TALKER);
        assert_eq!(hex(&gid(&token)), "eb85fa883b7846dc448a4501890ad062");
        assert_eq!(
            talker_node().token(),
            "@ros2_lv/0/8b20917502ee955ac4476e0266340d5c/0/0/NN/%/%/talker"
        );
        let t = parse_token(&token).unwrap();
        assert_eq!(
            (t.kind.as_str(), t.entity_id, t.topic.as_deref()),
            ("MP", 10, Some("/chatter"))
        );
        assert_eq!(Qos::parse(t.qos.as_deref().unwrap()), Some(qos));
    }

    #[test]
    fn keys_and_tokens_of_an_arm_namespace() {
        assert_eq!(
            data_key(0, "/left/measured_js", &JOINT_STATE, HashForm::Rihs01),
            "0/left/measured_js/sensor_msgs::msg::dds_::JointState_/\
             RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
        );
        assert_eq!(
            data_key(7, "left/servo_cf/", &WRENCH_STAMPED, HashForm::Humble),
            "7/left/servo_cf/geometry_msgs::msg::dds_::WrenchStamped_/TypeHashNotSupported"
        );
        assert_eq!(
            dds_type_name("crtk_msgs/msg/OperatingState"),
            "crtk_msgs::msg::dds_::OperatingState_"
        );
        let node = Node {
            domain: 3,
            zid: "0123456789abcdef0123456789abcdef".into(),
            id: 0,
            enclave: String::new(),
            namespace: "/lab".into(),
            name: "omnid".into(),
        };
        assert_eq!(
            node.token(),
            "@ros2_lv/3/0123456789abcdef0123456789abcdef/0/0/NN/%/%lab/omnid"
        );
        let sub = node.endpoint_token(
            4,
            Kind::Subscription,
            "/lab/left/servo_cf",
            &WRENCH_STAMPED,
            HashForm::Rihs01,
            Qos::CRTK,
        );
        assert_eq!(
            sub,
            "@ros2_lv/3/0123456789abcdef0123456789abcdef/0/4/MS/%/%lab/omnid/%lab%left%servo_cf/\
             geometry_msgs::msg::dds_::WrenchStamped_/\
             RIHS01_8dc3deaf06b2ab281f9f9a742a8961c328ca7cec16e3fd6586d3a5c83fa78f77/::,100:,:,:,,"
        );
        let t = parse_token(&sub).unwrap();
        assert_eq!(t.namespace, "/lab");
        assert_eq!(t.topic.as_deref(), Some("/lab/left/servo_cf"));
    }

    #[test]
    fn qos_chunks_leave_defaults_empty() {
        let best_effort = Qos {
            reliability: Reliability::BestEffort,
            durability: Durability::Volatile,
            depth: 5,
        };
        assert_eq!(best_effort.chunk(), "2::,5:,:,:,,");
        let latched = Qos {
            durability: Durability::TransientLocal,
            ..Qos::CRTK
        };
        assert_eq!(latched.chunk(), ":1:,100:,:,:,,");
        let default = Qos {
            depth: 42,
            ..Qos::CRTK
        };
        assert_eq!(default.chunk(), "::,:,:,:,,");
        for q in [best_effort, latched, default, Qos::CRTK] {
            assert_eq!(Qos::parse(&q.chunk()), Some(q));
        }
        assert_eq!(Qos::parse("::,10:,:,"), None);
        assert_eq!(Qos::parse("9::,10:,:,:,,"), None);
    }

    #[test]
    fn attachments_are_33_bytes_in_rmw_zenohs_layout() {
        let g = gid(TALKER);
        let a = attachment(1, 1_700_000_000_123_456_789, &g);
        assert_eq!(a.len(), 33);
        assert_eq!(&a[..8], &[1, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(&a[8..16], &1_700_000_000_123_456_789i64.to_le_bytes());
        assert_eq!(a[16], 0x10);
        assert_eq!(hex(&a[17..]), "eb85fa883b7846dc448a4501890ad062");
        assert_eq!(read_attachment(&a), Ok((1, 1_700_000_000_123_456_789, g)));
        assert_eq!(read_attachment(&a[..32]), Err(AttachmentError::Length(32)));
        let mut bad = a;
        bad[16] = 8;
        assert_eq!(read_attachment(&bad), Err(AttachmentError::GidLength(8)));
    }

    #[test]
    fn malformed_tokens_are_not_parsed() {
        for t in [
            "@ros2_lv/0/z/0/0/NN/%/%",
            "@ros2_lv/0/z/0/0/NN//%/node",
            "@ros2_lv/x/z/0/0/NN/%/%/node",
            "@ros2_lv/0/z/0/1/MP/%/%/node",
            "other/0/z/0/0/NN/%/%/node",
        ] {
            assert_eq!(parse_token(t), None, "{t}");
        }
    }
}
