//! The envelope every stored value is wrapped in (private: part of the on-disk format).
//!
//! ```text
//! [format: u8][crc32 (IEEE), u32 LE][payload]
//! crc32 = CRC32(format byte ‖ raw key ‖ payload)
//! ```
//! The key is covered too, so a value that ends up under the wrong key (a misdirected write or a flipped key
//! byte) fails verification instead of being read as another record.
//!
//! The format byte says what the payload is:
//! - [`RECORD_FORMAT_VERSION`] (1): the value itself. Every value but large record values, and every value
//!   of builds before value files.
//! - [`VALUE_ENTRY_FORMAT`] (`0x81`): the entry of a record value stored in a file of its own (length,
//!   CRC32, file name: `value_entry`), written for record values longer than
//!   [`crate::MAX_INLINE_VALUE_BYTES`]. Only records of a [`crate::RecordKind`] may hold one.
//!
//! Format bytes from `0x80` up are entries, below it versions of the inline value, so the two can never be
//! taken for each other; the CRC covers the format byte, so a flipped one fails verification. A build that
//! predates a format reports its records as [`StorageError::UnsupportedFormat`], never misreads them.

use crate::{Result, StorageError, key};

/// Version of the record envelope this build writes and reads (the format byte of a value stored inline).
pub const RECORD_FORMAT_VERSION: u8 = 1;
/// The format byte of a record whose value is in a file: the payload is the value's entry.
pub(crate) const VALUE_ENTRY_FORMAT: u8 = 0x81;
const HEADER_BYTES: usize = 5;

fn checksum(format: u8, key: &[u8], payload: &[u8]) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&[format]);
    hasher.update(key);
    hasher.update(payload);
    hasher.finalize()
}

fn seal_as(format: u8, key: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut stored = Vec::with_capacity(HEADER_BYTES + payload.len());
    stored.push(format);
    stored.extend_from_slice(&checksum(format, key, payload).to_le_bytes());
    stored.extend_from_slice(payload);
    stored
}

/// Wraps `payload` for storage under `key`.
pub(crate) fn seal(key: &[u8], payload: &[u8]) -> Vec<u8> {
    seal_as(RECORD_FORMAT_VERSION, key, payload)
}

/// Wraps the entry of a value in a file (`value_entry`) for storage under the value's `key`.
pub(crate) fn seal_entry(key: &[u8], entry: &[u8]) -> Vec<u8> {
    seal_as(VALUE_ENTRY_FORMAT, key, entry)
}

/// What a record's stored value holds, verified.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Opened<'a> {
    /// The value itself.
    Value(&'a [u8]),
    /// The entry of a value in a file (`value_entry`).
    Entry(&'a [u8]),
}

/// Verifies a stored value read under `key` and returns its payload; the entry of a value in a file is
/// [`StorageError::UnsupportedFormat`] (see [`open_record`]).
pub(crate) fn open<'a>(key: &[u8], stored: &'a [u8]) -> Result<&'a [u8]> {
    match open_record(key, stored)? {
        Opened::Value(payload) => Ok(payload),
        Opened::Entry(_) => Err(unsupported(key, VALUE_ENTRY_FORMAT)),
    }
}

fn unsupported(key: &[u8], found: u8) -> StorageError {
    StorageError::UnsupportedFormat {
        key: key::describe(key),
        found,
        supported: RECORD_FORMAT_VERSION,
    }
}

/// Verifies a record's stored value read under `key`: the value itself or the entry of a value in a file.
pub(crate) fn open_record<'a>(key: &[u8], stored: &'a [u8]) -> Result<Opened<'a>> {
    let corrupt = |reason: String| StorageError::Corrupt {
        key: key::describe(key),
        reason,
    };
    let Some((&format, rest)) = stored.split_first() else {
        return Err(corrupt("empty value".to_owned()));
    };
    if format != RECORD_FORMAT_VERSION && format != VALUE_ENTRY_FORMAT {
        return Err(unsupported(key, format));
    }
    if rest.len() < 4 {
        return Err(corrupt(format!(
            "truncated envelope of {} bytes",
            stored.len()
        )));
    }
    let (crc_bytes, payload) = rest.split_at(4);
    let mut crc = [0_u8; 4];
    crc.copy_from_slice(crc_bytes);
    let expected = u32::from_le_bytes(crc);
    let actual = checksum(format, key, payload);
    if expected != actual {
        return Err(corrupt(format!(
            "CRC32 mismatch (stored {expected:#010x}, computed {actual:#010x} over {} payload bytes)",
            payload.len()
        )));
    }
    Ok(if format == VALUE_ENTRY_FORMAT {
        Opened::Entry(payload)
    } else {
        Opened::Value(payload)
    })
}

/// Decodes an 8-byte little-endian counter payload (map version, session sequence number).
pub(crate) fn decode_u64(key: &[u8], payload: &[u8]) -> Result<u64> {
    let bytes: [u8; 8] = payload.try_into().map_err(|_| StorageError::Corrupt {
        key: key::describe(key),
        reason: format!("counter value has {} bytes, expected 8", payload.len()),
    })?;
    Ok(u64::from_le_bytes(bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip() {
        let stored = seal(b"k", b"hello");
        assert_eq!(open(b"k", &stored).unwrap(), b"hello");
        assert_eq!(open(b"k", &seal(b"k", b"")).unwrap(), b"");
    }

    #[test]
    fn every_single_byte_flip_is_detected() {
        let stored = seal(b"key", b"payload bytes");
        for index in 0..stored.len() {
            for bit in 0..8 {
                let mut bad = stored.clone();
                bad[index] ^= 1 << bit;
                assert!(
                    open(b"key", &bad).is_err(),
                    "flip of bit {bit} of byte {index} went unnoticed"
                );
            }
        }
    }

    #[test]
    fn wrong_key_truncation_and_version_are_detected() {
        let stored = seal(b"key", b"payload");
        assert!(matches!(
            open(b"kez", &stored),
            Err(StorageError::Corrupt { .. })
        ));
        assert!(matches!(
            open(b"key", &stored[..3]),
            Err(StorageError::Corrupt { .. })
        ));
        assert!(matches!(
            open(b"key", &[]),
            Err(StorageError::Corrupt { .. })
        ));
        assert!(matches!(
            open(b"key", &stored[..stored.len() - 1]),
            Err(StorageError::Corrupt { .. })
        ));
        let mut newer = stored;
        newer[0] = 2;
        assert!(matches!(
            open(b"key", &newer),
            Err(StorageError::UnsupportedFormat { found: 2, .. })
        ));
    }

    #[test]
    fn entries_and_values_are_told_apart_and_a_flipped_format_byte_is_detected() {
        let entry = seal_entry(b"key", b"entry bytes");
        assert_eq!(
            open_record(b"key", &entry).unwrap(),
            Opened::Entry(b"entry bytes")
        );
        let value = seal(b"key", b"entry bytes");
        assert_eq!(
            open_record(b"key", &value).unwrap(),
            Opened::Value(b"entry bytes")
        );
        // Where only values are expected, an entry is a format this reader does not take.
        assert!(matches!(
            open(b"key", &entry),
            Err(StorageError::UnsupportedFormat { found: 0x81, .. })
        ));
        let mut flipped = entry;
        flipped[0] = RECORD_FORMAT_VERSION;
        assert!(matches!(
            open_record(b"key", &flipped),
            Err(StorageError::Corrupt { .. })
        ));
        let mut flipped = value;
        flipped[0] = VALUE_ENTRY_FORMAT;
        assert!(matches!(
            open_record(b"key", &flipped),
            Err(StorageError::Corrupt { .. })
        ));
    }

    #[test]
    fn counters_must_be_eight_bytes() {
        assert_eq!(decode_u64(b"k", &7_u64.to_le_bytes()).unwrap(), 7);
        assert!(decode_u64(b"k", &[1, 2, 3]).is_err());
    }
}
