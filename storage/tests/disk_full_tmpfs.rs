//! Disk full on a real size-limited filesystem (issue 16 §1): a tmpfs of a few MiB mounted for the test,
//! filled by a filler file, under a [`SledStore`]. What sled does when its disk fills, checked rather
//! than assumed: the failing write is reported as out of space, every batch acknowledged before is
//! intact, and once space returns the same open store takes writes again.
//!
//! Measured (2026-11-24, sled 0.34): sled itself does not recover in place — after one failed flush it
//! refuses every later write with the same error even once space is back, until the database is
//! reopened. [`SledStore`] therefore reopens its database itself (see its docs): the test checks that
//! the open store is wedged while the disk is full, reopens on the first write once space is back
//! (its generation moves), and that nothing acknowledged was lost, in the open store and after a
//! restart.
//!
//! Mounting needs root (`CAP_SYS_ADMIN`), which CI containers may lack, so the test runs only with
//! `EVERMAP_TMPFS_TESTS=1` (and then fails if it cannot mount); CI covers the same paths through
//! `storage::DiskFullStore` (`tests/tests/disk_full.rs`, the agent's uploader tests).
//! `EVERMAP_TMPFS_TESTS=1 cargo nextest run -p storage -E 'test(tmpfs)'`

#![allow(
    clippy::unwrap_used,
    reason = "integration test helpers: a failed unwrap is a failed test"
)]
use storage::{
    BatchOutcome, MapStore as _, RecordId, RecordKind, SledStore, SledStoreOptions, WriteBatch,
};
use test_support::{Tmpfs, fill};

const SITE: &str = "store-tmpfs";
const SIZE_MIB: u64 = 16;
const VALUE_BYTES: usize = 64 << 10;

fn batch(seq: u64) -> WriteBatch {
    let mut batch = WriteBatch::new(SITE);
    batch
        .put(
            RecordKind::Trajectory,
            seq,
            vec![(seq % 251) as u8; VALUE_BYTES],
        )
        .bump_map_version()
        .for_session("robot-1", seq);
    batch
}

#[test]
fn sled_on_a_full_tmpfs_reports_it_keeps_what_it_acknowledged_and_recovers() {
    if std::env::var_os("EVERMAP_TMPFS_TESTS").is_none() {
        eprintln!("skipped: set EVERMAP_TMPFS_TESTS=1 to run it (needs root to mount a tmpfs)");
        return;
    }
    let fs = Tmpfs::mount(SIZE_MIB);
    let db = fs.path().join("db");
    let options = SledStoreOptions {
        background_flush_ms: 0,
        cache_capacity_bytes: 1 << 20,
        reopen_interval_ms: 0,
        ..SledStoreOptions::at(&db)
    };
    let store = SledStore::open(&options).unwrap();
    for seq in 1..=4 {
        store.apply_durable(&batch(seq)).unwrap();
    }
    let filler = fs.path().join("filler");
    fill(&filler, SIZE_MIB);

    // Write until the disk refuses (bounded: the disk is full already).
    let mut acked = 4;
    let error = loop {
        match store.apply_durable(&batch(acked + 1)) {
            Ok(_) => acked += 1,
            Err(e) => break e,
        }
        assert!(
            acked < 4 + (SIZE_MIB << 4),
            "sled never reported the full disk"
        );
    };
    eprintln!("acknowledged {acked} batches; then: {error}");
    assert!(
        error.is_out_of_space(),
        "not reported as a full disk: {error:?}"
    );

    assert!(store.is_wedged(), "a failed write wedges the store");
    // While the disk is full, writes keep failing as out of space (the reopen attempts find no room).
    let still_full = store.apply_durable(&batch(acked + 1)).unwrap_err();
    assert!(still_full.is_out_of_space(), "{still_full:?}");

    // Space returns: the same open store reopens its database and takes writes again.
    std::fs::remove_file(&filler).unwrap();
    let generation = store.generation();
    let after = store.apply_durable(&batch(acked + 1));
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
        store.apply_durable(&batch(next)).unwrap(),
        BatchOutcome::Applied { map_version: next }
    );
    let check = |store: &SledStore| {
        for seq in 1..=next {
            let value = store
                .get(SITE, RecordKind::Trajectory, &RecordId::from(seq))
                .unwrap()
                .unwrap_or_else(|| panic!("batch {seq} lost"));
            assert_eq!(value, vec![(seq % 251) as u8; VALUE_BYTES]);
        }
        assert_eq!(store.map_version(SITE).unwrap(), next);
        assert_eq!(store.last_applied_seq(SITE, "robot-1").unwrap(), Some(next));
    };
    check(&store);
    drop(store);
    // And a restart finds the same.
    check(&SledStore::open(&options).unwrap());
}
