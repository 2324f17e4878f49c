//! [`crate::MapStore`] on a sled 0.34 database.
//!
//! All records live in sled's default tree under the key layout of the private `key` module. Batches run as
//! sled transactions (serializable, retried on conflict), so the map-version read-modify-write and the session
//! sequence check are atomic with the batch. [`crate::MapStore::flush`] is `Db::flush`, which fsyncs.
//!
//! sled 0.34 is a beta with open reports of corruption after abrupt stops; `tests/kill_nine.rs` SIGKILLs a
//! writer at random moments and checks that every acknowledged batch survives whole.
//!
//! **Reopened in place after a failed write.** Once a write or flush has failed with an I/O error (a full
//! disk), sled refuses every later write with the same error, even once space is back, until the database
//! is reopened (measured on a real tmpfs: `tests/disk_full_tmpfs.rs`). The store does that itself: after
//! such a failure it is *wedged* — writes fail at once with [`StorageError::Wedged`] (out of space when
//! the cause was) — and the first write or flush at least [`SledStoreOptions::reopen_interval_ms`] after
//! the failure (or the last attempt) drops the database, opens it again (waiting, bounded, for operations
//! still holding the old one to finish: sled locks its directory), fsyncs the files recovery found, and
//! bumps [`crate::MapStore::generation`]. What was applied but never flushed before the failure may be gone
//! after that (or may have survived): callers that acknowledge only flushed writes lose nothing, and
//! callers that derived state from unflushed writes rebuild it from the store when the generation changes.
//! Reads keep working on the wedged database.
//!
//! **Reopened to bound its memory.** sled 0.34 keeps every value it has written or read since it was
//! opened in memory, whatever its cache capacity: its LRU only learns of an access once 64 have queued in
//! one of its 256 shards, so a database written at a site log's pace (a few batches a second) never
//! evicts anything (measured: 80 MB written with an 8 MiB cache hold 73 MiB; dropping and reopening the
//! database frees it all). The store counts the bytes of the values (and keys) it hands to sled or
//! gets from it, and once they pass [`SledStoreOptions::reopen_after_bytes`], its next successful flush
//! reopens the database — when no operation holds it (scans included), else a later flush does. That
//! reopen follows a successful flush, so it loses nothing and leaves
//! [`crate::MapStore::generation`] unchanged; it is counted by [`SledStore::memory_reopens`].
//!
//! **Checkpoints and large values in files.** sled 0.34 keeps the space of the large values it held long
//! after they are overwritten or removed, so large bytes are not sled values:
//! - each site checkpoint is a file under `<database dir>/checkpoints/<site>/` (see
//!   [`crate::MapStore::put_checkpoint`]), and sled holds only its index entry (log index, length, CRC32,
//!   file name). As sled values, a 16-session site's checkpoints made its store 1.6 GB against 22 MB
//!   without.
//! - each record value longer than [`crate::MAX_INLINE_VALUE_BYTES`] (4 KiB) is a file under
//!   `<database dir>/values/<site>/`, and sled holds only its entry (length, CRC32, file name) under the
//!   record's key. sled writes a tree page over a quarter of its segment (128 KiB) as a blob file, a leaf
//!   of 16 site log entries of 25–30 kB is one, and sled forgets the deletion of a rewritten page's old
//!   blob when the database is dropped — at every reopen above: such a site's `blobs/` grew with its age
//!   (420 files, 107 MB, for 0.75 MB of live entries in `tests/sled_blobs.rs`). Pages of values up to
//!   4 KiB stay under the blob size.
//!
//! Both are written crash-safely (a temporary file, fsync, rename, directory fsync) before the entry
//! naming them, and deleted only once the removal of their entry is durable; a deleted file frees its
//! space at once. Opening the store deletes the files no entry names (left by a crash between a file and
//! its entry). [`SledStore::size_on_disk`] counts them.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use std::thread;
use std::time::{Duration, Instant};

use sled::transaction::{
    ConflictableTransactionError, TransactionError, TransactionalTree, UnabortableTransactionError,
};

use crate::file_step::{FileStep, StepHook};
use crate::raw_kv::{RawIter, RawKv, RawTxn, impl_map_store_via_raw_kv};
use crate::side_files::{FileDir, SideFiles};
use crate::value_files::{self, ValueFiles};
use crate::{Result, SledStoreOptions, StorageError, checkpoints};

/// The checkpoint directory's name inside the database directory.
const CHECKPOINT_DIR: &str = "checkpoints";
/// The value directory's name inside the database directory.
const VALUE_DIR: &str = "values";

/// A [`crate::MapStore`] persisted in a sled database directory (one process at a time: sled locks it).
#[derive(Debug)]
pub struct SledStore {
    /// The open database; `None` after a reopen failed (the next attempt opens it). Every operation
    /// holds a clone of the `Arc` while it uses the database (a scan for as long as its iterator
    /// lives), so a strong count of 1 under the write lock means no operation is using it.
    db: RwLock<Option<Arc<sled::Db>>>,
    options: SledStoreOptions,
    /// Set while the database refuses writes after a failed one.
    wedge: Mutex<Option<Wedge>>,
    /// Reopens so far.
    generation: AtomicU64,
    /// Bytes of keys and values written to or read from the database since it was opened (see
    /// [`SledStoreOptions::reopen_after_bytes`]); shared with scans' iterators.
    held_bytes: Arc<AtomicU64>,
    /// Reopens that bounded the memory (see the module docs).
    memory_reopens: AtomicU64,
    /// The files of the checkpoints' bytes (see the module docs).
    checkpoint_files: FileDir,
    /// The files of large record values (see the module docs).
    value_files: ValueFiles<FileDir>,
    /// Called at each [`FileStep`].
    hook: StepHook,
}

/// Why and since when the database refuses writes.
#[derive(Debug)]
struct Wedge {
    cause: String,
    /// The error behind `cause`, if any.
    source: Option<Arc<StorageError>>,
    out_of_space: bool,
    /// The failure, or the last reopen attempt.
    since: Instant,
}

impl SledStore {
    /// Opens (creating if needed) the database at `options.path`, and its checkpoint and value
    /// directories `options.path/checkpoints` and `options.path/values`, from which it deletes the files
    /// no entry names (it reads every record to know). While another process holds the lock, retries up
    /// to `options.open_attempts` times, `options.open_retry_interval_ms` apart, then fails with
    /// [`StorageError::Locked`].
    pub fn open(options: &SledStoreOptions) -> Result<Self> {
        options.validate()?;
        // sled creates the database directory; the file directories go inside it, under its lock.
        let db = open_db(options)?;
        let store = Self {
            db: RwLock::new(Some(Arc::new(db))),
            options: options.clone(),
            wedge: Mutex::new(None),
            generation: AtomicU64::new(0),
            held_bytes: Arc::new(AtomicU64::new(0)),
            memory_reopens: AtomicU64::new(0),
            checkpoint_files: FileDir::open(options.path.join(CHECKPOINT_DIR), "checkpoint")?,
            value_files: ValueFiles::new(FileDir::open(options.path.join(VALUE_DIR), "value")?),
            hook: StepHook::default(),
        };
        checkpoints::remove_orphan_files(&store)?;
        value_files::remove_orphan_files(&store)?;
        Ok(store)
    }

    /// Opens the database at `path` with default options.
    pub fn open_path(path: impl Into<PathBuf>) -> Result<Self> {
        Self::open(&SledStoreOptions::at(path))
    }

    /// The database directory.
    pub fn path(&self) -> &Path {
        &self.options.path
    }

    /// Bytes the store occupies on disk: sled's files as sled reports them (its `blobs/` included), the
    /// checkpoint files and the value files.
    pub fn size_on_disk(&self) -> Result<u64> {
        Ok(self.db_for_read()?.size_on_disk()?
            + self.checkpoint_files.total_bytes()?
            + self.value_files.files().total_bytes()?)
    }

    /// Bytes of the checkpoint files (included in [`SledStore::size_on_disk`]).
    pub fn checkpoint_files_bytes(&self) -> Result<u64> {
        self.checkpoint_files.total_bytes()
    }

    /// Bytes of the files of large record values (included in [`SledStore::size_on_disk`]).
    pub fn value_files_bytes(&self) -> Result<u64> {
        self.value_files.files().total_bytes()
    }

    /// Calls `hook` at each step between a file (a checkpoint's, a large value's) and its entry (see
    /// [`FileStep`]), on the thread storing, flushing or compacting; replaces any earlier hook. For crash
    /// tests (`tests/kill_nine.rs` stops the writer there and kills it).
    pub fn on_file_step(&self, hook: impl Fn(FileStep) + Send + Sync + 'static) {
        self.hook.set(Box::new(hook));
    }

    /// Whether the database refuses writes after a failed one (until it is reopened).
    pub fn is_wedged(&self) -> bool {
        self.wedge
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .is_some()
    }

    /// Bytes of keys and values written to or read from the database since it was last (re)opened: what
    /// sled may be holding in memory (see the module docs).
    pub fn held_bytes(&self) -> u64 {
        self.held_bytes.load(Ordering::Relaxed)
    }

    /// Reopens so far that bounded the memory (after [`SledStoreOptions::reopen_after_bytes`]).
    pub fn memory_reopens(&self) -> u64 {
        self.memory_reopens.load(Ordering::Relaxed)
    }

    /// After a successful flush: reopens the database when it holds more than
    /// [`SledStoreOptions::reopen_after_bytes`] and no operation is using it (see the module docs).
    /// Nothing is lost: every write to it was flushed (by the caller, or by the drop, for a write made
    /// between the caller's flush and the lock). A failed open wedges the store, as a failed write does.
    fn bound_memory(&self) {
        let bound = self.options.reopen_after_bytes;
        if bound == 0 || self.held_bytes.load(Ordering::Relaxed) <= bound {
            return;
        }
        let mut slot = self.db.write().unwrap_or_else(PoisonError::into_inner);
        let Some(db) = slot.as_ref() else {
            return;
        };
        if Arc::strong_count(db) > 1 {
            return; // in use: a later flush reopens it
        }
        if db.flush().is_err() {
            return; // the next write or flush meets the failure and wedges the store
        }
        drop(slot.take());
        match open_db(&self.options) {
            Ok(db) => {
                *slot = Some(Arc::new(db));
                self.held_bytes.store(0, Ordering::Relaxed);
                self.memory_reopens.fetch_add(1, Ordering::Relaxed);
            }
            Err(error) => {
                drop(slot);
                let mut wedge = self.wedge.lock().unwrap_or_else(PoisonError::into_inner);
                if wedge.is_none() {
                    *wedge = Some(Wedge {
                        cause: format!("reopening the database to bound its memory: {error}"),
                        out_of_space: error.is_out_of_space(),
                        source: Some(Arc::new(error)),
                        since: Instant::now(),
                    });
                }
            }
        }
    }

    /// Test hook: wedges the store as a failed write would (a real one needs a full disk).
    #[cfg(test)]
    pub(crate) fn wedge_as_if(&self, error: &StorageError) {
        self.note_failure(error);
    }

    /// Test hook: the raw sled database, to corrupt stored bytes behind the store's back.
    #[cfg(test)]
    pub(crate) fn raw_db(&self) -> sled::Db {
        sled::Db::clone(&self.db_for_read().unwrap())
    }

    /// The current database, for a read (reads work on a wedged database; after a failed reopen the
    /// next attempt is made).
    fn db_for_read(&self) -> Result<Arc<sled::Db>> {
        if let Some(db) = self
            .db
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .as_ref()
        {
            return Ok(db.clone());
        }
        self.db_for_write()
    }

    /// The current database, for a write: reopened first when wedged and due, refused while wedged.
    fn db_for_write(&self) -> Result<Arc<sled::Db>> {
        let mut wedge = self.wedge.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(w) = wedge.as_mut() {
            let interval = Duration::from_millis(self.options.reopen_interval_ms);
            if w.since.elapsed() < interval {
                return Err(StorageError::Wedged {
                    cause: w.cause.clone(),
                    source: w.source.clone(),
                    out_of_space: w.out_of_space,
                });
            }
            w.since = Instant::now();
            self.reopen()?;
            *wedge = None;
        }
        drop(wedge);
        self.db
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
            .ok_or_else(|| StorageError::Wedged {
                cause: "the database is not open".to_owned(),
                source: None,
                out_of_space: false,
            })
    }

    /// Drops the database and opens it again (see the module docs). The caller holds the wedge lock.
    fn reopen(&self) -> Result<()> {
        let mut slot = self.db.write().unwrap_or_else(PoisonError::into_inner);
        // Dropping it flushes what it can; operations still holding a clone keep the old database (and
        // its lock) alive until they end: `open_db` waits for them, bounded.
        drop(slot.take());
        let db = open_db(&self.options)?;
        // What recovery found may have been written but never fsynced: make it durable before anyone
        // builds on it.
        sync_files(&self.options.path)?;
        *slot = Some(Arc::new(db));
        self.held_bytes.store(0, Ordering::Relaxed);
        self.generation.fetch_add(1, Ordering::SeqCst);
        Ok(())
    }

    /// Notes a failed write: an I/O failure wedges the database (see the module docs).
    fn note_failure(&self, error: &StorageError) {
        // The caller returns `error` itself: the wedge keeps a copy.
        let copy = match error {
            StorageError::Io(io) => StorageError::Io(copy_io_error(io)),
            StorageError::Sled(sled::Error::Io(io)) => {
                StorageError::Sled(sled::Error::Io(copy_io_error(io)))
            }
            _ => return,
        };
        let mut wedge = self.wedge.lock().unwrap_or_else(PoisonError::into_inner);
        if wedge.is_none() {
            *wedge = Some(Wedge {
                cause: error.to_string(),
                source: Some(Arc::new(copy)),
                out_of_space: error.is_out_of_space(),
                since: Instant::now(),
            });
        }
    }
}

/// A copy of an I/O error (`std::io::Error` is not `Clone`) with its kind, OS error code and message.
fn copy_io_error(error: &std::io::Error) -> std::io::Error {
    match error.raw_os_error() {
        Some(code) => std::io::Error::from_raw_os_error(code),
        None => std::io::Error::new(error.kind(), error.to_string()),
    }
}

/// Opens the database, retrying while its lock is held (see [`SledStore::open`]).
fn open_db(options: &SledStoreOptions) -> Result<sled::Db> {
    let config = sled::Config::new()
        .path(&options.path)
        .cache_capacity(options.cache_capacity_bytes)
        .flush_every_ms((options.background_flush_ms > 0).then_some(options.background_flush_ms));
    let interval = Duration::from_millis(options.open_retry_interval_ms);
    for attempt in 1..=options.open_attempts {
        match config.open() {
            Ok(db) => return Ok(db),
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

/// fsyncs every file of sled in the database directory and its subdirectories (sled keeps large pages in
/// `blobs/`), and the directories themselves. The checkpoint and value directories are left out: their
/// files were durable before any entry named them.
fn sync_files(dir: &Path) -> Result<()> {
    let ours = [dir.join(CHECKPOINT_DIR), dir.join(VALUE_DIR)];
    let mut dirs = vec![dir.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir)? {
            let entry = entry?;
            let kind = entry.file_type()?;
            if kind.is_dir() {
                if !ours.contains(&entry.path()) {
                    dirs.push(entry.path());
                }
            } else if kind.is_file() {
                std::fs::File::open(entry.path())?.sync_all()?;
            }
        }
        std::fs::File::open(&dir)?.sync_all()?;
    }
    Ok(())
}

/// sled 0.34 reports a held lock only as an `Io` error of kind `Other` with this message.
fn is_lock_error(error: &sled::Error) -> bool {
    matches!(error, sled::Error::Io(io) if io.to_string().contains("could not acquire lock"))
}

/// Adds `bytes` handed to sled or taken from it to the store's count of what sled holds
/// ([`SledStore::held_bytes`]).
fn count_held(held_bytes: &AtomicU64, bytes: usize) {
    held_bytes.fetch_add(u64::try_from(bytes).unwrap_or(u64::MAX), Ordering::Relaxed);
}

struct SledTxn<'a> {
    tree: &'a TransactionalTree,
    /// The store's count of bytes sled holds (see [`SledStore::held_bytes`]).
    held_bytes: &'a AtomicU64,
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
        let value = self.note(result)?.map(|value| value.to_vec());
        count_held(
            self.held_bytes,
            key.len() + value.as_ref().map_or(0, Vec::len),
        );
        Ok(value)
    }

    fn insert(&mut self, key: &[u8], value: Vec<u8>) -> Result<Option<Vec<u8>>> {
        count_held(self.held_bytes, key.len() + value.len());
        let result = self.tree.insert(key, value);
        Ok(self.note(result)?.map(|old| old.to_vec()))
    }

    fn remove(&mut self, key: &[u8]) -> Result<Option<Vec<u8>>> {
        let result = self.tree.remove(key);
        Ok(self.note(result)?.map(|old| old.to_vec()))
    }
}

/// A prefix scan of one database: holds that database, so no reopen happens under it, and counts what it
/// reads towards the bytes sled holds.
struct SledScan {
    iter: sled::Iter,
    _db: Arc<sled::Db>,
    held: Arc<AtomicU64>,
}

impl Iterator for SledScan {
    type Item = Result<(Vec<u8>, Vec<u8>)>;

    fn next(&mut self) -> Option<Self::Item> {
        let item = self.iter.next()?;
        Some(
            item.map(|(key, value)| {
                count_held(&self.held, key.len() + value.len());
                (key.to_vec(), value.to_vec())
            })
            .map_err(StorageError::from),
        )
    }
}

impl RawKv for SledStore {
    fn checkpoint_files(&self) -> &dyn SideFiles {
        &self.checkpoint_files
    }

    fn value_files(&self) -> &ValueFiles {
        &self.value_files
    }

    fn step(&self, step: FileStep) {
        self.hook.call(step);
    }

    fn raw_get(&self, key: &[u8]) -> Result<Option<Vec<u8>>> {
        let value = self.db_for_read()?.get(key)?.map(|value| value.to_vec());
        count_held(
            &self.held_bytes,
            key.len() + value.as_ref().map_or(0, Vec::len),
        );
        Ok(value)
    }

    fn raw_scan(&self, prefix: &[u8]) -> RawIter<'_> {
        match self.db_for_read() {
            Ok(db) => Box::new(SledScan {
                iter: db.scan_prefix(prefix),
                _db: db,
                held: Arc::clone(&self.held_bytes),
            }),
            Err(error) => Box::new(std::iter::once(Err(error))),
        }
    }

    fn transact<T>(&self, body: &dyn Fn(&mut dyn RawTxn) -> Result<T>) -> Result<T> {
        let db = self.db_for_write()?;
        let outcome = db.transaction(|tree| {
            let mut txn = SledTxn {
                tree,
                held_bytes: &self.held_bytes,
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
            Err(TransactionError::Storage(error)) => {
                let error = StorageError::from(error);
                self.note_failure(&error);
                Err(error)
            }
        }
    }

    fn raw_flush(&self) -> Result<()> {
        let db = self.db_for_write()?;
        if let Err(error) = db.flush() {
            let error = StorageError::from(error);
            self.note_failure(&error);
            return Err(error);
        }
        drop(db);
        self.bound_memory();
        Ok(())
    }

    fn generation(&self) -> u64 {
        self.generation.load(Ordering::SeqCst)
    }
}

impl_map_store_via_raw_kv!(SledStore);

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::{MapStore as _, RecordId, RecordKind, WriteBatch, conformance, key};

    /// The length of the longest value sled itself holds (checkpoint and value files apart).
    fn largest_sled_value(store: &SledStore) -> usize {
        store
            .raw_db()
            .iter()
            .map(|item| item.unwrap().1.len())
            .max()
            .unwrap()
    }

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
    fn past_its_bound_the_store_reopens_at_a_flush_when_unused_losing_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let store = SledStore::open(&SledStoreOptions {
            reopen_after_bytes: 27 << 10,
            ..SledStoreOptions::at(dir.path().join("db"))
        })
        .unwrap();
        // The largest values sled holds (longer ones go to files): about 4.3 kB of sled I/O per batch.
        let value = |version: u64| vec![version as u8; crate::MAX_INLINE_VALUE_BYTES];
        let write = |version: u64| {
            let mut batch = WriteBatch::new("depot");
            batch
                .put(RecordKind::Trajectory, version, value(version))
                .bump_map_version()
                .for_session("robot", version);
            store.apply(&batch).unwrap();
            store.flush().unwrap();
        };
        for version in 1..=6 {
            write(version);
        }
        assert_eq!(store.memory_reopens(), 0, "26 kB is within the bound");
        write(7);
        assert_eq!(store.memory_reopens(), 1);
        assert_eq!(store.held_bytes(), 0);
        assert_eq!(
            crate::MapStore::generation(&store),
            0,
            "nothing was lost: not a recovery"
        );
        // A scan in progress holds the database: flushes past the bound leave it open under it.
        let mut scan = store.scan("depot", RecordKind::Trajectory).unwrap();
        assert!(scan.next().is_some());
        for version in 8..=14 {
            write(version);
        }
        assert_eq!(store.memory_reopens(), 1, "reopened under a scan");
        assert!(scan.count() >= 6, "the scan reads on");
        write(15);
        assert_eq!(store.memory_reopens(), 2, "reopened once the scan ended");
        assert_eq!(store.map_version("depot").unwrap(), 15);
        assert_eq!(store.last_applied_seq("depot", "robot").unwrap(), Some(15));
        for version in 1..=15u64 {
            let stored = store
                .get("depot", RecordKind::Trajectory, &RecordId::from(version))
                .unwrap()
                .unwrap();
            assert_eq!(stored, value(version));
        }
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
    fn a_wedged_store_refuses_writes_then_reopens_itself_and_keeps_what_was_flushed() {
        let dir = tempfile::tempdir().unwrap();
        let options = SledStoreOptions {
            reopen_interval_ms: 200,
            background_flush_ms: 0,
            ..SledStoreOptions::at(dir.path().join("db"))
        };
        let store = SledStore::open(&options).unwrap();
        let batch = |seq: u64| {
            let mut batch = WriteBatch::new("depot");
            batch
                .put(RecordKind::Node, seq, vec![seq as u8; 100])
                .bump_map_version()
                .for_session("robot-1", seq);
            batch
        };
        store.apply_durable(&batch(1)).unwrap();
        // A non-I/O failure (a refused batch) does not wedge it.
        store.wedge_as_if(&StorageError::SiteNotFound {
            site: "depot".into(),
        });
        assert!(!store.is_wedged());
        store.wedge_as_if(&StorageError::Io(std::io::Error::from_raw_os_error(28)));
        assert!(store.is_wedged());
        // Within the interval: writes refused at once, as out of space; reads work.
        let error = store.apply_durable(&batch(2)).unwrap_err();
        assert!(
            matches!(error, StorageError::Wedged { .. }) && error.is_out_of_space(),
            "{error}"
        );
        assert_eq!(
            std::error::Error::source(&error).map(ToString::to_string),
            Some("I/O error: No space left on device (os error 28)".to_owned()),
            "the typed cause is kept"
        );
        assert!(store.flush().unwrap_err().is_out_of_space());
        assert_eq!(store.map_version("depot").unwrap(), 1);
        assert_eq!(crate::MapStore::generation(&store), 0);
        // A scan another thread holds on the old database delays the reopen (sled's lock), not forever.
        let scanning = {
            let db = store.raw_db();
            thread::Builder::new()
                .name("scan".to_owned())
                .spawn(move || {
                    let iter = db.iter();
                    thread::sleep(Duration::from_millis(300));
                    iter.count()
                })
                .unwrap()
        };
        thread::sleep(Duration::from_millis(250));
        // Past the interval: the write reopens the database and lands.
        assert_eq!(
            store.apply_durable(&batch(2)).unwrap(),
            crate::BatchOutcome::Applied { map_version: 2 }
        );
        assert!(scanning.join().unwrap() > 0);
        assert_eq!(crate::MapStore::generation(&store), 1);
        assert!(!store.is_wedged());
        assert_eq!(store.last_applied_seq("depot", "robot-1").unwrap(), Some(2));
        drop(store);
        let store = SledStore::open(&options).unwrap();
        assert_eq!(store.map_version("depot").unwrap(), 2);
        assert_eq!(
            crate::MapStore::generation(&store),
            0,
            "counted per open store"
        );
    }

    /// The files under the store's checkpoint directory, relative to it, sorted.
    fn checkpoint_files_on_disk(db: &Path) -> Vec<String> {
        files_on_disk(&db.join(CHECKPOINT_DIR))
    }

    /// The files under a directory of site directories, relative to it, sorted.
    fn files_on_disk(root: &Path) -> Vec<String> {
        test_support::files_in_site_dirs(root)
    }

    #[test]
    fn checkpoint_bytes_live_in_files_and_sled_stays_small() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("db");
        let store = SledStore::open(&SledStoreOptions::at(&db)).unwrap();
        let checkpoint = |index: u64| vec![index as u8; 2 << 20];
        for index in 1..=12_u64 {
            let mut batch = WriteBatch::new("depot");
            batch
                .put(RecordKind::Trajectory, index, b"entry".to_vec())
                .bump_map_version();
            store.apply_durable(&batch).unwrap();
            store
                .put_checkpoint("depot", index, &checkpoint(index))
                .unwrap();
            store
                .compact(
                    "depot",
                    RecordKind::Trajectory,
                    &crate::CheckpointRetention::DEFAULT,
                )
                .unwrap();
        }
        let crc = |index: u64| {
            crate::checkpoint_entry::CheckpointEntry::of("depot", index, &checkpoint(index)).crc
        };
        assert_eq!(
            checkpoint_files_on_disk(&db),
            [
                format!("depot/00000000000000000011-{:08x}.ckpt", crc(11)),
                format!("depot/00000000000000000012-{:08x}.ckpt", crc(12)),
            ]
        );
        assert_eq!(store.checkpoint_files_bytes().unwrap(), 2 * (2 << 20));
        assert_eq!(store.checkpoint("depot", 12).unwrap(), Some(checkpoint(12)));
        // No checkpoint bytes in sled: 24 MiB of checkpoints written, sled holds kilobytes of values.
        let largest = largest_sled_value(&store);
        assert!(largest < 1024, "a {largest}-byte value in sled");
        let sled_bytes = store.size_on_disk().unwrap() - store.checkpoint_files_bytes().unwrap();
        assert!(sled_bytes < 8 << 20, "sled's files take {sled_bytes} bytes");
    }

    #[test]
    fn opening_removes_orphan_files_and_a_missing_file_reads_as_corrupt() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("db");
        let options = SledStoreOptions::at(&db);
        {
            let store = SledStore::open(&options).unwrap();
            let mut batch = WriteBatch::new("depot");
            batch.bump_map_version();
            store.apply_durable(&batch).unwrap();
            store.apply_durable(&batch).unwrap();
            store.put_checkpoint("depot", 1, b"state 1").unwrap();
            store.put_checkpoint("depot", 2, b"state 2").unwrap();
        }
        let kept = checkpoint_files_on_disk(&db);
        assert_eq!(kept.len(), 2);
        // What crashes leave: a temporary file, a file whose entry never landed, a deleted site's dir.
        let root = db.join(CHECKPOINT_DIR);
        std::fs::write(root.join("depot/.x.ckpt.7-0.tmp"), b"half").unwrap();
        std::fs::write(root.join("depot/00000000000000000003-00000000.ckpt"), b"3").unwrap();
        std::fs::create_dir(root.join("gone")).unwrap();
        std::fs::write(root.join("gone/00000000000000000001-00000000.ckpt"), b"1").unwrap();
        let store = SledStore::open(&options).unwrap();
        assert_eq!(checkpoint_files_on_disk(&db), kept);
        assert!(!root.join("gone").exists());
        assert_eq!(
            store.checkpoint("depot", 2).unwrap().as_deref(),
            Some(&b"state 2"[..])
        );
        // A file deleted behind the store's back: the checkpoint is invalid, named by its file.
        std::fs::remove_file(root.join(&kept[1])).unwrap();
        let error = store.checkpoint("depot", 2).unwrap_err();
        assert!(
            matches!(&error, StorageError::Corrupt { reason, .. } if reason.contains(&kept[1])),
            "{error}"
        );
        assert_eq!(store.checkpoint_indexes("depot").unwrap(), [2, 1]);
    }

    #[test]
    fn large_values_live_in_files_and_sled_stays_small() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("db");
        let store = SledStore::open(&SledStoreOptions::at(&db)).unwrap();
        let entry = |index: u64| vec![index as u8; 30_000];
        for index in 1..=200_u64 {
            let mut batch = WriteBatch::new("Halle 7");
            batch
                .put(RecordKind::Trajectory, index, entry(index))
                .put(RecordKind::SiteMeta, "summary", vec![index as u8; 300])
                .bump_map_version();
            store.apply_durable(&batch).unwrap();
        }
        let files = files_on_disk(&db.join(VALUE_DIR));
        assert_eq!(files.len(), 200);
        assert!(
            files.iter().all(|file| file.starts_with("Halle%207/")
                && Path::new(file).extension() == Some("val".as_ref())),
            "{files:?}"
        );
        assert_eq!(store.value_files_bytes().unwrap(), 200 * 30_000);
        assert_eq!(
            store
                .get("Halle 7", RecordKind::Trajectory, &RecordId::from(123))
                .unwrap(),
            Some(entry(123))
        );
        // 6 MB of values written, sled holds none of them: no value over a few hundred bytes, no blob.
        let largest = largest_sled_value(&store);
        assert!(largest < 1024, "a {largest}-byte value in sled");
        let blobs = std::fs::read_dir(db.join("blobs")).map_or(0, Iterator::count);
        assert_eq!(blobs, 0, "sled wrote blobs");
        let sled_bytes = store.size_on_disk().unwrap() - store.value_files_bytes().unwrap();
        assert!(sled_bytes < 4 << 20, "sled's files take {sled_bytes} bytes");
    }

    #[test]
    fn opening_removes_orphan_value_files_and_a_missing_one_reads_as_corrupt() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("db");
        let options = SledStoreOptions::at(&db);
        let value = |n: u8| vec![n; 10_000];
        {
            let store = SledStore::open(&options).unwrap();
            for n in 1..=3 {
                store
                    .put(
                        "depot",
                        RecordKind::Submap,
                        &RecordId::from(u64::from(n)),
                        &value(n),
                    )
                    .unwrap();
            }
            store
                .delete("depot", RecordKind::Submap, &RecordId::from(3))
                .unwrap();
            store.flush().unwrap();
            // Dropped with a deletion pending: its file is left for the next open.
            store
                .delete("depot", RecordKind::Submap, &RecordId::from(2))
                .unwrap();
        }
        let root = db.join(VALUE_DIR);
        assert_eq!(files_on_disk(&root).len(), 2);
        // What crashes leave: a temporary file, a file whose batch never landed, a deleted site's dir.
        std::fs::write(root.join("depot/.x.val.7-0.tmp"), b"half").unwrap();
        std::fs::write(root.join("depot/00000000000000ff-00000000.val"), b"?").unwrap();
        std::fs::create_dir(root.join("gone")).unwrap();
        std::fs::write(root.join("gone/0000000000000001-00000000.val"), b"1").unwrap();
        let store = SledStore::open(&options).unwrap();
        let kept = files_on_disk(&root);
        assert_eq!(kept.len(), 1, "{kept:?}");
        assert!(!root.join("gone").exists());
        assert_eq!(
            store
                .get("depot", RecordKind::Submap, &RecordId::from(1))
                .unwrap(),
            Some(value(1))
        );
        // New files are numbered past the orphans.
        store
            .put("depot", RecordKind::Submap, &RecordId::from(4), &value(4))
            .unwrap();
        assert!(
            files_on_disk(&root)
                .iter()
                .any(|file| file.starts_with("depot/0000000000000100-")),
            "{:?}",
            files_on_disk(&root)
        );
        // A file deleted behind the store's back: the record is corrupt, named by its file.
        std::fs::remove_file(root.join(&kept[0])).unwrap();
        let error = store
            .get("depot", RecordKind::Submap, &RecordId::from(1))
            .unwrap_err();
        assert!(
            matches!(&error, StorageError::Corrupt { reason, .. } if reason.contains(&kept[0])),
            "{error}"
        );
    }

    #[test]
    fn a_store_of_an_earlier_build_opens_unchanged() {
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("db");
        let options = SledStoreOptions::at(&db);
        let big = vec![0x5A; 200_000];
        {
            // As an earlier build left it: large values inline, checkpoints in files, no value directory.
            let store = SledStore::open(&options).unwrap();
            let mut batch = WriteBatch::new("depot");
            batch.bump_map_version();
            store.apply_durable(&batch).unwrap();
            store.put_checkpoint("depot", 1, b"state 1").unwrap();
            let key = key::record_key("depot", RecordKind::Submap.as_byte(), &[7]);
            store
                .raw_db()
                .insert(&key, crate::envelope::seal(&key, &big))
                .unwrap();
            store.flush().unwrap();
        }
        std::fs::remove_dir(db.join(VALUE_DIR)).unwrap();
        let store = SledStore::open(&options).unwrap();
        assert!(db.join(VALUE_DIR).is_dir());
        assert_eq!(
            store
                .get("depot", RecordKind::Submap, &RecordId::new(vec![7]))
                .unwrap(),
            Some(big)
        );
        assert_eq!(
            store.checkpoint("depot", 1).unwrap().as_deref(),
            Some(&b"state 1"[..])
        );
        assert_eq!(checkpoint_files_on_disk(&db).len(), 1);
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
