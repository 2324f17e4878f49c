use super::*;
use crate::{MapStore as _, MemStore, RecordId, WriteBatch};

fn store_with_log(entries: u64) -> MemStore {
    let store = MemStore::new();
    for index in 1..=entries {
        let mut batch = WriteBatch::new("depot");
        batch
            .put(RecordKind::Trajectory, index, b"entry".to_vec())
            .bump_map_version();
        store.apply(&batch).unwrap();
    }
    store
}

/// Stores `state <index>` as the checkpoint at each index.
fn put_states(store: &MemStore, indexes: &[u64]) {
    for index in indexes {
        store
            .put_checkpoint("depot", *index, format!("state {index}").as_bytes())
            .unwrap();
    }
}

/// Compacts the site's log with the default retention.
fn compact(store: &MemStore) -> Compaction {
    store
        .compact(
            "depot",
            RecordKind::Trajectory,
            &CheckpointRetention::DEFAULT,
        )
        .unwrap()
}

/// The file of the site's checkpoint at `log_index` (there is one).
fn file_of(store: &MemStore, log_index: u64) -> String {
    let key = entry_key("depot", log_index);
    let stored = store.raw_get(&key).unwrap().unwrap();
    decode_entry(&key, &stored).unwrap().file
}

fn corrupt_checkpoint(store: &MemStore, log_index: u64) {
    let file = file_of(store, log_index);
    store.files().with_files(|files| {
        let bytes = files.get_mut(&file).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 0x10;
    });
}

fn file_names(store: &MemStore) -> Vec<String> {
    let mut names = Vec::new();
    store
        .files()
        .with_files(|files| names.extend(files.keys().cloned()));
    names
}

/// Runs `step` with a hook that stops it (a panic) at `at`, as a crash there would.
fn crash_at(store: &MemStore, at: FileStep, step: impl FnOnce()) {
    store.hook().set(Box::new(move |reached| {
        if reached == at {
            std::panic::panic_any("crash");
        }
    }));
    let crashed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(step));
    store.hook().set(Box::new(|_| {}));
    assert!(crashed.is_err(), "the step did not reach {at:?}");
}

#[test]
fn a_corrupt_checkpoint_is_reported_and_compaction_neither_counts_nor_trusts_it() {
    let store = store_with_log(30);
    put_states(&store, &[10, 20, 30]);
    corrupt_checkpoint(&store, 30);
    assert!(matches!(
        store.checkpoint("depot", 30),
        Err(StorageError::Corrupt { .. })
    ));
    // Still listed: the caller sees it, reads it, and falls back.
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [30, 20, 10]);
    let compaction = compact(&store);
    // Kept: the two newest that verify (20 and 10), so the log after 10 stays.
    assert_eq!(compaction.checkpoints_removed, 0);
    assert_eq!(compaction.log_compacted_through, 10);
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [30, 20, 10]);
    let log: Vec<u64> = store
        .scan("depot", RecordKind::Trajectory)
        .unwrap()
        .map(|r| r.unwrap().0.as_u64().unwrap())
        .collect();
    assert_eq!(log, (11..=30).collect::<Vec<_>>());
    assert_eq!(
        store
            .get("depot", RecordKind::Trajectory, &RecordId::from(11))
            .unwrap()
            .as_deref(),
        Some(&b"entry"[..])
    );
}

#[test]
fn with_one_checkpoint_that_verifies_no_log_entry_goes() {
    let store = store_with_log(12);
    store.put_checkpoint("depot", 6, b"state 6").unwrap();
    store.put_checkpoint("depot", 12, b"state 12").unwrap();
    corrupt_checkpoint(&store, 6);
    let compaction = compact(&store);
    assert_eq!(compaction.log_entries_removed, 0);
    assert_eq!(compaction.log_compacted_through, 0);
    assert_eq!(
        store.scan("depot", RecordKind::Trajectory).unwrap().count(),
        12
    );
}

#[test]
fn retention_needs_two_checkpoints() {
    assert!(CheckpointRetention::DEFAULT.validate().is_ok());
    let error = CheckpointRetention {
        checkpoints: 1,
        log_entries: 0,
    }
    .validate()
    .unwrap_err();
    assert!(error.to_string().contains("at least 2"), "{error}");
}

#[test]
fn a_missing_file_is_a_corrupt_checkpoint_named_by_its_file() {
    let store = store_with_log(20);
    put_states(&store, &[10, 20]);
    let file = file_of(&store, 20);
    store.files().with_files(|files| {
        files.remove(&file);
    });
    let error = store.checkpoint("depot", 20).unwrap_err();
    assert!(matches!(error, StorageError::Corrupt { .. }), "{error}");
    let message = error.to_string();
    assert!(
        message.contains("depot/checkpoint-file/") && message.contains(&file),
        "{message}"
    );
    assert!(message.contains("missing"), "{message}");
    // Listed, not counted: one checkpoint verifies, so no log entry goes.
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [20, 10]);
    let compaction = compact(&store);
    assert_eq!(compaction.log_entries_removed, 0);
    // A damaged file names itself too.
    corrupt_checkpoint(&store, 10);
    let error = store.checkpoint("depot", 10).unwrap_err().to_string();
    assert!(
        error.contains("CRC32 mismatch") && error.contains(&file_of(&store, 10)),
        "{error}"
    );
}

#[test]
fn a_crash_between_the_file_and_its_entry_leaves_an_orphan_the_next_open_removes() {
    let store = store_with_log(20);
    store.put_checkpoint("depot", 10, b"state 10").unwrap();
    crash_at(
        &store,
        FileStep::CheckpointFileDurable { log_index: 20 },
        || {
            let _ = store.put_checkpoint("depot", 20, b"state 20");
        },
    );
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [10]);
    assert_eq!(store.checkpoint("depot", 20).unwrap(), None);
    assert_eq!(file_names(&store).len(), 2, "the orphan is on disk");
    assert_eq!(remove_orphan_files(&store).unwrap(), 1);
    assert_eq!(file_names(&store), [file_of(&store, 10)]);
    // Written again, as a restarted server does.
    store.put_checkpoint("depot", 20, b"state 20").unwrap();
    assert_eq!(
        store.checkpoint("depot", 20).unwrap().as_deref(),
        Some(&b"state 20"[..])
    );
    assert_eq!(remove_orphan_files(&store).unwrap(), 0);
}

#[test]
fn a_crash_between_removing_entries_and_their_files_leaves_orphans_the_next_open_removes() {
    let store = store_with_log(30);
    put_states(&store, &[10, 20, 30]);
    crash_at(
        &store,
        FileStep::CheckpointIndexRemoved { log_index: 10 },
        || {
            compact(&store);
        },
    );
    // The entry and the log are compacted, the file is not deleted yet.
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [30, 20]);
    assert_eq!(
        store.scan("depot", RecordKind::Trajectory).unwrap().count(),
        10
    );
    assert_eq!(file_names(&store).len(), 3);
    assert_eq!(remove_orphan_files(&store).unwrap(), 1);
    let mut kept = vec![file_of(&store, 20), file_of(&store, 30)];
    kept.sort();
    assert_eq!(file_names(&store), kept);
    for index in [20, 30] {
        assert_eq!(
            store.checkpoint("depot", index).unwrap(),
            Some(format!("state {index}").into_bytes())
        );
    }
}

#[test]
fn compaction_and_rewrites_delete_the_files_they_unname_and_refusals_write_none() {
    let store = store_with_log(40);
    put_states(&store, &[10, 20, 30, 40]);
    compact(&store);
    let mut kept = vec![file_of(&store, 30), file_of(&store, 40)];
    kept.sort();
    assert_eq!(file_names(&store), kept);
    // Rewritten with other bytes: a new file, the old one deleted.
    store
        .put_checkpoint("depot", 40, b"state 40, again")
        .unwrap();
    assert_ne!(file_of(&store, 40), kept[1]);
    assert_eq!(file_names(&store).len(), 2);
    // Rewritten with the same bytes: the same file.
    let same = file_of(&store, 40);
    store
        .put_checkpoint("depot", 40, b"state 40, again")
        .unwrap();
    assert_eq!(file_of(&store, 40), same);
    assert_eq!(file_names(&store).len(), 2);
    // Refused: no file written.
    assert!(store.put_checkpoint("depot", 41, b"ahead").is_err());
    assert!(store.put_checkpoint("yard", 1, b"unknown site").is_err());
    assert_eq!(file_names(&store).len(), 2);
    // Deleting the site deletes its files.
    store.delete_site("depot").unwrap();
    assert!(file_names(&store).is_empty());
}

#[test]
fn inline_checkpoints_of_earlier_builds_are_read_compacted_exported_and_replaced() {
    let store = store_with_log(30);
    let inline = |index: u64| {
        let key = inline_key("depot", index);
        let sealed = envelope::seal(&key, format!("inline {index}").as_bytes());
        store.with_raw(|map| {
            map.insert(key, sealed);
        });
    };
    inline(10);
    inline(20);
    store.put_checkpoint("depot", 30, b"state 30").unwrap();
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [30, 20, 10]);
    assert_eq!(
        store.checkpoint("depot", 20).unwrap().as_deref(),
        Some(&b"inline 20"[..])
    );
    // Exported as checkpoints, imported into files.
    let mut archive = Vec::new();
    store.export_site("depot", &mut archive).unwrap();
    store.import_site("annex", &mut archive.as_slice()).unwrap();
    assert_eq!(store.checkpoint_indexes("annex").unwrap(), [30, 20, 10]);
    assert_eq!(
        store.checkpoint("annex", 10).unwrap().as_deref(),
        Some(&b"inline 10"[..])
    );
    assert!(
        store.raw_get(&inline_key("annex", 10)).unwrap().is_none(),
        "imported into a file"
    );
    assert_eq!(
        file_names(&store)
            .iter()
            .filter(|name| name.starts_with("annex/"))
            .count(),
        3
    );
    // Compacted like the others; a new checkpoint at an inline one's position replaces it.
    let compaction = compact(&store);
    assert_eq!(compaction.checkpoints_removed, 1);
    assert_eq!(compaction.log_compacted_through, 20);
    store.put_checkpoint("depot", 20, b"state 20").unwrap();
    assert!(store.raw_get(&inline_key("depot", 20)).unwrap().is_none());
    assert_eq!(
        store.checkpoint("depot", 20).unwrap().as_deref(),
        Some(&b"state 20"[..])
    );
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [30, 20]);
}
