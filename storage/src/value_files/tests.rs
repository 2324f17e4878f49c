//! The steps of value files on the in-memory store, where a crash is a panic at a [`FileStep`] (the
//! behaviour both stores share is in the conformance suite; `tests/kill_nine.rs` kills a real writer).

use super::*;
use crate::envelope;
use crate::{MapStore as _, MemStore, RecordId, RecordKind, WriteBatch};

/// A value that goes to a file (one byte over the inline limit), its bytes derived from `n`.
fn large(n: u8) -> Vec<u8> {
    vec![n; MAX_INLINE_VALUE_BYTES + 1]
}

fn node_key(id: u64) -> Vec<u8> {
    key::record_key(
        "depot",
        RecordKind::Node.as_byte(),
        RecordId::from(id).as_bytes(),
    )
}

fn put(store: &MemStore, id: u64, value: &[u8]) {
    store
        .put("depot", RecordKind::Node, &RecordId::from(id), value)
        .unwrap();
}

fn get(store: &MemStore, id: u64) -> Option<Vec<u8>> {
    store
        .get("depot", RecordKind::Node, &RecordId::from(id))
        .unwrap()
}

/// The file the record `id` names (it names one).
fn file_of(store: &MemStore, id: u64) -> String {
    let key = node_key(id);
    let stored = store.raw_get(&key).unwrap().unwrap();
    entry_of(&key, &stored).unwrap().file
}

fn file_names(store: &MemStore) -> Vec<String> {
    store.values().names().unwrap()
}

/// Runs `step` with a hook that stops it (a panic) at the first step `at` accepts, as a crash there
/// would.
fn crash_at(store: &MemStore, at: fn(FileStep) -> bool, step: impl FnOnce()) {
    store.hook().set(Box::new(move |reached| {
        if at(reached) {
            std::panic::panic_any("crash");
        }
    }));
    let crashed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(step));
    store.hook().set(Box::new(|_| {}));
    assert!(crashed.is_err(), "the step did not crash");
}

#[test]
fn values_over_the_limit_go_to_files_and_the_rest_stays_inline() {
    let store = MemStore::new();
    put(&store, 1, &vec![1; MAX_INLINE_VALUE_BYTES]);
    put(&store, 2, &large(2));
    let stored = |id| store.raw_get(&node_key(id)).unwrap().unwrap();
    assert_eq!(stored(1).len(), 5 + MAX_INLINE_VALUE_BYTES, "sealed inline");
    assert!(!names_a_file(&stored(1)));
    assert!(names_a_file(&stored(2)));
    assert!(
        stored(2).len() < 100,
        "an entry of {} bytes",
        stored(2).len()
    );
    assert_eq!(file_names(&store), [file_of(&store, 2)]);
    assert_eq!(
        file_of(&store, 2),
        format!(
            "depot/0000000000000000-{:08x}.val",
            crc32fast::hash(&[node_key(2), large(2)].concat())
        )
    );
    assert_eq!(get(&store, 2), Some(large(2)));
}

#[test]
fn replaced_and_deleted_values_lose_their_files_at_the_next_flush() {
    let store = MemStore::new();
    put(&store, 1, &large(1));
    let first = file_of(&store, 1);
    put(&store, 1, &large(2));
    assert_ne!(file_of(&store, 1), first, "a new file for each write");
    assert_eq!(
        file_names(&store).len(),
        2,
        "the old file waits for the flush"
    );
    store.flush().unwrap();
    assert_eq!(file_names(&store), [file_of(&store, 1)]);
    // Overwritten inline, deleted, and twice in one batch: only the last write's file stays.
    put(&store, 1, b"small");
    put(&store, 2, &large(3));
    store
        .delete("depot", RecordKind::Node, &RecordId::from(2))
        .unwrap();
    let mut batch = WriteBatch::new("depot");
    batch
        .put(RecordKind::Node, 3, large(4))
        .put(RecordKind::Node, 3, large(5));
    store.apply(&batch).unwrap();
    store.flush().unwrap();
    assert_eq!(file_names(&store), [file_of(&store, 3)]);
    assert_eq!(get(&store, 3), Some(large(5)));
    assert_eq!(get(&store, 1).as_deref(), Some(&b"small"[..]));
}

#[test]
fn refused_and_duplicate_batches_leave_no_file() {
    let store = MemStore::new();
    let mut batch = WriteBatch::new("depot");
    batch.put(RecordKind::Node, 1, large(1)).for_session("r", 1);
    store.apply(&batch).unwrap();
    let duplicate = store.apply(&batch).unwrap();
    assert!(!duplicate.is_applied());
    assert_eq!(file_names(&store), [file_of(&store, 1)]);
    // An invalid batch is refused before any file is written, a site being deleted in the transaction.
    let mut invalid = WriteBatch::new("depot");
    invalid.put(RecordKind::Node, 2, large(2)).put(
        RecordKind::Node,
        RecordId::new(vec![0; 2000]),
        b"".to_vec(),
    );
    assert!(store.apply(&invalid).is_err());
    let site_key = key::site_key("depot");
    store.with_raw(|map| {
        map.insert(site_key.clone(), envelope::seal(&site_key, &[2]));
    });
    assert!(matches!(
        store.put("depot", RecordKind::Node, &RecordId::from(3), &large(3)),
        Err(StorageError::SiteIncomplete { .. })
    ));
    assert_eq!(file_names(&store), [file_of(&store, 1)]);
}

#[test]
fn a_crash_between_the_files_and_the_batch_leaves_orphans_the_next_open_removes() {
    let store = MemStore::new();
    put(&store, 1, &large(1));
    crash_at(
        &store,
        |step| matches!(step, FileStep::ValueFilesDurable { files: 2 }),
        || {
            let mut batch = WriteBatch::new("depot");
            batch
                .put(RecordKind::Node, 2, large(2))
                .put(RecordKind::Node, 3, large(3))
                .put(RecordKind::Node, 4, b"small".to_vec());
            let _ = store.apply(&batch);
        },
    );
    assert_eq!(get(&store, 2), None, "the batch was not applied");
    assert_eq!(file_names(&store).len(), 3, "its files are on disk");
    assert_eq!(remove_orphan_files(&store).unwrap(), 2);
    assert_eq!(file_names(&store), [file_of(&store, 1)]);
    assert_eq!(get(&store, 1), Some(large(1)));
}

#[test]
fn a_crash_between_the_durable_removal_and_the_deletion_leaves_orphans_the_next_open_removes() {
    let store = MemStore::new();
    put(&store, 1, &large(1));
    put(&store, 2, &large(2));
    let kept = file_of(&store, 2);
    store
        .delete("depot", RecordKind::Node, &RecordId::from(1))
        .unwrap();
    crash_at(
        &store,
        |step| matches!(step, FileStep::ValueEntriesRemoved { files: 1 }),
        || {
            let _ = store.flush();
        },
    );
    assert_eq!(get(&store, 1), None);
    assert_eq!(file_names(&store).len(), 2, "the file is not deleted yet");
    // The next flush does not know of it any more (it went with the crash): the sweep does.
    store.flush().unwrap();
    assert_eq!(file_names(&store).len(), 2);
    assert_eq!(remove_orphan_files(&store).unwrap(), 1);
    assert_eq!(file_names(&store), [kept]);
}

#[test]
fn a_file_its_record_names_again_is_kept() {
    // A failed flush, then a reopen that lost the overwrite: the record names the old file again.
    let store = MemStore::new();
    put(&store, 1, &large(1));
    let key = node_key(1);
    let before = store.raw_get(&key).unwrap().unwrap();
    put(&store, 1, &large(2));
    let lost = file_of(&store, 1);
    store.with_raw(|map| {
        map.insert(key.clone(), before);
    });
    store.flush().unwrap();
    assert_eq!(get(&store, 1), Some(large(1)), "its file was kept");
    // The lost write's file is named by nothing: the sweep removes it.
    assert_eq!(file_names(&store).len(), 2);
    assert_eq!(remove_orphan_files(&store).unwrap(), 1);
    assert!(!file_names(&store).contains(&lost));
}

#[test]
fn new_files_are_numbered_past_every_file_found_at_open() {
    let store = MemStore::new();
    put(&store, 1, &large(1));
    assert_eq!(ValueEntry::serial(&file_of(&store, 1)), Some(0));
    // An orphan with a high number and a record naming a missing file with a higher one.
    store
        .values()
        .write("depot", "depot/00000000000000ff-00000000.val", b"orphan")
        .unwrap();
    let key = node_key(2);
    let entry = ValueEntry::of("depot", &key, 0x1000, &large(2));
    store.with_raw(|map| {
        map.insert(key.clone(), entry.seal(&key));
    });
    assert_eq!(remove_orphan_files(&store).unwrap(), 1);
    put(&store, 3, &large(3));
    assert_eq!(ValueEntry::serial(&file_of(&store, 3)), Some(0x1001));
    // The record whose file is missing reads as corrupt, naming it.
    let error = store
        .get("depot", RecordKind::Node, &RecordId::from(2))
        .unwrap_err();
    assert!(
        error.to_string().contains(&entry.file) && error.to_string().contains("missing"),
        "{error}"
    );
}
