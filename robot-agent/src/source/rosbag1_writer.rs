//! Writing a recording as a ROS1 bag (format 2.0, uncompressed chunks), so simulated sessions can be read
//! by every tool — ours, `rosbag`, `rqt_bag`, evo — like real data.
//!
//! No maintained Rust crate writes ROS1 bags (the `rosbag` crate we read with is read-only), and the
//! format is small: a bag header record padded to 4 KiB, chunks holding connection and message-data
//! records, one index-data record per connection after each chunk, then the connection records and one
//! chunk-info record per chunk at `index_pos`.
//!
//! Topics: `/scan` (`sensor_msgs/LaserScan`, frame `laser`), `/odom` (`nav_msgs/Odometry`, `odom` →
//! `base_link`), `/imu` (`sensor_msgs/Imu`, yaw rate only), `/tf_static` (`tf2_msgs/TFMessage`,
//! `base_link` → `laser`, written once at the start).

use std::io::{Seek, SeekFrom, Write};

use mapping::geometry::{Rigid2, Rigid2Ext as _};
use mapping::sensor::{SensorEvent, Timestamp};

use super::ros_definitions::{
    IMU_DEFINITION, LASER_SCAN_DEFINITION, ODOMETRY_DEFINITION, TF_MESSAGE_DEFINITION,
};

/// Messages per chunk (about 2.5 MB of scans).
const MESSAGES_PER_CHUNK: usize = 1000;

const OP_MESSAGE_DATA: u8 = 0x02;
const OP_BAG_HEADER: u8 = 0x03;
const OP_INDEX_DATA: u8 = 0x04;
const OP_CHUNK: u8 = 0x05;
const OP_CHUNK_INFO: u8 = 0x06;
const OP_CONNECTION: u8 = 0x07;

/// The bag's connections: (topic, type, md5sum, definition).
const CONNECTIONS: [(&str, &str, &str, &str); 4] = [
    (
        "/tf_static",
        "tf2_msgs/TFMessage",
        "94810edda583a504dfda3829e70d7eec",
        TF_MESSAGE_DEFINITION,
    ),
    (
        "/scan",
        "sensor_msgs/LaserScan",
        "90c7ef2dc6895d81024acba2ac42f369",
        LASER_SCAN_DEFINITION,
    ),
    (
        "/odom",
        "nav_msgs/Odometry",
        "cd5e73d190d741a2f92e81eda573aca7",
        ODOMETRY_DEFINITION,
    ),
    (
        "/imu",
        "sensor_msgs/Imu",
        "6a62c6daae103f4ff57a132d6f95cec2",
        IMU_DEFINITION,
    ),
];

fn field(out: &mut Vec<u8>, name: &str, value: &[u8]) {
    out.extend_from_slice(&((name.len() + 1 + value.len()) as u32).to_le_bytes());
    out.extend_from_slice(name.as_bytes());
    out.push(b'=');
    out.extend_from_slice(value);
}

fn record(out: &mut Vec<u8>, header: &[u8], data: &[u8]) {
    out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    out.extend_from_slice(header);
    out.extend_from_slice(&(data.len() as u32).to_le_bytes());
    out.extend_from_slice(data);
}

fn ros_time(t: Timestamp) -> [u8; 8] {
    let sec = t.0.div_euclid(1_000_000_000) as u32;
    let nsec = t.0.rem_euclid(1_000_000_000) as u32;
    let mut b = [0; 8];
    b[..4].copy_from_slice(&sec.to_le_bytes());
    b[4..].copy_from_slice(&nsec.to_le_bytes());
    b
}

/// Serializes ROS messages (little-endian, length-prefixed strings and arrays).
struct Ser(Vec<u8>);

impl Ser {
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn string(&mut self, s: &str) {
        self.u32(s.len() as u32);
        self.0.extend_from_slice(s.as_bytes());
    }
    fn header(&mut self, seq: u32, t: Timestamp, frame: &str) {
        self.u32(seq);
        self.0.extend_from_slice(&ros_time(t));
        self.string(frame);
    }
    fn zeros_f64(&mut self, n: usize) {
        for _ in 0..n {
            self.f64(0.0);
        }
    }
    /// A planar pose as geometry_msgs Point + Quaternion.
    fn pose(&mut self, pose: &Rigid2) {
        let half = 0.5 * pose.theta();
        for v in [pose.translation.x, pose.translation.y, 0.0] {
            self.f64(v);
        }
        for v in [0.0, 0.0, half.sin(), half.cos()] {
            self.f64(v);
        }
    }
}

/// Errors of [`write_bag`].
#[derive(Debug, thiserror::Error)]
pub enum BagWriteError {
    /// Writing failed.
    #[error("cannot write the bag: {0}")]
    Io(#[from] std::io::Error),
    /// There is nothing to write.
    #[error("no sensor events to write")]
    Empty,
}

struct Chunk {
    position: u64,
    start: Timestamp,
    end: Timestamp,
    /// Per connection: (time, offset in the chunk's data) of each message.
    index: Vec<Vec<(Timestamp, u32)>>,
    data: Vec<u8>,
}

/// Writes `events` (time-ordered) and the laser mounting `base_from_laser` as a ROS1 bag.
pub fn write_bag<W: Write + Seek>(
    out: &mut W,
    events: &[SensorEvent],
    base_from_laser: &Rigid2,
) -> Result<(), BagWriteError> {
    let first = events.first().ok_or(BagWriteError::Empty)?.time();
    out.write_all(b"#ROSBAG V2.0\n")?;
    let header_position = out.stream_position()?;
    write_bag_header(out, 0, 0, 0)?;

    let mut messages: Vec<(usize, Timestamp, Vec<u8>)> = Vec::with_capacity(events.len() + 1);
    let mut tf = Ser(Vec::new());
    tf.u32(1);
    tf.header(0, first, "base_link");
    tf.string("laser");
    let half = 0.5 * base_from_laser.theta();
    for v in [
        base_from_laser.translation.x,
        base_from_laser.translation.y,
        0.0,
    ] {
        tf.f64(v);
    }
    for v in [0.0, 0.0, half.sin(), half.cos()] {
        tf.f64(v);
    }
    messages.push((0, first, tf.0));
    let mut seq = [0u32; 4];
    for event in events {
        let mut m = Ser(Vec::new());
        let connection = match event {
            SensorEvent::Scan(scan) => {
                m.header(seq[1], scan.time, "laser");
                let n = scan.ranges.len();
                m.f32(scan.angle_min);
                m.f32(scan.angle_min + scan.angle_increment * n.saturating_sub(1) as f32);
                m.f32(scan.angle_increment);
                m.f32(scan.time_increment);
                m.f32(0.0);
                m.f32(scan.range_min);
                m.f32(scan.range_max);
                m.u32(n as u32);
                for r in &scan.ranges {
                    m.f32(*r);
                }
                m.u32(0);
                1
            }
            SensorEvent::Odometry(odometry) => {
                m.header(seq[2], odometry.time, "odom");
                m.string("base_link");
                m.pose(&odometry.pose);
                m.zeros_f64(36 + 6 + 36);
                2
            }
            SensorEvent::Imu(imu) => {
                m.header(seq[3], imu.time, "imu");
                for v in [0.0, 0.0, 0.0, 1.0] {
                    m.f64(v);
                }
                // Orientation unknown: covariance[0] = -1 per the message's convention.
                m.f64(-1.0);
                m.zeros_f64(8);
                for v in [0.0, 0.0, imu.yaw_rate] {
                    m.f64(v);
                }
                m.zeros_f64(9 + 3);
                m.f64(-1.0);
                m.zeros_f64(8);
                3
            }
        };
        seq[connection] += 1;
        messages.push((connection, event.time(), m.0));
    }

    let mut chunks = Vec::new();
    let mut written = [false; 4];
    for group in messages.chunks(MESSAGES_PER_CHUNK) {
        let mut chunk = Chunk {
            position: out.stream_position()?,
            start: group[0].1,
            end: group[0].1,
            index: vec![Vec::new(); 4],
            data: Vec::new(),
        };
        for (connection, time, payload) in group {
            if !written[*connection] {
                connection_record(&mut chunk.data, *connection);
                written[*connection] = true;
            }
            chunk.index[*connection].push((*time, chunk.data.len() as u32));
            let mut header = Vec::new();
            field(&mut header, "op", &[OP_MESSAGE_DATA]);
            field(&mut header, "conn", &(*connection as u32).to_le_bytes());
            field(&mut header, "time", &ros_time(*time));
            record(&mut chunk.data, &header, payload);
            chunk.start = chunk.start.min(*time);
            chunk.end = chunk.end.max(*time);
        }
        let mut bytes = Vec::new();
        let mut header = Vec::new();
        field(&mut header, "op", &[OP_CHUNK]);
        field(&mut header, "compression", b"none");
        field(
            &mut header,
            "size",
            &(chunk.data.len() as u32).to_le_bytes(),
        );
        record(&mut bytes, &header, &chunk.data);
        for (connection, entries) in chunk.index.iter().enumerate() {
            if entries.is_empty() {
                continue;
            }
            let mut header = Vec::new();
            field(&mut header, "op", &[OP_INDEX_DATA]);
            field(&mut header, "ver", &1u32.to_le_bytes());
            field(&mut header, "conn", &(connection as u32).to_le_bytes());
            field(&mut header, "count", &(entries.len() as u32).to_le_bytes());
            let mut data = Vec::with_capacity(12 * entries.len());
            for (time, offset) in entries {
                data.extend_from_slice(&ros_time(*time));
                data.extend_from_slice(&offset.to_le_bytes());
            }
            record(&mut bytes, &header, &data);
        }
        out.write_all(&bytes)?;
        chunk.data = Vec::new();
        chunks.push(chunk);
    }

    let index_position = out.stream_position()?;
    let mut bytes = Vec::new();
    let connections = (0..4).filter(|c| written[*c]).count() as u32;
    for connection in (0..4).filter(|c| written[*c]) {
        connection_record(&mut bytes, connection);
    }
    for chunk in &chunks {
        let counts: Vec<(u32, u32)> = chunk
            .index
            .iter()
            .enumerate()
            .filter(|(_, e)| !e.is_empty())
            .map(|(c, e)| (c as u32, e.len() as u32))
            .collect();
        let mut header = Vec::new();
        field(&mut header, "op", &[OP_CHUNK_INFO]);
        field(&mut header, "ver", &1u32.to_le_bytes());
        field(&mut header, "chunk_pos", &chunk.position.to_le_bytes());
        field(&mut header, "start_time", &ros_time(chunk.start));
        field(&mut header, "end_time", &ros_time(chunk.end));
        field(&mut header, "count", &(counts.len() as u32).to_le_bytes());
        let mut data = Vec::new();
        for (c, n) in counts {
            data.extend_from_slice(&c.to_le_bytes());
            data.extend_from_slice(&n.to_le_bytes());
        }
        record(&mut bytes, &header, &data);
    }
    out.write_all(&bytes)?;
    out.seek(SeekFrom::Start(header_position))?;
    write_bag_header(out, index_position, connections, chunks.len() as u32)?;
    out.seek(SeekFrom::End(0))?;
    out.flush()?;
    Ok(())
}

fn connection_record(out: &mut Vec<u8>, connection: usize) {
    let (topic, datatype, md5, definition) = CONNECTIONS[connection];
    let mut header = Vec::new();
    field(&mut header, "op", &[OP_CONNECTION]);
    field(&mut header, "conn", &(connection as u32).to_le_bytes());
    field(&mut header, "topic", topic.as_bytes());
    let mut data = Vec::new();
    field(&mut data, "topic", topic.as_bytes());
    field(&mut data, "type", datatype.as_bytes());
    field(&mut data, "md5sum", md5.as_bytes());
    field(&mut data, "message_definition", definition.as_bytes());
    if topic == "/tf_static" {
        field(&mut data, "latching", b"1");
    }
    record(out, &header, &data);
}

/// The bag header record, padded with spaces so the record is 4096 bytes long (so it can be rewritten in
/// place once the index position is known).
fn write_bag_header<W: Write>(
    out: &mut W,
    index_position: u64,
    connections: u32,
    chunks: u32,
) -> Result<(), BagWriteError> {
    let mut header = Vec::new();
    field(&mut header, "op", &[OP_BAG_HEADER]);
    field(&mut header, "index_pos", &index_position.to_le_bytes());
    field(&mut header, "conn_count", &connections.to_le_bytes());
    field(&mut header, "chunk_count", &chunks.to_le_bytes());
    let padding = 4096 - 8 - header.len();
    let mut bytes = Vec::with_capacity(4096);
    record(&mut bytes, &header, &vec![b' '; padding]);
    out.write_all(&bytes)?;
    Ok(())
}
