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
//!
//! Reads never fail. [`DiskFullStore::free`] gives the space back.

use std::io::{Read, Write};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use crate::{BatchOutcome, MapStore, RecordId, RecordIter, RecordKind, Result, StorageError};
use crate::{TransferSummary, WriteBatch};

/// Where a full disk makes writes fail.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FailAt {
    /// Writes fail before anything is stored.
    Apply,
    /// Writes are applied but flushes fail (the write is visible, not durable).
    Flush,
}

/// A store whose disk can be filled and freed (see the module docs).
pub struct DiskFullStore {
    inner: Arc<dyn MapStore>,
    fail_at: FailAt,
    full: AtomicBool,
    failures: AtomicU64,
}

/// The error a full disk gives.
pub fn out_of_space() -> StorageError {
    // ENOSPC: "No space left on device (os error 28)", as Linux reports it.
    StorageError::Io(std::io::Error::from_raw_os_error(28))
}

impl DiskFullStore {
    /// Wraps `inner`; the disk starts with room.
    pub fn new(inner: Arc<dyn MapStore>, fail_at: FailAt) -> Self {
        Self {
            inner,
            fail_at,
            full: AtomicBool::new(false),
            failures: AtomicU64::new(0),
        }
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
        if self.fail_at == at && self.full.load(Ordering::SeqCst) {
            self.failures.fetch_add(1, Ordering::SeqCst);
            Err(out_of_space())
        } else {
            Ok(())
        }
    }

    /// Writes that are not batches (deletion, import) fail whichever [`FailAt`] is chosen.
    fn check_any(&self) -> Result<()> {
        if self.full.load(Ordering::SeqCst) {
            self.failures.fetch_add(1, Ordering::SeqCst);
            Err(out_of_space())
        } else {
            Ok(())
        }
    }
}

impl MapStore for DiskFullStore {
    fn apply(&self, batch: &WriteBatch) -> Result<BatchOutcome> {
        self.check(FailAt::Apply)?;
        self.inner.apply(batch)
    }

    fn flush(&self) -> Result<()> {
        self.check(FailAt::Flush)?;
        self.inner.flush()
    }

    fn get(&self, site: &str, kind: RecordKind, id: &RecordId) -> Result<Option<Vec<u8>>> {
        self.inner.get(site, kind, id)
    }

    fn scan(&self, site: &str, kind: RecordKind) -> Result<RecordIter<'_>> {
        self.inner.scan(site, kind)
    }

    fn list_sites(&self) -> Result<Vec<String>> {
        self.inner.list_sites()
    }

    fn map_version(&self, site: &str) -> Result<u64> {
        self.inner.map_version(site)
    }

    fn last_applied_seq(&self, site: &str, session: &str) -> Result<Option<u64>> {
        self.inner.last_applied_seq(site, session)
    }

    fn delete_site(&self, site: &str) -> Result<()> {
        self.check_any()?;
        self.inner.delete_site(site)
    }

    fn export_site(&self, site: &str, out: &mut dyn Write) -> Result<TransferSummary> {
        self.inner.export_site(site, out)
    }

    fn import_site(&self, site: &str, input: &mut dyn Read) -> Result<TransferSummary> {
        self.check_any()?;
        self.inner.import_site(site, input)
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
}
