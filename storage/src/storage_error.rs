//! The one error type of this crate.

use std::path::PathBuf;
use std::sync::Arc;

use thiserror::Error;

/// Result of every fallible storage operation.
pub type Result<T, E = StorageError> = std::result::Result<T, E>;

/// Everything that can go wrong when reading or writing a [`crate::MapStore`].
///
/// A record that fails its checksum is always reported as [`StorageError::Corrupt`]: no operation returns,
/// exports or overwrites-around a corrupt value silently.
#[derive(Debug, Error)]
pub enum StorageError {
    /// A stored record failed verification (bad CRC, truncated envelope, malformed internal value).
    #[error("corrupt record {key}: {reason}")]
    Corrupt {
        /// Human-readable form of the record's key (`site/kind/id`).
        key: String,
        /// What exactly failed.
        reason: String,
    },
    /// A stored record was written in a record format this build does not know (probably by a newer build).
    #[error(
        "record {key} has storage format version {found}, this build reads only version {supported}"
    )]
    UnsupportedFormat {
        /// Human-readable form of the record's key.
        key: String,
        /// Version byte found on disk.
        found: u8,
        /// Version this build writes and reads.
        supported: u8,
    },
    /// A site id is empty, too long or contains control characters.
    #[error("invalid site id {site:?}: {reason}")]
    InvalidSiteId {
        /// The rejected id.
        site: String,
        /// Why it was rejected.
        reason: &'static str,
    },
    /// A session id is empty, too long or contains control characters.
    #[error("invalid session id {session:?}: {reason}")]
    InvalidSessionId {
        /// The rejected id.
        session: String,
        /// Why it was rejected.
        reason: &'static str,
    },
    /// A record id or value exceeds the size limit.
    #[error("{what} of record {key} is too large: {len} bytes (limit {max} bytes)")]
    TooLarge {
        /// Human-readable form of the record's key.
        key: String,
        /// `"id"` or `"value"`.
        what: &'static str,
        /// Offending length in bytes.
        len: usize,
        /// Limit in bytes.
        max: usize,
    },
    /// The site's import or deletion was interrupted; it refuses writes until deleted or imported again.
    #[error(
        "site {site:?} is incomplete (an import or deletion of it was interrupted): delete it or import it again"
    )]
    SiteIncomplete {
        /// The site.
        site: String,
    },
    /// The operation needs an existing site.
    #[error("site {site:?} does not exist")]
    SiteNotFound {
        /// The site.
        site: String,
    },
    /// Import refuses to merge into a site that already holds data.
    #[error("cannot import into site {site:?}: it already holds data (delete it first)")]
    SiteNotEmpty {
        /// The site.
        site: String,
    },
    /// A site archive stream is malformed, truncated or fails a chunk checksum. Nothing was imported.
    #[error("invalid site archive: {reason}")]
    BadArchive {
        /// What exactly failed.
        reason: String,
    },
    /// The database directory stayed locked by another process for every opening attempt.
    #[error(
        "store at {} is locked by another process (still locked after {attempts} attempts over {waited_ms} ms); \
         is another evermap-server running on it?",
        path.display()
    )]
    Locked {
        /// Database directory.
        path: PathBuf,
        /// Opening attempts made.
        attempts: u32,
        /// Total time spent waiting between attempts, in milliseconds.
        waited_ms: u64,
    },
    /// Storage options failed validation.
    #[error("invalid storage option {field}: {reason}")]
    InvalidOptions {
        /// Option name.
        field: &'static str,
        /// Why it is invalid.
        reason: String,
    },
    /// The sled database reported an error (its own corruption detection included).
    #[error("sled database error: {0}")]
    Sled(#[from] sled::Error),
    /// The database refuses writes since one failed (sled after a full disk) and will be reopened by a
    /// later write (see [`crate::SledStore`]); retry.
    #[error(
        "the store refuses writes since one failed ({cause}); it is reopened on a later write, retry"
    )]
    Wedged {
        /// The failure that wedged it.
        cause: String,
        /// The error `cause` quotes, when one wedged it: shared by every refusal until the reopen.
        source: Option<Arc<StorageError>>,
        /// The failure was a full disk.
        out_of_space: bool,
    },
    /// A checkpoint was to cover log entries the site does not hold yet.
    #[error(
        "a checkpoint of site {site:?} at log index {log_index} is ahead of the site's map version {map_version}"
    )]
    CheckpointAhead {
        /// The site.
        site: String,
        /// The log index the checkpoint was to cover.
        log_index: u64,
        /// The site's map version.
        map_version: u64,
    },
    /// A file beside the database (a checkpoint's or a large record value's, see [`crate::SledStore`])
    /// could not be written, read or removed.
    #[error("cannot {action} {what} file {} of site {site:?}: {source}", file.display())]
    File {
        /// What the file holds: `"checkpoint"`, `"value"`.
        what: &'static str,
        /// The site.
        site: String,
        /// The file.
        file: PathBuf,
        /// What was being done: `"write"`, `"read"`, `"remove"`.
        action: &'static str,
        /// The failure.
        source: std::io::Error,
    },
    /// A directory of files beside the database, or a file in it that no entry names, could not be
    /// created, listed, measured or removed.
    #[error("cannot {action} {} ({what} files): {source}", path.display())]
    FileDir {
        /// What the directory's files hold: `"checkpoint"`, `"value"`.
        what: &'static str,
        /// The directory or file.
        path: PathBuf,
        /// What was being done, e.g. `"list"`.
        action: &'static str,
        /// The failure.
        source: std::io::Error,
    },
    /// Reading or writing a stream or file failed.
    #[error("I/O error: {0}")]
    Io(#[from] std::io::Error),
}

impl StorageError {
    /// Whether the disk is full (`ENOSPC`, also as sled reports it): a write failed for lack of space,
    /// and may succeed once space returns. Nothing of a failed batch was stored.
    pub fn is_out_of_space(&self) -> bool {
        if let Self::Wedged { out_of_space, .. } = self {
            return *out_of_space;
        }
        let (Self::Io(io)
        | Self::Sled(sled::Error::Io(io))
        | Self::File { source: io, .. }
        | Self::FileDir { source: io, .. }) = self
        else {
            return false;
        };
        io.kind() == std::io::ErrorKind::StorageFull || io.raw_os_error() == Some(ENOSPC)
    }
}

/// Linux's "No space left on device".
const ENOSPC: i32 = 28;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_disk_is_recognized_however_it_is_reported() {
        let full = std::io::Error::from_raw_os_error(ENOSPC);
        assert!(
            StorageError::Io(std::io::Error::from(std::io::ErrorKind::StorageFull))
                .is_out_of_space()
        );
        assert!(StorageError::Sled(sled::Error::Io(full)).is_out_of_space());
        let denied = std::io::Error::from(std::io::ErrorKind::PermissionDenied);
        assert!(!StorageError::Io(denied).is_out_of_space());
        assert!(!StorageError::SiteNotFound { site: "a".into() }.is_out_of_space());
    }
}
