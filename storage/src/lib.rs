//! # storage — persistence of site maps
//!
//! The server keeps one multi-session map per site for months; the agent keeps an outbox of uploads. Both
//! persist through [`MapStore`]: a store of versioned, checksummed records addressed by
//! (site id, [`RecordKind`], [`RecordId`]), holding opaque bytes that the callers encode (the `proto` crate).
//!
//! - Every stored value carries a format version byte and a CRC32 over version, key and value. Reads verify
//!   both; a damaged record is reported as [`StorageError::Corrupt`], never used. A value longer than
//!   [`MAX_INLINE_VALUE_BYTES`] is kept in a file of its own, the database holding only its entry
//!   (length, CRC32 over key and value, file name), written and freed crash-safely.
//! - Writes are [`WriteBatch`]es, applied all or nothing. A batch can bump the site's map version and be
//!   conditional on an upload's session sequence number (exactly-once uploads), atomically with its records.
//! - [`MapStore::apply_durable`] returns only after the batch is on disk.
//! - A site can be exported to, and imported from, a single checksummed stream ([`SITE_ARCHIVE_MAGIC`]),
//!   its checkpoints included.
//! - A site's state can be checkpointed atomically with the log position it covers
//!   ([`MapStore::put_checkpoint`]; [`SledStore`] keeps the bytes in files of their own, with only an
//!   index entry in sled), and its log compacted up to the older kept checkpoint ([`MapStore::compact`],
//!   [`CheckpointRetention`]).
//!
//! Implementations: [`SledStore`] (the server's, on disk) and [`MemStore`] (tests), which share one
//! implementation of these semantics over a small private key-value interface and pass one conformance suite.
//! [`DiskFullStore`] wraps either and runs out of space on demand (the disk-full tests).
//!
//! ```
//! use storage::{BatchOutcome, MapStore as _, MemStore, RecordId, RecordKind, WriteBatch};
//!
//! let store = MemStore::new();
//! let mut batch = WriteBatch::new("warehouse-3");
//! batch.put(RecordKind::Submap, 7, b"encoded submap".to_vec()).bump_map_version().for_session("robot-1", 1);
//! assert_eq!(store.apply_durable(&batch)?, BatchOutcome::Applied { map_version: 1 });
//! // The robot re-sends the same upload: it is not applied twice.
//! assert_eq!(store.apply_durable(&batch)?, BatchOutcome::Duplicate { last_applied: 1 });
//! assert_eq!(store.get("warehouse-3", RecordKind::Submap, &RecordId::from(7))?.as_deref(), Some(&b"encoded submap"[..]));
//! # Ok::<(), storage::StorageError>(())
//! ```

mod checkpoint_entry;
mod checkpoints;
#[cfg(test)]
mod conformance;
mod disk_full_store;
mod envelope;
mod file_step;
mod key;
mod map_store;
mod mem_store;
mod raw_kv;
mod record;
mod side_files;
mod site_archive;
mod sled_store;
mod sled_store_options;
mod storage_error;
mod value_entry;
mod value_files;
mod write_batch;

pub use checkpoints::{CheckpointRetention, Compaction};
pub use disk_full_store::{DiskFullStore, FailAt, out_of_space};
pub use envelope::RECORD_FORMAT_VERSION;
pub use file_step::FileStep;
pub use map_store::{MapStore, RecordIter};
pub use mem_store::MemStore;
pub use record::{
    MAX_ID_BYTES, MAX_NAME_BYTES, MAX_VALUE_BYTES, RecordId, RecordKind, validate_session_id,
    validate_site_id,
};
pub use site_archive::{
    MAX_CHUNK_BYTES, SITE_ARCHIVE_MAGIC, SITE_ARCHIVE_VERSION, TransferSummary,
};
pub use sled_store::SledStore;
pub use sled_store_options::{DEFAULT_REOPEN_AFTER_BYTES, SledStoreOptions};
pub use storage_error::{Result, StorageError};
pub use value_files::MAX_INLINE_VALUE_BYTES;
pub use write_batch::{BatchOp, BatchOutcome, WriteBatch};
