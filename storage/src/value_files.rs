//! Large record values in files of their own, written once over [`RawKv`] and its value files like the
//! rest of [`crate::MapStore`]'s semantics.
//!
//! Why: sled 0.34 writes a tree page larger than a quarter of its log segment (128 KiB by default) as a
//! blob file of its own, and a leaf page holds up to 16 items whatever their size, so the pages of a site
//! log's 25–30-kB entries are blobs. When such a page is rewritten, sled defers deleting the old blob
//! until its log segment is inactive, and forgets the deferred deletions when the database is dropped —
//! which [`crate::SledStore`] does every [`crate::SledStoreOptions::reopen_after_bytes`] to bound its
//! memory. Every reopen leaked blobs, so a site's disk grew with its age (`tests/sled_blobs.rs`: 420 blob
//! files, 107 MB, for 0.75 MB of live log entries). So a record value longer than
//! [`MAX_INLINE_VALUE_BYTES`] goes to a file (`side_files`: `values/<site dir>/<serial>-<CRC32>.val`), and
//! sled holds only its entry (length, CRC32, file name: `value_entry`) under the record's own key, which
//! keeps the value and its record one atomic write. Smaller values stay inline, as before.
//!
//! The order of the steps makes every crash safe, as for checkpoints:
//!
//! 1. [`crate::MapStore::apply`] writes the batch's large values to new files durably (a temporary file,
//!    fsync, rename, directory fsync), then applies the batch, their entries included, in one
//!    transaction. A crash between leaves orphan files; a refused or failed batch deletes its files.
//!    Until a flush makes the entries durable, their files are *fresh*: when the database is reopened
//!    after a failed write ([`crate::SledStore`], which bumps [`crate::MapStore::generation`]), the
//!    reopen may lose entries applied but never flushed, so the next flush deletes each fresh file of an
//!    earlier generation that no record names (the batch is gone; a retry writes a new file). Without
//!    it, a disk that filled between a batch's value file and sled's write left that file, named by
//!    nothing, until the store was next opened (`tests/value_files_sled_full.rs`).
//! 2. A value overwritten or deleted (by a batch, by a compaction of the log) leaves its file named by no
//!    entry. The file is deleted by the next [`crate::MapStore::flush`] that succeeds (the flush made the
//!    change durable), unless the record names it again (a change a failed flush lost when the store
//!    reopened). A crash, or a store dropped, before that leaves orphan files.
//! 3. When the store opens, [`remove_orphan_files`] deletes every value file no entry names.
//!
//! Deleting a site, or importing into one, deletes its whole value directory once the removal of its
//! records is durable. A new file's name is never one a file had before (a serial number the store never
//! used), so an entry's file is never replaced under it and deleting an unnamed file needs no lock; only a
//! site's whole directory is deleted under [`SideFiles::exclusive`], which waits for the batches writing
//! files there (they hold [`SideFiles::shared`] from their first file until their entries are stored).
//!
//! Reading a value in a file reads its entry, then the file, and checks the length and the CRC (which
//! covers the record's key as well as its bytes): a missing, short or damaged file is
//! [`StorageError::Corrupt`] naming the file, and its bytes are never returned. Site archives carry the
//! values themselves (their format is unchanged); an import writes the large ones to files. Values stored
//! inline by earlier builds, large or not, read, scan, export, and are overwritten or deleted as before.

use std::collections::BTreeSet;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError};

use crate::envelope::{self, Opened, VALUE_ENTRY_FORMAT};
use crate::file_step::FileStep;
use crate::key;
use crate::raw_kv::RawKv;
use crate::side_files::{SideFiles, site_dir};
use crate::value_entry::ValueEntry;
use crate::{Result, StorageError};

/// Longest record value stored inline in the key-value database, in bytes (4 KiB). A longer one goes to a
/// file of its own, and the database holds only its entry (about 50 bytes and the file name).
///
/// Why 4 KiB: sled 0.34 writes a tree page larger than a quarter of its log segment (128 KiB with the
/// default 512-KiB segments) as a blob file, which it may leak (see [`crate::SledStore`]), and a leaf
/// page holds up to 17 items (it splits past 16) whatever their size. 17 values of at most 4 KiB (and 5
/// bytes of envelope) with the longest keys (a 255-byte site id, a 1024-byte record id) make about
/// 90 KiB, so no page of records is ever a blob; with the usual short keys, about 70 KiB. Values up to
/// that size (counters, node and constraint records, summaries) stay one database read, without a file
/// each.
pub const MAX_INLINE_VALUE_BYTES: usize = 4 << 10;

/// A file whose entry a committed change removed: deleted after the next successful flush.
#[derive(Debug)]
pub(crate) struct Unnamed {
    site: String,
    /// The record's key, checked again before the file is deleted.
    key: Vec<u8>,
    file: String,
}

/// A file an applied change named, not known durable yet (see the module docs).
#[derive(Debug)]
pub(crate) struct Fresh {
    /// The store's [`RawKv::generation`] after the change was applied.
    generation: u64,
    named: Unnamed,
}

/// A store's value files and their bookkeeping. Thread-safe.
#[derive(Debug)]
pub(crate) struct ValueFiles<F: ?Sized + SideFiles = dyn SideFiles> {
    /// The serial number of the next file (see `value_entry`): past every one on disk or named when the
    /// store opened.
    next_serial: AtomicU64,
    /// Files whose entries were removed by changes not known durable yet.
    unnamed: Mutex<Vec<Unnamed>>,
    /// Files named by changes applied since the last successful flush.
    fresh: Mutex<Vec<Fresh>>,
    files: F,
}

impl<F: SideFiles> ValueFiles<F> {
    /// Bookkeeping of `files`, which must hold no file yet or be swept by [`remove_orphan_files`] before
    /// anything is written.
    pub(crate) fn new(files: F) -> Self {
        Self {
            next_serial: AtomicU64::new(0),
            unnamed: Mutex::new(Vec::new()),
            fresh: Mutex::new(Vec::new()),
            files,
        }
    }
}

impl<F: ?Sized + SideFiles> ValueFiles<F> {
    /// The files.
    pub(crate) fn files(&self) -> &F {
        &self.files
    }

    /// The stored form of `value` under the site's record `key`: the value sealed, or — when it is longer
    /// than [`MAX_INLINE_VALUE_BYTES`] — its entry sealed, its bytes written to a new file, durable when
    /// this returns (the file is returned too).
    pub(crate) fn seal(
        &self,
        site: &str,
        key: &[u8],
        value: &[u8],
    ) -> Result<(Vec<u8>, Option<String>)> {
        if value.len() <= MAX_INLINE_VALUE_BYTES {
            return Ok((envelope::seal(key, value), None));
        }
        let serial = self.next_serial.fetch_add(1, Ordering::Relaxed);
        let entry = ValueEntry::of(site, key, serial, value);
        self.files.write(site, &entry.file, value)?;
        Ok((entry.seal(key), Some(entry.file)))
    }

    /// The verified value of the site's record stored as `stored` under `key`: inline, or read from its
    /// file.
    pub(crate) fn read(&self, site: &str, key: &[u8], stored: &[u8]) -> Result<Vec<u8>> {
        let payload = match envelope::open_record(key, stored)? {
            Opened::Value(value) => return Ok(value.to_vec()),
            Opened::Entry(payload) => payload,
        };
        let entry = ValueEntry::decode(key, payload)?;
        let path = self.files.path(&entry.file);
        let bytes = self
            .files
            .read(site, &entry.file)?
            .ok_or_else(|| StorageError::Corrupt {
                key: key::describe(key),
                reason: format!("value file {} is missing", path.display()),
            })?;
        entry.verify(key, &bytes, &path)?;
        Ok(bytes)
    }

    /// Notes that `stored`, the value under the site's record `key`, was replaced or removed by a committed
    /// change: the file it names, if any, is deleted after the next successful flush. (An entry that does
    /// not verify names no file: the orphan sweep at the next open decides.)
    pub(crate) fn unname(&self, site: &str, key: &[u8], stored: &[u8]) {
        if let Some(entry) = entry_of(key, stored) {
            self.pending().push(Unnamed {
                site: site.to_owned(),
                key: key.to_vec(),
                file: entry.file,
            });
        }
    }

    /// Takes the files unnamed so far, before a flush.
    pub(crate) fn take_unnamed(&self) -> Vec<Unnamed> {
        std::mem::take(&mut *self.pending())
    }

    /// Gives back files taken before a flush that failed.
    pub(crate) fn restore_unnamed(&self, mut unnamed: Vec<Unnamed>) {
        self.pending().append(&mut unnamed);
    }

    fn pending(&self) -> std::sync::MutexGuard<'_, Vec<Unnamed>> {
        self.unnamed.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Notes that an applied change made the site's record `key` name `file`, the store being at
    /// `generation` after it: fresh until a flush makes it durable.
    pub(crate) fn note_fresh(&self, site: &str, key: &[u8], file: String, generation: u64) {
        self.fresh_files().push(Fresh {
            generation,
            named: Unnamed {
                site: site.to_owned(),
                key: key.to_vec(),
                file,
            },
        });
    }

    /// Takes the fresh files, before a flush.
    pub(crate) fn take_fresh(&self) -> Vec<Fresh> {
        std::mem::take(&mut *self.fresh_files())
    }

    fn fresh_files(&self) -> std::sync::MutexGuard<'_, Vec<Fresh>> {
        self.fresh.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Whether a stored record value is the entry of a value in a file (unverified: a cheap first check).
pub(crate) fn names_a_file(stored: &[u8]) -> bool {
    stored.first() == Some(&VALUE_ENTRY_FORMAT)
}

/// The entry `stored` under `key` is, if it is one that verifies.
fn entry_of(key: &[u8], stored: &[u8]) -> Option<ValueEntry> {
    if !names_a_file(stored) {
        return None;
    }
    match envelope::open_record(key, stored) {
        Ok(Opened::Entry(payload)) => ValueEntry::decode(key, payload).ok(),
        _ => None,
    }
}

/// Deletes the value file `file` unless the record under `key` names it (or cannot be read: then the
/// orphan sweep at the next open decides).
pub(crate) fn remove_unless_named(
    kv: &impl RawKv,
    site: &str,
    key: &[u8],
    file: &str,
) -> Result<()> {
    let named = match kv.raw_get(key) {
        Ok(None) => false,
        Ok(Some(stored)) => {
            names_a_file(&stored) && entry_of(key, &stored).is_none_or(|entry| entry.file == file)
        }
        Err(_) => true,
    };
    if named {
        return Ok(());
    }
    kv.value_files().files().remove(site, file)
}

/// After a successful flush: deletes the files `due` (taken before it) that no record names. A file that
/// cannot be deleted stays, an orphan, until the sweep at the next open: the flush did succeed.
pub(crate) fn remove_unnamed(kv: &impl RawKv, due: Vec<Unnamed>) {
    if due.is_empty() {
        return;
    }
    kv.step(FileStep::ValueEntriesRemoved { files: due.len() });
    for Unnamed { site, key, file } in due {
        let _ = remove_unless_named(kv, &site, &key, &file);
    }
}

/// After a flush (`flushed`: whether it succeeded) of the files `fresh` taken before it: deletes those
/// named by changes applied on a database reopened since (the store's generation moved) that no record
/// names now — the reopen lost the change —, keeps those a record names, and gives back the others when
/// the flush failed (still not durable). A file whose record cannot be read, or that cannot be deleted,
/// stays, an orphan, until the sweep at the next open.
pub(crate) fn settle_fresh(kv: &impl RawKv, fresh: Vec<Fresh>, flushed: bool) {
    if fresh.is_empty() {
        return;
    }
    let generation = kv.generation();
    let mut still_fresh = Vec::new();
    for item in fresh {
        if item.generation < generation {
            let Unnamed { site, key, file } = &item.named;
            let _ = remove_unless_named(kv, site, key, file);
        } else if !flushed {
            still_fresh.push(item);
        }
    }
    let values = kv.value_files();
    values.fresh_files().append(&mut still_fresh);
}

/// Deletes a site's value directory once its records are gone (deleted, or purged for an import) and
/// their removal is durable (the caller flushed).
pub(crate) fn remove_site_files(kv: &impl RawKv, site: &str) -> Result<()> {
    let files = kv.value_files().files();
    let _alone = files.exclusive();
    files.remove_dir(site, &site_dir(site))
}

/// Deletes every value file no record names (see the module docs), returns how many, and sets the next
/// serial number past every file on disk or named. Run when the store opens, before anything writes to
/// it: it reads every record.
pub(crate) fn remove_orphan_files(kv: &impl RawKv) -> Result<u64> {
    let mut named = BTreeSet::new();
    for item in kv.raw_scan(&[key::NS_RECORD]) {
        let (key, stored) = item?;
        // An entry that does not verify names no file: its file is an orphan.
        if let Some(entry) = entry_of(&key, &stored) {
            named.insert(entry.file);
        }
    }
    let values = kv.value_files();
    let on_disk = values.files().names()?;
    let next = on_disk
        .iter()
        .chain(&named)
        .filter_map(|file| ValueEntry::serial(file))
        .max()
        .map_or(0, |serial| serial.saturating_add(1));
    values.next_serial.fetch_max(next, Ordering::Relaxed);
    values.files().retain(&named)
}

#[cfg(test)]
mod tests;
