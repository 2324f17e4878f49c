//! A site log's large values do not leak sled blob files (before: they did).
//!
//! sled 0.34 writes a tree page larger than a quarter of its segment (128 KiB by default) as a file of
//! its own under `<db>/blobs/`, and a leaf page holds up to 16 items whatever their size, so a page of
//! 30-kB site log entries is such a blob. When the page is rewritten, sled defers deleting the old blob
//! until its log segment is inactive, and forgets the deferred deletions when the database is dropped: the
//! store reopens it every `reopen_after_bytes` (to bound its memory), so every reopen leaked blobs and a
//! site's disk grew with its age. Large values now go to files of their own (`SledStore`'s module docs),
//! sled holds only small entries, and no page of them comes near the blob size.

use std::path::Path;

use storage::{CheckpointRetention, MapStore as _, RecordKind, SledStore, SledStoreOptions};
use support::site_log_version;

mod support;

/// (files, bytes) under `<db>/blobs`.
fn blobs(db: &Path) -> (usize, u64) {
    let Ok(entries) = std::fs::read_dir(db.join("blobs")) else {
        return (0, 0);
    };
    // sled deletes blobs from its own threads: one may go between the listing and its size.
    entries
        .filter_map(|entry| entry.ok()?.metadata().ok())
        .fold((0, 0), |(files, bytes), meta| {
            (files + 1, bytes + meta.len())
        })
}

/// 1000 versions of a site log of 30-kB entries, written durably as the server does, checkpointed every
/// 15 versions and compacted keeping 2 checkpoints (the newest 15–30 entries stay), with the database
/// reopened every 64 KiB of sled I/O.
///
/// Measured (debug build, default 512-KiB segments), 25 entries (0.75 MB) live at the end:
/// - values in sled (before value files): 398 reopens left 420 blob files of 107 MB, the store 108 MB
///   (without reopens: 34 blob files of 13 MB, at most 42 of 15 MB; the store 15.7 MB);
/// - values in files: 3 reopens, no blob file at any time, the store 1.3 MB (0.75 MB of it value files).
#[test]
fn a_compacted_site_log_leaves_no_blobs_behind() {
    const VERSIONS: u64 = 1000;
    const ENTRY_BYTES: usize = 30_000;
    let dir = tempfile::tempdir().expect("tempdir");
    let db = dir.path().join("db");
    let store = SledStore::open(&SledStoreOptions {
        reopen_after_bytes: 64 << 10,
        ..SledStoreOptions::at(&db)
    })
    .expect("open");
    let mut state = 7_u64;
    let mut most_blobs = (0, 0);
    for version in 1..=VERSIONS {
        let batch = site_log_version(&mut state, version, ENTRY_BYTES);
        store.apply_durable(&batch).expect("apply");
        if version % 15 == 0 {
            store
                .put_checkpoint("site", version, format!("state {version}").as_bytes())
                .expect("checkpoint");
            store
                .compact(
                    "site",
                    RecordKind::Trajectory,
                    &CheckpointRetention::DEFAULT,
                )
                .expect("compact");
        }
        let now = blobs(&db);
        most_blobs = (most_blobs.0.max(now.0), most_blobs.1.max(now.1));
    }
    let entries = store
        .scan("site", RecordKind::Trajectory)
        .expect("scan")
        .count();
    let disk = store.size_on_disk().expect("size");
    let (files, bytes) = blobs(&db);
    eprintln!(
        "{VERSIONS} versions, {} reopens, {entries} log entries kept: blobs {files} files, {bytes} bytes \
         (at most {} files, {} bytes), store {disk} bytes",
        store.memory_reopens(),
        most_blobs.0,
        most_blobs.1
    );
    assert!((15..=30).contains(&entries), "{entries} log entries kept");
    assert!(
        store.memory_reopens() >= 2,
        "{} reopens: the leak needs them",
        store.memory_reopens()
    );
    assert!(
        most_blobs.0 <= 2 && most_blobs.1 <= 256 << 10,
        "sled held {} blob files of {} bytes",
        most_blobs.0,
        most_blobs.1
    );
    assert_eq!(
        store.value_files_bytes().expect("value files"),
        entries as u64 * ENTRY_BYTES as u64,
        "the value files are exactly the live entries"
    );
    assert!(disk < 4 << 20, "the store takes {disk} bytes");
}
