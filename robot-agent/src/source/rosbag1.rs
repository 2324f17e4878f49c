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

/// Largest uncompressed chunk accepted, bytes. `rosbag` reserves a chunk's declared `size` before
/// decompressing it, so without a cap a 4-byte field makes it allocate up to 4 GiB. ROS1 writes chunks of
/// about 768 KiB (`rosbag record --chunksize`) plus at most one message.
pub const MAX_CHUNK_BYTES: u32 = 256 << 20;

/// Walks the top-level records before handing the file to `rosbag` (which trusts lengths and offsets),
/// so that truncated bags, bags with non-standard index records, offsets outside the chunk section and
/// chunk sizes that cannot be true get a clear error instead of a panic or a huge allocation.
fn prescan(path: &Path, bytes: &[u8]) -> Result<(), SourceError> {
    let malformed = |what: String| SourceError::Malformed {
        path: path.display().to_string(),
        format: "ROS1 bag",
        source: None,
        what,
    };
    let mut pos = 13;
    let mut index_pos = None;
    // Where the chunk section starts: after the bag header record, the first record.
    let mut chunk_section = None;
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
                chunk_section.get_or_insert(data_at + 4 + data_len as usize);
            }
            Some([0x05]) => {
                let size = field(b"size").and_then(|v| u32_at(v, 0)).unwrap_or(0);
                let uncompressed = field(b"compression") == Some(b"none".as_slice());
                if size > MAX_CHUNK_BYTES || (uncompressed && size != data_len) {
                    return Err(malformed(format!(
                        "chunk at byte {pos} declares {size} uncompressed bytes for {data_len} stored \
                         bytes (at most {MAX_CHUNK_BYTES}, and exactly the stored size when uncompressed)"
                    )));
                }
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
    match (index_pos, chunk_section) {
        (Some(p), Some(start)) if p >= start as u64 && p <= bytes.len() as u64 => Ok(()),
        (Some(p), Some(start)) => Err(malformed(format!(
            "index_pos {p} is outside the chunk section (bytes {start}..={}): the bag was not closed \
             properly (try `rosbag reindex`)",
            bytes.len()
        ))),
        _ => Err(malformed("no bag header record".into())),
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
    let malformed_by =
        |what: String, source: Box<dyn std::error::Error + Send + Sync>| SourceError::Malformed {
            path: path.display().to_string(),
            format: "ROS1 bag",
            source: Some(source),
            what,
        };
    let bag = RosBag::new(path).map_err(|e| malformed_by(e.to_string(), e.into()))?;

    let mut connections: BTreeMap<u32, RosKind> = BTreeMap::new();
    let mut collector = RosCollector::default();
    for record in bag.chunk_records() {
        let record = record.map_err(|e| malformed_by(format!("chunk section: {e}"), e.into()))?;
        let ChunkRecord::Chunk(chunk) = record else {
            continue;
        };
        for message in chunk.messages() {
            match message.map_err(|e| malformed_by(format!("inside a chunk: {e}"), e.into()))? {
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

#[cfg(test)]
mod tests {
    use mapping::geometry::{Rigid2, rigid2};
    use mapping::sensor::{LaserScan, OdometryReading, SensorEvent, Timestamp};

    use super::*;

    fn small_bag() -> Vec<u8> {
        let time = Timestamp(1_000_000_000);
        let events = vec![
            SensorEvent::Odometry(OdometryReading {
                time,
                pose: rigid2(0.0, 0.0, 0.0),
            }),
            SensorEvent::Scan(LaserScan {
                time,
                angle_min: -1.0,
                angle_increment: 0.5,
                time_increment: 0.0,
                range_min: 0.1,
                range_max: 30.0,
                ranges: vec![1.0, 2.0, 3.0, 4.0, 5.0],
            }),
        ];
        let mut out = std::io::Cursor::new(Vec::new());
        super::super::write_bag(&mut out, &events, &Rigid2::identity()).unwrap();
        out.into_inner()
    }

    /// Overwrites the value of the first header field `name=` (`value.len()` bytes).
    fn patch_field(bag: &mut [u8], name: &[u8], value: &[u8]) {
        let needle: Vec<u8> = [name, b"="].concat();
        let at = bag
            .windows(needle.len())
            .position(|w| w == needle.as_slice())
            .unwrap()
            + needle.len();
        bag[at..at + value.len()].copy_from_slice(value);
    }

    fn read_bytes(bytes: &[u8]) -> Result<Recording, SourceError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("test.bag");
        std::fs::write(&path, bytes).unwrap();
        read(&path)
    }

    #[test]
    fn a_written_bag_reads_back() {
        let recording = read_bytes(&small_bag()).unwrap();
        assert_eq!(recording.report.scans, 1);
        assert_eq!(recording.report.odometry, 1);
    }

    /// Fuzz finding (regression): an `index_pos` before the chunk section made `rosbag` slice
    /// `data[start..index_pos]` backwards, a panic.
    #[test]
    fn index_pos_before_the_chunk_section_is_malformed() {
        let mut bag = small_bag();
        patch_field(&mut bag, b"index_pos", &5_u64.to_le_bytes());
        let err = read_bytes(&bag).unwrap_err().to_string();
        assert!(
            err.contains("index_pos 5 is outside the chunk section"),
            "{err}"
        );
    }

    /// Fuzz finding (regression): a chunk's `size` field is reserved by `rosbag` before decompressing,
    /// so 4 bytes made it allocate 4 GiB.
    #[test]
    fn impossible_chunk_sizes_are_malformed() {
        for size in [u32::MAX, MAX_CHUNK_BYTES + 1, 7] {
            let mut bag = small_bag();
            patch_field(&mut bag, b"size", &size.to_le_bytes());
            let err = read_bytes(&bag).unwrap_err().to_string();
            assert!(
                err.contains(&format!("declares {size} uncompressed bytes")),
                "{err}"
            );
        }
    }
}
