//! A batch whose large value's file was written but whose flush failed in sled, then lost by the reopen
//! that follows (the disk filled between the file and sled's write): its value file must not stay behind,
//! named by nothing, until the store is next opened. Without a tmpfs (no root): the process's file-size
//! limit (`RLIMIT_FSIZE`) makes sled's growing log fail (`EFBIG`) while the small value files still fit.
//! Runs alone in its binary: the limit is the process's.

#![allow(
    clippy::unwrap_used,
    reason = "integration test helpers: a failed unwrap is a failed test"
)]
use std::path::Path;

use storage::{
    BatchOutcome, MapStore as _, RecordId, RecordKind, SledStore, SledStoreOptions, WriteBatch,
};

const SITE: &str = "depot";
const VALUE_BYTES: usize = 8 << 10;

fn value(seq: u64) -> Vec<u8> {
    vec![(seq % 251) as u8; VALUE_BYTES]
}

fn batch(seq: u64) -> WriteBatch {
    let mut batch = WriteBatch::new(SITE);
    batch
        .put(RecordKind::Trajectory, seq, value(seq))
        .bump_map_version()
        .for_session("robot-1", seq);
    batch
}

/// Sets the process's file-size limit (`None`: unlimited); a write past it fails with `EFBIG` (the signal
/// it would raise is ignored).
#[allow(
    unsafe_code,
    reason = "setrlimit and signal have no safe wrapper in std"
)]
fn limit_file_size(bytes: Option<u64>) {
    let limit = libc::rlimit {
        rlim_cur: bytes.unwrap_or(libc::RLIM_INFINITY),
        rlim_max: libc::RLIM_INFINITY,
    };
    // SAFETY: plain system calls with valid arguments; SIG_IGN installs no handler code.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
        assert_eq!(libc::setrlimit(libc::RLIMIT_FSIZE, &raw const limit), 0);
    }
}

/// The value files on disk, relative to the value directory.
fn value_files(db: &Path) -> Vec<String> {
    test_support::files_in_site_dirs(&db.join("values"))
}

/// The largest file of sled's (its log grows as it is written).
fn largest_sled_file(db: &Path) -> u64 {
    std::fs::read_dir(db)
        .unwrap()
        .filter_map(|entry| entry.unwrap().metadata().ok())
        .filter(std::fs::Metadata::is_file)
        .map(|meta| meta.len())
        .max()
        .unwrap_or(0)
}

#[test]
fn a_batch_lost_by_the_reopen_after_a_failed_flush_leaves_no_value_file() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("db");
    let options = SledStoreOptions {
        background_flush_ms: 0,
        reopen_interval_ms: 0,
        ..SledStoreOptions::at(&db)
    };
    let store = SledStore::open(&options).unwrap();
    for seq in 1..=4 {
        store.apply_durable(&batch(seq)).unwrap();
    }
    // sled's log may grow a little more; the value files (8 KiB) always fit.
    limit_file_size(Some(largest_sled_file(&db) + (16 << 10)));
    let mut acked = 4;
    let error = loop {
        match store.apply_durable(&batch(acked + 1)) {
            Ok(_) => acked += 1,
            Err(error) => break error,
        }
        assert!(acked < 400, "sled never met the file-size limit");
    };
    eprintln!("acknowledged {acked} batches; then: {error}");
    assert!(
        store.is_wedged(),
        "sled's failure wedges the store: {error}"
    );
    assert_eq!(
        value_files(&db).len(),
        acked as usize + 1,
        "the failed batch's value file was written before sled failed"
    );

    limit_file_size(None);
    let outcome = store.apply_durable(&batch(acked + 1)).unwrap();
    // Applied: the reopen lost it (measured: it does); Duplicate: it survived.
    eprintln!("the failed batch sent again: {outcome:?}");
    assert_eq!(store.generation(), 1, "the store reopened itself");
    let next = acked + 2;
    assert_eq!(
        store.apply_durable(&batch(next)).unwrap(),
        BatchOutcome::Applied { map_version: next }
    );
    for seq in 1..=next {
        assert_eq!(
            store
                .get(SITE, RecordKind::Trajectory, &RecordId::from(seq))
                .unwrap(),
            Some(value(seq)),
            "batch {seq}"
        );
    }
    // One value file per stored value: none left behind by the batch the reopen lost.
    assert_eq!(
        value_files(&db).len(),
        next as usize,
        "{:?}",
        value_files(&db)
    );
    drop(store);
    let store = SledStore::open(&options).unwrap();
    assert_eq!(store.map_version(SITE).unwrap(), next);
    assert_eq!(value_files(&db).len(), next as usize);
}
