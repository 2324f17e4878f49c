//! Checkpoints of a site and compaction of its log (issue 34), written once over [`RawKv`] like the rest
//! of [`crate::MapStore`]'s semantics.
//!
//! A checkpoint is an opaque value (the caller's encoding of the site's whole state) stored under the
//! log position it covers: the internal record `site/checkpoint/<log index, u64 big-endian>`, sealed with
//! the format version byte and CRC32 like every record. Storing the index *as the key* makes the
//! checkpoint and the position it covers one atomic write (one transaction, then an fsync): there is no
//! second record that could disagree with it. The transaction also refuses a position beyond the site's
//! map version (a checkpoint of changes the store does not hold).
//!
//! Compaction ([`compact`]) keeps the newest [`CheckpointRetention::checkpoints`] checkpoints that
//! verify and deletes older ones, then deletes the log entries up to the *oldest* retained checkpoint's
//! position (less [`CheckpointRetention::log_entries`] kept for audit): if the newest checkpoint later
//! proves unreadable, the one before it and the log after it are still there. With fewer verified
//! checkpoints than it keeps, it deletes no log entry. Each step is its own atomic write, and every
//! state between them is a valid store (log entries are deleted oldest first, and only ones that every
//! retained checkpoint covers), so a crash anywhere in a compaction loses nothing.

use crate::envelope;
use crate::key::{self, KIND_CHECKPOINT, KIND_MAP_VERSION};
use crate::raw_kv::{RawKv, site_must_be_complete};
use crate::{MAX_VALUE_BYTES, RecordKind, Result, StorageError, validate_site_id};

/// Log entries deleted per transaction.
const CHUNK_RECORDS: usize = 512;

/// What a compaction keeps of a site's history.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CheckpointRetention {
    /// Checkpoints kept (the newest ones that verify), at least 2: the log after the oldest kept one is
    /// kept, so an unreadable newest checkpoint falls back to an older one.
    pub checkpoints: usize,
    /// Log entries kept before the oldest kept checkpoint's position, for audit (0: none).
    pub log_entries: u64,
}

impl CheckpointRetention {
    /// Two checkpoints, no log entry before the older one.
    pub const DEFAULT: Self = Self {
        checkpoints: 2,
        log_entries: 0,
    };

    /// Checks the retention: at least 2 checkpoints.
    pub fn validate(&self) -> Result<()> {
        if self.checkpoints < 2 {
            return Err(StorageError::InvalidOptions {
                field: "checkpoints",
                reason: format!(
                    "{} checkpoint(s) kept: at least 2 are, so that an unreadable newest one falls back to the one before",
                    self.checkpoints
                ),
            });
        }
        Ok(())
    }
}

impl Default for CheckpointRetention {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// What a compaction removed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Compaction {
    /// Checkpoints deleted (older than the kept ones).
    pub checkpoints_removed: u64,
    /// Log entries deleted.
    pub log_entries_removed: u64,
    /// The log position up to which entries may be deleted now: the oldest kept checkpoint's, less the
    /// entries kept for audit (0: no log entry may be, too few checkpoints verify).
    pub log_compacted_through: u64,
}

fn checkpoint_key(site: &str, log_index: u64) -> Vec<u8> {
    key::record_key(site, KIND_CHECKPOINT, &log_index.to_be_bytes())
}

fn index_of(key: &[u8], prefix_len: usize) -> Result<u64> {
    let bytes: [u8; 8] = key[prefix_len..]
        .try_into()
        .map_err(|_| StorageError::Corrupt {
            key: key::describe(key),
            reason: "a checkpoint's id is not an 8-byte log index".to_owned(),
        })?;
    Ok(u64::from_be_bytes(bytes))
}

pub(crate) fn put_checkpoint(
    kv: &impl RawKv,
    site: &str,
    log_index: u64,
    checkpoint: &[u8],
) -> Result<()> {
    validate_site_id(site)?;
    let key = checkpoint_key(site, log_index);
    if checkpoint.len() > MAX_VALUE_BYTES {
        return Err(StorageError::TooLarge {
            key: key::describe(&key),
            what: "value",
            len: checkpoint.len(),
            max: MAX_VALUE_BYTES,
        });
    }
    let sealed = envelope::seal(&key, checkpoint);
    let site_key = key::site_key(site);
    let version_key = key::record_key(site, KIND_MAP_VERSION, &[]);
    kv.transact(&|txn| {
        site_must_be_complete(site, &site_key, txn.get(&site_key)?.as_deref())?;
        let map_version = txn
            .get(&version_key)?
            .map(|stored| {
                envelope::decode_u64(&version_key, envelope::open(&version_key, &stored)?)
            })
            .transpose()?
            .unwrap_or(0);
        if log_index > map_version {
            return Err(StorageError::CheckpointAhead {
                site: site.to_owned(),
                log_index,
                map_version,
            });
        }
        txn.insert(&key, sealed.clone())
    })?;
    kv.raw_flush()
}

pub(crate) fn checkpoint_indexes(kv: &impl RawKv, site: &str) -> Result<Vec<u64>> {
    validate_site_id(site)?;
    let prefix = key::kind_prefix(site, KIND_CHECKPOINT);
    let mut indexes = kv
        .raw_scan(&prefix)
        .map(|item| index_of(&item?.0, prefix.len()))
        .collect::<Result<Vec<u64>>>()?;
    indexes.reverse();
    Ok(indexes)
}

pub(crate) fn checkpoint(kv: &impl RawKv, site: &str, log_index: u64) -> Result<Option<Vec<u8>>> {
    validate_site_id(site)?;
    let key = checkpoint_key(site, log_index);
    kv.raw_get(&key)?
        .map(|stored| Ok(envelope::open(&key, &stored)?.to_vec()))
        .transpose()
}

pub(crate) fn compact(
    kv: &impl RawKv,
    site: &str,
    log_kind: RecordKind,
    retention: &CheckpointRetention,
) -> Result<Compaction> {
    validate_site_id(site)?;
    retention.validate()?;
    let site_key = key::site_key(site);
    site_must_be_complete(site, &site_key, kv.raw_get(&site_key)?.as_deref())?;
    // Newest first: which verify.
    let prefix = key::kind_prefix(site, KIND_CHECKPOINT);
    let mut stored: Vec<(u64, bool)> = kv
        .raw_scan(&prefix)
        .map(|item| {
            let (key, value) = item?;
            let index = index_of(&key, prefix.len())?;
            Ok((index, envelope::open(&key, &value).is_ok()))
        })
        .collect::<Result<_>>()?;
    stored.reverse();
    let mut kept = 0;
    let mut oldest_kept = None;
    let mut older = Vec::new();
    for (index, verifies) in stored {
        if kept == retention.checkpoints {
            older.push(index);
        } else if verifies {
            kept += 1;
            oldest_kept = Some(index);
        }
    }
    let mut compaction = Compaction::default();
    if !older.is_empty() {
        kv.transact(&|txn| {
            older
                .iter()
                .try_for_each(|index| txn.remove(&checkpoint_key(site, *index)))
        })?;
        compaction.checkpoints_removed = older.len() as u64;
    }
    let through = match oldest_kept {
        Some(index) if kept == retention.checkpoints => index.saturating_sub(retention.log_entries),
        _ => 0,
    };
    let log_prefix = key::kind_prefix(site, log_kind.as_byte());
    loop {
        let keys: Vec<Vec<u8>> = kv
            .raw_scan(&log_prefix)
            .take(CHUNK_RECORDS)
            .map(|item| item.map(|(key, _)| key))
            .take_while(|item| {
                item.as_ref().map_or(true, |key| {
                    <[u8; 8]>::try_from(&key[log_prefix.len()..])
                        .is_ok_and(|id| u64::from_be_bytes(id) <= through)
                })
            })
            .collect::<Result<_>>()?;
        if keys.is_empty() {
            break;
        }
        kv.transact(&|txn| keys.iter().try_for_each(|key| txn.remove(key)))?;
        compaction.log_entries_removed += keys.len() as u64;
    }
    compaction.log_compacted_through = through;
    kv.raw_flush()?;
    Ok(compaction)
}

#[cfg(test)]
mod tests;
