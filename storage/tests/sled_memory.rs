//! The sled store's memory stays bounded while its database grows (issue 16 §5): sled 0.34 keeps every
//! value it has written in memory whatever its cache capacity, so without
//! `SledStoreOptions::reopen_after_bytes` a site log written for hours stays whole in memory. (Values
//! longer than `MAX_INLINE_VALUE_BYTES`, such as the server's 25–30-kB site log entries, go to files and
//! never reach sled's memory; the test writes values sled does hold.)
//!
//! One test in its own binary: it counts the live heap through the global allocator, which other tests
//! running beside it would disturb.

use peak_alloc::PeakAlloc;
use storage::{
    DEFAULT_REOPEN_AFTER_BYTES, MAX_INLINE_VALUE_BYTES, MapStore as _, RecordKind, SledStore,
    SledStoreOptions,
};
use support::site_log_version;

mod support;

#[global_allocator]
static HEAP: PeakAlloc = PeakAlloc;

/// Bytes per MiB.
const MIB: usize = 1 << 20;

#[test]
fn a_growing_site_log_does_not_stay_in_memory() {
    const VERSIONS: u64 = 12_000;
    let dir = tempfile::tempdir().expect("tempdir");
    let store = SledStore::open(&SledStoreOptions::at(dir.path().join("db"))).expect("open");
    let before = HEAP.current_usage();
    let mut state = 1u64;
    let mut most = 0usize;
    // 48 MB of site log in the largest values sled holds, flushed every 8 batches (the store reopens at
    // a flush).
    for version in 1..=VERSIONS {
        let mut batch = site_log_version(&mut state, version, MAX_INLINE_VALUE_BYTES);
        batch.for_session(format!("session-{}", version / 1500), version);
        store.apply(&batch).expect("apply");
        if version % 8 == 0 {
            store.flush().expect("flush");
        }
        most = most.max(HEAP.current_usage().saturating_sub(before));
    }
    let bound = usize::try_from(DEFAULT_REOPEN_AFTER_BYTES).expect("bound") + 8 * MIB;
    assert!(
        most < bound,
        "the store held {:.1} MiB after 48 MB written (bound {:.1} MiB, {} reopens)",
        most as f64 / MIB as f64,
        bound as f64 / MIB as f64,
        store.memory_reopens()
    );
    assert!(
        store.memory_reopens() >= 2,
        "{} reopens",
        store.memory_reopens()
    );
    assert_eq!(
        store.generation(),
        0,
        "a reopen that bounds memory loses nothing"
    );
    assert_eq!(store.map_version("site").expect("version"), VERSIONS);
    assert_eq!(
        store
            .scan("site", RecordKind::Trajectory)
            .expect("scan")
            .count(),
        VERSIONS as usize
    );
}
