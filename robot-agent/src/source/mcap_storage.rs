//! rosbag2's MCAP storage (the default since Iron) read with the `mcap` crate, Foxglove's reference
//! implementation: the data section is streamed front to back (chunks uncompressed, zstd or lz4), so a
//! file whose summary or index is missing reads the same as a clean one, and a truncated file is an
//! error at the record where it ends. A channel's type is its schema's name
//! (`sensor_msgs/msg/LaserScan`), its serialization its `message_encoding` (`cdr`).

use std::collections::BTreeMap;
use std::path::Path;

use mcap::McapError;

use super::SourceError;
use super::ros_collector::RosKind;
use super::rosbag2::{StoredTopic, Visitor};

/// The first bytes of every MCAP file.
pub const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// Streams every message of an MCAP file into `visitor`, in file order.
pub fn read(path: &Path, visitor: &mut dyn Visitor) -> Result<(), SourceError> {
    let malformed = |what: String| SourceError::Malformed {
        path: path.display().to_string(),
        format: "MCAP",
        what,
    };
    let bytes = std::fs::read(path).map_err(|source| SourceError::Io {
        path: path.display().to_string(),
        source,
    })?;
    if !bytes.starts_with(MCAP_MAGIC) {
        return Err(malformed(
            "the file does not start with the MCAP magic bytes: not an MCAP file".into(),
        ));
    }
    let stream = mcap::MessageStream::new(&bytes).map_err(|e| malformed(describe(&e)))?;
    let mut kinds: BTreeMap<u16, RosKind> = BTreeMap::new();
    for message in stream {
        let message = message.map_err(|e| malformed(describe(&e)))?;
        let channel = &message.channel;
        let kind = if let Some(&kind) = kinds.get(&channel.id) {
            kind
        } else {
            let kind = visitor.topic(&StoredTopic {
                name: &channel.topic,
                type_name: channel.schema.as_ref().map_or("", |s| s.name.as_str()),
                serialization: &channel.message_encoding,
            })?;
            kinds.insert(channel.id, kind);
            kind
        };
        visitor.message(kind, &channel.topic, message.log_time, &message.data);
    }
    Ok(())
}

/// The `mcap` crate's error in words a user can act on.
fn describe(error: &McapError) -> String {
    match error {
        McapError::UnexpectedEof | McapError::UnexpectedEoc => format!(
            "{error}: the file is truncated (a recording that was not closed properly; `mcap recover` \
             from the MCAP CLI can salvage it)"
        ),
        McapError::BadMagic => format!("{error}: not an MCAP file, or its end is missing"),
        McapError::UnsupportedCompression(name) => format!(
            "a chunk is compressed with `{name}`, which is not read (MCAP chunks may be uncompressed, \
             zstd or lz4)"
        ),
        McapError::BadChunkCrc { .. } | McapError::DecompressionError(_) => {
            format!("{error}: a chunk is damaged")
        }
        _ => error.to_string(),
    }
}
