//! Recordings in: ROS1 bags, ROS 2 recordings (rosbag2: MCAP or sqlite3, CDR) and CARMEN logs become one
//! time-ordered list of [`SensorEvent`]s plus the laser's mounting pose; a live ROS 2 robot over zenoh
//! ([`LiveRos2Source`]) gives the same events one at a time, and both are read by SLAM as a
//! [`SensorStream`].

mod carmen;
mod cdr_reader;
mod cdr_writer;
mod mcap_storage;
mod recording;
pub mod rmw_zenoh;
mod ros2_live;
pub mod ros2_messages;
pub mod ros2_nav_messages;
mod ros_collector;
mod ros_definitions;
pub mod ros_messages;
mod rosbag1;
mod rosbag1_writer;
mod rosbag2;
mod rosbag2_metadata;
mod sensor_stream;
mod sqlite3_storage;

use std::path::Path;

pub use cdr_reader::CdrReader;
pub use cdr_writer::CdrWriter;
pub use mcap_storage::McapFormatError;
pub use recording::{ReadReport, Recording};
pub use ros_messages::DecodeError;
pub use ros2_live::{
    ArrivalCounters, LiveDecoder, LiveRos2Source, LiveStats, MAX_TRACKED_PUBLISHERS,
    OdometryHistory, Ros2LiveError, Ros2LiveOptions, StreamEnd, TopicCounts, decode_samples,
    own_gid_prefix,
};
pub use rosbag1_writer::{BagWriteError, write_bag};
pub use sensor_stream::{RecordingStream, SensorStream};

/// Why a recording could not be read.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// The file could not be opened or read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// The file is in a format we do not read.
    #[error("{path}: unsupported format: {what}")]
    Unsupported {
        /// The file.
        path: String,
        /// What was found.
        what: String,
    },
    /// The file is damaged or not what its header says.
    #[error("{path}: malformed {format} data: {what}")]
    Malformed {
        /// The file.
        path: String,
        /// `ROS1 bag`, `CARMEN log`, `MCAP`, `rosbag2 sqlite3`, `rosbag2`, ...
        format: &'static str,
        /// What is wrong, and where (with the text of `source`, when there is one).
        what: String,
        /// The reader's own error, where a library found it (the ROS1 bag, SQLite, MCAP or YAML reader),
        /// kept for `source()`.
        source: Option<Box<dyn std::error::Error + Send + Sync>>,
    },
    /// A topic evermap reads by its conventional name (`/scan`, `/odom`, `/imu`, `/tf`, `/tf_static`)
    /// carries another type than the one evermap reads there.
    #[error(
        "{path}: topic {topic} has type `{found}`, but evermap reads {topic} as `{expected}` \
         (record the expected type there, or rename the topic when converting)"
    )]
    TopicType {
        /// The file.
        path: String,
        /// The topic.
        topic: String,
        /// Its type in the file.
        found: String,
        /// The type evermap reads on that topic.
        expected: &'static str,
    },
}

/// Reads a ROS1 bag (`#ROSBAG V2.0`), a ROS 2 recording (a rosbag2 folder, its `metadata.yaml`, or one
/// `.mcap` or `.db3` file) or a CARMEN log (`.clf`, `.log`, optionally gzip-compressed), recognised by
/// content (and, for rosbag2, by being a folder or a `metadata.yaml`).
pub fn read_recording(path: &Path) -> Result<Recording, SourceError> {
    let io_error = |source| SourceError::Io {
        path: path.display().to_string(),
        source,
    };
    if path.is_dir() {
        return rosbag2::read(path);
    }
    let mut head = [0u8; 32];
    let n = {
        use std::io::Read as _;
        let mut file = std::fs::File::open(path).map_err(io_error)?;
        let mut filled = 0;
        while filled < head.len() {
            let k = file.read(&mut head[filled..]).map_err(io_error)?;
            if k == 0 {
                break;
            }
            filled += k;
        }
        filled
    };
    let head = &head[..n];
    if rosbag2::is_rosbag2(path, head) {
        rosbag2::read(path)
    } else if head.starts_with(b"#ROSBAG V2.0") {
        rosbag1::read(path)
    } else if head.starts_with(b"#ROSRECORD") || head.starts_with(b"#ROSBAG") {
        let first_line = head.split(|&b| b == b'\n').next().unwrap_or_default();
        let version = String::from_utf8_lossy(first_line).trim().to_string();
        Err(SourceError::Unsupported {
            path: path.display().to_string(),
            what: format!(
                "{version} (only ROS1 bag format 2.0 is supported; migrate it with `rosbag fix` from ROS1)"
            ),
        })
    } else if head.starts_with(&[0x1f, 0x8b]) {
        let file = std::fs::File::open(path).map_err(io_error)?;
        carmen::read(
            std::io::BufReader::new(flate2::read::MultiGzDecoder::new(file)),
            path,
        )
    } else {
        let file = std::fs::File::open(path).map_err(io_error)?;
        carmen::read(std::io::BufReader::new(file), path)
    }
}

/// Reads a CARMEN log from `input` (already decompressed); `path` names it in errors. What
/// [`read_recording`] does for a CARMEN file, for callers that hold the text in memory (the fuzz harness).
pub fn read_carmen(input: impl std::io::BufRead, path: &Path) -> Result<Recording, SourceError> {
    carmen::read(input, path)
}
