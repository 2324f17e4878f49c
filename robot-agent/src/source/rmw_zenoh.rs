//! The wire format of ROS 2 over zenoh (`rmw_zenoh_cpp`, the zenoh middleware of ROS 2 Jazzy and later),
//! as far as a subscriber and a publisher of plain topics need it. Source: rmw_zenoh's `docs/design.md`
//! and its `liveliness_utils` / `attachment_helpers` sources (github.com/ros2/rmw_zenoh), cross-checked
//! with independent re-implementations of the protocol; written here from that description, not copied.
//!
//! **Data.** One zenoh publication per message, its payload the message's CDR bytes (encapsulation
//! header included, as in a rosbag2 recording), on the key expression
//!
//! ```text
//! <domain_id>/<fully qualified topic name without its leading '/'>/<DDS type name>/<type hash>
//! 0/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c19139...
//! ```
//!
//! The DDS type name is the ROS type `pkg/msg/Type` mangled the way the DDS type support names it:
//! `pkg::msg::dds_::Type_`. The type hash is `RIHS01_` and the 64 hex digits of the SHA-256 of the type's
//! description (REP 2011, "ROS Interface Hashing Standard" version 1); ROS 2 Humble's rmw_zenoh, which
//! has no type hashes, writes `TypeHashNotSupported` there. A subscriber here puts `*` in that chunk, so
//! it takes a topic whatever the publisher's ROS version; a publisher here writes the Jazzy hash of each
//! type it sends ([`OCCUPANCY_GRID`], [`TF_MESSAGE`], [`POSE_WITH_COVARIANCE_STAMPED`]: constants, and the
//! live test checks each against the hash Python's `rosbags` computes from the message definitions).
//!
//! **Attachment.** Each publication carries a zenoh attachment serialized with zenoh-ext's serializer:
//! the publisher's sequence number (`int64`, little endian, 1 for its first message), the source
//! timestamp (`int64` nanoseconds since the Unix epoch, little endian) and the publisher's GID (16 bytes,
//! written as a byte sequence: its length 16 as a LEB128 varint, then the bytes) — 33 bytes in all. The
//! first zenoh-1.0 releases of rmw_zenoh put each field's name before it (a zenoh-ext string: a varint
//! length and the UTF-8 bytes: `"sequence_number"`, `"source_timestamp"`, `"source_gid"`); [`Attachment::decode`]
//! reads both, [`Attachment::encode`] writes the current form.
//!
//! **Graph.** Every ROS entity announces itself with a zenoh liveliness token; `ros2 topic list` and
//! `ros2 node list` on rmw_zenoh read them. A publisher's token is
//!
//! ```text
//! @ros2_lv/<domain_id>/<session zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node name>/
//!     <topic>/<DDS type name>/<type hash>/<qos>
//! ```
//!
//! where an empty enclave or namespace is written `%` and every `/` inside a name is replaced by `%`
//! (`/map` → `%map`); the QoS is `<reliability>:<durability>:<history>,<depth>:<deadline>:<lifespan>:<liveliness>`
//! with rmw's enum values (reliable 1, best effort 2; transient local 1, volatile 2; keep last 1) and
//! the last three left at their defaults (`,` / `,,` with empty values). A node's token is the same up
//! to the node name, with `NN` and its node id twice. Data flows without these tokens (a zenoh
//! subscription matches any publication on its key); they only make the agent visible in the ROS graph.
//! Their exact QoS chunk has not been checked against a ROS node on this machine (there is none).

/// A ROS 2 message type as rmw_zenoh names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RosType {
    /// `pkg/msg/Type`.
    pub name: &'static str,
    /// `RIHS01_<sha256 hex>` of the type description (ROS 2 Jazzy's definitions).
    pub hash: &'static str,
}

/// `sensor_msgs/msg/LaserScan`.
pub const LASER_SCAN: RosType = RosType {
    name: "sensor_msgs/msg/LaserScan",
    hash: "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828",
};
/// `nav_msgs/msg/Odometry`.
pub const ODOMETRY: RosType = RosType {
    name: "nav_msgs/msg/Odometry",
    hash: "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
};
/// `sensor_msgs/msg/Imu`.
pub const IMU: RosType = RosType {
    name: "sensor_msgs/msg/Imu",
    hash: "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b",
};
/// `tf2_msgs/msg/TFMessage`.
pub const TF_MESSAGE: RosType = RosType {
    name: "tf2_msgs/msg/TFMessage",
    hash: "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
};
/// `nav_msgs/msg/OccupancyGrid`.
pub const OCCUPANCY_GRID: RosType = RosType {
    name: "nav_msgs/msg/OccupancyGrid",
    hash: "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
};
/// `geometry_msgs/msg/PoseWithCovarianceStamped`.
pub const POSE_WITH_COVARIANCE_STAMPED: RosType = RosType {
    name: "geometry_msgs/msg/PoseWithCovarianceStamped",
    hash: "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
};

/// A topic name or type that cannot be put on a key expression.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("ROS name {name:?}: {reason}")]
pub struct RosNameError {
    /// The name.
    pub name: String,
    /// What is wrong with it.
    pub reason: &'static str,
}

/// The DDS type name rmw_zenoh puts in key expressions: `pkg/msg/Type` → `pkg::msg::dds_::Type_`.
pub fn dds_type_name(ros_type: &str) -> Result<String, RosNameError> {
    let parts: Vec<&str> = ros_type.split('/').collect();
    let error = |reason| RosNameError {
        name: ros_type.to_owned(),
        reason,
    };
    let [package, kind, name] = parts[..] else {
        return Err(error("a type name is `package/msg/Type`"));
    };
    if [package, kind, name].iter().any(|p| !is_name_token(p)) {
        return Err(error(
            "each part must be non-empty letters, digits and underscores",
        ));
    }
    Ok(format!("{package}::{kind}::dds_::{name}_"))
}

fn is_name_token(s: &str) -> bool {
    !s.is_empty() && s.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_')
}

/// A fully qualified topic name (`/scan`, `/robot1/scan`) without its leading `/`, checked: ROS names
/// are `/`-separated tokens of letters, digits and underscores (so no zenoh wildcard can slip in).
fn topic_chunks(topic: &str) -> Result<&str, RosNameError> {
    let error = |reason| RosNameError {
        name: topic.to_owned(),
        reason,
    };
    let Some(relative) = topic.strip_prefix('/') else {
        return Err(error(
            "give the fully qualified name, starting with '/' (e.g. /scan)",
        ));
    };
    if !relative.split('/').all(is_name_token) {
        return Err(error(
            "each '/'-separated part must be non-empty letters, digits and underscores",
        ));
    }
    Ok(relative)
}

/// The key expression of `topic` of type `ros_type` in `domain_id`, with the type hash `hash` (`*` to
/// match any publisher's).
pub fn topic_key(
    domain_id: u32,
    topic: &str,
    ros_type: &str,
    hash: &str,
) -> Result<String, RosNameError> {
    Ok(format!(
        "{domain_id}/{}/{}/{hash}",
        topic_chunks(topic)?,
        dds_type_name(ros_type)?
    ))
}

/// Zenoh-ext serialization's LEB128 length prefix.
fn write_varint(out: &mut Vec<u8>, mut n: usize) {
    loop {
        let byte = (n & 0x7f) as u8;
        n >>= 7;
        if n == 0 {
            out.push(byte);
            return;
        }
        out.push(byte | 0x80);
    }
}

/// The metadata rmw_zenoh attaches to each publication.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Attachment {
    /// The publisher's message counter (1 for its first message).
    pub sequence_number: i64,
    /// When the message was published, nanoseconds since the Unix epoch.
    pub source_timestamp_ns: i64,
    /// The publisher's GID.
    pub source_gid: [u8; 16],
}

/// An attachment that is neither form rmw_zenoh writes.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("rmw_zenoh attachment of {len} bytes: {reason}")]
pub struct AttachmentError {
    /// Its length.
    pub len: usize,
    /// What did not fit.
    pub reason: String,
}

/// Reads zenoh-ext serialized values front to back, bounds-checked.
struct ExtReader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl ExtReader<'_> {
    fn error(&self, reason: impl Into<String>) -> AttachmentError {
        AttachmentError {
            len: self.bytes.len(),
            reason: reason.into(),
        }
    }

    fn varint(&mut self) -> Result<usize, AttachmentError> {
        let mut n = 0usize;
        for shift in (0..).step_by(7).take(10) {
            let Some(&byte) = self.bytes.get(self.pos) else {
                return Err(self.error("truncated length"));
            };
            self.pos += 1;
            n |= usize::from(byte & 0x7f)
                .checked_shl(shift)
                .ok_or_else(|| self.error("length overflows"))?;
            if byte & 0x80 == 0 {
                return Ok(n);
            }
        }
        Err(self.error("length longer than 10 bytes"))
    }

    fn take(&mut self, n: usize) -> Result<&[u8], AttachmentError> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&end| end <= self.bytes.len())
            .ok_or_else(|| self.error(format!("truncated at byte {}", self.pos)))?;
        let slice = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(slice)
    }

    fn i64(&mut self) -> Result<i64, AttachmentError> {
        let b = self.take(8)?;
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        Ok(i64::from_le_bytes(a))
    }

    fn bytes(&mut self) -> Result<&[u8], AttachmentError> {
        let n = self.varint()?;
        self.take(n)
    }

    fn key(&mut self, expected: &str) -> Result<(), AttachmentError> {
        let key = self.bytes()?;
        if key == expected.as_bytes() {
            return Ok(());
        }
        let found = String::from_utf8_lossy(key).into_owned();
        Err(self.error(format!("expected the key {expected:?}, found {found:?}")))
    }
}

impl Attachment {
    /// The current (33-byte) form.
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(33);
        out.extend_from_slice(&self.sequence_number.to_le_bytes());
        out.extend_from_slice(&self.source_timestamp_ns.to_le_bytes());
        write_varint(&mut out, self.source_gid.len());
        out.extend_from_slice(&self.source_gid);
        out
    }

    /// Reads either form (see the module docs).
    pub fn decode(bytes: &[u8]) -> Result<Self, AttachmentError> {
        let keyed = bytes.get(..16) == Some(b"\x0fsequence_number".as_slice());
        let mut r = ExtReader { bytes, pos: 0 };
        if keyed {
            r.key("sequence_number")?;
        }
        let sequence_number = r.i64()?;
        if keyed {
            r.key("source_timestamp")?;
        }
        let source_timestamp_ns = r.i64()?;
        if keyed {
            r.key("source_gid")?;
        }
        let gid = r.bytes()?;
        let gid_len = gid.len();
        let Ok(source_gid) = <[u8; 16]>::try_from(gid) else {
            return Err(r.error(format!("a GID has 16 bytes, this one {gid_len}")));
        };
        if r.pos != bytes.len() {
            return Err(r.error(format!("{} bytes left over", bytes.len() - r.pos)));
        }
        Ok(Self {
            sequence_number,
            source_timestamp_ns,
            source_gid,
        })
    }
}

/// How a publisher's messages are kept for late subscribers, in a liveliness token's QoS chunk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Durability {
    /// Late subscribers get the last `depth` messages (`/map`, as Nav2's map server offers it).
    TransientLocal,
    /// Late subscribers get only what comes after them.
    Volatile,
}

/// The name of an entity in a liveliness token: `%` for empty, `/` replaced by `%`.
fn mangle(name: &str) -> String {
    if name.is_empty() || name == "/" {
        "%".into()
    } else {
        name.replace('/', "%")
    }
}

/// The liveliness token of a node (see the module docs).
pub fn node_token(domain_id: u32, zid: &str, node_id: u32, namespace: &str, node: &str) -> String {
    format!(
        "@ros2_lv/{domain_id}/{zid}/{node_id}/{node_id}/NN/%/{}/{}",
        mangle(namespace),
        mangle(node)
    )
}

/// The liveliness token of a reliable, keep-last-`depth` publisher of `topic` (see the module docs).
#[allow(clippy::too_many_arguments)] // one token, one argument per field: a struct would only rename them
pub fn publisher_token(
    domain_id: u32,
    zid: &str,
    node_id: u32,
    entity_id: u32,
    node: &str,
    topic: &str,
    ros_type: &RosType,
    durability: Durability,
    depth: u32,
) -> Result<String, RosNameError> {
    topic_chunks(topic)?;
    let durability = match durability {
        Durability::TransientLocal => 1,
        Durability::Volatile => 2,
    };
    Ok(format!(
        "@ros2_lv/{domain_id}/{zid}/{node_id}/{entity_id}/MP/%/%/{}/{}/{}/{}/1:{durability}:1,{depth}:,:,:,,",
        mangle(node),
        mangle(topic),
        dds_type_name(ros_type.name)?,
        ros_type.hash
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn key_expressions_follow_rmw_zenoh() {
        assert_eq!(
            topic_key(0, "/scan", LASER_SCAN.name, LASER_SCAN.hash).unwrap(),
            format!(
                "0/scan/sensor_msgs::msg::dds_::LaserScan_/{}",
                LASER_SCAN.hash
            )
        );
        assert_eq!(
            topic_key(42, "/robot_1/odom", "nav_msgs/msg/Odometry", "*").unwrap(),
            "42/robot_1/odom/nav_msgs::msg::dds_::Odometry_/*"
        );
        for bad in ["scan", "/", "/a//b", "/a/", "/sc*n", "/a/**", "/$x"] {
            assert!(topic_key(0, bad, LASER_SCAN.name, "*").is_err(), "{bad}");
        }
        assert!(dds_type_name("sensor_msgs/LaserScan").is_err());
        assert!(dds_type_name("a/msg/B*").is_err());
        for t in [
            LASER_SCAN,
            ODOMETRY,
            IMU,
            TF_MESSAGE,
            OCCUPANCY_GRID,
            POSE_WITH_COVARIANCE_STAMPED,
        ] {
            assert!(
                t.hash.starts_with("RIHS01_") && t.hash.len() == 7 + 64,
                "{t:?}"
            );
        }
    }

    #[test]
    fn attachments_round_trip_and_both_forms_decode() {
        let a = Attachment {
            sequence_number: 7,
            source_timestamp_ns: 1_700_000_000_123_456_789,
            source_gid: std::array::from_fn(|i| i as u8),
        };
        let bytes = a.encode();
        assert_eq!(bytes.len(), 33);
        assert_eq!(bytes[16], 16);
        assert_eq!(Attachment::decode(&bytes).unwrap(), a);

        // The keyed form of the first zenoh-1.0 releases.
        let mut keyed = Vec::new();
        for (key, value) in [
            ("sequence_number", &bytes[..8]),
            ("source_timestamp", &bytes[8..16]),
        ] {
            write_varint(&mut keyed, key.len());
            keyed.extend_from_slice(key.as_bytes());
            keyed.extend_from_slice(value);
        }
        write_varint(&mut keyed, 10);
        keyed.extend_from_slice(b"source_gid");
        keyed.extend_from_slice(&bytes[16..]);
        assert_eq!(Attachment::decode(&keyed).unwrap(), a);

        for cut in [0, 8, 16, 20, 32] {
            assert!(Attachment::decode(&bytes[..cut]).is_err(), "cut {cut}");
        }
        let mut long = bytes.clone();
        long.push(0);
        assert!(Attachment::decode(&long).is_err());
        let mut short_gid = bytes[..16].to_vec();
        short_gid.push(3);
        short_gid.extend_from_slice(&[1, 2, 3]);
        assert!(Attachment::decode(&short_gid).is_err());
    }

    #[test]
    fn liveliness_tokens_name_the_entity() {
        assert_eq!(
            node_token(0, "abc", 3, "/", "evermap_agent"),
            "@ros2_lv/0/abc/3/3/NN/%/%/evermap_agent"
        );
        let token = publisher_token(
            0,
            "abc",
            3,
            4,
            "evermap_agent",
            "/map",
            &OCCUPANCY_GRID,
            Durability::TransientLocal,
            1,
        )
        .unwrap();
        assert_eq!(
            token,
            format!(
                "@ros2_lv/0/abc/3/4/MP/%/%/evermap_agent/%map/nav_msgs::msg::dds_::OccupancyGrid_/{}/1:1:1,1:,:,:,,",
                OCCUPANCY_GRID.hash
            )
        );
    }
}
