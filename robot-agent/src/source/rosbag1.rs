//! ROS1 bag (format 2.0) reading with the `rosbag` crate. We walk the chunk section record by record,
//! so bags with missing or non-standard index records read the same as clean ones; the index section
//! is never needed.

use std::collections::BTreeMap;
use std::path::Path;

use rosbag::{ChunkRecord, MessageRecord, RosBag};

use super::SourceError;
use super::recording::Recording;
use super::ros_collector::{Decoders, RosCollector, RosKind};
use super::ros_messages;

fn kind_of(datatype: &str) -> RosKind {
    match datatype {
        "sensor_msgs/LaserScan" => RosKind::Scan,
        "nav_msgs/Odometry" => RosKind::Odometry,
        "sensor_msgs/Imu" => RosKind::Imu,
        "tf2_msgs/TFMessage" | "tf/tfMessage" => RosKind::Tf,
        _ => RosKind::Other,
    }
}

/// ROS1 serialization's decoders.
const ROS1_DECODERS: Decoders = Decoders {
    laser_scan: ros_messages::laser_scan,
    odometry: ros_messages::odometry,
    imu: ros_messages::imu,
    tf_message: ros_messages::tf_message,
};

fn u32_at(bytes: &[u8], at: usize) -> Option<u32> {
    bytes
        .get(at..at + 4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

/// Header fields of one record: `(name, value)` pairs.
fn header_fields(header: &[u8]) -> Vec<(&[u8], &[u8])> {
    let mut fields = Vec::new();
    let mut i = 0;
    while let Some(n) = u32_at(header, i) {
        let Some(field) = header.get(i + 4..i + 4 + n as usize) else {
            break;
        };
        if let Some(eq) = field.iter().position(|&b| b == b'=') {
            fields.push((&field[..eq], &field[eq + 1..]));
        }
        i += 4 + n as usize;
    }
    fields
}

/// Walks the top-level records before handing the file to `rosbag` (which trusts lengths and offsets),
/// so that truncated bags and bags with non-standard index records get a clear error instead of a
/// panic or a confusing one.
fn prescan(path: &Path, bytes: &[u8]) -> Result<(), SourceError> {
    let malformed = |what: String| SourceError::Malformed {
        path: path.display().to_string(),
        format: "ROS1 bag",
        what,
    };
    let mut pos = 13;
    let mut index_pos = None;
    while pos < bytes.len() {
        let header_len = u32_at(bytes, pos)
            .ok_or_else(|| malformed(format!("file ends inside a record header at byte {pos}")))?;
        let header = bytes
            .get(pos + 4..pos + 4 + header_len as usize)
            .ok_or_else(|| {
                malformed(format!(
                    "record header at byte {pos} runs past the end of the file (truncated bag)"
                ))
            })?;
        let data_at = pos + 4 + header_len as usize;
        let data_len = u32_at(bytes, data_at)
            .ok_or_else(|| malformed(format!("file ends inside the record at byte {pos}")))?;
        if data_at + 4 + data_len as usize > bytes.len() {
            return Err(malformed(format!(
                "record at byte {pos} runs past the end of the file (truncated bag)"
            )));
        }
        let fields = header_fields(header);
        let field = |name: &[u8]| fields.iter().find(|(k, _)| *k == name).map(|(_, v)| *v);
        match field(b"op") {
            Some([0x03]) => {
                index_pos = field(b"index_pos")
                    .and_then(|v| v.try_into().ok())
                    .map(u64::from_le_bytes);
            }
            Some([0x04]) => {
                let ver = field(b"ver").and_then(|v| u32_at(v, 0));
                let count = field(b"count").and_then(|v| u32_at(v, 0));
                if let (Some(1), Some(count)) = (ver, count)
                    && u64::from(data_len) != u64::from(count) * 12
                {
                    return Err(malformed(format!(
                        "non-standard index record at byte {pos}: {data_len} data bytes for {count} entries \
                         (format 2.0 stores 12 bytes per entry), so the records after it cannot be located; \
                         rewrite the bag with `rosbag reindex` or `rosbag fix`"
                    )));
                }
            }
            None => return Err(malformed(format!("record at byte {pos} has no op field"))),
            Some(_) => {}
        }
        pos = data_at + 4 + data_len as usize;
    }
    match index_pos {
        Some(p) if p > 0 && p <= bytes.len() as u64 => Ok(()),
        Some(p) => Err(malformed(format!(
            "index_pos {p} is outside the file ({} bytes): the bag was not closed properly (try `rosbag reindex`)",
            bytes.len()
        ))),
        None => Err(malformed("no bag header record".into())),
    }
}

/// Reads every LaserScan, Odometry, Imu and TF message of a bag.
pub fn read(path: &Path) -> Result<Recording, SourceError> {
    let bytes = std::fs::read(path).map_err(|source| SourceError::Io {
        path: path.display().to_string(),
        source,
    })?;
    prescan(path, &bytes)?;
    drop(bytes);
    let malformed = |what: String| SourceError::Malformed {
        path: path.display().to_string(),
        format: "ROS1 bag",
        what,
    };
    let bag = RosBag::new(path).map_err(|e| malformed(e.to_string()))?;

    let mut connections: BTreeMap<u32, RosKind> = BTreeMap::new();
    let mut collector = RosCollector::default();
    for record in bag.chunk_records() {
        let record = record.map_err(|e| malformed(format!("chunk section: {e}")))?;
        let ChunkRecord::Chunk(chunk) = record else {
            continue;
        };
        for message in chunk.messages() {
            match message.map_err(|e| malformed(format!("inside a chunk: {e}")))? {
                MessageRecord::Connection(c) => {
                    connections.insert(c.id, kind_of(c.tp));
                }
                MessageRecord::MessageData(m) => {
                    let Some(&kind) = connections.get(&m.conn_id) else {
                        collector.report.skipped_malformed += 1;
                        collector
                            .report
                            .problem(format!("message on unknown connection {}", m.conn_id));
                        continue;
                    };
                    collector.add(kind, m.data, &m.time, &ROS1_DECODERS);
                }
            }
        }
    }
    Ok(collector.finish())
}
