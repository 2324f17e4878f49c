//! rosbag2's sqlite3 storage (`.db3`, the default before Iron) read with `rusqlite` on a bundled
//! SQLite: the `topics` table names each topic's type and serialization, the `messages` table holds
//! `(topic_id, timestamp, data)`. The file is opened read-only and immutable, so reading never writes
//! a journal, a lock or a `-shm` file next to a recording (which may sit on a read-only share).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use rusqlite::{Connection, OpenFlags};

use super::SourceError;
use super::ros_collector::RosKind;
use super::rosbag2::{StoredTopic, Visitor};

/// The first 16 bytes of every SQLite 3 database.
pub const SQLITE_MAGIC: &[u8] = b"SQLite format 3\0";

/// `path` as an SQLite URI that opens it read-only and immutable.
fn immutable_uri(path: &Path) -> String {
    let mut uri = String::from("file:");
    for byte in path.as_os_str().as_encoded_bytes() {
        match byte {
            b'?' | b'#' | b'%' | 0x00..=0x1f | 0x7f..=0xff => {
                let _ = write!(uri, "%{byte:02X}");
            }
            _ => uri.push(char::from(*byte)),
        }
    }
    uri.push_str("?mode=ro&immutable=1");
    uri
}

/// Streams every message of a rosbag2 sqlite3 file into `visitor` in the order it was written (row id),
/// as the MCAP and ROS1 readers stream theirs in file order; the recording is sorted by header stamp
/// afterwards, so only messages with equal stamps keep this order.
pub fn read(path: &Path, visitor: &mut dyn Visitor) -> Result<(), SourceError> {
    let malformed_by = |what: String, source: Option<Box<dyn std::error::Error + Send + Sync>>| {
        SourceError::Malformed {
            path: path.display().to_string(),
            format: "rosbag2 sqlite3",
            source,
            what,
        }
    };
    let malformed = |what: String| malformed_by(what, None);
    let mut head = Vec::with_capacity(SQLITE_MAGIC.len());
    {
        use std::io::Read as _;
        let file = std::fs::File::open(path).map_err(|source| SourceError::Io {
            path: path.display().to_string(),
            source,
        })?;
        file.take(SQLITE_MAGIC.len() as u64)
            .read_to_end(&mut head)
            .map_err(|source| SourceError::Io {
                path: path.display().to_string(),
                source,
            })?;
    }
    if head != SQLITE_MAGIC {
        return Err(malformed(
            "the file does not start with `SQLite format 3`: not an SQLite database".into(),
        ));
    }
    let db = Connection::open_with_flags(
        immutable_uri(path),
        OpenFlags::SQLITE_OPEN_READ_ONLY
            | OpenFlags::SQLITE_OPEN_URI
            | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )
    .map_err(|e| malformed_by(format!("cannot open: {e}"), Some(Box::new(e))))?;
    let sql = |e: rusqlite::Error| {
        malformed_by(
            format!("{e} (is it a rosbag2 recording?)"),
            Some(Box::new(e)),
        )
    };

    let mut topics: BTreeMap<i64, (String, RosKind)> = BTreeMap::new();
    {
        let mut statement = db
            .prepare("SELECT id, name, type, serialization_format FROM topics ORDER BY id")
            .map_err(sql)?;
        let mut rows = statement.query([]).map_err(sql)?;
        while let Some(row) = rows.next().map_err(sql)? {
            let id: i64 = row.get(0).map_err(sql)?;
            let name: String = row.get(1).map_err(sql)?;
            let type_name: String = row.get(2).map_err(sql)?;
            let serialization: String = row.get(3).map_err(sql)?;
            let kind = visitor.topic(&StoredTopic {
                name: &name,
                type_name: &type_name,
                serialization: &serialization,
            })?;
            topics.insert(id, (name, kind));
        }
    }
    let mut statement = db
        .prepare("SELECT topic_id, timestamp, data FROM messages ORDER BY id")
        .map_err(sql)?;
    let mut rows = statement.query([]).map_err(sql)?;
    while let Some(row) = rows.next().map_err(sql)? {
        let topic_id: i64 = row.get(0).map_err(sql)?;
        let timestamp: i64 = row.get(1).map_err(sql)?;
        let data = row.get_ref(2).map_err(sql)?.as_blob().map_err(|e| {
            malformed_by(
                format!("message at {timestamp} on topic id {topic_id}: data is not a blob ({e})"),
                Some(Box::new(e)),
            )
        })?;
        let Some((name, kind)) = topics.get(&topic_id) else {
            visitor.unknown_topic(topic_id, timestamp);
            continue;
        };
        visitor.message(*kind, name, timestamp.cast_unsigned(), data);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Nothing;

    impl Visitor for Nothing {
        fn topic(&mut self, _: &StoredTopic<'_>) -> Result<RosKind, SourceError> {
            Ok(RosKind::Other)
        }
        fn message(&mut self, _: RosKind, _: &str, _: u64, _: &[u8]) {}
        fn unknown_topic(&mut self, _: i64, _: i64) {}
    }

    // Reference: issue 35 — errors keep their `source()` chain instead of being turned into strings.
    #[test]
    fn a_damaged_database_is_malformed_and_keeps_sqlites_error() {
        let dir = tempfile::tempdir().expect("temporary folder");
        let path = dir.path().join("damaged.db3");
        let mut bytes = SQLITE_MAGIC.to_vec();
        bytes.extend(std::iter::repeat_n(0xA5u8, 4096));
        std::fs::write(&path, bytes).expect("written");
        let error = read(&path, &mut Nothing).expect_err("a damaged database is refused");
        assert!(
            matches!(
                error,
                SourceError::Malformed {
                    format: "rosbag2 sqlite3",
                    ..
                }
            ),
            "{error:?}"
        );
        let source = std::error::Error::source(&error).expect("SQLite's error is kept");
        assert!(
            source.downcast_ref::<rusqlite::Error>().is_some(),
            "{source:?}"
        );
    }

    #[test]
    fn uri_escapes_what_sqlite_would_read_as_syntax() {
        assert_eq!(
            immutable_uri(Path::new("/a b/c?d#e%f.db3")),
            "file:/a b/c%3Fd%23e%25f.db3?mode=ro&immutable=1"
        );
    }
}
