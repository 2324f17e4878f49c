//! Options of [`crate::SledStore`].

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::{Result, StorageError};

/// Default [`SledStoreOptions::reopen_after_bytes`]: 16 MiB.
pub const DEFAULT_REOPEN_AFTER_BYTES: u64 = 16 << 20;

/// Where and how [`crate::SledStore`] opens its database (the server's `[storage]` config section).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SledStoreOptions {
    /// Database directory, created if missing. Default `./evermap-data`.
    pub path: PathBuf,
    /// Opening attempts while another process holds the database lock (a killed server's lock can outlive
    /// it briefly); count, at least 1. Default 10.
    pub open_attempts: u32,
    /// Pause between opening attempts, in milliseconds. Default 100.
    pub open_retry_interval_ms: u64,
    /// sled page cache size, in bytes; at least 1 MiB. Default 256 MiB. sled 0.34 does not keep to it
    /// (see [`Self::reopen_after_bytes`]).
    pub cache_capacity_bytes: u64,
    /// Bytes of values (and keys) written or read since the database was opened after which the store
    /// reopens it, at its next successful flush when no operation holds it (0: never). Default 16 MiB.
    /// Values longer than [`crate::MAX_INLINE_VALUE_BYTES`] are files, not sled values: only their small
    /// entries count. Why: `docs/TUNING.md#sled-reopen-after-bytes`.
    pub reopen_after_bytes: u64,
    /// Period of sled's background flush, in milliseconds; 0 disables it (then only
    /// [`crate::MapStore::flush`] and [`crate::MapStore::apply_durable`] make data durable). Default 500.
    pub background_flush_ms: u64,
    /// After a write failed (a full disk), sled refuses writes until the database is reopened: the store
    /// reopens it on the first write at least this long after the failure or the last attempt, in
    /// milliseconds (writes before fail at once); at most 60000. Default 1000.
    pub reopen_interval_ms: u64,
}

impl SledStoreOptions {
    /// Default database directory.
    pub const DEFAULT_PATH: &'static str = "./evermap-data";

    /// Defaults, with the database at `path`.
    pub fn at(path: impl Into<PathBuf>) -> Self {
        Self {
            path: path.into(),
            ..Self::default()
        }
    }

    /// Checks every field.
    pub fn validate(&self) -> Result<()> {
        let invalid = |field, reason: &str| {
            Err(StorageError::InvalidOptions {
                field,
                reason: reason.to_owned(),
            })
        };
        if self.path.as_os_str().is_empty() {
            return invalid("path", "must not be empty");
        }
        if !(1..=1000).contains(&self.open_attempts) {
            return invalid("open_attempts", "must be in 1..=1000");
        }
        if self.open_retry_interval_ms > 60_000 {
            return invalid("open_retry_interval_ms", "must be at most 60000 ms");
        }
        if self.reopen_interval_ms > 60_000 {
            return invalid("reopen_interval_ms", "must be at most 60000 ms");
        }
        if self.cache_capacity_bytes < 1 << 20 {
            return invalid(
                "cache_capacity_bytes",
                "must be at least 1 MiB (1048576 bytes)",
            );
        }
        Ok(())
    }
}

impl Default for SledStoreOptions {
    fn default() -> Self {
        Self {
            path: PathBuf::from(Self::DEFAULT_PATH),
            open_attempts: 10,
            open_retry_interval_ms: 100,
            cache_capacity_bytes: 256 << 20,
            reopen_after_bytes: DEFAULT_REOPEN_AFTER_BYTES,
            background_flush_ms: 500,
            reopen_interval_ms: 1000,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_values_are_refused() {
        SledStoreOptions::default().validate().unwrap();
        assert_eq!(
            SledStoreOptions::default().path,
            PathBuf::from("./evermap-data")
        );
        for bad in [
            SledStoreOptions {
                open_attempts: 0,
                ..SledStoreOptions::default()
            },
            SledStoreOptions {
                path: PathBuf::new(),
                ..SledStoreOptions::default()
            },
            SledStoreOptions {
                cache_capacity_bytes: 1000,
                ..SledStoreOptions::default()
            },
            SledStoreOptions {
                open_retry_interval_ms: 120_000,
                ..SledStoreOptions::default()
            },
            SledStoreOptions {
                reopen_interval_ms: 120_000,
                ..SledStoreOptions::default()
            },
        ] {
            assert!(
                matches!(bad.validate(), Err(StorageError::InvalidOptions { .. })),
                "{bad:?}"
            );
        }
    }
}
