//! The entry of a record value stored in a file of its own (private: part of the on-disk format): all the
//! key-value store holds of the value, under the record's own key.
//!
//! ```text
//! [byte length: u64 LE][CRC32 (IEEE): u32 LE][file name: UTF-8]
//! CRC32 = CRC32(record key ‖ the value's bytes)
//! ```
//! The entry is sealed in the record envelope with the format byte `VALUE_ENTRY_FORMAT` (`envelope`), which
//! tells it from a value stored inline. The file's CRC covers the record's key as well as its bytes, so a
//! file read for another record (a misplaced or stale file) fails verification instead of being used.
//!
//! The file is `<site dir>/<serial number, 16 hex digits>-<CRC32, 8 hex digits>.val` under the store's
//! value directory (`side_files`). The serial number is the store's count of value files written, so no
//! two writes ever share a name, and a file an entry names is never replaced under it (the CRC only helps
//! a reader of the directory).

use std::path::Path;

use crate::envelope;
use crate::key;
use crate::side_files::{is_file_name, site_dir};
use crate::{Result, StorageError};

/// Bytes before the file name.
const HEADER_BYTES: usize = 8 + 4;

/// What the key-value store holds of a record value stored in a file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct ValueEntry {
    /// The value's length, in bytes.
    pub(crate) len: u64,
    /// CRC32 of the record's key and the value's bytes (see the module docs).
    pub(crate) crc: u32,
    /// The file, relative to the value directory.
    pub(crate) file: String,
}

fn checksum(key: &[u8], bytes: &[u8]) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(key);
    hasher.update(bytes);
    hasher.finalize()
}

impl ValueEntry {
    /// The entry of `bytes` as the value of the site's record under `key`, in the file numbered `serial`.
    pub(crate) fn of(site: &str, key: &[u8], serial: u64, bytes: &[u8]) -> Self {
        let crc = checksum(key, bytes);
        Self {
            len: bytes.len() as u64,
            crc,
            file: format!("{}/{serial:016x}-{crc:08x}.val", site_dir(site)),
        }
    }

    /// The serial number in the name of a value file, `None` for any other name.
    pub(crate) fn serial(file: &str) -> Option<u64> {
        let (_, name) = file.rsplit_once('/')?;
        let (serial, crc) = name.strip_suffix(".val")?.split_once('-')?;
        if serial.len() != 16 || crc.len() != 8 {
            return None;
        }
        u64::from_str_radix(serial, 16).ok()
    }

    /// The entry's stored form under the record's `key` (sealed).
    pub(crate) fn seal(&self, key: &[u8]) -> Vec<u8> {
        let mut out = Vec::with_capacity(HEADER_BYTES + self.file.len());
        out.extend_from_slice(&self.len.to_le_bytes());
        out.extend_from_slice(&self.crc.to_le_bytes());
        out.extend_from_slice(self.file.as_bytes());
        envelope::seal_entry(key, &out)
    }

    /// Decodes an entry opened from the envelope under `key`.
    pub(crate) fn decode(key: &[u8], payload: &[u8]) -> Result<Self> {
        let corrupt = |reason: String| StorageError::Corrupt {
            key: key::describe(key),
            reason,
        };
        let (Some(len), Some(crc), Some(file)) = (
            payload.get(..8),
            payload.get(8..HEADER_BYTES),
            payload.get(HEADER_BYTES..),
        ) else {
            return Err(corrupt(format!(
                "value file entry of {} bytes",
                payload.len()
            )));
        };
        let file = std::str::from_utf8(file)
            .ok()
            .filter(|file| is_file_name(file))
            .ok_or_else(|| corrupt("value file entry names no valid file".to_owned()))?;
        Ok(Self {
            len: u64::from_le_bytes(len.try_into().unwrap_or_default()),
            crc: u32::from_le_bytes(crc.try_into().unwrap_or_default()),
            file: file.to_owned(),
        })
    }

    /// Checks `bytes`, read from `path`, against the entry under `key`: [`StorageError::Corrupt`] naming
    /// the file if they are not the record's value.
    pub(crate) fn verify(&self, key: &[u8], bytes: &[u8], path: &Path) -> Result<()> {
        let corrupt = |reason: String| StorageError::Corrupt {
            key: key::describe(key),
            reason: format!("value file {}: {reason}", path.display()),
        };
        if bytes.len() as u64 != self.len {
            return Err(corrupt(format!(
                "{} bytes, its entry says {}",
                bytes.len(),
                self.len
            )));
        }
        let actual = checksum(key, bytes);
        if actual != self.crc {
            return Err(corrupt(format!(
                "CRC32 mismatch (entry {:#010x}, computed {actual:#010x} over {} bytes)",
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
    use crate::envelope::{Opened, open_record};

    fn opened(key: &[u8], stored: &[u8]) -> ValueEntry {
        let Opened::Entry(payload) = open_record(key, stored).unwrap() else {
            panic!("not an entry");
        };
        ValueEntry::decode(key, payload).unwrap()
    }

    #[test]
    fn entries_round_trip_name_their_serial_and_malformed_ones_are_corrupt() {
        let entry = ValueEntry::of("Halle 7", b"key", 0x2a, b"value bytes");
        assert_eq!(
            entry.file,
            format!("Halle%207/000000000000002a-{:08x}.val", entry.crc)
        );
        assert_eq!(ValueEntry::serial(&entry.file), Some(0x2a));
        assert_eq!(opened(b"key", &entry.seal(b"key")), entry);
        for name in [
            "a/2a-00000000.val",
            "a/000000000000002a-0.val",
            "a/000000000000002a-00000000.ckpt",
            "000000000000002a-00000000.val",
            "a/00000000000000zz-00000000.val",
        ] {
            assert_eq!(ValueEntry::serial(name), None, "{name}");
        }
        let mut payload = 11_u64.to_le_bytes().to_vec();
        payload.extend_from_slice(&7_u32.to_le_bytes());
        for bad in [&payload[..5], &payload[..]] {
            assert!(
                matches!(
                    ValueEntry::decode(b"k", bad),
                    Err(StorageError::Corrupt { .. })
                ),
                "{bad:?}"
            );
        }
        payload.extend_from_slice(b"../../etc/passwd");
        assert!(ValueEntry::decode(b"k", &payload).is_err());
    }

    #[test]
    fn bytes_of_another_length_or_record_do_not_verify() {
        let entry = ValueEntry::of("depot", b"key", 1, b"value");
        let path = Path::new("f.val");
        entry.verify(b"key", b"value", path).unwrap();
        let error = entry.verify(b"key", b"vaLue", path).unwrap_err();
        assert!(error.to_string().contains("CRC32 mismatch"), "{error}");
        assert!(error.to_string().contains("f.val"), "{error}");
        assert!(entry.verify(b"key", b"valu", path).is_err());
        assert!(entry.verify(b"kez", b"value", path).is_err());
    }
}
