//! The envelope every stored value is wrapped in (private: part of the on-disk format).
//!
//! ```text
//! [format version: u8 = RECORD_FORMAT_VERSION][crc32 (IEEE), u32 LE][payload]
//! crc32 = CRC32(format version byte ‖ raw key ‖ payload)
//! ```
//! The key is covered too, so a value that ends up under the wrong key (a misdirected write or a flipped key
//! byte) fails verification instead of being read as another record.

use crate::{Result, StorageError, key};

/// Version of the record envelope this build writes and reads.
pub const RECORD_FORMAT_VERSION: u8 = 1;
const HEADER_BYTES: usize = 5;

fn checksum(key: &[u8], payload: &[u8]) -> u32 {
    let mut hasher = crc32fast::Hasher::new();
    hasher.update(&[RECORD_FORMAT_VERSION]);
    hasher.update(key);
    hasher.update(payload);
    hasher.finalize()
}

/// Wraps `payload` for storage under `key`.
pub(crate) fn seal(key: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut stored = Vec::with_capacity(HEADER_BYTES + payload.len());
    stored.push(RECORD_FORMAT_VERSION);
    stored.extend_from_slice(&checksum(key, payload).to_le_bytes());
    stored.extend_from_slice(payload);
    stored
}

/// Verifies a stored value read under `key` and returns its payload.
pub(crate) fn open<'a>(key: &[u8], stored: &'a [u8]) -> Result<&'a [u8]> {
    let corrupt = |reason: String| StorageError::Corrupt {
        key: key::describe(key),
        reason,
    };
    let Some((&version, rest)) = stored.split_first() else {
        return Err(corrupt("empty value".to_owned()));
    };
    if version != RECORD_FORMAT_VERSION {
        return Err(StorageError::UnsupportedFormat {
            key: key::describe(key),
            found: version,
            supported: RECORD_FORMAT_VERSION,
        });
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
    let actual = checksum(key, payload);
    if expected != actual {
        return Err(corrupt(format!(
            "CRC32 mismatch (stored {expected:#010x}, computed {actual:#010x} over {} payload bytes)",
            payload.len()
        )));
    }
    Ok(payload)
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
    fn counters_must_be_eight_bytes() {
        assert_eq!(decode_u64(b"k", &7_u64.to_le_bytes()).unwrap(), 7);
        assert!(decode_u64(b"k", &[1, 2, 3]).is_err());
    }
}
