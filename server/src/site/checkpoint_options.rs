//! When a site is checkpointed and how much history it keeps (`[checkpoints]` in the server's TOML).

use serde::Deserialize;
use storage::CheckpointRetention;

/// Invalid [`CheckpointOptions`].
#[derive(Debug, thiserror::Error)]
pub enum CheckpointOptionsError {
    /// `every_n_versions` is 0.
    #[error("every_n_versions must be at least 1")]
    NoInterval,
    /// The retention is refused by the store.
    #[error("{0}")]
    Retention(#[from] storage::StorageError),
}

/// When a site task writes a checkpoint of its site, and what compaction keeps (issue 34).
///
/// A checkpoint is due at every session end and after `every_n_versions` versions without one; it is
/// written at the first change from then on at which no session is mid-start (see
/// `SiteMap::checkpoint`), after the change is acknowledged. Each written checkpoint is followed by a
/// compaction that keeps the newest `keep` checkpoints and the log after the oldest of them (plus
/// `keep_log_entries` entries before it).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CheckpointOptions {
    /// Write checkpoints (and compact the log). Default true; false: the site starts by replaying its
    /// whole log, and its log is never compacted.
    pub enabled: bool,
    /// A checkpoint is due after this many versions without one, besides every session end, versions;
    /// at least 1. Default 200 (about one 300-s session of one robot).
    pub every_n_versions: u64,
    /// Checkpoints kept, count; at least 2 (an unreadable newest one falls back to the one before, and
    /// the log after that one is kept). Default 2.
    pub keep: usize,
    /// Log entries kept before the oldest kept checkpoint, for audit, count. Default 0.
    pub keep_log_entries: u64,
}

impl CheckpointOptions {
    /// The defaults (see each field).
    pub const DEFAULT: Self = Self {
        enabled: true,
        every_n_versions: 200,
        keep: 2,
        keep_log_entries: 0,
    };

    /// No checkpoints: the site replays its whole log at start.
    pub const DISABLED: Self = Self {
        enabled: false,
        ..Self::DEFAULT
    };

    /// What compaction keeps.
    pub fn retention(&self) -> CheckpointRetention {
        CheckpointRetention {
            checkpoints: self.keep,
            log_entries: self.keep_log_entries,
        }
    }

    /// Checks every field.
    pub fn validate(&self) -> Result<(), CheckpointOptionsError> {
        if self.every_n_versions == 0 {
            return Err(CheckpointOptionsError::NoInterval);
        }
        self.retention().validate()?;
        Ok(())
    }
}

impl Default for CheckpointOptions {
    fn default() -> Self {
        Self::DEFAULT
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_validate_and_bad_values_are_refused() {
        assert!(CheckpointOptions::default().validate().is_ok());
        let none = CheckpointOptions {
            every_n_versions: 0,
            ..CheckpointOptions::DEFAULT
        };
        assert!(matches!(
            none.validate(),
            Err(CheckpointOptionsError::NoInterval)
        ));
        let one = CheckpointOptions {
            keep: 1,
            ..CheckpointOptions::DEFAULT
        };
        assert!(
            one.validate()
                .unwrap_err()
                .to_string()
                .contains("at least 2")
        );
    }
}
