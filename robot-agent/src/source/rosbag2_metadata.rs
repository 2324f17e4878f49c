//! rosbag2's `metadata.yaml`: which storage plugin wrote the recording, its files, its topics and their
//! types, and whether rosbag2 compressed it. Parsed with `serde_yaml` (archived upstream but stable, and
//! already in the build through zenoh's configuration: it costs no compile time); only the fields
//! evermap uses are read, so every version of the file since Foxy (4 to 9) reads the same.

use serde::Deserialize;

/// The top level of `metadata.yaml`.
#[derive(Debug, Deserialize)]
struct MetadataFile {
    rosbag2_bagfile_information: Rosbag2Metadata,
}

/// What `metadata.yaml` says about a recording.
#[derive(Clone, Debug, Deserialize, PartialEq, Eq)]
pub struct Rosbag2Metadata {
    /// Format version of the file (rosbag2 writes 4..9).
    pub version: u32,
    /// The storage plugin: `mcap` or `sqlite3`.
    pub storage_identifier: String,
    /// The storage files, relative to the folder, in recording order.
    #[serde(default)]
    pub relative_file_paths: Vec<String>,
    /// Every topic with its type and serialization.
    #[serde(default)]
    pub topics_with_message_count: Vec<TopicWithCount>,
    /// `""` or `zstd` (rosbag2's own compression, outside the storage format).
    #[serde(default, deserialize_with = "null_as_empty")]
    pub compression_format: String,
    /// `""`/`NONE`, `FILE` or `MESSAGE`.
    #[serde(default, deserialize_with = "null_as_empty")]
    pub compression_mode: String,
}

/// One entry of `topics_with_message_count`.
#[derive(Clone, Debug, Deserialize, PartialEq, Eq)]
pub struct TopicWithCount {
    /// The topic.
    pub topic_metadata: TopicMetadata,
    /// Messages recorded on it.
    #[serde(default)]
    pub message_count: u64,
}

/// A topic's name, type and serialization.
#[derive(Clone, Debug, Deserialize, PartialEq, Eq)]
pub struct TopicMetadata {
    /// `/scan`.
    pub name: String,
    /// `sensor_msgs/msg/LaserScan`.
    #[serde(rename = "type")]
    pub type_name: String,
    /// `cdr`.
    pub serialization_format: String,
}

fn null_as_empty<'de, D: serde::Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    Ok(Option::<String>::deserialize(d)?.unwrap_or_default())
}

impl Rosbag2Metadata {
    /// Parses the text of a `metadata.yaml`; the YAML reader's error says what is missing or malformed,
    /// and where.
    pub fn parse(text: &str) -> Result<Self, serde_yaml::Error> {
        let file: MetadataFile = serde_yaml::from_str(text)?;
        Ok(file.rosbag2_bagfile_information)
    }

    /// Whether rosbag2 compressed the files or messages itself (not the storage's own chunk
    /// compression, which MCAP readers handle).
    pub fn is_compressed(&self) -> bool {
        !(self.compression_mode.is_empty() || self.compression_mode.eq_ignore_ascii_case("none"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_fields_evermap_uses_and_says_what_is_wrong() {
        let text = "rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: mcap\n  \
                    relative_file_paths:\n  - a.mcap\n  compression_format: ''\n  compression_mode: ''\n  \
                    custom_data: ~\n  topics_with_message_count:\n  - message_count: 3\n    topic_metadata:\n      \
                    name: /scan\n      type: sensor_msgs/msg/LaserScan\n      serialization_format: cdr\n      \
                    offered_qos_profiles: []\n";
        let m = Rosbag2Metadata::parse(text).unwrap();
        assert_eq!(m.version, 9);
        assert_eq!(m.storage_identifier, "mcap");
        assert_eq!(m.relative_file_paths, vec!["a.mcap".to_string()]);
        assert_eq!(m.topics_with_message_count.len(), 1);
        assert_eq!(
            m.topics_with_message_count[0].topic_metadata.type_name,
            "sensor_msgs/msg/LaserScan"
        );
        assert!(!m.is_compressed());

        let error =
            Rosbag2Metadata::parse("rosbag2_bagfile_information:\n  version: 9\n").unwrap_err();
        assert!(error.to_string().contains("storage_identifier"), "{error}");
        assert!(Rosbag2Metadata::parse("not: [yaml").is_err());
    }
}
