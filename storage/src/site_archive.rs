//! The site archive: one site's records as a single stream (export/import, backups, moving a site).
//!
//! ```text
//! stream  = MAGIC (8 bytes "EVMAP-SA") ‖ format version (u16 LE) ‖ chunk*
//! chunk   = body length (u32 LE) ‖ CRC32 of body (u32 LE) ‖ body
//! body    = 0x01 ‖ source site id (UTF-8)                              first chunk: Begin
//!         | 0x02 ‖ kind (u8) ‖ id length (u16 LE) ‖ id ‖ payload          one per record
//!         | 0x03 ‖ record count (u64 LE)                                 last chunk: End
//! ```
//! Chunks are written and read one at a time, so neither side ever holds more than one record: there is no
//! whole-site size limit. A chunk body is at most [`MAX_CHUNK_BYTES`], which bounds what a corrupt length
//! field can make the reader allocate. The End chunk's count and the required end of stream after it catch
//! truncation and trailing garbage. Record kinds include the internal ones (map version, session sequence
//! numbers), so an imported site resumes exactly-once uploads where the exported one stopped.

use std::io::{self, Read, Write};

use crate::{MAX_ID_BYTES, MAX_VALUE_BYTES, Result, StorageError};

/// First bytes of every site archive.
pub const SITE_ARCHIVE_MAGIC: [u8; 8] = *b"EVMAP-SA";
/// Archive format version this build writes and reads.
pub const SITE_ARCHIVE_VERSION: u16 = 1;
/// Largest chunk body accepted, in bytes: the largest record plus its framing.
pub const MAX_CHUNK_BYTES: usize = MAX_VALUE_BYTES + MAX_ID_BYTES + 16;

const TAG_BEGIN: u8 = 1;
const TAG_RECORD: u8 = 2;
const TAG_END: u8 = 3;

/// Summary of an export or import.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TransferSummary {
    /// Records transferred (internal counters such as the map version included).
    pub records: u64,
    /// Payload bytes transferred (record values only).
    pub payload_bytes: u64,
}

/// One decoded chunk.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Chunk {
    Begin {
        site: String,
    },
    Record {
        kind: u8,
        id: Vec<u8>,
        payload: Vec<u8>,
    },
    End {
        records: u64,
    },
}

fn bad(reason: impl Into<String>) -> StorageError {
    StorageError::BadArchive {
        reason: reason.into(),
    }
}

/// Writes an archive: header on creation, then chunks.
pub(crate) struct ArchiveWriter<'w> {
    out: &'w mut dyn Write,
    summary: TransferSummary,
}

impl<'w> ArchiveWriter<'w> {
    pub(crate) fn new(out: &'w mut dyn Write, site: &str) -> Result<Self> {
        out.write_all(&SITE_ARCHIVE_MAGIC)?;
        out.write_all(&SITE_ARCHIVE_VERSION.to_le_bytes())?;
        let mut writer = Self {
            out,
            summary: TransferSummary::default(),
        };
        let mut body = vec![TAG_BEGIN];
        body.extend_from_slice(site.as_bytes());
        writer.chunk(&body)?;
        Ok(writer)
    }

    pub(crate) fn record(&mut self, kind: u8, id: &[u8], payload: &[u8]) -> Result<()> {
        let id_len =
            u16::try_from(id.len()).map_err(|_| bad("record id longer than 65535 bytes"))?;
        let mut body = Vec::with_capacity(4 + id.len() + payload.len());
        body.push(TAG_RECORD);
        body.push(kind);
        body.extend_from_slice(&id_len.to_le_bytes());
        body.extend_from_slice(id);
        body.extend_from_slice(payload);
        self.chunk(&body)?;
        self.summary.records += 1;
        self.summary.payload_bytes += payload.len() as u64;
        Ok(())
    }

    pub(crate) fn finish(mut self) -> Result<TransferSummary> {
        let mut body = vec![TAG_END];
        body.extend_from_slice(&self.summary.records.to_le_bytes());
        self.chunk(&body)?;
        self.out.flush()?;
        Ok(self.summary)
    }

    fn chunk(&mut self, body: &[u8]) -> Result<()> {
        if body.len() > MAX_CHUNK_BYTES {
            return Err(bad(format!(
                "chunk of {} bytes exceeds the {MAX_CHUNK_BYTES}-byte limit",
                body.len()
            )));
        }
        let len = body.len() as u32;
        self.out.write_all(&len.to_le_bytes())?;
        self.out.write_all(&crc32fast::hash(body).to_le_bytes())?;
        self.out.write_all(body)?;
        Ok(())
    }
}

/// Reads and checks an archive chunk by chunk.
pub(crate) struct ArchiveReader<'r> {
    input: &'r mut dyn Read,
    chunks_read: u64,
}

impl<'r> ArchiveReader<'r> {
    /// Reads and checks the header.
    pub(crate) fn new(input: &'r mut dyn Read) -> Result<Self> {
        let mut magic = [0_u8; 8];
        read_exact(input, &mut magic, "header")?;
        if magic != SITE_ARCHIVE_MAGIC {
            return Err(bad("not a site archive (bad magic bytes)"));
        }
        let mut version = [0_u8; 2];
        read_exact(input, &mut version, "header")?;
        let version = u16::from_le_bytes(version);
        if version != SITE_ARCHIVE_VERSION {
            return Err(bad(format!(
                "archive format version {version}, this build reads only version {SITE_ARCHIVE_VERSION}"
            )));
        }
        Ok(Self {
            input,
            chunks_read: 0,
        })
    }

    /// Reads the next chunk; after `End`, also checks that the stream ends there.
    pub(crate) fn next_chunk(&mut self) -> Result<Chunk> {
        let index = self.chunks_read;
        let mut frame = [0_u8; 8];
        read_exact(self.input, &mut frame, "chunk header")?;
        let len = u32::from_le_bytes([frame[0], frame[1], frame[2], frame[3]]) as usize;
        let crc = u32::from_le_bytes([frame[4], frame[5], frame[6], frame[7]]);
        if len > MAX_CHUNK_BYTES {
            return Err(bad(format!(
                "chunk {index} claims {len} bytes, over the {MAX_CHUNK_BYTES}-byte limit"
            )));
        }
        // `take` + `read_to_end` allocates only as much as actually arrives.
        let mut body = Vec::new();
        self.input.take(len as u64).read_to_end(&mut body)?;
        if body.len() != len {
            return Err(bad(format!(
                "truncated in chunk {index}: {} of {len} bytes",
                body.len()
            )));
        }
        if crc32fast::hash(&body) != crc {
            return Err(bad(format!(
                "CRC32 mismatch in chunk {index} ({len} bytes)"
            )));
        }
        self.chunks_read += 1;
        let chunk = decode(&body).map_err(|reason| bad(format!("chunk {index}: {reason}")))?;
        if matches!(chunk, Chunk::End { .. }) {
            let mut probe = [0_u8; 1];
            if read_some(self.input, &mut probe)? != 0 {
                return Err(bad("trailing bytes after the end chunk"));
            }
        }
        Ok(chunk)
    }
}

fn decode(body: &[u8]) -> Result<Chunk, String> {
    let Some((&tag, rest)) = body.split_first() else {
        return Err("empty chunk".to_owned());
    };
    match tag {
        TAG_BEGIN => {
            let site = std::str::from_utf8(rest).map_err(|_| "site id is not UTF-8".to_owned())?;
            Ok(Chunk::Begin {
                site: site.to_owned(),
            })
        }
        TAG_RECORD => {
            if rest.len() < 3 {
                return Err("record chunk too short".to_owned());
            }
            let kind = rest[0];
            let id_len = usize::from(u16::from_le_bytes([rest[1], rest[2]]));
            let rest = &rest[3..];
            if id_len > MAX_ID_BYTES || id_len > rest.len() {
                return Err(format!("bad record id length {id_len}"));
            }
            let (id, payload) = rest.split_at(id_len);
            if payload.len() > MAX_VALUE_BYTES {
                return Err(format!(
                    "record value of {} bytes over the limit",
                    payload.len()
                ));
            }
            Ok(Chunk::Record {
                kind,
                id: id.to_vec(),
                payload: payload.to_vec(),
            })
        }
        TAG_END => {
            let bytes: [u8; 8] = rest
                .try_into()
                .map_err(|_| "end chunk is not 8 bytes".to_owned())?;
            Ok(Chunk::End {
                records: u64::from_le_bytes(bytes),
            })
        }
        other => Err(format!("unknown chunk tag {other}")),
    }
}

fn read_exact(input: &mut dyn Read, buf: &mut [u8], what: &str) -> Result<()> {
    input.read_exact(buf).map_err(|error| {
        if error.kind() == io::ErrorKind::UnexpectedEof {
            bad(format!("truncated in {what}"))
        } else {
            StorageError::Io(error)
        }
    })
}

fn read_some(input: &mut dyn Read, buf: &mut [u8]) -> Result<usize> {
    loop {
        match input.read(buf) {
            Ok(n) => return Ok(n),
            Err(error) if error.kind() == io::ErrorKind::Interrupted => {}
            Err(error) => return Err(StorageError::Io(error)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Vec<u8> {
        let mut out = Vec::new();
        let mut writer = ArchiveWriter::new(&mut out, "depot").unwrap();
        writer.record(2, b"id-1", b"payload one").unwrap();
        writer.record(0xF0, b"", &7_u64.to_le_bytes()).unwrap();
        let summary = writer.finish().unwrap();
        assert_eq!(
            summary,
            TransferSummary {
                records: 2,
                payload_bytes: 19
            }
        );
        out
    }

    fn read_all(bytes: &[u8]) -> Result<Vec<Chunk>> {
        let mut input = bytes;
        let mut reader = ArchiveReader::new(&mut input)?;
        let mut chunks = Vec::new();
        loop {
            let chunk = reader.next_chunk()?;
            let end = matches!(chunk, Chunk::End { .. });
            chunks.push(chunk);
            if end {
                return Ok(chunks);
            }
        }
    }

    #[test]
    fn round_trip() {
        let chunks = read_all(&sample()).unwrap();
        assert_eq!(
            chunks,
            [
                Chunk::Begin {
                    site: "depot".to_owned()
                },
                Chunk::Record {
                    kind: 2,
                    id: b"id-1".to_vec(),
                    payload: b"payload one".to_vec()
                },
                Chunk::Record {
                    kind: 0xF0,
                    id: Vec::new(),
                    payload: 7_u64.to_le_bytes().to_vec()
                },
                Chunk::End { records: 2 },
            ]
        );
    }

    #[test]
    fn every_byte_flip_and_truncation_is_refused() {
        let good = sample();
        for index in 0..good.len() {
            let mut flipped = good.clone();
            flipped[index] ^= 0x10;
            assert!(
                read_all(&flipped).is_err(),
                "flip at byte {index} went unnoticed"
            );
            assert!(
                read_all(&good[..index]).is_err(),
                "truncation to {index} bytes went unnoticed"
            );
        }
        let mut trailing = good;
        trailing.push(0);
        assert!(matches!(
            read_all(&trailing),
            Err(StorageError::BadArchive { .. })
        ));
    }

    #[test]
    fn absurd_length_is_refused_without_allocating() {
        let mut bytes = SITE_ARCHIVE_MAGIC.to_vec();
        bytes.extend_from_slice(&SITE_ARCHIVE_VERSION.to_le_bytes());
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        bytes.extend_from_slice(&[0; 4]);
        assert!(matches!(
            read_all(&bytes),
            Err(StorageError::BadArchive { .. })
        ));
    }
}
