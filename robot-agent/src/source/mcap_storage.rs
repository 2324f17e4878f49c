//! rosbag2's MCAP storage (the default since Iron), framed and decompressed by the `mcap` crate,
//! Foxglove's reference implementation: the data section is streamed front to back (chunks
//! uncompressed, zstd or lz4), so a file whose summary or index is missing reads the same as a clean one,
//! and a truncated file is an error at the record where it ends. A channel's type is its schema's name
//! (`sensor_msgs/msg/LaserScan`), its serialization its `message_encoding` (`cdr`).
//!
//! What is ours and why (each found by the fuzz harness, target `rosbag2_mcap`; the crate, 0.26.0, is
//! the newest release): the crate's sans-io `LinearReader` is driven here with a limit on record lengths
//! ([`max_record_bytes`]), which its `MessageStream` does not set — without one it reserved whatever
//! length a record inside a compressed chunk declared, and 8 corrupt bytes made it allocate exabytes and
//! abort the process. Its record parser (`parse_record`, binrw) allocates a string's declared length
//! (up to 4 GiB) before checking it against the record, so the three records evermap needs — schema,
//! channel, message — are parsed by the few bounds-checked lines below ([`Fields`]) and the others
//! (indexes, statistics, attachments, metadata, the summary) are skipped unparsed. And the records inside
//! an uncompressed chunk are checked to lie within it before the crate reads them
//! ([`check_uncompressed_chunks`]): one that overran its chunk underflowed the crate's count of the
//! chunk's bytes left (a panic in debug builds, a misread rest of the file in release).

use std::collections::BTreeMap;
use std::path::Path;

use mcap::McapError;
use mcap::records::op;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};

use super::SourceError;
use super::ros_collector::RosKind;
use super::rosbag2::{StoredTopic, Visitor};

/// The first bytes of every MCAP file.
pub const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";

/// The longest record (a message, schema or channel, inside a chunk or not) read from a file of
/// `file_bytes` bytes: 16 times the file (a compressed chunk may expand more, but a single message that
/// does is an empty map or image, far under the floor), at least 64 MiB, at most 1 GiB.
pub fn max_record_bytes(file_bytes: usize) -> usize {
    file_bytes.saturating_mul(16).clamp(64 << 20, 1 << 30)
}

/// A channel as its records define it.
#[derive(Clone, PartialEq, Eq)]
struct ChannelDef {
    topic: String,
    message_encoding: String,
    schema_id: u16,
}

/// What is wrong with an MCAP file, and where: the source of a [`SourceError::Malformed`] whose
/// `format` is `MCAP` (its `what` is this error's text).
#[derive(Debug, thiserror::Error)]
pub enum McapFormatError {
    /// The file does not start with [`MCAP_MAGIC`].
    #[error("the file does not start with the MCAP magic bytes: not an MCAP file")]
    NotMcap,
    /// The `mcap` crate's reader refused the file (truncated, a bad CRC, a record too long, ...).
    #[error("{}", describe(source))]
    Reader {
        /// The reader's error.
        #[source]
        source: McapError,
    },
    /// The crate's reader kept asking for bytes after it was told the file had ended.
    #[error("the reader kept asking for bytes past the end of the file")]
    ReadPastEnd,
    /// A field of a record extends past the record's end.
    #[error(
        "a {record} record of {record_bytes} bytes is cut off at byte {at} (a field of {field_bytes} bytes)"
    )]
    CutOff {
        /// The record: `schema`, `channel`, `message` or `chunk`.
        record: &'static str,
        /// The record's length.
        record_bytes: usize,
        /// Where in the record the field starts.
        at: usize,
        /// The field's declared length.
        field_bytes: usize,
    },
    /// A string field is not UTF-8.
    #[error("a string in a {record} record is not UTF-8: {source}")]
    NotUtf8 {
        /// The record: `schema` or `channel`.
        record: &'static str,
        /// The decoder's error.
        #[source]
        source: std::string::FromUtf8Error,
    },
    /// A record inside an uncompressed chunk extends past the chunk's records.
    #[error(
        "a record inside the uncompressed chunk at byte {chunk_at} overruns the chunk (at byte {at} of \
         its {records_bytes} bytes of records): the file is damaged"
    )]
    ChunkOverrun {
        /// The chunk record's offset in the file.
        chunk_at: usize,
        /// The offset of the overrunning record among the chunk's records.
        at: usize,
        /// The length of the chunk's records.
        records_bytes: usize,
    },
    /// A schema record has id 0 (reserved for "no schema").
    #[error("a schema record has id 0, which is invalid")]
    SchemaIdZero,
    /// Two schema records give one id different names.
    #[error("schema {id} is defined twice, as `{earlier}` and `{name}`")]
    SchemaTwice {
        /// The schema id.
        id: u16,
        /// The name first given.
        earlier: String,
        /// The name given now.
        name: String,
    },
    /// A channel names a schema no earlier record defines.
    #[error("channel {id} ({topic}) names schema {schema_id}, which no earlier record defines")]
    UnknownSchema {
        /// The channel id.
        id: u16,
        /// The channel's topic.
        topic: String,
        /// The schema it names.
        schema_id: u16,
    },
    /// Two channel records give one id different definitions.
    #[error("channel {id} is defined twice, as {earlier} and {topic}")]
    ChannelTwice {
        /// The channel id.
        id: u16,
        /// The topic first given.
        earlier: String,
        /// The topic given now.
        topic: String,
    },
    /// A message is on a channel no earlier record defines.
    #[error(
        "a message at {log_time_ns} ns is on channel {channel_id}, which no earlier record defines"
    )]
    UnknownChannel {
        /// The message's log time.
        log_time_ns: u64,
        /// The channel it names.
        channel_id: u16,
    },
}

/// Streams every message of an MCAP file into `visitor`, in file order.
pub fn read(path: &Path, visitor: &mut dyn Visitor) -> Result<(), SourceError> {
    let malformed = |error: McapFormatError| SourceError::Malformed {
        path: path.display().to_string(),
        format: "MCAP",
        what: error.to_string(),
        source: Some(Box::new(error)),
    };
    let bytes = std::fs::read(path).map_err(|source| SourceError::Io {
        path: path.display().to_string(),
        source,
    })?;
    if !bytes.starts_with(MCAP_MAGIC) {
        return Err(malformed(McapFormatError::NotMcap));
    }
    check_uncompressed_chunks(&bytes).map_err(malformed)?;
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default().with_record_length_limit(max_record_bytes(bytes.len())),
    );
    let mut schemas: BTreeMap<u16, String> = BTreeMap::new();
    let mut channels: BTreeMap<u16, ChannelDef> = BTreeMap::new();
    let mut kinds: BTreeMap<u16, RosKind> = BTreeMap::new();
    let mut past_data_end = false;
    let mut pos = 0;
    let mut eof_signalled = false;
    while let Some(event) = reader.next_event() {
        let event = event.map_err(|source| malformed(McapFormatError::Reader { source }))?;
        let (opcode, data) = match event {
            LinearReadEvent::ReadRequest(need) => {
                let n = need.min(bytes.len() - pos);
                if n == 0 {
                    // The reader asked past the end: tell it once, then it must finish or fail.
                    if eof_signalled {
                        return Err(malformed(McapFormatError::ReadPastEnd));
                    }
                    eof_signalled = true;
                }
                reader.insert(n).copy_from_slice(&bytes[pos..pos + n]);
                reader.notify_read(n);
                pos += n;
                continue;
            }
            LinearReadEvent::Record { opcode, data } => (opcode, data),
        };
        // The summary repeats schemas and channels: read on to the end magic (a truncated file is
        // still an error) without looking at it.
        if past_data_end {
            continue;
        }
        match opcode {
            op::DATA_END => past_data_end = true,
            op::SCHEMA => {
                let (id, name) = parse_schema(data).map_err(malformed)?;
                if id == 0 {
                    return Err(malformed(McapFormatError::SchemaIdZero));
                }
                if let Some(earlier) = schemas.insert(id, name.clone())
                    && earlier != name
                {
                    return Err(malformed(McapFormatError::SchemaTwice {
                        id,
                        earlier,
                        name,
                    }));
                }
            }
            op::CHANNEL => {
                let (id, def) = parse_channel(data).map_err(malformed)?;
                let schema_id = def.schema_id;
                if schema_id != 0 && !schemas.contains_key(&schema_id) {
                    return Err(malformed(McapFormatError::UnknownSchema {
                        id,
                        topic: def.topic,
                        schema_id,
                    }));
                }
                if let Some(earlier) = channels.get(&id)
                    && *earlier != def
                {
                    return Err(malformed(McapFormatError::ChannelTwice {
                        id,
                        earlier: earlier.topic.clone(),
                        topic: def.topic,
                    }));
                }
                channels.insert(id, def);
            }
            op::MESSAGE => {
                let (channel_id, log_time, payload) = parse_message(data).map_err(malformed)?;
                let Some(channel) = channels.get(&channel_id) else {
                    return Err(malformed(McapFormatError::UnknownChannel {
                        log_time_ns: log_time,
                        channel_id,
                    }));
                };
                let kind = if let Some(&kind) = kinds.get(&channel_id) {
                    kind
                } else {
                    let kind = visitor.topic(&StoredTopic {
                        name: &channel.topic,
                        type_name: schemas.get(&channel.schema_id).map_or("", String::as_str),
                        serialization: &channel.message_encoding,
                    })?;
                    kinds.insert(channel_id, kind);
                    kind
                };
                visitor.message(kind, &channel.topic, log_time, payload);
            }
            _ => {}
        }
    }
    Ok(())
}

/// A schema record: its id and name (the ROS type).
fn parse_schema(data: &[u8]) -> Result<(u16, String), McapFormatError> {
    let mut f = Fields::new(data, "schema");
    let id = f.u16()?;
    let name = f.string()?;
    let _encoding = f.string()?;
    let _data = f.bytes()?;
    Ok((id, name))
}

/// A channel record: its id and definition.
fn parse_channel(data: &[u8]) -> Result<(u16, ChannelDef), McapFormatError> {
    let mut f = Fields::new(data, "channel");
    let id = f.u16()?;
    let schema_id = f.u16()?;
    let def = ChannelDef {
        schema_id,
        topic: f.string()?,
        message_encoding: f.string()?,
    };
    let _metadata = f.bytes()?;
    Ok((id, def))
}

/// A message record: its channel, log time (ns) and payload.
fn parse_message(data: &[u8]) -> Result<(u16, u64, &[u8]), McapFormatError> {
    let mut f = Fields::new(data, "message");
    let channel_id = f.u16()?;
    let _sequence = f.u32()?;
    let log_time = f.u64()?;
    let _publish_time = f.u64()?;
    Ok((channel_id, log_time, f.rest()))
}

/// Reads the fields of one record body front to back, bounds-checked: a length that does not fit in
/// the record is an error before anything is allocated.
struct Fields<'a> {
    body: &'a [u8],
    pos: usize,
    record: &'static str,
}

impl<'a> Fields<'a> {
    fn new(body: &'a [u8], record: &'static str) -> Self {
        Self {
            body,
            pos: 0,
            record,
        }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], McapFormatError> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&end| end <= self.body.len())
            .ok_or(McapFormatError::CutOff {
                record: self.record,
                record_bytes: self.body.len(),
                at: self.pos,
                field_bytes: n,
            })?;
        let bytes = &self.body[self.pos..end];
        self.pos = end;
        Ok(bytes)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], McapFormatError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }

    fn u16(&mut self) -> Result<u16, McapFormatError> {
        Ok(u16::from_le_bytes(self.array()?))
    }

    fn u32(&mut self) -> Result<u32, McapFormatError> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    fn u64(&mut self) -> Result<u64, McapFormatError> {
        Ok(u64::from_le_bytes(self.array()?))
    }

    /// A `u32` length and that many bytes.
    fn bytes(&mut self) -> Result<&'a [u8], McapFormatError> {
        let n = self.u32()? as usize;
        self.take(n)
    }

    /// A `u32` length and that many bytes of UTF-8.
    fn string(&mut self) -> Result<String, McapFormatError> {
        let record = self.record;
        let bytes = self.bytes()?;
        String::from_utf8(bytes.to_vec())
            .map_err(|source| McapFormatError::NotUtf8 { record, source })
    }

    fn rest(&mut self) -> &'a [u8] {
        let rest = &self.body[self.pos..];
        self.pos = self.body.len();
        rest
    }
}

/// Checks that every record inside every uncompressed chunk lies within its chunk (see the module
/// docs). Walks the top-level records only as far as they are whole: where the file is cut off or
/// damaged otherwise, the crate's reader says so.
fn check_uncompressed_chunks(file: &[u8]) -> Result<(), McapFormatError> {
    let mut pos = MCAP_MAGIC.len();
    while let Some(head) = file.get(pos..pos + 9) {
        let opcode = head[0];
        let Ok(len) = usize::try_from(u64::from_le_bytes(
            head[1..9].try_into().unwrap_or_default(),
        )) else {
            return Ok(());
        };
        let Some(body) = file.get(pos + 9..).and_then(|rest| rest.get(..len)) else {
            return Ok(());
        };
        if opcode == op::FOOTER {
            return Ok(());
        }
        if opcode == op::CHUNK {
            check_chunk(body, pos)?;
        }
        pos += 9 + len;
    }
    Ok(())
}

/// [`check_uncompressed_chunks`] for one chunk record's body, at file offset `at`.
fn check_chunk(body: &[u8], at: usize) -> Result<(), McapFormatError> {
    let mut f = Fields::new(body, "chunk");
    let header = (|| {
        f.take(8 + 8 + 8 + 4)?; // start and end time, uncompressed size and CRC
        let compression = f.bytes()?;
        let records_size = f.u64()?;
        Ok::<_, McapFormatError>((compression.is_empty(), records_size))
    })();
    let Ok((true, records_size)) = header else {
        // Compressed (the decompressor checks the records), or a header the crate will refuse.
        return Ok(());
    };
    let Some(records) = usize::try_from(records_size)
        .ok()
        .and_then(|n| body.get(f.pos..)?.get(..n))
    else {
        return Ok(());
    };
    let mut r = 0;
    while r < records.len() {
        let left = records.len() - r;
        let overrun = || McapFormatError::ChunkOverrun {
            chunk_at: at,
            at: r,
            records_bytes: records.len(),
        };
        if left < 9 {
            return Err(overrun());
        }
        let len = u64::from_le_bytes(records[r + 1..r + 9].try_into().unwrap_or_default());
        if len > (left - 9) as u64 {
            return Err(overrun());
        }
        r += 9 + len as usize;
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
        McapError::RecordTooLarge { .. }
        | McapError::ChunkTooLarge(_)
        | McapError::ChunkBufferTooLarge(_) => format!(
            "{error}: longer than any record this reader accepts (16 times the file, at least 64 MiB, \
             at most 1 GiB): the file is damaged"
        ),
        _ => error.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(opcode: u8, body: &[u8]) -> Vec<u8> {
        let mut out = vec![opcode];
        out.extend_from_slice(&(body.len() as u64).to_le_bytes());
        out.extend_from_slice(body);
        out
    }

    fn string(s: &[u8], declared: u32) -> Vec<u8> {
        let mut out = declared.to_le_bytes().to_vec();
        out.extend_from_slice(s);
        out
    }

    /// Counts what it is given.
    #[derive(Default)]
    struct Count(usize);

    impl Visitor for Count {
        fn topic(&mut self, _topic: &StoredTopic<'_>) -> Result<RosKind, SourceError> {
            Ok(RosKind::Other)
        }
        fn message(&mut self, _kind: RosKind, _topic: &str, _log_time_ns: u64, _data: &[u8]) {
            self.0 += 1;
        }
        fn unknown_topic(&mut self, _topic_id: i64, _log_time_ns: i64) {}
    }

    fn read_bytes(bytes: &[u8]) -> Result<usize, SourceError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.mcap");
        std::fs::write(&path, bytes).unwrap();
        let mut count = Count::default();
        read(&path, &mut count)?;
        Ok(count.0)
    }

    /// The MCAP reader's error under a `Malformed` one, checking that the latter's text is the former's.
    fn format_error(error: &SourceError) -> &McapFormatError {
        let SourceError::Malformed {
            format: "MCAP",
            what,
            source: Some(source),
            ..
        } = error
        else {
            panic!("not a malformed MCAP file: {error:?}");
        };
        let format = source
            .downcast_ref::<McapFormatError>()
            .expect("an McapFormatError");
        assert_eq!(*what, format.to_string());
        format
    }

    /// `bytes` as a zstd frame of one raw (stored) block: what a zstd chunk holds, with no compressor
    /// needed to write one whose records lie.
    fn zstd_raw_frame(bytes: &[u8]) -> Vec<u8> {
        let mut out = vec![0x28, 0xB5, 0x2F, 0xFD, 0x00, 0x18]; // magic, no size/checksum, 8 MiB window
        let header = (u32::try_from(bytes.len()).unwrap() << 3) | 1; // raw, last block
        out.extend_from_slice(&header.to_le_bytes()[..3]);
        out.extend_from_slice(bytes);
        out
    }

    /// A file with one schema, one channel and one message, the channel's topic string declaring
    /// `topic_len` bytes, and the message inside a chunk when `chunk` names its compression (`""` or
    /// `"zstd"`), its record's length field `extra` bytes longer than the record.
    fn file(topic_len: u32, chunk: Option<&str>, extra: u64) -> Vec<u8> {
        let mut out = MCAP_MAGIC.to_vec();
        out.extend(record(
            op::HEADER,
            &[string(b"ros2", 4), string(b"", 0)].concat(),
        ));
        let schema = [
            &1u16.to_le_bytes()[..],
            &string(b"std_msgs/msg/String", 19),
            &string(b"ros2msg", 7),
            &string(b"", 0),
        ]
        .concat();
        let channel = [
            &1u16.to_le_bytes()[..],
            &1u16.to_le_bytes()[..],
            &string(b"/chatter", topic_len),
            &string(b"cdr", 3),
            &0u32.to_le_bytes()[..],
        ]
        .concat();
        let message = [
            &1u16.to_le_bytes()[..],
            &0u32.to_le_bytes()[..],
            &5u64.to_le_bytes()[..],
            &5u64.to_le_bytes()[..],
            b"\x00\x01\x00\x00",
        ]
        .concat();
        out.extend(record(op::SCHEMA, &schema));
        out.extend(record(op::CHANNEL, &channel));
        let mut message = record(op::MESSAGE, &message);
        message[1..9].copy_from_slice(&26u64.wrapping_add(extra).to_le_bytes());
        if let Some(compression) = chunk {
            let records = if compression.is_empty() {
                message.clone()
            } else {
                zstd_raw_frame(&message)
            };
            let mut body = Vec::new();
            body.extend_from_slice(&5u64.to_le_bytes());
            body.extend_from_slice(&5u64.to_le_bytes());
            body.extend_from_slice(&(message.len() as u64).to_le_bytes());
            body.extend_from_slice(&0u32.to_le_bytes());
            body.extend(string(compression.as_bytes(), compression.len() as u32));
            body.extend_from_slice(&(records.len() as u64).to_le_bytes());
            body.extend(records);
            out.extend(record(op::CHUNK, &body));
        } else {
            out.extend(message);
        }
        out.extend(record(op::DATA_END, &0u32.to_le_bytes()));
        out.extend(record(op::FOOTER, &[0u8; 20]));
        out.extend_from_slice(MCAP_MAGIC);
        out
    }

    #[test]
    fn a_well_formed_file_reads_with_or_without_chunks() {
        for chunk in [None, Some(""), Some("zstd")] {
            assert_eq!(read_bytes(&file(8, chunk, 0)).unwrap(), 1, "{chunk:?}");
        }
    }

    // Reference: issue 35 item 6 — the MCAP reader's error stays the source of a malformed file's.
    #[test]
    fn a_truncated_file_keeps_the_readers_error_as_its_source() {
        let bytes = file(8, None, 0);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cut.mcap");
        std::fs::write(&path, &bytes[..bytes.len() - 30]).unwrap();
        let error = read(&path, &mut Count::default()).unwrap_err();
        assert!(
            matches!(error, SourceError::Malformed { format: "MCAP", .. }),
            "{error}"
        );
        assert!(error.to_string().contains("truncated"), "{error}");
        let McapFormatError::Reader { source } = format_error(&error) else {
            panic!("not the reader's error: {error:?}");
        };
        assert!(
            matches!(source, McapError::UnexpectedEof | McapError::UnexpectedEoc),
            "{source:?}"
        );
        // The chain: Malformed → McapFormatError::Reader → the crate's McapError.
        let reader = std::error::Error::source(&error)
            .and_then(std::error::Error::source)
            .expect("the reader's error");
        assert!(reader.is::<McapError>(), "{reader:?}");
    }

    /// Regression (found by the fuzz harness, `rosbag2_mcap`): a string length of 4 GiB inside a
    /// channel record made the crate's parser allocate it (920 MB in the finding) before failing.
    #[test]
    fn a_string_longer_than_its_record_is_refused_before_allocating() {
        let error = read_bytes(&file(u32::MAX, None, 0)).unwrap_err();
        assert!(
            matches!(
                format_error(&error),
                McapFormatError::CutOff {
                    record: "channel",
                    field_bytes: 4_294_967_295,
                    ..
                }
            ),
            "{error:?}"
        );
        let text = error.to_string();
        assert!(
            text.contains("channel record") && text.contains("cut off"),
            "{text}"
        );
    }

    /// Regression (found by the fuzz harness, `rosbag2_mcap`): a record overrunning its uncompressed
    /// chunk underflowed the crate's count of the chunk's bytes left (`attempt to subtract with
    /// overflow` in debug builds).
    #[test]
    fn a_record_overrunning_its_uncompressed_chunk_is_refused() {
        for extra in [1, 1 << 20, u64::MAX - 100] {
            let error = read_bytes(&file(8, Some(""), extra)).unwrap_err();
            assert!(
                matches!(
                    format_error(&error),
                    McapFormatError::ChunkOverrun { at: 0, .. }
                ),
                "{extra}: {error:?}"
            );
            assert!(
                error.to_string().contains("overruns the chunk"),
                "{extra}: {error}"
            );
        }
    }

    /// Regression (found by the fuzz harness, `rosbag2_mcap`): a record declaring 8·10¹⁸ bytes inside a
    /// compressed chunk made the crate reserve them and abort the process; records are now limited.
    #[test]
    fn records_are_limited_to_what_the_file_can_hold() {
        assert_eq!(max_record_bytes(1000), 64 << 20);
        assert_eq!(max_record_bytes(10 << 20), 160 << 20);
        assert_eq!(max_record_bytes(usize::MAX), 1 << 30);
        // Inside a zstd chunk, a message record declaring 8·10¹⁸ bytes.
        let bytes = file(8, Some("zstd"), 8_000_000_000_000_000_000);
        let error = read_bytes(&bytes).unwrap_err();
        assert!(
            matches!(format_error(&error), McapFormatError::Reader { .. }),
            "{error:?}"
        );
        assert!(
            error.to_string().contains("longer than any record"),
            "{error}"
        );
    }
}
