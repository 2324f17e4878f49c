//! Checkpoints of a site and compaction of its log (issue 34), written once over [`RawKv`] and its
//! checkpoint files like the rest of [`crate::MapStore`]'s semantics.
//!
//! A checkpoint is an opaque value (the caller's encoding of the site's whole state) covering the site's
//! log up to a position. Its bytes go to a file of their own (`side_files`: sled would keep the space
//! of every large value it ever held); the key-value store holds only its index entry (length, CRC32, file
//! name: `checkpoint_entry`) under the position it covers, `site/checkpoint-file/<log index, u64
//! big-endian>`. Storing the index *as the key* makes the checkpoint and the position it covers one
//! atomic write: there is no second record that could disagree with it. The order of the steps makes
//! every crash safe:
//!
//! 1. [`put_checkpoint`] writes the file durably (a temporary file, fsync, rename, directory fsync), then
//!    stores the entry in one transaction — which also refuses an unknown or incomplete site and a
//!    position beyond the site's map version (a checkpoint of changes the store does not hold) — and
//!    flushes. A crash before the entry is durable leaves an orphan file and no checkpoint.
//! 2. [`compact`] removes entries (and log entries) in transactions and flushes, and only then deletes the
//!    files they named. A crash before the deletions leaves orphan files.
//! 3. When the store opens, [`remove_orphan_files`] deletes every file no entry names (orphans, and the
//!    temporary files of interrupted writes).
//!
//! Reading a checkpoint reads its entry, then its file, and checks the length and the CRC (which covers
//! the site and the log index as well as the bytes): a missing, short or damaged file is
//! [`StorageError::Corrupt`] naming the file — the same "no valid checkpoint here" as a damaged record, so
//! a reader falls back to the checkpoint before it — and its bytes are never returned. An entry whose file
//! is gone stays listed, as invalid, until compaction drops it with the older checkpoints.
//!
//! Checkpoints stored inline by earlier builds (the record `site/checkpoint/<log index>`, sealed like
//! every record) are still listed, read, compacted and exported; a new checkpoint at the same position
//! replaces one. Site archives carry every checkpoint as such a record, so their format is unchanged; an
//! import writes the bytes to files.
//!
//! Compaction ([`compact`]) keeps the newest [`CheckpointRetention::checkpoints`] checkpoints that
//! verify and deletes older ones, then deletes the log entries up to the *oldest* retained checkpoint's
//! position (less [`CheckpointRetention::log_entries`] kept for audit; the files of those in value files
//! go after the flush that ends it, as `value_files` describes): if the newest checkpoint later
//! proves unreadable, the one before it and the log after it are still there. With fewer verified
//! checkpoints than it keeps, it deletes no log entry. Each step is its own atomic write, and every
//! state between them is a valid store (log entries are deleted oldest first, and only ones that every
//! retained checkpoint covers), so a crash anywhere in a compaction loses nothing.

use std::collections::BTreeSet;

use crate::checkpoint_entry::CheckpointEntry;
use crate::envelope;
use crate::file_step::FileStep;
use crate::key::{self, KIND_CHECKPOINT, KIND_CHECKPOINT_FILE, KIND_MAP_VERSION};
use crate::raw_kv::{self, RawKv, site_must_be_complete};
use crate::side_files::site_dir;
use crate::value_files;
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

/// Reads a record, directly or inside a transaction.
type Get<'a> = dyn FnMut(&[u8]) -> Result<Option<Vec<u8>>> + 'a;

/// Key of a checkpoint stored inline (earlier builds; the kind of checkpoints in site archives).
fn inline_key(site: &str, log_index: u64) -> Vec<u8> {
    key::record_key(site, KIND_CHECKPOINT, &log_index.to_be_bytes())
}

/// Key of a checkpoint's index entry.
fn entry_key(site: &str, log_index: u64) -> Vec<u8> {
    key::record_key(site, KIND_CHECKPOINT_FILE, &log_index.to_be_bytes())
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

fn decode_entry(key: &[u8], stored: &[u8]) -> Result<CheckpointEntry> {
    CheckpointEntry::decode(key, envelope::open(key, stored)?)
}

/// Refuses a checkpoint of an unknown or incomplete site, or beyond the site's map version.
fn check_position(site: &str, log_index: u64, get: &mut Get<'_>) -> Result<()> {
    let site_key = key::site_key(site);
    site_must_be_complete(site, &site_key, get(&site_key)?.as_deref())?;
    let version_key = key::record_key(site, KIND_MAP_VERSION, &[]);
    let map_version = get(&version_key)?
        .map(|stored| envelope::decode_u64(&version_key, envelope::open(&version_key, &stored)?))
        .transpose()?
        .unwrap_or(0);
    if log_index > map_version {
        return Err(StorageError::CheckpointAhead {
            site: site.to_owned(),
            log_index,
            map_version,
        });
    }
    Ok(())
}

/// Deletes the checkpoint file `file` unless the entry under `key` names it (or cannot be read: then the
/// orphan sweep at the next open decides).
fn remove_unless_named(kv: &impl RawKv, site: &str, key: &[u8], file: &str) -> Result<()> {
    let files = kv.checkpoint_files();
    let _alone = files.exclusive();
    let named = match kv.raw_get(key) {
        Ok(None) => false,
        Ok(Some(stored)) => decode_entry(key, &stored).map_or(true, |entry| entry.file == file),
        Err(_) => true,
    };
    if named {
        return Ok(());
    }
    files.remove(site, file)
}

pub(crate) fn put_checkpoint(
    kv: &impl RawKv,
    site: &str,
    log_index: u64,
    checkpoint: &[u8],
) -> Result<()> {
    validate_site_id(site)?;
    let key = entry_key(site, log_index);
    if checkpoint.len() > MAX_VALUE_BYTES {
        return Err(StorageError::TooLarge {
            key: key::describe(&key),
            what: "value",
            len: checkpoint.len(),
            max: MAX_VALUE_BYTES,
        });
    }
    // Refused before a file is written; checked again in the transaction.
    check_position(site, log_index, &mut |k| kv.raw_get(k))?;
    let entry = CheckpointEntry::of(site, log_index, checkpoint);
    let sealed = envelope::seal(&key, &entry.encode());
    let inline = inline_key(site, log_index);
    let files = kv.checkpoint_files();
    let lock = files.exclusive();
    files.write(site, &entry.file, checkpoint)?;
    kv.step(FileStep::CheckpointFileDurable { log_index });
    let stored = kv.transact(&|txn| {
        check_position(site, log_index, &mut |k| txn.get(k))?;
        let replaced = txn.get(&key)?;
        txn.insert(&key, sealed.clone())?;
        txn.remove(&inline)?;
        Ok(replaced)
    });
    drop(lock);
    let replaced = match stored {
        Ok(replaced) => replaced,
        Err(error) => {
            // Best effort: an orphan left here goes at the next open.
            let _ = remove_unless_named(kv, site, &key, &entry.file);
            return Err(error);
        }
    };
    raw_kv::flush(kv)?;
    // A checkpoint rewritten at the same position with other bytes: the file of the one it replaced.
    if let Some(old) = replaced.and_then(|stored| decode_entry(&key, &stored).ok())
        && old.file != entry.file
    {
        kv.step(FileStep::CheckpointIndexRemoved { log_index });
        remove_unless_named(kv, site, &key, &old.file)?;
    }
    Ok(())
}

pub(crate) fn checkpoint_indexes(kv: &impl RawKv, site: &str) -> Result<Vec<u64>> {
    validate_site_id(site)?;
    let mut indexes = BTreeSet::new();
    for kind in [KIND_CHECKPOINT_FILE, KIND_CHECKPOINT] {
        let prefix = key::kind_prefix(site, kind);
        for item in kv.raw_scan(&prefix) {
            indexes.insert(index_of(&item?.0, prefix.len())?);
        }
    }
    Ok(indexes.into_iter().rev().collect())
}

pub(crate) fn checkpoint(kv: &impl RawKv, site: &str, log_index: u64) -> Result<Option<Vec<u8>>> {
    validate_site_id(site)?;
    let key = entry_key(site, log_index);
    if let Some(stored) = kv.raw_get(&key)? {
        return file_bytes(kv, site, &key, &stored).map(Some);
    }
    let inline = inline_key(site, log_index);
    kv.raw_get(&inline)?
        .map(|stored| Ok(envelope::open(&inline, &stored)?.to_vec()))
        .transpose()
}

/// The verified bytes of the checkpoint whose index entry, stored under `key`, is `stored`.
pub(crate) fn file_bytes(
    kv: &impl RawKv,
    site: &str,
    key: &[u8],
    stored: &[u8],
) -> Result<Vec<u8>> {
    let log_index = index_of(key, key::kind_prefix(site, KIND_CHECKPOINT_FILE).len())?;
    let entry = decode_entry(key, stored)?;
    let files = kv.checkpoint_files();
    let path = files.path(&entry.file);
    let bytes = files
        .read(site, &entry.file)?
        .ok_or_else(|| StorageError::Corrupt {
            key: key::describe(key),
            reason: format!("file {} is missing", path.display()),
        })?;
    entry.verify(key, (site, log_index), &bytes, &path)?;
    Ok(bytes)
}

/// Whether the checkpoint at `log_index` reads back; `Err` only for a failure that is not a damaged
/// checkpoint (I/O, the backend).
fn verifies(kv: &impl RawKv, site: &str, log_index: u64) -> Result<bool> {
    match checkpoint(kv, site, log_index) {
        Ok(found) => Ok(found.is_some()),
        Err(StorageError::Corrupt { .. } | StorageError::UnsupportedFormat { .. }) => Ok(false),
        Err(error) => Err(error),
    }
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
    // Newest first: the first ones that verify are kept, everything older goes.
    let mut kept = 0;
    let mut oldest_kept = None;
    let mut older = Vec::new();
    for index in checkpoint_indexes(kv, site)? {
        if kept == retention.checkpoints {
            older.push(index);
        } else if verifies(kv, site, index)? {
            kept += 1;
            oldest_kept = Some(index);
        }
    }
    let mut compaction = Compaction::default();
    // The files the removed entries name (an undecodable entry's file is left to the orphan sweep).
    let mut unnamed_files = Vec::new();
    if !older.is_empty() {
        for &index in &older {
            let key = entry_key(site, index);
            if let Some(stored) = kv.raw_get(&key)?
                && let Ok(entry) = decode_entry(&key, &stored)
            {
                unnamed_files.push((index, key, entry.file));
            }
        }
        kv.transact(&|txn| {
            older.iter().try_for_each(|&index| {
                txn.remove(&entry_key(site, index))?;
                txn.remove(&inline_key(site, index)).map(drop)
            })
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
        // The removed entries that named value files: their files go after the flush below.
        let removed: Vec<(&Vec<u8>, Vec<u8>)> = kv.transact(&|txn| {
            let mut removed = Vec::new();
            for key in &keys {
                if let Some(old) = txn
                    .remove(key)?
                    .filter(|old| value_files::names_a_file(old))
                {
                    removed.push((key, old));
                }
            }
            Ok(removed)
        })?;
        for (key, old) in removed {
            kv.value_files().unname(site, key, &old);
        }
        compaction.log_entries_removed += keys.len() as u64;
    }
    compaction.log_compacted_through = through;
    raw_kv::flush(kv)?;
    // Only now that no durable entry names them: the files.
    for (log_index, key, file) in unnamed_files {
        kv.step(FileStep::CheckpointIndexRemoved { log_index });
        remove_unless_named(kv, site, &key, &file)?;
    }
    Ok(compaction)
}

/// Deletes a site's checkpoint files once its records are gone (deleted or purged for an import) and
/// their removal is durable (the caller flushed).
pub(crate) fn remove_site_files(kv: &impl RawKv, site: &str) -> Result<()> {
    let files = kv.checkpoint_files();
    let _alone = files.exclusive();
    files.remove_dir(site, &site_dir(site))
}

/// Writes an imported checkpoint (`id`: its log index, 8 bytes big-endian) to its file durably and returns
/// its index entry (key, sealed value), for the import to store.
pub(crate) fn import_file(
    kv: &impl RawKv,
    site: &str,
    id: &[u8],
    checkpoint: &[u8],
) -> Result<(Vec<u8>, Vec<u8>)> {
    let log_index = index_of(id, 0)?;
    let key = entry_key(site, log_index);
    let entry = CheckpointEntry::of(site, log_index, checkpoint);
    kv.checkpoint_files().write(site, &entry.file, checkpoint)?;
    let sealed = envelope::seal(&key, &entry.encode());
    Ok((key, sealed))
}

/// Deletes every checkpoint file no index entry names (see the module docs); returns how many. Run when the
/// store opens, before anything writes to it (`value_files` sweeps the value files).
pub(crate) fn remove_orphan_files(kv: &impl RawKv) -> Result<u64> {
    let mut named = BTreeSet::new();
    for item in kv.raw_scan(&[key::NS_SITE]) {
        let (site_key, _) = item?;
        let Ok(site) = std::str::from_utf8(&site_key[1..]) else {
            continue;
        };
        if validate_site_id(site).is_err() {
            continue;
        }
        for item in kv.raw_scan(&key::kind_prefix(site, KIND_CHECKPOINT_FILE)) {
            let (key, stored) = item?;
            // An entry that does not read back is no checkpoint: its file is an orphan.
            if let Ok(entry) = decode_entry(&key, &stored) {
                named.insert(entry.file);
            }
        }
    }
    kv.checkpoint_files().retain(&named)
}

#[cfg(test)]
mod tests;
