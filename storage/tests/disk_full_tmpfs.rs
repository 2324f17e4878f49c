//! Disk full on a real size-limited filesystem (issue 16 §1): a tmpfs of a few MiB mounted for the test,
//! filled by a filler file, under a [`SledStore`]. What the store does when its disk fills, checked rather
//! than assumed: the failing write is reported as out of space, every batch acknowledged before is
//! intact, and once space returns the same open store takes writes again. A full disk meets a batch at
//! one of two places, one test each:
//!
//! - **At its value file** (values over [`MAX_INLINE_VALUE_BYTES`], written to a file of their own before
//!   sled sees the batch: a site log's entries). The write fails before anything reaches sled: nothing
//!   of the batch is stored (no value file, no temporary file, no entry), sled is untouched, so the store
//!   is *not* wedged and needs no reopen — the first write once space is back lands, the failed batch is
//!   applied afresh (it never was), and [`storage::MapStore::generation`] does not move. (Until the large
//!   values moved to files (7ffec16), these values went to sled and this test expected the wedge below;
//!   a full disk now stops them earlier, which is what the contract asks, not less.)
//! - **In sled** (small values, stored inline). Measured (2026-11-24, sled 0.34): sled itself does not
//!   recover in place — after one failed flush it refuses every later write with the same error even
//!   once space is back, until the database is reopened. [`SledStore`] therefore reopens its database
//!   itself (see its docs): the test checks that the open store is wedged while the disk is full,
//!   reopens on the first write once space is back (its generation moves), and that nothing
//!   acknowledged was lost, in the open store and after a restart.
//!
//! Both check that the value directory holds one file per stored large value afterwards. The third
//! case, a value file written and then sled failing (the disk filling between them), is in
//! `tests/value_files_sled_full.rs`, which needs no root.
//!
//! Mounting needs root (`CAP_SYS_ADMIN`), which CI containers may lack, so the tests run only with
//! `EVERMAP_TMPFS_TESTS=1` (and then fail if they cannot mount); CI covers the same paths through
//! `storage::DiskFullStore` (`tests/tests/disk_full.rs`, the agent's uploader tests).
//! `EVERMAP_TMPFS_TESTS=1 cargo nextest run --workspace -E 'binary(disk_full_tmpfs)'`

#![allow(
    clippy::unwrap_used,
    reason = "integration test helpers: a failed unwrap is a failed test"
)]
use std::path::Path;

use storage::{
    BatchOutcome, MAX_INLINE_VALUE_BYTES, MapStore as _, RecordId, RecordKind, SledStore,
    SledStoreOptions, StorageError, WriteBatch,
};
use test_support::{Tmpfs, fill};

const SITE: &str = "store-tmpfs";
const SIZE_MIB: u64 = 16;
/// A large value: in a file of its own.
const LARGE_BYTES: usize = 64 << 10;
/// A small value: inline in sled.
const SMALL_BYTES: usize = 2 << 10;

fn value(seq: u64, bytes: usize) -> Vec<u8> {
    vec![(seq % 251) as u8; bytes]
}

fn batch(seq: u64, bytes: usize) -> WriteBatch {
    let mut batch = WriteBatch::new(SITE);
    batch
        .put(RecordKind::Trajectory, seq, value(seq, bytes))
        .bump_map_version()
        .for_session("robot-1", seq);
    batch
}

/// Every file under the value directory (temporary ones included), relative to it.
fn value_files(db: &Path) -> Vec<String> {
    test_support::files_in_site_dirs(&db.join("values"))
}

/// A store on a fresh tmpfs holding 4 batches of `bytes`-byte values, its disk then filled; the batches
/// acknowledged until the disk refused one, and the error. The filler is `<tmpfs>/filler`.
fn fill_under_a_store(
    fs: &Tmpfs,
    bytes: usize,
) -> (SledStore, SledStoreOptions, u64, StorageError) {
    let options = SledStoreOptions {
        background_flush_ms: 0,
        cache_capacity_bytes: 1 << 20,
        reopen_interval_ms: 0,
        ..SledStoreOptions::at(fs.path().join("db"))
    };
    let store = SledStore::open(&options).unwrap();
    for seq in 1..=4 {
        store.apply_durable(&batch(seq, bytes)).unwrap();
    }
    fill(&fs.path().join("filler"), SIZE_MIB);

    // Write until the disk refuses (bounded: the disk is full already).
    let mut acked = 4;
    let error = loop {
        match store.apply_durable(&batch(acked + 1, bytes)) {
            Ok(_) => acked += 1,
            Err(e) => break e,
        }
        assert!(
            acked < 4 + (SIZE_MIB << 4),
            "the store never reported the full disk"
        );
    };
    eprintln!("{bytes}-byte values: acknowledged {acked} batches; then: {error}");
    assert!(
        error.is_out_of_space(),
        "not reported as a full disk: {error:?}"
    );
    (store, options, acked, error)
}

/// Batches 1..=`last` are all there, whole, and nothing else: in the open store, and after a restart.
fn check_all_there(store: SledStore, options: &SledStoreOptions, last: u64, bytes: usize) {
    let check = |store: &SledStore| {
        for seq in 1..=last {
            let stored = store
                .get(SITE, RecordKind::Trajectory, &RecordId::from(seq))
                .unwrap()
                .unwrap_or_else(|| panic!("batch {seq} lost"));
            assert_eq!(stored, value(seq, bytes), "batch {seq}");
        }
        assert_eq!(store.map_version(SITE).unwrap(), last);
        assert_eq!(store.last_applied_seq(SITE, "robot-1").unwrap(), Some(last));
        // One value file per stored large value: nothing partial, nothing orphaned.
        let files = value_files(store.path());
        let expected = if bytes > MAX_INLINE_VALUE_BYTES {
            last as usize
        } else {
            0
        };
        assert_eq!(files.len(), expected, "{files:?}");
    };
    check(&store);
    drop(store);
    // And a restart finds the same.
    check(&SledStore::open(options).unwrap());
}

#[test]
fn large_values_on_a_full_tmpfs_are_refused_at_their_file_and_the_store_goes_on() {
    if !test_support::tmpfs_tests_enabled() {
        return;
    }
    let fs = Tmpfs::mount(SIZE_MIB);
    let (store, options, acked, error) = fill_under_a_store(&fs, LARGE_BYTES);
    assert!(
        matches!(
            &error,
            StorageError::File {
                what: "value",
                action: "write",
                ..
            }
        ),
        "the value file is what the full disk refused: {error:?}"
    );
    // Nothing reached sled: the store is not wedged, and nothing of the batch is on disk.
    assert!(!store.is_wedged(), "sled never saw the failed batch");
    assert_eq!(store.map_version(SITE).unwrap(), acked);
    assert_eq!(value_files(store.path()).len(), acked as usize);
    // While the disk is full, writes keep failing as out of space, and leave nothing behind either.
    let still_full = store
        .apply_durable(&batch(acked + 1, LARGE_BYTES))
        .unwrap_err();
    assert!(still_full.is_out_of_space(), "{still_full:?}");
    assert!(!store.is_wedged());
    assert_eq!(value_files(store.path()).len(), acked as usize);

    // Space returns: the same open store takes the failed batch (it was never stored), no reopen needed.
    std::fs::remove_file(fs.path().join("filler")).unwrap();
    assert_eq!(
        store.apply_durable(&batch(acked + 1, LARGE_BYTES)).unwrap(),
        BatchOutcome::Applied {
            map_version: acked + 1
        }
    );
    let next = acked + 2;
    assert_eq!(
        store.apply_durable(&batch(next, LARGE_BYTES)).unwrap(),
        BatchOutcome::Applied { map_version: next }
    );
    assert_eq!(store.generation(), 0, "no reopen");
    check_all_there(store, &options, next, LARGE_BYTES);
}

#[test]
fn sled_on_a_full_tmpfs_reports_it_keeps_what_it_acknowledged_and_recovers() {
    if !test_support::tmpfs_tests_enabled() {
        return;
    }
    let fs = Tmpfs::mount(SIZE_MIB);
    let (store, options, acked, _) = fill_under_a_store(&fs, SMALL_BYTES);

    assert!(store.is_wedged(), "a failed write in sled wedges the store");
    // While the disk is full, writes keep failing as out of space (the reopen attempts find no room).
    let still_full = store
        .apply_durable(&batch(acked + 1, SMALL_BYTES))
        .unwrap_err();
    assert!(still_full.is_out_of_space(), "{still_full:?}");

    // Space returns: the same open store reopens its database and takes writes again.
    std::fs::remove_file(fs.path().join("filler")).unwrap();
    let generation = store.generation();
    let after = store.apply_durable(&batch(acked + 1, SMALL_BYTES));
    eprintln!(
        "after freeing space, the same store: {after:?} (generation {generation} -> {})",
        store.generation()
    );
    let after = after.unwrap();
    assert!(store.generation() > 0, "the store was reopened");
    assert!(!store.is_wedged());
    eprintln!(
        "the batch that failed, sent again: {after:?} (Applied: the reopen lost it; Duplicate: it survived)"
    );
    let next = acked + 2;
    assert_eq!(
        store.apply_durable(&batch(next, SMALL_BYTES)).unwrap(),
        BatchOutcome::Applied { map_version: next }
    );
    check_all_there(store, &options, next, SMALL_BYTES);
}
