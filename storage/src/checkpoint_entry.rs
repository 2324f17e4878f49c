//! The index entry of a checkpoint whose bytes are in a file (private: part of the on-disk format): all
//! the key-value store holds of it.
//!
//! ```text
//! [entry format: u8 = 1][byte length: u64 LE][CRC32 (IEEE): u32 LE][file name: UTF-8]
//! CRC32 = CRC32(site/checkpoint/<log index> key ‖ the checkpoint's bytes)
//! ```
//! The entry is sealed in the record envelope under `site/checkpoint-file/<log index>` like every
//! record. The file's CRC covers the checkpoint's key as well as its bytes, so a file read for another site
//! or log index (a misplaced or stale file) fails verification instead of being used.

use std::path::Path;

use crate::key::{self, KIND_CHECKPOINT};
use crate::side_files::{is_file_name, site_dir};
use crate::{Result, StorageError};

/// Format byte of the entries this build writes and reads.
const ENTRY_FORMAT: u8 = 1;
/// Bytes before the file name.
const HEADER_BYTES: usize = 1 + 8 + 4;

/// What the key-value store holds of a checkpoint stored in a file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct CheckpointEntry {
    /// The checkpoint's length, in bytes.
    pub(crate) len: u64,
    /// CRC32 of the checkpoint's key and bytes (see the module docs).
    pub(crate) crc: u32,
    /// The file, relative to the checkpoint directory.
    pub(crate) file: String,
}

fn checksum(site: &str, log_index: u64, bytes: &[u8]) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&key::record_key(
        site,
        KIND_CHECKPOINT,
        &log_index.to_be_bytes(),
    ));
    hasher.update(bytes);
    hasher.finalize()
}

/// The file name of a site's checkpoint at `log_index` whose checksum is `crc` (relative to the checkpoint
/// directory; see `side_files`).
fn file_name(site: &str, log_index: u64, crc: u32) -> String {
    format!("{}/{log_index:020}-{crc:08x}.ckpt", site_dir(site))
}

impl CheckpointEntry {
    /// The entry of `bytes` as the site's checkpoint at `log_index`, and the file it goes to.
    pub(crate) fn of(site: &str, log_index: u64, bytes: &[u8]) -> Self {
        let crc = checksum(site, log_index, bytes);
        Self {
            len: bytes.len() as u64,
            crc,
            file: file_name(site, log_index, crc),
        }
    }

    /// The entry's stored form (before the envelope).
    pub(crate) fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_BYTES + self.file.len());
        out.push(ENTRY_FORMAT);
        out.extend_from_slice(&self.len.to_le_bytes());
        out.extend_from_slice(&self.crc.to_le_bytes());
        out.extend_from_slice(self.file.as_bytes());
        out
    }

    /// Decodes an entry opened from the envelope under `key`.
    pub(crate) fn decode(key: &[u8], payload: &[u8]) -> Result<Self> {
        let corrupt = |reason: String| StorageError::Corrupt {
            key: key::describe(key),
            reason,
        };
        if payload.first() != Some(&ENTRY_FORMAT) {
            return Err(corrupt(format!(
                "checkpoint index entry of format {:?}, this build reads {ENTRY_FORMAT}",
                payload.first()
            )));
        }
        let (Some(len), Some(crc), Some(file)) = (
            payload.get(1..9),
            payload.get(9..HEADER_BYTES),
            payload.get(HEADER_BYTES..),
        ) else {
            return Err(corrupt(format!(
                "checkpoint index entry of {} bytes",
                payload.len()
            )));
        };
        let file = std::str::from_utf8(file)
            .ok()
            .filter(|file| is_file_name(file))
            .ok_or_else(|| corrupt("checkpoint index entry names no valid file".to_owned()))?;
        Ok(Self {
            len: u64::from_le_bytes(len.try_into().unwrap_or_default()),
            crc: u32::from_le_bytes(crc.try_into().unwrap_or_default()),
            file: file.to_owned(),
        })
    }

    /// Checks `bytes`, read from `path`, against the entry under `key` of the site's checkpoint at
    /// `log_index`: [`StorageError::Corrupt`] naming the file if they are not the checkpoint's.
    pub(crate) fn verify(
        &self,
        key: &[u8],
        (site, log_index): (&str, u64),
        bytes: &[u8],
        path: &Path,
    ) -> Result<()> {
        let corrupt = |reason: String| StorageError::Corrupt {
            key: key::describe(key),
            reason: format!("file {}: {reason}", path.display()),
        };
        if bytes.len() as u64 != self.len {
            return Err(corrupt(format!(
                "{} bytes, its index entry says {}",
                bytes.len(),
                self.len
            )));
        }
        let actual = checksum(site, log_index, bytes);
        if actual != self.crc {
            return Err(corrupt(format!(
                "CRC32 mismatch (index entry {:#010x}, computed {actual:#010x} over {} bytes)",
                self.crc,
                bytes.len()
            )));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn entries_round_trip_and_malformed_ones_are_corrupt() {
        let entry = CheckpointEntry::of("depot", 7, b"state 7");
        assert_eq!(
            entry.file,
            format!("depot/00000000000000000007-{:08x}.ckpt", entry.crc)
        );
        assert_eq!(
            CheckpointEntry::decode(b"k", &entry.encode()).unwrap(),
            entry
        );
        let encoded = entry.encode();
        for bad in [
            &encoded[..5],
            &encoded[..HEADER_BYTES],
            &[2_u8; 20][..],
            &[][..],
        ] {
            assert!(
                matches!(
                    CheckpointEntry::decode(b"k", bad),
                    Err(StorageError::Corrupt { .. })
                ),
                "{bad:?}"
            );
        }
        let mut escaping = encoded[..HEADER_BYTES].to_vec();
        escaping.extend_from_slice(b"../../etc/passwd");
        assert!(CheckpointEntry::decode(b"k", &escaping).is_err());
    }

    #[test]
    fn bytes_of_another_length_site_or_index_do_not_verify() {
        let entry = CheckpointEntry::of("depot", 7, b"state 7");
        let path = Path::new("f.ckpt");
        let check = |site, index, bytes: &[u8]| entry.verify(b"k", (site, index), bytes, path);
        check("depot", 7, b"state 7").unwrap();
        let error = check("depot", 7, b"state 8").unwrap_err();
        assert!(error.to_string().contains("CRC32 mismatch"), "{error}");
        assert!(error.to_string().contains("f.ckpt"), "{error}");
        assert!(check("depot", 7, b"state").is_err());
        assert!(check("yard", 7, b"state 7").is_err());
        assert!(check("depot", 8, b"state 7").is_err());
    }
}
