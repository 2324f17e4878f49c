//! The behaviour every [`MapStore`] must show, as one generic suite that each store's tests run
//! (`mem_store.rs`, `sled_store.rs`). `run_all` returns how many cases ran, which the callers check against
//! [`MIN_CASES`] so the suite cannot pass by running nothing. The cases on large values look at the value
//! files and damage them through the stores' private [`RawKv`] interface, which both implement.

use std::collections::BTreeSet;
use std::thread;

use crate::envelope;
use crate::key;
use crate::raw_kv::RawKv;
use crate::value_files;
use crate::{
    BatchOutcome, CheckpointRetention, MAX_ID_BYTES, MAX_INLINE_VALUE_BYTES, MapStore, RecordId,
    RecordKind, StorageError, WriteBatch,
};

/// Cases `run_all` must run.
pub(crate) const MIN_CASES: usize = 22;

type Case<S> = fn(&S);

/// Runs every case on a fresh store from `make`; returns the number of cases run.
pub(crate) fn run_all<S: MapStore + RawKv>(make: &dyn Fn() -> S) -> usize {
    let cases: [(&str, Case<S>); 22] = [
        ("put_get_overwrite_delete", put_get_overwrite_delete),
        (
            "scan_is_per_site_and_kind_in_id_order",
            scan_is_per_site_and_kind_in_id_order,
        ),
        ("invalid_batch_writes_nothing", invalid_batch_writes_nothing),
        (
            "map_version_is_per_site_and_monotonic",
            map_version_is_per_site_and_monotonic,
        ),
        (
            "session_sequence_applies_exactly_once",
            session_sequence_applies_exactly_once,
        ),
        ("list_and_delete_sites", list_and_delete_sites),
        ("export_import_round_trip", export_import_round_trip),
        (
            "import_refuses_non_empty_site",
            import_refuses_non_empty_site,
        ),
        (
            "corrupt_or_truncated_import_writes_nothing",
            corrupt_or_truncated_import_writes_nothing,
        ),
        ("values_of_any_size", values_of_any_size),
        ("names_and_ids_are_validated", names_and_ids_are_validated),
        ("durable_apply_and_flush", durable_apply_and_flush),
        (
            "concurrent_bumps_are_serialized",
            concurrent_bumps_are_serialized,
        ),
        (
            "checkpoints_are_stored_under_their_log_position",
            checkpoints_are_stored_under_their_log_position,
        ),
        (
            "compaction_keeps_the_log_after_the_older_kept_checkpoint",
            compaction_keeps_the_log_after_the_older_kept_checkpoint,
        ),
        (
            "export_import_carries_checkpoints",
            export_import_carries_checkpoints,
        ),
        (
            "large_values_are_kept_apart_and_freed",
            large_values_are_kept_apart_and_freed,
        ),
        (
            "compaction_frees_the_files_of_large_log_entries",
            compaction_frees_the_files_of_large_log_entries,
        ),
        (
            "export_import_carries_large_values_inline",
            export_import_carries_large_values_inline,
        ),
        (
            "a_missing_or_damaged_value_file_reads_as_corrupt_naming_it",
            a_missing_or_damaged_value_file_reads_as_corrupt_naming_it,
        ),
        (
            "orphan_value_files_are_removed_at_open",
            orphan_value_files_are_removed_at_open,
        ),
        (
            "large_values_stored_inline_by_earlier_builds_still_work",
            large_values_stored_inline_by_earlier_builds_still_work,
        ),
    ];
    let mut ran = 0;
    for (name, case) in cases {
        let store = make();
        eprintln!("conformance case {name}");
        case(&store);
        ran += 1;
    }
    ran
}

fn id(n: u64) -> RecordId {
    RecordId::from_u64(n)
}

fn scan_all(store: &impl MapStore, site: &str, kind: RecordKind) -> Vec<(RecordId, Vec<u8>)> {
    store
        .scan(site, kind)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap()
}

fn put_get_overwrite_delete(store: &impl MapStore) {
    assert_eq!(
        store.get("depot", RecordKind::Submap, &id(1)).unwrap(),
        None
    );
    assert!(
        store
            .put("depot", RecordKind::Submap, &id(1), b"first")
            .unwrap()
            .is_applied()
    );
    assert_eq!(
        store
            .get("depot", RecordKind::Submap, &id(1))
            .unwrap()
            .unwrap(),
        b"first"
    );
    store
        .put("depot", RecordKind::Submap, &id(1), b"second")
        .unwrap();
    assert_eq!(
        store
            .get("depot", RecordKind::Submap, &id(1))
            .unwrap()
            .unwrap(),
        b"second"
    );
    assert_eq!(
        store.get("depot", RecordKind::Node, &id(1)).unwrap(),
        None,
        "kinds are separate"
    );
    assert_eq!(
        store.get("other", RecordKind::Submap, &id(1)).unwrap(),
        None,
        "sites are separate"
    );
    store.delete("depot", RecordKind::Submap, &id(1)).unwrap();
    assert_eq!(
        store.get("depot", RecordKind::Submap, &id(1)).unwrap(),
        None
    );
    store.delete("depot", RecordKind::Submap, &id(1)).unwrap();

    // Later ops of a batch win.
    let mut batch = WriteBatch::new("depot");
    batch
        .put(RecordKind::Node, 5, b"a".to_vec())
        .delete(RecordKind::Node, 5)
        .put(RecordKind::Node, 6, b"x".to_vec());
    batch.put(RecordKind::Node, 6, b"y".to_vec());
    store.apply(&batch).unwrap();
    assert_eq!(store.get("depot", RecordKind::Node, &id(5)).unwrap(), None);
    assert_eq!(
        store
            .get("depot", RecordKind::Node, &id(6))
            .unwrap()
            .unwrap(),
        b"y"
    );
}

fn scan_is_per_site_and_kind_in_id_order(store: &impl MapStore) {
    let mut batch = WriteBatch::new("a");
    for n in [300_u64, 2, 70_000, 1] {
        batch.put(RecordKind::Node, n, n.to_string().into_bytes());
    }
    batch.put(RecordKind::Submap, 9, b"submap".to_vec());
    store.apply(&batch).unwrap();
    let mut other = WriteBatch::new("ab");
    other.put(RecordKind::Node, 4, b"other site".to_vec());
    store.apply(&other).unwrap();

    let nodes = scan_all(store, "a", RecordKind::Node);
    let ids: Vec<u64> = nodes.iter().map(|(id, _)| id.as_u64().unwrap()).collect();
    assert_eq!(ids, [1, 2, 300, 70_000]);
    assert!(
        nodes
            .iter()
            .all(|(id, value)| id.as_u64().unwrap().to_string().into_bytes() == *value)
    );
    assert_eq!(
        scan_all(store, "a", RecordKind::Submap),
        [(id(9), b"submap".to_vec())]
    );
    assert_eq!(
        scan_all(store, "ab", RecordKind::Node),
        [(id(4), b"other site".to_vec())]
    );
    assert!(scan_all(store, "a", RecordKind::Constraint).is_empty());
    assert!(scan_all(store, "nowhere", RecordKind::Node).is_empty());
}

fn invalid_batch_writes_nothing(store: &impl MapStore) {
    let mut batch = WriteBatch::new("depot");
    batch
        .put(RecordKind::Node, 1, b"ok".to_vec())
        .bump_map_version()
        .for_session("robot", 1);
    batch.put(
        RecordKind::Node,
        RecordId::new(vec![0; MAX_ID_BYTES + 1]),
        b"bad id".to_vec(),
    );
    assert!(matches!(
        store.apply(&batch),
        Err(StorageError::TooLarge { what: "id", .. })
    ));
    assert_eq!(store.get("depot", RecordKind::Node, &id(1)).unwrap(), None);
    assert_eq!(store.map_version("depot").unwrap(), 0);
    assert_eq!(store.last_applied_seq("depot", "robot").unwrap(), None);
    assert!(store.list_sites().unwrap().is_empty());
}

fn map_version_is_per_site_and_monotonic(store: &impl MapStore) {
    assert_eq!(store.map_version("depot").unwrap(), 0);
    let mut plain = WriteBatch::new("depot");
    plain.put(RecordKind::SiteMeta, "name", b"Depot".to_vec());
    assert_eq!(
        store.apply(&plain).unwrap(),
        BatchOutcome::Applied { map_version: 0 }
    );
    for expected in 1..=5 {
        let mut bump = WriteBatch::new("depot");
        bump.put(RecordKind::Submap, expected, vec![1; 3])
            .bump_map_version();
        assert_eq!(
            store.apply(&bump).unwrap(),
            BatchOutcome::Applied {
                map_version: expected
            }
        );
    }
    assert_eq!(
        store.apply(&plain).unwrap(),
        BatchOutcome::Applied { map_version: 5 }
    );
    assert_eq!(store.map_version("depot").unwrap(), 5);
    assert_eq!(store.map_version("yard").unwrap(), 0);
    let mut yard = WriteBatch::new("yard");
    yard.bump_map_version();
    assert_eq!(
        store.apply(&yard).unwrap(),
        BatchOutcome::Applied { map_version: 1 }
    );
    assert_eq!(store.map_version("depot").unwrap(), 5);
}

fn session_sequence_applies_exactly_once(store: &impl MapStore) {
    let upload = |session: &str, seq: u64, record: u64| {
        let mut batch = WriteBatch::new("depot");
        batch
            .put(RecordKind::Node, record, seq.to_le_bytes().to_vec())
            .bump_map_version()
            .for_session(session, seq);
        store.apply(&batch).unwrap()
    };
    assert_eq!(store.last_applied_seq("depot", "r1").unwrap(), None);
    assert_eq!(
        upload("r1", 1, 10),
        BatchOutcome::Applied { map_version: 1 }
    );
    assert_eq!(
        upload("r1", 1, 11),
        BatchOutcome::Duplicate { last_applied: 1 }
    );
    assert_eq!(
        store.get("depot", RecordKind::Node, &id(11)).unwrap(),
        None,
        "a duplicate writes nothing"
    );
    assert_eq!(
        store.map_version("depot").unwrap(),
        1,
        "a duplicate does not bump"
    );
    assert_eq!(
        upload("r1", 3, 12),
        BatchOutcome::Applied { map_version: 2 },
        "gaps are allowed"
    );
    assert_eq!(
        upload("r1", 2, 13),
        BatchOutcome::Duplicate { last_applied: 3 }
    );
    assert_eq!(
        upload("r2", 1, 14),
        BatchOutcome::Applied { map_version: 3 },
        "sessions are independent"
    );
    assert_eq!(store.last_applied_seq("depot", "r1").unwrap(), Some(3));
    assert_eq!(store.last_applied_seq("depot", "r2").unwrap(), Some(1));
    assert_eq!(
        store.last_applied_seq("yard", "r1").unwrap(),
        None,
        "sites are independent"
    );
}

fn list_and_delete_sites(store: &impl MapStore) {
    assert!(store.list_sites().unwrap().is_empty());
    for site in ["yard", "depot", "dock"] {
        let mut batch = WriteBatch::new(site);
        for n in 0..700 {
            batch.put(RecordKind::Node, n, vec![7; 10]);
        }
        batch.bump_map_version().for_session("r", 5);
        store.apply(&batch).unwrap();
    }
    assert_eq!(store.list_sites().unwrap(), ["depot", "dock", "yard"]);
    store.delete_site("dock").unwrap();
    assert_eq!(store.list_sites().unwrap(), ["depot", "yard"]);
    assert!(scan_all(store, "dock", RecordKind::Node).is_empty());
    assert_eq!(store.map_version("dock").unwrap(), 0);
    assert_eq!(store.last_applied_seq("dock", "r").unwrap(), None);
    assert_eq!(scan_all(store, "depot", RecordKind::Node).len(), 700);
    store.delete_site("never-existed").unwrap();
    // A deleted site can be used again from scratch.
    let mut batch = WriteBatch::new("dock");
    batch.bump_map_version();
    assert_eq!(
        store.apply(&batch).unwrap(),
        BatchOutcome::Applied { map_version: 1 }
    );
}

/// A site with every kind, counters, and enough records to span several import transactions.
fn fill_sample_site(store: &impl MapStore, site: &str) {
    for chunk in 0..3_u64 {
        let mut batch = WriteBatch::new(site);
        for n in 0..600 {
            let record = chunk * 600 + n;
            batch.put(
                RecordKind::Node,
                record,
                format!("node {record}").into_bytes(),
            );
        }
        batch.bump_map_version().for_session("robot-a", chunk + 1);
        store.apply(&batch).unwrap();
    }
    let mut batch = WriteBatch::new(site);
    for kind in RecordKind::ALL {
        batch.put(kind, "k", format!("{kind} value").into_bytes());
    }
    batch.put(RecordKind::Submap, 1, vec![0xAB; 200_000]).put(
        RecordKind::Constraint,
        "empty",
        Vec::new(),
    );
    batch.bump_map_version().for_session("robot-b", 42);
    store.apply(&batch).unwrap();
}

fn site_contents(store: &impl MapStore, site: &str) -> Vec<(RecordKind, RecordId, Vec<u8>)> {
    RecordKind::ALL
        .into_iter()
        .flat_map(|kind| {
            scan_all(store, site, kind)
                .into_iter()
                .map(move |(id, value)| (kind, id, value))
        })
        .collect()
}

fn export_import_round_trip(store: &impl MapStore) {
    fill_sample_site(store, "source");
    let mut archive = Vec::new();
    let exported = store.export_site("source", &mut archive).unwrap();
    // 1800 nodes + 7 kinds + submap + constraint, + map version + 2 session counters.
    assert_eq!(exported.records, 1800 + 7 + 2 + 3);
    let imported = store.import_site("copy", &mut archive.as_slice()).unwrap();
    assert_eq!(imported, exported);
    assert_eq!(site_contents(store, "copy"), site_contents(store, "source"));
    assert_eq!(site_contents(store, "copy").len(), 1809);
    assert_eq!(store.map_version("copy").unwrap(), 4);
    assert_eq!(store.last_applied_seq("copy", "robot-a").unwrap(), Some(3));
    assert_eq!(store.last_applied_seq("copy", "robot-b").unwrap(), Some(42));
    assert_eq!(store.list_sites().unwrap(), ["copy", "source"]);
    // The copy exports to the same records (only the site id in the begin chunk differs).
    let mut again = Vec::new();
    store.export_site("copy", &mut again).unwrap();
    let header = 8 + 2 + 8 + 1; // magic, version, chunk frame, begin tag
    assert_eq!(
        again[header + "copy".len()..],
        archive[header + "source".len()..]
    );
    assert!(matches!(
        store.export_site("nowhere", &mut Vec::new()),
        Err(StorageError::SiteNotFound { .. })
    ));
}

fn import_refuses_non_empty_site(store: &impl MapStore) {
    fill_sample_site(store, "source");
    let mut archive = Vec::new();
    store.export_site("source", &mut archive).unwrap();
    let before = site_contents(store, "source");
    assert!(matches!(
        store.import_site("source", &mut archive.as_slice()),
        Err(StorageError::SiteNotEmpty { .. })
    ));
    assert_eq!(
        site_contents(store, "source"),
        before,
        "a refused import leaves the site alone"
    );
}

fn corrupt_or_truncated_import_writes_nothing(store: &impl MapStore) {
    fill_sample_site(store, "source");
    let mut archive = Vec::new();
    store.export_site("source", &mut archive).unwrap();
    let mut flipped_late = archive.clone();
    let late = archive.len() - 1000; // inside the last records: earlier chunks were already written
    flipped_late[late] ^= 0x01;
    let truncated = &archive[..archive.len() - 17]; // exactly the end chunk missing
    let mut trailing = archive.clone();
    trailing.extend_from_slice(b"junk");
    let mut bad_magic = archive.clone();
    bad_magic[0] = b'X';
    for (what, bad) in [
        ("flipped byte", flipped_late.as_slice()),
        ("truncated", truncated),
        ("trailing bytes", trailing.as_slice()),
        ("bad magic", bad_magic.as_slice()),
        ("empty", &[][..]),
    ] {
        let mut input = bad;
        let error = store.import_site("copy", &mut input).unwrap_err();
        assert!(
            matches!(error, StorageError::BadArchive { .. }),
            "{what}: {error}"
        );
        assert!(
            site_contents(store, "copy").is_empty(),
            "{what}: records left behind"
        );
        assert_eq!(store.map_version("copy").unwrap(), 0, "{what}");
        assert_eq!(
            store.last_applied_seq("copy", "robot-a").unwrap(),
            None,
            "{what}"
        );
        assert_eq!(store.list_sites().unwrap(), ["source"], "{what}");
    }
    // The site is usable afterwards: a good import succeeds.
    store.import_site("copy", &mut archive.as_slice()).unwrap();
    assert_eq!(site_contents(store, "copy"), site_contents(store, "source"));
}

fn values_of_any_size(store: &impl MapStore) {
    let big: Vec<u8> = (0..3_000_000_u32).map(|n| (n % 251) as u8).collect();
    store
        .put("depot", RecordKind::Submap, &id(1), &big)
        .unwrap();
    store.put("depot", RecordKind::Submap, &id(2), &[]).unwrap();
    assert_eq!(
        store
            .get("depot", RecordKind::Submap, &id(1))
            .unwrap()
            .unwrap(),
        big
    );
    assert_eq!(
        store
            .get("depot", RecordKind::Submap, &id(2))
            .unwrap()
            .unwrap(),
        Vec::<u8>::new()
    );
    let max_id = RecordId::new(vec![0xFF; MAX_ID_BYTES]);
    store.put("depot", RecordKind::Node, &max_id, b"v").unwrap();
    assert_eq!(
        store
            .get("depot", RecordKind::Node, &max_id)
            .unwrap()
            .unwrap(),
        b"v"
    );
}

fn names_and_ids_are_validated(store: &impl MapStore) {
    assert!(matches!(
        store.put("", RecordKind::Node, &id(1), b"v"),
        Err(StorageError::InvalidSiteId { .. })
    ));
    assert!(matches!(
        store.get("a\u{0}b", RecordKind::Node, &id(1)),
        Err(StorageError::InvalidSiteId { .. })
    ));
    let mut batch = WriteBatch::new("depot");
    batch.for_session("", 1);
    assert!(matches!(
        store.apply(&batch),
        Err(StorageError::InvalidSessionId { .. })
    ));
    assert!(matches!(
        store.last_applied_seq("depot", ""),
        Err(StorageError::InvalidSessionId { .. })
    ));
    let long_site = "s".repeat(255);
    store
        .put(&long_site, RecordKind::Node, &id(1), b"v")
        .unwrap();
    assert_eq!(store.list_sites().unwrap(), [long_site]);
}

fn durable_apply_and_flush(store: &impl MapStore) {
    let mut batch = WriteBatch::new("depot");
    batch
        .put(RecordKind::Outbox, 1, b"upload".to_vec())
        .bump_map_version();
    assert_eq!(
        store.apply_durable(&batch).unwrap(),
        BatchOutcome::Applied { map_version: 1 }
    );
    store.flush().unwrap();
    assert_eq!(
        store
            .get("depot", RecordKind::Outbox, &id(1))
            .unwrap()
            .unwrap(),
        b"upload"
    );
}

fn concurrent_bumps_are_serialized(store: &impl MapStore) {
    const THREADS: u64 = 4;
    const BUMPS: u64 = 40;
    let versions: BTreeSet<u64> = thread::scope(|scope| {
        let workers: Vec<_> = (0..THREADS)
            .map(|worker| {
                thread::Builder::new()
                    .name(format!("bumper-{worker}"))
                    .spawn_scoped(scope, move || {
                        (0..BUMPS)
                            .map(|n| {
                                let mut batch = WriteBatch::new("depot");
                                batch
                                    .put(RecordKind::Node, worker * 1000 + n, vec![1])
                                    .bump_map_version();
                                match store.apply(&batch).unwrap() {
                                    BatchOutcome::Applied { map_version } => map_version,
                                    BatchOutcome::Duplicate { .. } => unreachable!("no session"),
                                }
                            })
                            .collect::<Vec<_>>()
                    })
                    .unwrap()
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|worker| worker.join().unwrap())
            .collect()
    });
    assert_eq!(
        versions,
        (1..=THREADS * BUMPS).collect(),
        "every bump got its own version"
    );
    assert_eq!(store.map_version("depot").unwrap(), THREADS * BUMPS);
    assert_eq!(
        scan_all(store, "depot", RecordKind::Node).len() as u64,
        THREADS * BUMPS
    );
}

/// A site log of `entries` entries under `Trajectory` (id = index = map version), as the server writes it.
fn write_log(store: &impl MapStore, site: &str, entries: std::ops::RangeInclusive<u64>) {
    for index in entries {
        let mut batch = WriteBatch::new(site);
        batch
            .put(
                RecordKind::Trajectory,
                index,
                format!("entry {index}").into_bytes(),
            )
            .bump_map_version();
        assert_eq!(
            store.apply_durable(&batch).unwrap(),
            BatchOutcome::Applied { map_version: index }
        );
    }
}

fn log_indexes(store: &impl MapStore, site: &str) -> Vec<u64> {
    scan_all(store, site, RecordKind::Trajectory)
        .into_iter()
        .map(|(id, _)| id.as_u64().unwrap())
        .collect()
}

fn checkpoints_are_stored_under_their_log_position(store: &impl MapStore) {
    assert!(matches!(
        store.put_checkpoint("depot", 0, b"state"),
        Err(StorageError::SiteNotFound { .. })
    ));
    write_log(store, "depot", 1..=5);
    assert!(matches!(
        store.put_checkpoint("depot", 6, b"state 6"),
        Err(StorageError::CheckpointAhead {
            log_index: 6,
            map_version: 5,
            ..
        })
    ));
    store.put_checkpoint("depot", 2, b"state 2").unwrap();
    store.put_checkpoint("depot", 5, b"state 5").unwrap();
    store.put_checkpoint("depot", 300, b"").unwrap_err();
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [5, 2]);
    assert_eq!(
        store.checkpoint("depot", 5).unwrap().as_deref(),
        Some(&b"state 5"[..])
    );
    assert_eq!(store.checkpoint("depot", 3).unwrap(), None);
    // Rewritten at its position: the new bytes replace the old.
    store.put_checkpoint("depot", 5, b"state 5, again").unwrap();
    assert_eq!(
        store.checkpoint("depot", 5).unwrap().as_deref(),
        Some(&b"state 5, again"[..])
    );
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [5, 2]);
    assert!(store.checkpoint_indexes("other").unwrap().is_empty());
    // Checkpoints are not records of any kind: scans and versions do not see them.
    assert_eq!(log_indexes(store, "depot"), [1, 2, 3, 4, 5]);
    assert_eq!(store.map_version("depot").unwrap(), 5);
    store.delete_site("depot").unwrap();
    assert!(store.checkpoint_indexes("depot").unwrap().is_empty());
}

fn compaction_keeps_the_log_after_the_older_kept_checkpoint(store: &impl MapStore) {
    let retention = CheckpointRetention::DEFAULT;
    write_log(store, "depot", 1..=30);
    // One checkpoint: an unreadable one would have nothing to fall back to but the whole log.
    store.put_checkpoint("depot", 10, b"state 10").unwrap();
    let compaction = store
        .compact("depot", RecordKind::Trajectory, &retention)
        .unwrap();
    assert_eq!(compaction.log_entries_removed, 0);
    assert_eq!(log_indexes(store, "depot").len(), 30);
    store.put_checkpoint("depot", 20, b"state 20").unwrap();
    store.put_checkpoint("depot", 25, b"state 25").unwrap();
    let compaction = store
        .compact("depot", RecordKind::Trajectory, &retention)
        .unwrap();
    assert_eq!(compaction.checkpoints_removed, 1);
    assert_eq!(compaction.log_entries_removed, 20);
    assert_eq!(compaction.log_compacted_through, 20);
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [25, 20]);
    assert_eq!(log_indexes(store, "depot"), (21..=30).collect::<Vec<_>>());
    // Again: nothing more to do. With entries kept for audit, fewer go.
    let again = store
        .compact("depot", RecordKind::Trajectory, &retention)
        .unwrap();
    assert_eq!(
        (again.checkpoints_removed, again.log_entries_removed),
        (0, 0)
    );
    write_log(store, "depot", 31..=40);
    store.put_checkpoint("depot", 40, b"state 40").unwrap();
    let audit = CheckpointRetention {
        checkpoints: 2,
        log_entries: 3,
    };
    let compaction = store
        .compact("depot", RecordKind::Trajectory, &audit)
        .unwrap();
    assert_eq!(compaction.log_compacted_through, 22);
    assert_eq!(log_indexes(store, "depot"), (23..=40).collect::<Vec<_>>());
    assert_eq!(store.checkpoint_indexes("depot").unwrap(), [40, 25]);
    assert!(matches!(
        store.compact(
            "depot",
            RecordKind::Trajectory,
            &CheckpointRetention {
                checkpoints: 1,
                log_entries: 0
            }
        ),
        Err(StorageError::InvalidOptions { .. })
    ));
}

fn export_import_carries_checkpoints(store: &impl MapStore) {
    let retention = CheckpointRetention::DEFAULT;
    write_log(store, "depot", 1..=6);
    store.put_checkpoint("depot", 3, b"state 3").unwrap();
    store.put_checkpoint("depot", 6, b"state 6").unwrap();
    store
        .compact("depot", RecordKind::Trajectory, &retention)
        .unwrap();
    let mut archive = Vec::new();
    store.export_site("depot", &mut archive).unwrap();
    store.import_site("annex", &mut archive.as_slice()).unwrap();
    assert_eq!(store.checkpoint_indexes("annex").unwrap(), [6, 3]);
    assert_eq!(
        store.checkpoint("annex", 6).unwrap().as_deref(),
        Some(&b"state 6"[..])
    );
    assert_eq!(log_indexes(store, "annex"), [4, 5, 6]);
    assert_eq!(store.map_version("annex").unwrap(), 6);
}

/// A value stored in a file: one byte over the inline limit plus `extra`, its bytes derived from `n`.
fn large(n: u64, extra: usize) -> Vec<u8> {
    (0..MAX_INLINE_VALUE_BYTES + 1 + extra)
        .map(|i| (i as u64).wrapping_mul(n | 1).wrapping_add(n) as u8)
        .collect()
}

/// The names of the store's value files, sorted.
fn value_files(store: &impl RawKv) -> Vec<String> {
    store.value_files().files().names().unwrap()
}

/// The value file the record names (it names one).
fn value_file_of(store: &impl RawKv, site: &str, kind: RecordKind, id: &RecordId) -> String {
    let key = key::record_key(site, kind.as_byte(), id.as_bytes());
    let stored = store.raw_get(&key).unwrap().unwrap();
    let envelope::Opened::Entry(payload) = envelope::open_record(&key, &stored).unwrap() else {
        panic!("{} holds its value inline", key::describe(&key));
    };
    crate::value_entry::ValueEntry::decode(&key, payload)
        .unwrap()
        .file
}

fn large_values_are_kept_apart_and_freed(store: &(impl MapStore + RawKv)) {
    let get = |n: u64| store.get("depot", RecordKind::Submap, &id(n)).unwrap();
    let at_limit = vec![7; MAX_INLINE_VALUE_BYTES];
    let mut batch = WriteBatch::new("depot");
    batch
        .put(RecordKind::Submap, 1, at_limit.clone())
        .put(RecordKind::Submap, 2, large(2, 0))
        .put(RecordKind::Submap, 3, large(3, 300_000))
        .put(RecordKind::Submap, 4, b"small".to_vec())
        .bump_map_version();
    store.apply_durable(&batch).unwrap();
    assert_eq!(get(1), Some(at_limit), "up to the limit: inline");
    assert_eq!(get(2), Some(large(2, 0)));
    assert_eq!(get(3), Some(large(3, 300_000)));
    assert_eq!(value_files(store).len(), 2, "one file per large value");
    // Scans return the values, wherever they are.
    let scanned = scan_all(store, "depot", RecordKind::Submap);
    assert_eq!(
        scanned
            .iter()
            .map(|(_, value)| value.len())
            .collect::<Vec<_>>(),
        [
            MAX_INLINE_VALUE_BYTES,
            MAX_INLINE_VALUE_BYTES + 1,
            MAX_INLINE_VALUE_BYTES + 300_001,
            5
        ]
    );
    assert_eq!(scanned[2].1, large(3, 300_000));
    // Overwritten large by large, large by small, small by large; deleted: after the flush, one file
    // per large value left.
    let mut batch = WriteBatch::new("depot");
    batch
        .put(RecordKind::Submap, 2, large(20, 5))
        .put(RecordKind::Submap, 3, b"now small".to_vec())
        .put(RecordKind::Submap, 4, large(40, 0))
        .put(RecordKind::Submap, 5, large(50, 0));
    store.apply(&batch).unwrap();
    store.delete("depot", RecordKind::Submap, &id(5)).unwrap();
    store.flush().unwrap();
    assert_eq!(get(2), Some(large(20, 5)));
    assert_eq!(get(3).as_deref(), Some(&b"now small"[..]));
    assert_eq!(get(4), Some(large(40, 0)));
    assert_eq!(get(5), None);
    let mut expected = vec![
        value_file_of(store, "depot", RecordKind::Submap, &id(2)),
        value_file_of(store, "depot", RecordKind::Submap, &id(4)),
    ];
    expected.sort();
    assert_eq!(value_files(store), expected);
    // Other sites keep theirs when a site is deleted, whose files go.
    store
        .put("yard", RecordKind::Node, &id(1), &large(9, 0))
        .unwrap();
    store.delete_site("depot").unwrap();
    assert_eq!(
        value_files(store),
        [value_file_of(store, "yard", RecordKind::Node, &id(1))]
    );
    assert_eq!(
        store.get("yard", RecordKind::Node, &id(1)).unwrap(),
        Some(large(9, 0))
    );
}

fn compaction_frees_the_files_of_large_log_entries(store: &(impl MapStore + RawKv)) {
    let retention = CheckpointRetention::DEFAULT;
    // A site log of 30-kB entries, as the server writes, checkpointed every 5 entries.
    for index in 1..=20 {
        let mut batch = WriteBatch::new("depot");
        batch
            .put(RecordKind::Trajectory, index, large(index, 25_000))
            .bump_map_version();
        store.apply_durable(&batch).unwrap();
        if index % 5 == 0 {
            store
                .put_checkpoint("depot", index, format!("state {index}").as_bytes())
                .unwrap();
            store
                .compact("depot", RecordKind::Trajectory, &retention)
                .unwrap();
        }
    }
    // Kept: checkpoints 15 and 20, the log after 15.
    assert_eq!(log_indexes(store, "depot"), [16, 17, 18, 19, 20]);
    let mut expected: Vec<String> = (16..=20)
        .map(|n| value_file_of(store, "depot", RecordKind::Trajectory, &id(n)))
        .collect();
    expected.sort();
    assert_eq!(
        value_files(store),
        expected,
        "the compacted entries' files are gone"
    );
    for (n, value) in scan_all(store, "depot", RecordKind::Trajectory) {
        assert_eq!(value, large(n.as_u64().unwrap(), 25_000));
    }
}

fn export_import_carries_large_values_inline(store: &(impl MapStore + RawKv)) {
    let mut batch = WriteBatch::new("depot");
    batch
        .put(RecordKind::Submap, 1, large(1, 100_000))
        .put(RecordKind::Node, 2, b"small".to_vec())
        .bump_map_version();
    store.apply_durable(&batch).unwrap();
    let mut archive = Vec::new();
    store.export_site("depot", &mut archive).unwrap();
    // The archive holds the value's bytes themselves, not its entry.
    assert!(
        archive
            .windows(64)
            .any(|window| window == &large(1, 100_000)[1000..1064])
    );
    store.import_site("annex", &mut archive.as_slice()).unwrap();
    assert_eq!(site_contents(store, "annex"), site_contents(store, "depot"));
    assert_eq!(
        value_files(store).len(),
        2,
        "imported into a file of its own"
    );
    let copy = value_file_of(store, "annex", RecordKind::Submap, &id(1));
    assert!(copy.starts_with("annex/"), "{copy}");
    // Exports of the two sites are the same records.
    let mut again = Vec::new();
    store.export_site("annex", &mut again).unwrap();
    let header = 8 + 2 + 8 + 1;
    assert_eq!(
        again[header + "annex".len()..],
        archive[header + "depot".len()..]
    );
}

fn a_missing_or_damaged_value_file_reads_as_corrupt_naming_it(store: &(impl MapStore + RawKv)) {
    let mut batch = WriteBatch::new("depot");
    for n in 1..=3 {
        batch.put(RecordKind::Submap, n, large(n, 10));
    }
    batch.bump_map_version();
    store.apply_durable(&batch).unwrap();
    let files = store.value_files().files();
    let damaged = value_file_of(store, "depot", RecordKind::Submap, &id(1));
    let mut bytes = files.read("depot", &damaged).unwrap().unwrap();
    bytes[100] ^= 0x04;
    files.write("depot", &damaged, &bytes).unwrap();
    let short = value_file_of(store, "depot", RecordKind::Submap, &id(2));
    files.write("depot", &short, &large(2, 10)[..4000]).unwrap();
    let missing = value_file_of(store, "depot", RecordKind::Submap, &id(3));
    files.remove("depot", &missing).unwrap();
    for (n, file, what) in [
        (1, &damaged, "CRC32 mismatch"),
        (2, &short, "4000 bytes, its entry says 4107"),
        (3, &missing, "missing"),
    ] {
        let error = store.get("depot", RecordKind::Submap, &id(n)).unwrap_err();
        let message = error.to_string();
        assert!(matches!(error, StorageError::Corrupt { .. }), "{message}");
        assert!(
            message.contains("depot/submap/")
                && message.contains(file.as_str())
                && message.contains(what),
            "{message}"
        );
    }
    // Scans report each one and go on; exports refuse.
    let scanned: Vec<_> = store.scan("depot", RecordKind::Submap).unwrap().collect();
    assert_eq!(scanned.len(), 3);
    assert!(
        scanned
            .iter()
            .all(|item| matches!(item, Err(StorageError::Corrupt { .. })))
    );
    assert!(matches!(
        store.export_site("depot", &mut Vec::new()),
        Err(StorageError::Corrupt { .. })
    ));
    // Rewritten, the record is whole again.
    store
        .put("depot", RecordKind::Submap, &id(3), &large(33, 0))
        .unwrap();
    assert_eq!(
        store.get("depot", RecordKind::Submap, &id(3)).unwrap(),
        Some(large(33, 0))
    );
}

fn orphan_value_files_are_removed_at_open(store: &(impl MapStore + RawKv)) {
    store
        .put("depot", RecordKind::Node, &id(1), &large(1, 0))
        .unwrap();
    let named = value_file_of(store, "depot", RecordKind::Node, &id(1));
    let files = store.value_files().files();
    // What crashes leave: a file whose batch never landed, a deleted site's file.
    files
        .write(
            "depot",
            "depot/7fffffffffffffff-00000000.val",
            b"never named",
        )
        .unwrap();
    files
        .write(
            "gone",
            "gone/0000000000000001-00000000.val",
            b"deleted site",
        )
        .unwrap();
    assert_eq!(value_files::remove_orphan_files(store).unwrap(), 2);
    assert_eq!(value_files(store), [named]);
    assert_eq!(
        store.get("depot", RecordKind::Node, &id(1)).unwrap(),
        Some(large(1, 0))
    );
    // New files are numbered past the orphans found.
    store
        .put("depot", RecordKind::Node, &id(2), &large(2, 0))
        .unwrap();
    let newer = value_file_of(store, "depot", RecordKind::Node, &id(2));
    assert!(newer.starts_with("depot/8000000000000000-"), "{newer}");
}

fn large_values_stored_inline_by_earlier_builds_still_work(store: &(impl MapStore + RawKv)) {
    store.put("depot", RecordKind::Node, &id(9), b"x").unwrap();
    let old = |n: u64| {
        let key = key::record_key("depot", RecordKind::Submap.as_byte(), id(n).as_bytes());
        let sealed = envelope::seal(&key, &large(n, 50_000));
        store
            .transact(&|txn| txn.insert(&key, sealed.clone()))
            .unwrap();
    };
    old(1);
    old(2);
    assert!(value_files(store).is_empty());
    assert_eq!(
        store.get("depot", RecordKind::Submap, &id(1)).unwrap(),
        Some(large(1, 50_000))
    );
    assert_eq!(scan_all(store, "depot", RecordKind::Submap).len(), 2);
    let mut archive = Vec::new();
    store.export_site("depot", &mut archive).unwrap();
    store.import_site("annex", &mut archive.as_slice()).unwrap();
    assert_eq!(site_contents(store, "annex"), site_contents(store, "depot"));
    assert_eq!(value_files(store).len(), 2, "imported into files");
    // Overwritten, the value goes to a file; deleted, nothing is left.
    store
        .put("depot", RecordKind::Submap, &id(1), &large(11, 0))
        .unwrap();
    store.delete("depot", RecordKind::Submap, &id(2)).unwrap();
    store.flush().unwrap();
    assert_eq!(
        store.get("depot", RecordKind::Submap, &id(1)).unwrap(),
        Some(large(11, 0))
    );
    assert_eq!(
        store.get("depot", RecordKind::Submap, &id(2)).unwrap(),
        None
    );
    assert_eq!(value_files(store).len(), 3);
}
