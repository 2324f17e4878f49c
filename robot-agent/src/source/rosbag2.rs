//! ROS 2 recordings (rosbag2): a folder with `metadata.yaml` and its storage files, or one storage file
//! on its own — MCAP (`mcap_storage`) or sqlite3 (`sqlite3_storage`). Messages are CDR
//! (`ros2_messages`); they are picked by type, as in ROS1 bags (`sensor_msgs/msg/LaserScan`,
//! `nav_msgs/msg/Odometry`, `sensor_msgs/msg/Imu`, `tf2_msgs/msg/TFMessage`), and go through the same
//! collector as the ROS1 reader's (`RosCollector`), so the same recording gives the same events and the
//! same `base_from_laser` from either format.
//!
//! What is refused, with an error that says so: a folder without `metadata.yaml`; a storage plugin
//! other than `mcap` or `sqlite3`; rosbag2's own file or message compression (`ros2 bag decompress`
//! first; MCAP's chunk compression is read); a topic whose type in the storage file differs from
//! `metadata.yaml`'s; one of the conventional topics (`/scan`, `/odom`, `/imu`, `/tf`, `/tf_static`)
//! with another type than evermap reads there; a topic evermap reads in another serialization than CDR.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

use super::SourceError;
use super::recording::Recording;
use super::ros_collector::{Decoders, RosCollector, RosKind};
use super::rosbag2_metadata::Rosbag2Metadata;
use super::{mcap_storage, ros2_messages, sqlite3_storage};

/// A topic as a storage file declares it.
pub struct StoredTopic<'a> {
    /// `/scan`.
    pub name: &'a str,
    /// `sensor_msgs/msg/LaserScan` (empty if the file does not say).
    pub type_name: &'a str,
    /// `cdr`.
    pub serialization: &'a str,
}

/// What a storage reader hands its messages to.
pub trait Visitor {
    /// A topic seen for the first time: which kind its messages are, or why the recording is refused.
    fn topic(&mut self, topic: &StoredTopic<'_>) -> Result<RosKind, SourceError>;
    /// One message of a topic `topic` returned `kind` for; `log_time_ns` is when it was recorded.
    fn message(&mut self, kind: RosKind, topic: &str, log_time_ns: u64, data: &[u8]);
    /// A message on a topic id the file does not declare.
    fn unknown_topic(&mut self, topic_id: i64, log_time_ns: i64);
}

/// CDR's decoders.
pub(super) const CDR_DECODERS: Decoders = Decoders {
    laser_scan: ros2_messages::laser_scan,
    odometry: ros2_messages::odometry,
    imu: ros2_messages::imu,
    tf_message: ros2_messages::tf_message,
};

/// The kind of a ROS 2 type name.
fn kind_of(type_name: &str) -> RosKind {
    match type_name {
        "sensor_msgs/msg/LaserScan" => RosKind::Scan,
        "nav_msgs/msg/Odometry" => RosKind::Odometry,
        "sensor_msgs/msg/Imu" => RosKind::Imu,
        "tf2_msgs/msg/TFMessage" => RosKind::Tf,
        _ => RosKind::Other,
    }
}

/// The type evermap reads on a conventional topic name.
fn expected_type(topic: &str) -> Option<&'static str> {
    match topic {
        "/scan" => Some("sensor_msgs/msg/LaserScan"),
        "/odom" => Some("nav_msgs/msg/Odometry"),
        "/imu" => Some("sensor_msgs/msg/Imu"),
        "/tf" | "/tf_static" => Some("tf2_msgs/msg/TFMessage"),
        _ => None,
    }
}

/// Where a message was, for the read report.
struct At<'a>(&'a str, u64);

impl fmt::Display for At<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {} ns", self.0, self.1)
    }
}

/// Checks topics and collects messages, over every storage file of a recording.
struct Reader<'a> {
    /// The storage file being read (for errors).
    file: PathBuf,
    /// `metadata.yaml`'s topic types, when there is one.
    declared: Option<&'a BTreeMap<String, String>>,
    collector: RosCollector,
}

impl Visitor for Reader<'_> {
    fn topic(&mut self, topic: &StoredTopic<'_>) -> Result<RosKind, SourceError> {
        let path = self.file.display().to_string();
        if let Some(declared) = self.declared.and_then(|d| d.get(topic.name))
            && declared != topic.type_name
        {
            return Err(SourceError::Malformed {
                path,
                format: "rosbag2",
                source: None,
                what: format!(
                    "topic {} has type `{}` in the storage file but `{declared}` in metadata.yaml",
                    topic.name, topic.type_name
                ),
            });
        }
        if let Some(expected) = expected_type(topic.name)
            && expected != topic.type_name
        {
            return Err(SourceError::TopicType {
                path,
                topic: topic.name.to_string(),
                found: topic.type_name.to_string(),
                expected,
            });
        }
        let kind = kind_of(topic.type_name);
        if kind != RosKind::Other && topic.serialization != "cdr" {
            return Err(SourceError::Unsupported {
                path,
                what: format!(
                    "topic {} ({}) is serialized as `{}`; only CDR is read",
                    topic.name, topic.type_name, topic.serialization
                ),
            });
        }
        Ok(kind)
    }

    fn message(&mut self, kind: RosKind, topic: &str, log_time_ns: u64, data: &[u8]) {
        self.collector
            .add(kind, data, &At(topic, log_time_ns), &CDR_DECODERS);
    }

    fn unknown_topic(&mut self, topic_id: i64, log_time_ns: i64) {
        self.collector.report.skipped_malformed += 1;
        self.collector.report.problem(format!(
            "message at {log_time_ns} ns on topic id {topic_id}, which the file does not declare"
        ));
    }
}

/// The storage formats read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Storage {
    Mcap,
    Sqlite3,
}

fn read_file(storage: Storage, path: &Path, visitor: &mut dyn Visitor) -> Result<(), SourceError> {
    match storage {
        Storage::Mcap => mcap_storage::read(path, visitor),
        Storage::Sqlite3 => sqlite3_storage::read(path, visitor),
    }
}

/// Whether `path` names a rosbag2 recording by its form alone: a folder, a `metadata.yaml`, or a file
/// starting with the MCAP or SQLite magic bytes (`head`: the file's first bytes).
pub fn is_rosbag2(path: &Path, head: &[u8]) -> bool {
    path.is_dir()
        || path.file_name().is_some_and(|n| n == "metadata.yaml")
        || head.starts_with(mcap_storage::MCAP_MAGIC)
        || head.starts_with(sqlite3_storage::SQLITE_MAGIC)
        || path
            .extension()
            .is_some_and(|e| e == "mcap" || e == "db3" || e == "yaml")
}

/// Reads a rosbag2 recording: its folder, its `metadata.yaml`, or one `.mcap` / `.db3` file (recognised
/// by content; the extension only decides which error a file that is neither gets).
pub fn read(path: &Path) -> Result<Recording, SourceError> {
    let shown = path.display().to_string();
    let metadata_path = if path.is_dir() {
        let candidate = path.join("metadata.yaml");
        if !candidate.is_file() {
            return Err(SourceError::Malformed {
                path: shown,
                format: "rosbag2",
                source: None,
                what: "the folder has no metadata.yaml, so it is not a rosbag2 recording (pass its .mcap \
                       or .db3 file to read that file alone)"
                    .into(),
            });
        }
        Some(candidate)
    } else if path.extension().is_some_and(|e| e == "yaml") {
        Some(path.to_path_buf())
    } else {
        None
    };
    let Some(metadata_path) = metadata_path else {
        let storage = storage_of_file(path)?;
        let mut reader = Reader {
            file: path.to_path_buf(),
            declared: None,
            collector: RosCollector::default(),
        };
        read_file(storage, path, &mut reader)?;
        return Ok(reader.collector.finish());
    };
    read_folder(&metadata_path)
}

/// Which storage a lone file is, by its first bytes (then by its extension, for the error).
fn storage_of_file(path: &Path) -> Result<Storage, SourceError> {
    let io_error = |source| SourceError::Io {
        path: path.display().to_string(),
        source,
    };
    let mut head = Vec::with_capacity(16);
    {
        use std::io::Read as _;
        std::fs::File::open(path)
            .map_err(io_error)?
            .take(16)
            .read_to_end(&mut head)
            .map_err(io_error)?;
    }
    if head.starts_with(mcap_storage::MCAP_MAGIC) {
        Ok(Storage::Mcap)
    } else if head.starts_with(sqlite3_storage::SQLITE_MAGIC) {
        Ok(Storage::Sqlite3)
    } else if path.extension().is_some_and(|e| e == "db3") {
        // Let the sqlite3 reader say what is wrong with it.
        Ok(Storage::Sqlite3)
    } else if path.extension().is_some_and(|e| e == "mcap") {
        Ok(Storage::Mcap)
    } else {
        Err(SourceError::Unsupported {
            path: path.display().to_string(),
            what: "neither an MCAP file nor an SQLite database".into(),
        })
    }
}

fn read_folder(metadata_path: &Path) -> Result<Recording, SourceError> {
    let shown = metadata_path.display().to_string();
    let text = std::fs::read_to_string(metadata_path).map_err(|source| SourceError::Io {
        path: shown.clone(),
        source,
    })?;
    let metadata = Rosbag2Metadata::parse(&text).map_err(|e| SourceError::Malformed {
        path: shown.clone(),
        format: "rosbag2 metadata.yaml",
        what: e.to_string(),
        source: Some(Box::new(e)),
    })?;
    let storage = match metadata.storage_identifier.as_str() {
        "mcap" => Storage::Mcap,
        "sqlite3" => Storage::Sqlite3,
        other => {
            return Err(SourceError::Unsupported {
                path: shown,
                what: format!("rosbag2 storage `{other}` (only `mcap` and `sqlite3` are read)"),
            });
        }
    };
    if metadata.is_compressed() || !metadata.compression_format.is_empty() {
        let what = match metadata.compression_format.to_ascii_lowercase().as_str() {
            "zstd" => format!(
                "rosbag2 {} compression with zstd; decompress it first (`ros2 bag decompress`); \
                 MCAP's own chunk compression (`--storage-preset-profile zstd_fast`) is read",
                metadata.compression_mode
            ),
            "" => format!(
                "compression mode `{}` without a compression format",
                metadata.compression_mode
            ),
            other => format!("unknown rosbag2 compression format `{other}`"),
        };
        return Err(SourceError::Unsupported { path: shown, what });
    }
    if metadata.relative_file_paths.is_empty() {
        return Err(SourceError::Malformed {
            path: shown,
            format: "rosbag2 metadata.yaml",
            source: None,
            what: "relative_file_paths lists no storage file".into(),
        });
    }
    let declared: BTreeMap<String, String> = metadata
        .topics_with_message_count
        .iter()
        .map(|t| {
            (
                t.topic_metadata.name.clone(),
                t.topic_metadata.type_name.clone(),
            )
        })
        .collect();
    let folder = metadata_path.parent().unwrap_or(Path::new("."));
    let mut reader = Reader {
        file: PathBuf::new(),
        declared: Some(&declared),
        collector: RosCollector::default(),
    };
    for relative in &metadata.relative_file_paths {
        let file = folder.join(relative);
        // A storage file named by a hostile metadata.yaml may be a device or a pipe (`/dev/zero`,
        // absolute paths are allowed as in rosbag2): reading one would never end.
        let kind = std::fs::metadata(&file).map_err(|source| SourceError::Io {
            path: file.display().to_string(),
            source,
        })?;
        if !kind.is_file() {
            return Err(SourceError::Malformed {
                path: shown,
                format: "rosbag2 metadata.yaml",
                source: None,
                what: format!(
                    "relative_file_paths names {}, which is not a regular file",
                    file.display()
                ),
            });
        }
        reader.file.clone_from(&file);
        read_file(storage, &file, &mut reader)?;
    }
    Ok(reader.collector.finish())
}

#[cfg(test)]
mod tests;
