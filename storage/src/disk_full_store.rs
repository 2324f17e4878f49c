//! A [`MapStore`] wrapper that runs out of disk space on demand, for the disk-full tests of the server
//! and the agent (like [`crate::MemStore`], a test double, public so other crates' tests can use it).
//!
//! Why inject instead of filling a real disk: a size-limited filesystem (tmpfs, a loop device) needs
//! `mount`, a privilege CI containers usually lack. The wrapper fails with the error a full disk gives
//! (`ENOSPC`, [`std::io::ErrorKind::StorageFull`]) at either of the two points where a real one does:
//! - [`FailAt::Apply`]: the write itself fails and nothing is stored (a backend that writes through);
//! - [`FailAt::Flush`]: the write is applied (visible to reads) but cannot be made durable — what a
//!   log-structured store with a write buffer (sled) does when its flush hits the full disk. Callers must
//!   not acknowledge such a write, and must not apply it twice when the client retries.
//! - [`FailAt::Wedge`]: what sled 0.34 does on a real full disk (measured in
//!   `tests/disk_full_tmpfs.rs`): as `Flush`, and the failed flush *wedges* the store — every later
//!   write fails ([`StorageError::Wedged`]), room or not, until the store is reopened. It reopens itself
//!   on the first write once the disk has room, as [`crate::SledStore`] does, and the reopened store
//!   holds only what the last successful flush made durable (what was applied after it is gone, as on
//!   the tmpfs); [`MapStore::generation`] counts the reopens. The flushed state is kept as site archives
//!   taken at every successful flush, and a reopen imports them into a fresh [`crate::MemStore`]: for
//!   small test stores only.
//!
//! Reads never fail (scans are read whole before they are returned). [`DiskFullStore::free`] gives the
//! space back.

use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock};

use crate::{BatchOutcome, MapStore, RecordId, RecordIter, RecordKind, Result, StorageError};
use crate::{CheckpointRetention, Compaction};
use crate::{MemStore, TransferSummary, WriteBatch};

/// Where a full disk makes writes fail.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FailAt {
    /// Writes fail before anything is stored.
    Apply,
    /// Writes are applied but flushes fail (the write is visible, not durable).
    Flush,
    /// As `Flush`, and the store then refuses every write until it reopens itself, losing what was
    /// not flushed (sled on a real full disk; see the module docs).
    Wedge,
}

/// A store whose disk can be filled and freed (see the module docs).
pub struct DiskFullStore {
    inner: RwLock<Arc<dyn MapStore>>,
    fail_at: FailAt,
    full: AtomicBool,
    failures: AtomicU64,
    /// [`FailAt::Wedge`]: a flush failed and the store was not reopened since.
    wedged: AtomicBool,
    /// [`FailAt::Wedge`]: every site's archive as of the last successful flush.
    flushed: Mutex<Vec<(String, Vec<u8>)>>,
    generation: AtomicU64,
}

/// The error a full disk gives.
pub fn out_of_space() -> StorageError {
    // ENOSPC: "No space left on device (os error 28)", as Linux reports it.
    StorageError::Io(std::io::Error::from_raw_os_error(28))
}

impl DiskFullStore {
    /// Wraps `inner`; the disk starts with room.
    pub fn new(inner: Arc<dyn MapStore>, fail_at: FailAt) -> Self {
        let store = Self {
            inner: RwLock::new(inner),
            fail_at,
            full: AtomicBool::new(false),
            failures: AtomicU64::new(0),
            wedged: AtomicBool::new(false),
            flushed: Mutex::new(Vec::new()),
            generation: AtomicU64::new(0),
        };
        if fail_at == FailAt::Wedge {
            // Whatever the inner store holds counts as flushed.
            let _ = store.note_flushed();
        }
        store
    }

    /// Whether the store refuses writes until it reopens ([`FailAt::Wedge`]).
    pub fn is_wedged(&self) -> bool {
        self.wedged.load(Ordering::SeqCst)
    }

    fn inner(&self) -> Arc<dyn MapStore> {
        Arc::clone(&self.inner.read().unwrap_or_else(PoisonError::into_inner))
    }

    /// [`FailAt::Wedge`]: before a write, reopens a wedged store if the disk has room, else refuses.
    fn unwedge(&self) -> Result<()> {
        if !self.wedged.load(Ordering::SeqCst) {
            return Ok(());
        }
        if self.full.load(Ordering::SeqCst) {
            self.failures.fetch_add(1, Ordering::SeqCst);
            let cause = out_of_space();
            return Err(StorageError::Wedged {
                cause: cause.to_string(),
                source: Some(Arc::new(cause)),
                out_of_space: true,
            });
        }
        let reopened = MemStore::new();
        for (site, archive) in self
            .flushed
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .iter()
        {
            reopened.import_site(site, &mut archive.as_slice())?;
        }
        *self.inner.write().unwrap_or_else(PoisonError::into_inner) = Arc::new(reopened);
        self.wedged.store(false, Ordering::SeqCst);
        self.generation.fetch_add(1, Ordering::SeqCst);
        Ok(())
    }

    /// [`FailAt::Wedge`]: keeps what is now durable (every site's archive).
    fn note_flushed(&self) -> Result<()> {
        let inner = self.inner();
        let mut archives = Vec::new();
        for site in inner.list_sites()? {
            let mut archive = Vec::new();
            inner.export_site(&site, &mut archive)?;
            archives.push((site, archive));
        }
        *self.flushed.lock().unwrap_or_else(PoisonError::into_inner) = archives;
        Ok(())
    }

    /// From now on writes fail as on a full disk.
    pub fn fill(&self) {
        self.full.store(true, Ordering::SeqCst);
    }

    /// The disk has room again.
    pub fn free(&self) {
        self.full.store(false, Ordering::SeqCst);
    }

    /// Operations failed for lack of space so far.
    pub fn failures(&self) -> u64 {
        self.failures.load(Ordering::SeqCst)
    }

    fn check(&self, at: FailAt) -> Result<()> {
        let fails_here =
            self.fail_at == at || (self.fail_at == FailAt::Wedge && at == FailAt::Flush);
        if fails_here && self.full.load(Ordering::SeqCst) {
            if self.fail_at == FailAt::Wedge {
                self.wedged.store(true, Ordering::SeqCst);
            }
            self.failures.fetch_add(1, Ordering::SeqCst);
            Err(out_of_space())
        } else {
            Ok(())
        }
    }

    /// Writes that are not batches (deletion, import) fail whichever [`FailAt`] is chosen.
    fn check_any(&self) -> Result<()> {
        self.unwedge()?;
        if self.full.load(Ordering::SeqCst) {
            if self.fail_at == FailAt::Wedge {
                self.wedged.store(true, Ordering::SeqCst);
            }
            self.failures.fetch_add(1, Ordering::SeqCst);
            Err(out_of_space())
        } else {
            Ok(())
        }
    }
}

impl MapStore for DiskFullStore {
    fn apply(&self, batch: &WriteBatch) -> Result<BatchOutcome> {
        self.unwedge()?;
        self.check(FailAt::Apply)?;
        self.inner().apply(batch)
    }

    fn flush(&self) -> Result<()> {
        self.unwedge()?;
        self.check(FailAt::Flush)?;
        self.inner().flush()?;
        if self.fail_at == FailAt::Wedge {
            self.note_flushed()?;
        }
        Ok(())
    }

    fn generation(&self) -> u64 {
        self.generation.load(Ordering::SeqCst) + self.inner().generation()
    }

    fn get(&self, site: &str, kind: RecordKind, id: &RecordId) -> Result<Option<Vec<u8>>> {
        self.inner().get(site, kind, id)
    }

    fn scan(&self, site: &str, kind: RecordKind) -> Result<RecordIter<'_>> {
        let records: Vec<_> = self.inner().scan(site, kind)?.collect();
        Ok(Box::new(records.into_iter()))
    }

    fn list_sites(&self) -> Result<Vec<String>> {
        self.inner().list_sites()
    }

    fn map_version(&self, site: &str) -> Result<u64> {
        self.inner().map_version(site)
    }

    fn last_applied_seq(&self, site: &str, session: &str) -> Result<Option<u64>> {
        self.inner().last_applied_seq(site, session)
    }

    fn delete_site(&self, site: &str) -> Result<()> {
        self.check_any()?;
        self.inner().delete_site(site)?;
        if self.fail_at == FailAt::Wedge {
            self.note_flushed()?;
        }
        Ok(())
    }

    fn put_checkpoint(&self, site: &str, log_index: u64, checkpoint: &[u8]) -> Result<()> {
        self.check_any()?;
        self.inner().put_checkpoint(site, log_index, checkpoint)?;
        if self.fail_at == FailAt::Wedge {
            self.note_flushed()?;
        }
        Ok(())
    }

    fn checkpoint_indexes(&self, site: &str) -> Result<Vec<u64>> {
        self.inner().checkpoint_indexes(site)
    }

    fn checkpoint(&self, site: &str, log_index: u64) -> Result<Option<Vec<u8>>> {
        self.inner().checkpoint(site, log_index)
    }

    fn compact(
        &self,
        site: &str,
        log_kind: RecordKind,
        retention: &CheckpointRetention,
    ) -> Result<Compaction> {
        self.check_any()?;
        let compaction = self.inner().compact(site, log_kind, retention)?;
        if self.fail_at == FailAt::Wedge {
            self.note_flushed()?;
        }
        Ok(compaction)
    }

    fn export_site(&self, site: &str, out: &mut dyn Write) -> Result<TransferSummary> {
        self.inner().export_site(site, out)
    }

    fn import_site(&self, site: &str, input: &mut dyn Read) -> Result<TransferSummary> {
        self.check_any()?;
        let summary = self.inner().import_site(site, input)?;
        if self.fail_at == FailAt::Wedge {
            self.note_flushed()?;
        }
        Ok(summary)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::MemStore;

    fn batch(seq: u64) -> WriteBatch {
        let mut batch = WriteBatch::new("s");
        batch
            .put(RecordKind::Trajectory, seq, vec![1, 2, 3])
            .bump_map_version()
            .for_session("robot-1", seq);
        batch
    }

    #[test]
    fn a_full_disk_fails_where_it_was_told_to_and_recovers() {
        let at_apply = DiskFullStore::new(Arc::new(MemStore::new()), FailAt::Apply);
        at_apply.apply_durable(&batch(1)).unwrap();
        at_apply.fill();
        let error = at_apply.apply_durable(&batch(2)).unwrap_err();
        assert!(error.is_out_of_space(), "{error}");
        assert_eq!(at_apply.map_version("s").unwrap(), 1, "nothing stored");
        at_apply.free();
        at_apply.apply_durable(&batch(2)).unwrap();
        assert_eq!(at_apply.map_version("s").unwrap(), 2);

        let at_flush = DiskFullStore::new(Arc::new(MemStore::new()), FailAt::Flush);
        at_flush.fill();
        assert!(
            at_flush
                .apply_durable(&batch(1))
                .unwrap_err()
                .is_out_of_space()
        );
        assert_eq!(
            at_flush.map_version("s").unwrap(),
            1,
            "applied, not durable"
        );
        assert_eq!(at_flush.failures(), 1);
        at_flush.free();
        at_flush.flush().unwrap();
    }

    #[test]
    fn a_wedged_store_refuses_writes_until_it_reopens_with_what_was_flushed() {
        let store = DiskFullStore::new(Arc::new(MemStore::new()), FailAt::Wedge);
        store.apply_durable(&batch(1)).unwrap();
        store.fill();
        assert_eq!(
            store.apply(&batch(2)).unwrap(),
            BatchOutcome::Applied { map_version: 2 },
            "applied while full"
        );
        assert!(store.flush().unwrap_err().is_out_of_space());
        assert!(store.is_wedged());
        assert_eq!(store.map_version("s").unwrap(), 2, "visible, not durable");
        let error = store.apply(&batch(3)).unwrap_err();
        assert!(
            matches!(
                error,
                StorageError::Wedged {
                    out_of_space: true,
                    ..
                }
            ),
            "{error}"
        );
        assert_eq!(store.generation(), 0);
        store.free();
        // The first write with room reopens it: batch 2 was never flushed, so it is gone.
        assert_eq!(
            store.apply_durable(&batch(2)).unwrap(),
            BatchOutcome::Applied { map_version: 2 }
        );
        assert_eq!(store.generation(), 1);
        assert!(!store.is_wedged());
        assert_eq!(store.last_applied_seq("s", "robot-1").unwrap(), Some(2));
        assert_eq!(store.scan("s", RecordKind::Trajectory).unwrap().count(), 2);
    }
}
