//! The persistence interface of the server and the agent.

use std::io::{Read, Write};

use crate::{
    BatchOutcome, CheckpointRetention, Compaction, RecordId, RecordKind, Result, TransferSummary,
    WriteBatch,
};

/// Records of one (site, kind) in id order, each verified; an `Err` item is a corrupt record or a
/// backend failure (iteration may continue past a corrupt record).
pub type RecordIter<'a> = Box<dyn Iterator<Item = Result<(RecordId, Vec<u8>)>> + Send + 'a>;

/// A store of versioned, checksummed records for many sites.
///
/// Records are addressed by (site id, [`RecordKind`], [`RecordId`]) and hold opaque bytes. Every value is
/// stored with a format version byte and a CRC32 (over version, key and value); every read verifies both and
/// returns [`crate::StorageError::Corrupt`] rather than a damaged value. A value longer than
/// [`crate::MAX_INLINE_VALUE_BYTES`] is kept in a file of its own ([`crate::SledStore`]: under
/// `<database dir>/values/`), the record holding its length, CRC32 and file name: a missing or damaged file
/// reads as corrupt too.
///
/// Writes go through [`WriteBatch`]es, applied all or nothing. A batch can bump the site's map version (stored
/// atomically with the batch) and be conditional on an upload's session sequence number (exactly-once
/// uploads). [`MapStore::apply`] makes the batch visible to readers at once; it is on disk after
/// [`MapStore::flush`] (or when the backend's background flush runs). [`MapStore::apply_durable`] returns
/// only once the batch is on disk: acknowledge uploads to robots only after it.
///
/// A site whose import or deletion was interrupted is *incomplete*: it is not listed, refuses batches with
/// [`crate::StorageError::SiteIncomplete`], and is cleared by [`MapStore::delete_site`] or
/// [`MapStore::import_site`]. Reads do not check this.
///
/// Scans and exports are not snapshots: do not write to a site while exporting it. Implementations are
/// thread-safe; batches on the same site are serialized.
pub trait MapStore: Send + Sync {
    /// Applies `batch` atomically: every put and delete, the map version bump and the session sequence
    /// number, or nothing. Returns [`BatchOutcome::Duplicate`] (and writes nothing) when the batch's session
    /// sequence number was already applied.
    fn apply(&self, batch: &WriteBatch) -> Result<BatchOutcome>;

    /// Makes every batch applied so far durable (on disk, fsynced), then deletes the files of the large
    /// values that batches before it overwrote or deleted (until a flush, a crash must find them). Only
    /// that for in-memory stores.
    fn flush(&self) -> Result<()>;

    /// How many times the store has been reopened in place since it was opened (0 for backends that never
    /// are). A backend that a failed write leaves refusing writes (sled after a full disk) reopens itself
    /// on a later write (see [`crate::SledStore`]); writes applied but not flushed before that may be gone
    /// afterwards, or may have survived. Everything readable after a reopen is durable. A caller that
    /// applied writes it has not seen flushed under an unchanged generation must rebuild what it derived
    /// from them from the store, and acknowledge nothing before (read the generation before a write and
    /// after its flush: only an unchanged one proves the flush covered the write).
    fn generation(&self) -> u64 {
        0
    }

    /// [`MapStore::apply`] then [`MapStore::flush`]: returns only after the batch is on disk.
    fn apply_durable(&self, batch: &WriteBatch) -> Result<BatchOutcome> {
        let outcome = self.apply(batch)?;
        self.flush()?;
        Ok(outcome)
    }

    /// Puts one record (a batch of one put).
    fn put(
        &self,
        site: &str,
        kind: RecordKind,
        id: &RecordId,
        value: &[u8],
    ) -> Result<BatchOutcome> {
        let mut batch = WriteBatch::new(site);
        batch.put(kind, id.clone(), value);
        self.apply(&batch)
    }

    /// Deletes one record (a batch of one delete); deleting an absent record is not an error.
    fn delete(&self, site: &str, kind: RecordKind, id: &RecordId) -> Result<BatchOutcome> {
        let mut batch = WriteBatch::new(site);
        batch.delete(kind, id.clone());
        self.apply(&batch)
    }

    /// The verified value of a record, `None` if absent.
    fn get(&self, site: &str, kind: RecordKind, id: &RecordId) -> Result<Option<Vec<u8>>>;

    /// The records of (site, kind) in id order.
    fn scan(&self, site: &str, kind: RecordKind) -> Result<RecordIter<'_>>;

    /// The complete sites, sorted by id.
    fn list_sites(&self) -> Result<Vec<String>>;

    /// The site's map version: how many applied batches bumped it (0 for a new or unknown site).
    fn map_version(&self, site: &str) -> Result<u64>;

    /// The last applied sequence number of a session on a site, `None` if none was applied.
    fn last_applied_seq(&self, site: &str, session: &str) -> Result<Option<u64>>;

    /// Removes a site and all its records, durably. Not atomic for large sites, but crash-safe: the site is
    /// marked incomplete first, so an interrupted deletion leaves an unlisted site that a retry finishes.
    fn delete_site(&self, site: &str) -> Result<()>;

    /// Stores `checkpoint` (the caller's encoding of the site's state) as covering the site's log up to
    /// and including `log_index`, atomically with that position (it is the index entry's key), and
    /// durably: returns once it is on disk. The bytes go to a file of their own ([`crate::SledStore`]:
    /// `<database dir>/checkpoints/<site>/<log index>-<CRC32>.ckpt`, written to a temporary file, fsynced
    /// and renamed; [`crate::MemStore`]: memory), then the index entry (length, CRC32, file name) is
    /// stored. Refused, before any file is written, for an unknown or incomplete site and for a
    /// `log_index` beyond the site's map version ([`crate::StorageError::CheckpointAhead`]). A checkpoint
    /// stored again at the same `log_index` replaces it. Older checkpoints stay until
    /// [`MapStore::compact`] removes them.
    fn put_checkpoint(&self, site: &str, log_index: u64, checkpoint: &[u8]) -> Result<()>;

    /// The log indexes of the site's stored checkpoints, newest first (unverified: a corrupt one is
    /// listed, and [`MapStore::checkpoint`] reports it).
    fn checkpoint_indexes(&self, site: &str) -> Result<Vec<u64>>;

    /// The verified checkpoint covering the log up to `log_index`, `None` if absent;
    /// [`crate::StorageError::Corrupt`] if it fails its checksum or its length, or its file is missing
    /// (the error names the file): never bytes that are not the checkpoint's.
    fn checkpoint(&self, site: &str, log_index: u64) -> Result<Option<Vec<u8>>>;

    /// Deletes the checkpoints older than the newest `retention.checkpoints` that verify, then the
    /// records of `log_kind` (the site's log, ids from [`RecordId::from_u64`]) up to the oldest kept
    /// checkpoint's index less `retention.log_entries` — none while fewer checkpoints verify than are
    /// kept. The files of the removed checkpoints and log entries are deleted once their removal is
    /// durable. Crash-safe at every step (see the `checkpoints` module; a file a crash leaves behind is
    /// deleted when the store next opens); durable when it returns.
    fn compact(
        &self,
        site: &str,
        log_kind: RecordKind,
        retention: &CheckpointRetention,
    ) -> Result<Compaction>;

    /// Writes every record of a complete site (counters included) to `out` as a site archive
    /// (see [`crate::SITE_ARCHIVE_MAGIC`] for the format). Fails on the first corrupt record.
    fn export_site(&self, site: &str, out: &mut dyn Write) -> Result<TransferSummary>;

    /// Reads a site archive into `site`, which must hold no data (leftovers of an interrupted import or
    /// deletion are cleared first). The archive may come from another site id. On any error (corrupt or
    /// truncated stream, I/O) everything written so far is removed and the site does not exist afterwards.
    /// Durable when it returns `Ok`.
    fn import_site(&self, site: &str, input: &mut dyn Read) -> Result<TransferSummary>;
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::MemStore;

    #[test]
    fn usable_as_a_shared_trait_object() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let id = RecordId::from("meta");
        store.put("depot", RecordKind::SiteMeta, &id, b"v").unwrap();
        assert_eq!(
            store
                .get("depot", RecordKind::SiteMeta, &id)
                .unwrap()
                .unwrap(),
            b"v"
        );
        assert_eq!(
            store.scan("depot", RecordKind::SiteMeta).unwrap().count(),
            1
        );
    }
}
