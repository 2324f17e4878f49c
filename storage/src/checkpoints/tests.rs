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

fn corrupt_checkpoint(store: &MemStore, log_index: u64) {
    let key = checkpoint_key("depot", log_index);
    store.with_raw(|map| {
        let value = map.get_mut(&key).unwrap();
        let last = value.len() - 1;
        value[last] ^= 0x10;
    });
}

#[test]
fn a_corrupt_checkpoint_is_reported_and_compaction_neither_counts_nor_trusts_it() {
    let store = store_with_log(30);
    for index in [10, 20, 30] {
        store
            .put_checkpoint("depot", index, format!("state {index}").as_bytes())
            .unwrap();
    }
    corrupt_checkpoint(&store, 30);
    assert!(matches!(
        store.checkpoint("depot", 30),
        Err(StorageError::Corrupt { .. })
    ));
    // Still listed: the caller sees it, reads it, and falls back.
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [30, 20, 10]);
    let compaction = store
        .compact(
            "depot",
            RecordKind::Trajectory,
            &CheckpointRetention::DEFAULT,
        )
        .unwrap();
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
    let compaction = store
        .compact(
            "depot",
            RecordKind::Trajectory,
            &CheckpointRetention::DEFAULT,
        )
        .unwrap();
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
