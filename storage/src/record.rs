//! What a record is addressed by: site, kind and id.

use std::fmt;

use crate::{Result, StorageError};

/// Longest accepted site id or session id, in bytes (UTF-8).
pub const MAX_NAME_BYTES: usize = 255;
/// Longest accepted record id, in bytes.
pub const MAX_ID_BYTES: usize = 1024;
/// Largest accepted record value, in bytes (256 MiB). Bounds memory when reading archives.
pub const MAX_VALUE_BYTES: usize = 256 << 20;

/// The kind of a record: the second level of the key, after the site. Scans go by (site, kind).
///
/// The byte values are part of the on-disk format and of site archives: never renumber a kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[non_exhaustive]
#[repr(u8)]
pub enum RecordKind {
    /// Site-wide metadata (name, frame origin, options...).
    SiteMeta = 1,
    /// A submap (grid and its pose).
    Submap = 2,
    /// A trajectory node (scan pose, gravity-aligned data).
    Node = 3,
    /// A pose-graph constraint.
    Constraint = 4,
    /// A trajectory (one robot session's chain of nodes).
    Trajectory = 5,
    /// A mapping session of one robot.
    Session = 6,
    /// An outbox entry (agent side: an upload not yet acknowledged).
    Outbox = 7,
}

impl RecordKind {
    /// Every kind, in byte order.
    pub const ALL: [Self; 7] = [
        Self::SiteMeta,
        Self::Submap,
        Self::Node,
        Self::Constraint,
        Self::Trajectory,
        Self::Session,
        Self::Outbox,
    ];

    /// The kind's byte in keys and archives.
    pub fn as_byte(self) -> u8 {
        self as u8
    }

    /// The kind with this byte, if any.
    pub fn from_byte(byte: u8) -> Option<Self> {
        Self::ALL.into_iter().find(|kind| kind.as_byte() == byte)
    }

    /// Short lowercase name, used in messages.
    pub fn name(self) -> &'static str {
        match self {
            Self::SiteMeta => "site-meta",
            Self::Submap => "submap",
            Self::Node => "node",
            Self::Constraint => "constraint",
            Self::Trajectory => "trajectory",
            Self::Session => "session",
            Self::Outbox => "outbox",
        }
    }
}

impl fmt::Display for RecordKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A record's id within its (site, kind): opaque bytes, ordered bytewise in scans.
///
/// [`RecordId::from_u64`] (and `From<u64>`) encodes big-endian so that numeric ids scan in numeric order.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct RecordId(Vec<u8>);

impl RecordId {
    /// An id from raw bytes.
    pub fn new(bytes: impl Into<Vec<u8>>) -> Self {
        Self(bytes.into())
    }

    /// A numeric id, big-endian so scans return ids in increasing numeric order.
    pub fn from_u64(value: u64) -> Self {
        Self(value.to_be_bytes().to_vec())
    }

    /// A two-part numeric id (e.g. trajectory, index), ordered by the first part then the second.
    pub fn from_pair(major: u64, minor: u64) -> Self {
        let mut bytes = major.to_be_bytes().to_vec();
        bytes.extend_from_slice(&minor.to_be_bytes());
        Self(bytes)
    }

    /// The value of an id made by [`RecordId::from_u64`] (`None` unless exactly 8 bytes).
    pub fn as_u64(&self) -> Option<u64> {
        let bytes: [u8; 8] = self.0.as_slice().try_into().ok()?;
        Some(u64::from_be_bytes(bytes))
    }

    /// The id's bytes.
    pub fn as_bytes(&self) -> &[u8] {
        &self.0
    }

    /// The id's bytes, by value.
    pub fn into_bytes(self) -> Vec<u8> {
        self.0
    }
}

impl From<u64> for RecordId {
    fn from(value: u64) -> Self {
        Self::from_u64(value)
    }
}

impl From<&str> for RecordId {
    fn from(value: &str) -> Self {
        Self(value.as_bytes().to_vec())
    }
}

impl From<&[u8]> for RecordId {
    fn from(value: &[u8]) -> Self {
        Self(value.to_vec())
    }
}

impl From<Vec<u8>> for RecordId {
    fn from(value: Vec<u8>) -> Self {
        Self(value)
    }
}

impl fmt::Display for RecordId {
    /// Printable UTF-8 ids as text, others as hex.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match std::str::from_utf8(&self.0) {
            Ok(text) if !text.is_empty() && text.chars().all(|c| c.is_ascii_graphic()) => {
                f.write_str(text)
            }
            _ => {
                f.write_str("0x")?;
                for byte in &self.0 {
                    write!(f, "{byte:02x}")?;
                }
                Ok(())
            }
        }
    }
}

/// Checks a site id: 1..=[`MAX_NAME_BYTES`] bytes of UTF-8 without control characters.
pub fn validate_site_id(site: &str) -> Result<()> {
    check_name(site).map_err(|reason| StorageError::InvalidSiteId {
        site: site.to_owned(),
        reason,
    })
}

/// Checks a session id: same rules as site ids.
pub fn validate_session_id(session: &str) -> Result<()> {
    check_name(session).map_err(|reason| StorageError::InvalidSessionId {
        session: session.to_owned(),
        reason,
    })
}

fn check_name(name: &str) -> Result<(), &'static str> {
    if name.is_empty() {
        return Err("must not be empty");
    }
    if name.len() > MAX_NAME_BYTES {
        return Err("longer than 255 bytes");
    }
    if name.chars().any(char::is_control) {
        return Err("contains a control character");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kind_bytes_round_trip_and_are_unique() {
        for kind in RecordKind::ALL {
            assert_eq!(RecordKind::from_byte(kind.as_byte()), Some(kind));
        }
        assert_eq!(RecordKind::from_byte(0), None);
        assert_eq!(RecordKind::from_byte(0xF0), None);
    }

    #[test]
    fn numeric_ids_sort_numerically() {
        let mut ids: Vec<RecordId> = [300_u64, 2, 70_000, 1]
            .into_iter()
            .map(RecordId::from)
            .collect();
        ids.sort();
        let values: Vec<u64> = ids.iter().map(|id| id.as_u64().unwrap()).collect();
        assert_eq!(values, [1, 2, 300, 70_000]);
        assert!(RecordId::from_pair(1, 9) < RecordId::from_pair(2, 0));
    }

    #[test]
    fn ids_display_as_text_or_hex() {
        assert_eq!(RecordId::from("node-7").to_string(), "node-7");
        assert_eq!(RecordId::from_u64(1).to_string(), "0x0000000000000001");
    }

    #[test]
    fn names_are_validated() {
        assert!(validate_site_id("warehouse-3").is_ok());
        assert!(validate_site_id("").is_err());
        assert!(validate_site_id("a\nb").is_err());
        assert!(validate_site_id(&"x".repeat(256)).is_err());
        assert!(validate_session_id(&"x".repeat(255)).is_ok());
    }
}
