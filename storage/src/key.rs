//! Layout of raw keys in the key-value backends (private: part of the on-disk format).
//!
//! ```text
//! [0x00][site]                               site registry entry (value: SiteState)
//! [0x01][site len: u8][site][kind: u8][id]   record of a site
//! ```
//! The site is length-prefixed, so the prefix of site `a` never matches site `ab`. Record kinds at
//! [`INTERNAL_KIND_MIN`] and above are written only by this crate (map version, session sequence numbers,
//! checkpoints and their index entries).

use std::fmt::Write as _;

use crate::RecordKind;

/// Namespace byte of site registry entries.
pub(crate) const NS_SITE: u8 = 0x00;
/// Namespace byte of records.
pub(crate) const NS_RECORD: u8 = 0x01;
/// Kind bytes from here up are internal.
pub(crate) const INTERNAL_KIND_MIN: u8 = 0xF0;
/// Internal kind: the site's map version (empty id, value u64 LE).
pub(crate) const KIND_MAP_VERSION: u8 = 0xF0;
/// Internal kind: last applied sequence number of a session (id = session id, value u64 LE).
pub(crate) const KIND_SESSION_SEQ: u8 = 0xF1;
/// Internal kind: a checkpoint of the site stored inline (id = the log index it covers, u64 BE; value
/// opaque). Written by builds before checkpoint files, still read; also the kind of checkpoints in site
/// archives.
pub(crate) const KIND_CHECKPOINT: u8 = 0xF2;
/// Internal kind: the index entry of a checkpoint whose bytes are in a file (id = the log index it covers,
/// u64 BE; value: the private `checkpoint_entry` encoding, naming the file).
pub(crate) const KIND_CHECKPOINT_FILE: u8 = 0xF3;

/// Key of a site's registry entry.
pub(crate) fn site_key(site: &str) -> Vec<u8> {
    let mut key = Vec::with_capacity(1 + site.len());
    key.push(NS_SITE);
    key.extend_from_slice(site.as_bytes());
    key
}

/// Prefix of every record of a site. Site ids are at most 255 bytes (checked before any call).
pub(crate) fn site_prefix(site: &str) -> Vec<u8> {
    debug_assert!(u8::try_from(site.len()).is_ok());
    let mut key = Vec::with_capacity(2 + site.len() + 1);
    key.push(NS_RECORD);
    key.push(site.len() as u8);
    key.extend_from_slice(site.as_bytes());
    key
}

/// Prefix of a site's records of one kind.
pub(crate) fn kind_prefix(site: &str, kind: u8) -> Vec<u8> {
    let mut key = site_prefix(site);
    key.push(kind);
    key
}

/// Full key of a record.
pub(crate) fn record_key(site: &str, kind: u8, id: &[u8]) -> Vec<u8> {
    let mut key = kind_prefix(site, kind);
    key.extend_from_slice(id);
    key
}

/// Human-readable form of a raw key, for error messages: `site/kind/id`.
pub(crate) fn describe(key: &[u8]) -> String {
    match key.split_first() {
        Some((&NS_SITE, site)) => format!("{}/<registry>", String::from_utf8_lossy(site)),
        Some((&NS_RECORD, rest)) => {
            let Some((&len, rest)) = rest.split_first() else {
                return hex(key);
            };
            let len = usize::from(len);
            if rest.len() <= len {
                return hex(key);
            }
            let (site, rest) = rest.split_at(len);
            let (kind, id) = (rest[0], &rest[1..]);
            let kind_name = match kind {
                KIND_MAP_VERSION => "map-version".to_owned(),
                KIND_SESSION_SEQ => "session-seq".to_owned(),
                KIND_CHECKPOINT => "checkpoint".to_owned(),
                KIND_CHECKPOINT_FILE => "checkpoint-file".to_owned(),
                other => RecordKind::from_byte(other)
                    .map_or_else(|| format!("kind{other}"), |k| k.name().to_owned()),
            };
            format!(
                "{}/{kind_name}/{}",
                String::from_utf8_lossy(site),
                crate::RecordId::new(id)
            )
        }
        _ => hex(key),
    }
}

fn hex(bytes: &[u8]) -> String {
    let mut out = String::from("raw:0x");
    for byte in bytes {
        let _ = write!(out, "{byte:02x}");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn site_prefixes_do_not_overlap() {
        let a = kind_prefix("a", 2);
        let ab = kind_prefix("ab", 2);
        assert!(!ab.starts_with(&a));
        assert!(!a.starts_with(&ab));
        assert!(record_key("a", 2, b"x").starts_with(&site_prefix("a")));
        assert!(!record_key("ab", 2, b"x").starts_with(&site_prefix("a")));
    }

    #[test]
    fn keys_describe_readably() {
        assert_eq!(
            describe(&record_key("depot", RecordKind::Node.as_byte(), b"n1")),
            "depot/node/n1"
        );
        assert_eq!(
            describe(&record_key("depot", KIND_MAP_VERSION, b"")),
            "depot/map-version/0x"
        );
        assert_eq!(describe(&site_key("depot")), "depot/<registry>");
        assert_eq!(describe(&[7, 1]), "raw:0x0701");
    }
}
