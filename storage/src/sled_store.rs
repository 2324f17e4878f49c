//! [`crate::MapStore`] on a sled 0.34 database.
//!
//! All records live in sled's default tree under the key layout of the private `key` module. Batches run as
//! sled transactions (serializable, retried on conflict), so the map-version read-modify-write and the session
//! sequence check are atomic with the batch. [`crate::MapStore::flush`] is `Db::flush`, which fsyncs.
//!
//! sled 0.34 is a beta with open reports of corruption after abrupt stops; `tests/kill_nine.rs` SIGKILLs a
//! writer at random moments and checks that every acknowledged batch survives whole.

use std::path::{Path, PathBuf};
use std::thread;
use std::time::Duration;

use sled::transaction::{
    ConflictableTransactionError, TransactionError, TransactionalTree, UnabortableTransactionError,
};

use crate::raw_kv::{RawIter, RawKv, RawTxn, impl_map_store_via_raw_kv};
use crate::{Result, SledStoreOptions, StorageError};

/// A [`crate::MapStore`] persisted in a sled database directory (one process at a time: sled locks it).
#[derive(Debug)]
pub struct SledStore {
    db: sled::Db,
    path: PathBuf,
}

impl SledStore {
    /// Opens (creating if needed) the database at `options.path`. While another process holds the lock,
    /// retries up to `options.open_attempts` times, `options.open_retry_interval_ms` apart, then fails with
    /// [`StorageError::Locked`].
    pub fn open(options: &SledStoreOptions) -> Result<Self> {
        options.validate()?;
        let config = sled::Config::new()
            .path(&options.path)
            .cache_capacity(options.cache_capacity_bytes)
            .flush_every_ms(
                (options.background_flush_ms > 0).then_some(options.background_flush_ms),
            );
        let interval = Duration::from_millis(options.open_retry_interval_ms);
        for attempt in 1..=options.open_attempts {
            match config.open() {
                Ok(db) => {
                    return Ok(Self {
                        db,
                        path: options.path.clone(),
                    });
                }
                Err(error) if is_lock_error(&error) => {
                    if attempt < options.open_attempts {
                        thread::sleep(interval);
                    }
                }
                Err(error) => return Err(error.into()),
            }
        }
        Err(StorageError::Locked {
            path: options.path.clone(),
            attempts: options.open_attempts,
            waited_ms: u64::from(options.open_attempts - 1) * options.open_retry_interval_ms,
        })
    }

    /// Opens the database at `path` with default options.
    pub fn open_path(path: impl Into<PathBuf>) -> Result<Self> {
        Self::open(&SledStoreOptions::at(path))
    }

    /// The database directory.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Bytes the database occupies on disk, as sled reports it.
    pub fn size_on_disk(&self) -> Result<u64> {
        Ok(self.db.size_on_disk()?)
    }

    /// Test hook: the raw sled database, to corrupt stored bytes behind the store's back.
    #[cfg(test)]
    pub(crate) fn raw_db(&self) -> &sled::Db {
        &self.db
    }
}

/// sled 0.34 reports a held lock only as an `Io` error of kind `Other` with this message.
fn is_lock_error(error: &sled::Error) -> bool {
    matches!(error, sled::Error::Io(io) if io.to_string().contains("could not acquire lock"))
}

struct SledTxn<'a> {
    tree: &'a TransactionalTree,
    /// A conflict or storage failure to hand back to sled (which retries on conflict).
    interrupted: Option<UnabortableTransactionError>,
}

impl SledTxn<'_> {
    fn note<T>(&mut self, result: Result<T, UnabortableTransactionError>) -> Result<T> {
        result.map_err(|error| {
            let message = error.to_string();
            self.interrupted = Some(error);
            StorageError::Sled(sled::Error::Unsupported(format!(
                "transaction interrupted: {message}"
            )))
        })
    }
}

impl RawTxn for SledTxn<'_> {
    fn get(&mut self, key: &[u8]) -> Result<Option<Vec<u8>>> {
        let result = self.tree.get(key);
        Ok(self.note(result)?.map(|value| value.to_vec()))
    }

    fn insert(&mut self, key: &[u8], value: Vec<u8>) -> Result<()> {
        let result = self.tree.insert(key, value);
        self.note(result).map(drop)
    }

    fn remove(&mut self, key: &[u8]) -> Result<()> {
        let result = self.tree.remove(key);
        self.note(result).map(drop)
    }
}

impl RawKv for SledStore {
    fn raw_get(&self, key: &[u8]) -> Result<Option<Vec<u8>>> {
        Ok(self.db.get(key)?.map(|value| value.to_vec()))
    }

    fn raw_scan(&self, prefix: &[u8]) -> RawIter<'_> {
        Box::new(self.db.scan_prefix(prefix).map(|item| {
            item.map(|(key, value)| (key.to_vec(), value.to_vec()))
                .map_err(StorageError::from)
        }))
    }

    fn transact<T>(&self, body: &dyn Fn(&mut dyn RawTxn) -> Result<T>) -> Result<T> {
        let outcome = self.db.transaction(|tree| {
            let mut txn = SledTxn {
                tree,
                interrupted: None,
            };
            match body(&mut txn) {
                Ok(value) => Ok(value),
                Err(error) => match txn.interrupted.take() {
                    Some(interruption) => Err(ConflictableTransactionError::from(interruption)),
                    None => Err(ConflictableTransactionError::Abort(error)),
                },
            }
        });
        match outcome {
            Ok(value) => Ok(value),
            Err(TransactionError::Abort(error)) => Err(error),
            Err(TransactionError::Storage(error)) => Err(error.into()),
        }
    }

    fn raw_flush(&self) -> Result<()> {
        self.db.flush()?;
        Ok(())
    }
}

impl_map_store_via_raw_kv!(SledStore);

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::{MapStore as _, RecordId, RecordKind, WriteBatch, conformance, key};

    fn temp_store() -> (tempfile::TempDir, SledStore) {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(&SledStoreOptions::at(dir.path().join("db"))).unwrap();
        (dir, store)
    }

    #[test]
    fn conformance_suite() {
        let dir = tempfile::tempdir().unwrap();
        let counter = std::sync::atomic::AtomicUsize::new(0);
        let cases = conformance::run_all(&|| {
            let n = counter.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            SledStore::open(&SledStoreOptions::at(dir.path().join(format!("db{n}")))).unwrap()
        });
        assert!(
            cases >= conformance::MIN_CASES,
            "only {cases} conformance cases ran"
        );
    }

    #[test]
    fn flipped_byte_in_sled_is_reported_as_corrupt() {
        let (_dir, store) = temp_store();
        let id = RecordId::from_u64(3);
        store
            .put("depot", RecordKind::Node, &id, b"node payload")
            .unwrap();
        let raw_key = key::record_key("depot", RecordKind::Node.as_byte(), id.as_bytes());
        let mut raw = store.raw_db().get(&raw_key).unwrap().unwrap().to_vec();
        raw[7] ^= 0x40; // a payload byte
        store.raw_db().insert(&raw_key, raw).unwrap();
        let error = store.get("depot", RecordKind::Node, &id).unwrap_err();
        assert!(
            matches!(&error, StorageError::Corrupt { key, .. } if key == "depot/node/0x0000000000000003"),
            "{error}"
        );
        assert!(error.to_string().contains("CRC32 mismatch"), "{error}");
    }

    #[test]
    fn corrupt_map_version_refuses_batches() {
        let (_dir, store) = temp_store();
        let mut batch = WriteBatch::new("depot");
        batch.bump_map_version();
        store.apply(&batch).unwrap();
        let raw_key = key::record_key("depot", key::KIND_MAP_VERSION, &[]);
        let mut raw = store.raw_db().get(&raw_key).unwrap().unwrap().to_vec();
        raw[5] ^= 0x01;
        store.raw_db().insert(&raw_key, raw).unwrap();
        assert!(matches!(
            store.map_version("depot"),
            Err(StorageError::Corrupt { .. })
        ));
        // The failure happens inside the transaction, after the puts were staged: none may land.
        batch
            .put(RecordKind::Node, 1, b"staged".to_vec())
            .for_session("robot", 1);
        assert!(matches!(
            store.apply(&batch),
            Err(StorageError::Corrupt { .. })
        ));
        assert_eq!(
            store
                .get("depot", RecordKind::Node, &RecordId::from(1))
                .unwrap(),
            None
        );
        assert_eq!(store.last_applied_seq("depot", "robot").unwrap(), None);
    }

    #[test]
    fn data_survives_reopen() {
        let dir = tempfile::tempdir().unwrap();
        let options = SledStoreOptions::at(dir.path().join("db"));
        {
            let store = SledStore::open(&options).unwrap();
            let mut batch = WriteBatch::new("depot");
            batch
                .put(RecordKind::Submap, 1, b"grid".to_vec())
                .bump_map_version()
                .for_session("robot-1", 4);
            store.apply_durable(&batch).unwrap();
        }
        let store = SledStore::open(&options).unwrap();
        assert_eq!(
            store
                .get("depot", RecordKind::Submap, &RecordId::from(1))
                .unwrap()
                .unwrap(),
            b"grid"
        );
        assert_eq!(store.map_version("depot").unwrap(), 1);
        assert_eq!(store.last_applied_seq("depot", "robot-1").unwrap(), Some(4));
        assert_eq!(store.list_sites().unwrap(), ["depot"]);
    }

    #[test]
    fn second_open_waits_then_reports_lock() {
        let dir = tempfile::tempdir().unwrap();
        let options = SledStoreOptions {
            open_attempts: 3,
            open_retry_interval_ms: 10,
            ..SledStoreOptions::at(dir.path().join("db"))
        };
        let first = SledStore::open(&options).unwrap();
        let error = SledStore::open(&options).unwrap_err();
        assert!(
            matches!(error, StorageError::Locked { attempts: 3, .. }),
            "{error}"
        );
        assert!(
            error.to_string().contains("locked by another process"),
            "{error}"
        );

        // Released during the retries: the second open succeeds.
        let first = Arc::new(first);
        let holder = Arc::clone(&first);
        let release = thread::Builder::new()
            .name("release-lock".to_owned())
            .spawn(move || {
                thread::sleep(Duration::from_millis(100));
                drop(holder);
            })
            .unwrap();
        drop(first);
        let patient = SledStoreOptions {
            open_attempts: 50,
            open_retry_interval_ms: 20,
            ..options
        };
        let reopened = SledStore::open(&patient);
        release.join().unwrap();
        assert!(reopened.is_ok(), "{:?}", reopened.err());
    }

    #[test]
    fn non_lock_errors_are_not_retried() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("not-a-dir");
        std::fs::write(&file, b"x").unwrap();
        let error = SledStore::open(&SledStoreOptions::at(&file)).unwrap_err();
        assert!(!matches!(error, StorageError::Locked { .. }), "{error}");
    }
}
