//! The kill -9 test: a child process (`storage-torture`) applies batches durably to a `SledStore`, writes
//! checkpoints of the site and compacts its log (issue 34), and prints each step it finished; we SIGKILL
//! it at a random moment — while it applies batches, while it opens and restores the site, or just after
//! it began a checkpoint write or a compaction, or exactly between a checkpoint's file becoming durable
//! and its index entry being stored, or between a compaction removing an entry durably and deleting its
//! file, or between a batch's value files becoming durable and the batch being applied, or between a
//! compaction removing log entries with value files durably and deleting the files (the writer pauses
//! there, `PAUSE_AT`) — reopen the store and check:
//! - every acknowledged batch is present whole, no batch is present in part, and no record is corrupt
//!   (the batches' Node records are never compacted: all of them, exactly);
//! - every acknowledged batch is still readable: in the log, or covered by a checkpoint that verifies;
//! - no checkpoint is corrupt, and every one that reads back holds exactly what its log index implies (a
//!   digest of the log entries up to it, chained, and a body derived from that): none is returned valid
//!   with other content; the newest acknowledged one is there unless compaction kept newer ones;
//! - the log is one run without gaps up to the last batch, untouched while fewer than 2 checkpoints
//!   verify and complete after the oldest stored one; restoring from every stored checkpoint plus the
//!   log after it gives the digest of the whole log, and the next writer restored from the newest one;
//! - at most 2 checkpoints are stored, and one more for each checkpoint write begun since the last
//!   compaction that returned (a kill between a checkpoint and its compaction leaves it for the next);
//! - the checkpoint directory holds exactly one file per stored checkpoint, named by its index (the
//!   orphans a kill left were deleted when the store opened), and a checkpoint killed between its file
//!   and its entry, or between its entry's removal and its file's, is not listed;
//! - the value directory holds exactly one file per stored value longer than `MAX_INLINE_VALUE_BYTES`
//!   (nodes and log entries), and a batch killed between its value files and its transaction is not
//!   applied.
//!
//! Repeated over many cycles on the same database, which keeps growing across kills.
//!
//! `kill_nine_cycles` is bounded for CI (60 cycles, 60 s; about 10 s here). `kill_nine_long` (ignored)
//! runs 300 cycles: `cargo nextest run --workspace --run-ignored only -E 'test(kill_nine_long)'`; set
//! `EVERMAP_TORTURE_CYCLES` and `EVERMAP_TORTURE_SEED` to change the cycle count and the random seed.

#![expect(clippy::unwrap_used, reason = "test code")]

#[path = "../src/bin/storage-torture/workload.rs"]
#[expect(dead_code, reason = "only the writer builds whole batches")]
mod workload;

use std::io::{BufRead as _, BufReader};
use std::os::unix::process::ExitStatusExt as _;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::thread;
use std::time::{Duration, Instant};

use rand::{Rng as _, SeedableRng as _};
use storage::{MAX_INLINE_VALUE_BYTES, MapStore as _, RecordId, RecordKind, SledStore};

/// Batches one child may write before exiting by itself (a safety bound; kills come much earlier).
const MAX_BATCHES_PER_CHILD: u64 = 5_000;
/// Longest wait for the writer's next line.
const WAIT: Duration = Duration::from_secs(20);

/// One line of the writer (see `storage-torture`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Event {
    Restored(u64),
    Batch(u64),
    CheckpointBegins(u64),
    Checkpointed { index: u64, micros: u64 },
    CompactionBegins(u64),
    Compacted { micros: u64, removed: u64 },
    FileDurable(u64),
    IndexRemoved(u64),
    ValueFilesDurable,
    ValueEntriesRemoved,
}

impl Event {
    fn parse(line: &str) -> Option<Self> {
        let mut words = line.split(' ');
        let tag = words.next()?;
        let mut numbers = words.map(|word| word.parse::<u64>().ok());
        let mut next = || numbers.next().flatten();
        Some(match tag {
            "r" => Self::Restored(next()?),
            "b" => Self::Batch(next()?),
            "C" => Self::CheckpointBegins(next()?),
            "c" => Self::Checkpointed {
                index: next()?,
                micros: next()?,
            },
            "K" => Self::CompactionBegins(next()?),
            "F" => Self::FileDurable(next()?),
            "D" => Self::IndexRemoved(next()?),
            "V" => Self::ValueFilesDurable,
            "U" => Self::ValueEntriesRemoved,
            "k" => {
                let _index = next()?;
                Self::Compacted {
                    micros: next()?,
                    removed: next()?,
                }
            }
            _ => return None,
        })
    }
}

/// When a cycle kills the writer.
#[derive(Clone, Copy, Debug)]
enum Moment {
    /// A random time after spawning (opening, restoring, the first batches).
    Start,
    /// A random time after the first acknowledged batch.
    Batches,
    /// A random time within half the last checkpoint write's duration after one begins.
    Checkpoint,
    /// A random time within half the last compaction's duration after one begins.
    Compaction,
    /// Between a checkpoint's file being durable and its index entry being stored (the writer pauses).
    FileDurable,
    /// Between a compaction removing a checkpoint's entry durably and deleting its file (the writer
    /// pauses).
    IndexRemoved,
    /// Between a batch's value files being durable and the batch being applied (the writer pauses).
    ValueFilesDurable,
    /// Between a compaction removing log entries that name value files durably and deleting the files
    /// (the writer pauses).
    ValueEntriesRemoved,
}

impl Moment {
    /// The writer's `PAUSE_AT` argument for the moments it pauses at.
    fn pause_at(self) -> Option<&'static str> {
        match self {
            Self::FileDurable => Some("file-durable"),
            Self::IndexRemoved => Some("index-removed"),
            Self::ValueFilesDurable => Some("value-files-durable"),
            Self::ValueEntriesRemoved => Some("value-entries-removed"),
            Self::Start | Self::Batches | Self::Checkpoint | Self::Compaction => None,
        }
    }
}

#[derive(Debug, Default)]
struct Tally {
    cycles: u64,
    killed_by_signal: u64,
    killed_before_first_ack: u64,
    /// Kills that landed after a checkpoint write began and before it returned.
    killed_in_checkpoint: u64,
    /// Kills that landed after a compaction began and before it returned.
    killed_in_compaction: u64,
    /// Kills between a checkpoint's file and its index entry.
    killed_between_file_and_entry: u64,
    /// Kills between an index entry's removal and its file's deletion.
    killed_between_entry_and_file_removal: u64,
    /// Kills between a batch's value files and the batch.
    killed_between_value_files_and_batch: u64,
    /// Kills between the durable removal of log entries naming value files and the files' deletion.
    killed_between_value_entries_and_files: u64,
    /// Value files found at the last verification.
    value_files: usize,
    acked_batches: u64,
    unacked_but_applied: u64,
    acked_checkpoints: u64,
    acked_compactions: u64,
    log_entries_removed: u64,
    /// Writers that restored from a checkpoint (not from the whole log).
    restored_from_checkpoint: u64,
    last_seq: u64,
    /// The newest acknowledged checkpoint.
    newest_acked_checkpoint: u64,
    /// Checkpoint writes begun since the last compaction returned.
    checkpoints_since_compaction: usize,
    /// What the last verification found.
    newest_checkpoint: u64,
    log_begins_at: u64,
}

/// Reads the writer's lines until its stdout closes; only complete lines count.
fn spawn_reader(stdout: std::process::ChildStdout) -> mpsc::Receiver<Event> {
    let (sender, receiver) = mpsc::channel();
    thread::Builder::new()
        .name("ack-reader".to_owned())
        .spawn(move || {
            let mut reader = BufReader::new(stdout);
            let mut line = String::new();
            while reader.read_line(&mut line).unwrap_or(0) > 0 {
                if let Some(event) = line.strip_suffix('\n').and_then(Event::parse)
                    && sender.send(event).is_err()
                {
                    return;
                }
                line.clear();
            }
        })
        .unwrap();
    receiver
}

/// The digests of the workload's log up to each index (index 0: the empty log), extended on demand.
struct Digests(Vec<u64>);

impl Digests {
    fn up_to(&mut self, index: u64) -> u64 {
        let index = usize::try_from(index).unwrap();
        while self.0.len() <= index {
            let seq = self.0.len() as u64;
            let previous = *self.0.last().unwrap();
            self.0
                .push(workload::digest(previous, seq, &workload::log_value(seq)));
        }
        self.0[index]
    }
}

/// What a verification found.
struct Verified {
    last: u64,
    /// The stored checkpoints, newest first (all verify).
    checkpoints: Vec<u64>,
    /// The first log entry (`last + 1`: an empty log).
    log_begins_at: u64,
    /// The value files (one per stored large value).
    value_files: usize,
}

/// Checks the whole database against the workload, every acknowledged batch up to `max_acked` and the
/// newest acknowledged checkpoint.
fn verify(
    path: &Path,
    max_acked: u64,
    acked_checkpoint: u64,
    uncompacted: usize,
    unlisted: Option<u64>,
    digests: &mut Digests,
) -> Verified {
    let large = |value: &[u8]| usize::from(value.len() > MAX_INLINE_VALUE_BYTES);
    let store = SledStore::open_path(path).unwrap();
    let last = store
        .last_applied_seq(workload::SITE, workload::SESSION)
        .unwrap()
        .unwrap_or(0);
    assert!(
        last >= max_acked,
        "batch {max_acked} was acknowledged but the store ends at batch {last}"
    );
    assert_eq!(
        store.map_version(workload::SITE).unwrap(),
        last,
        "map version disagrees with the session"
    );
    if last == 0 {
        assert!(store.list_sites().unwrap().is_empty());
        assert!(store.checkpoint_indexes(workload::SITE).unwrap().is_empty());
        assert_eq!(value_files(path), 0, "value files of no batch");
        return Verified {
            last,
            checkpoints: Vec::new(),
            log_begins_at: 1,
            value_files: 0,
        };
    }
    let latest = store
        .get(
            workload::SITE,
            RecordKind::SiteMeta,
            &RecordId::from("latest"),
        )
        .unwrap()
        .unwrap();
    assert_eq!(
        latest,
        last.to_le_bytes(),
        "SiteMeta latest disagrees with the session"
    );
    let outbox: Vec<_> = store
        .scan(workload::SITE, RecordKind::Outbox)
        .unwrap()
        .map(Result::unwrap)
        .collect();
    assert_eq!(
        outbox,
        [(RecordId::from(last), workload::outbox_value(last))],
        "outbox is not exactly batch {last}"
    );

    let mut expected =
        (1..=last).flat_map(|seq| (0..workload::node_count(seq)).map(move |i| (seq, i)));
    // Values stored in files: one file each.
    let mut large_values = 0;
    for item in store.scan(workload::SITE, RecordKind::Node).unwrap() {
        let (id, value) = item.unwrap_or_else(|error| panic!("corrupt record after kill: {error}"));
        let (seq, i) = expected
            .next()
            .unwrap_or_else(|| panic!("extra node {id} beyond batch {last}: partial batch"));
        assert_eq!(
            id,
            RecordId::from_pair(seq, i),
            "node missing or misplaced (batch {seq} incomplete?)"
        );
        assert_eq!(
            value,
            workload::node_value(seq, i),
            "wrong value of node ({seq}, {i})"
        );
        large_values += large(&value);
    }
    assert_eq!(
        expected.next(),
        None,
        "nodes of acknowledged batches are missing"
    );

    // Checkpoints: each one stored verifies and holds what its index implies.
    let checkpoints = store.checkpoint_indexes(workload::SITE).unwrap();
    assert!(
        checkpoints.len() <= workload::KEEP_CHECKPOINTS + uncompacted,
        "compaction keeps {} checkpoints and {uncompacted} were begun since, {} are stored: \
         {checkpoints:?}",
        workload::KEEP_CHECKPOINTS,
        checkpoints.len()
    );
    let mut restore_points = Vec::new();
    for &index in &checkpoints {
        assert!(
            (1..=last).contains(&index),
            "checkpoint {index} is beyond the log (1..={last})"
        );
        let payload = store
            .checkpoint(workload::SITE, index)
            .unwrap_or_else(|error| panic!("checkpoint {index} is corrupt after a kill: {error}"))
            .unwrap_or_else(|| panic!("checkpoint {index} is listed but absent"));
        let expected = workload::checkpoint_payload(index, digests.up_to(index));
        assert!(
            payload == expected,
            "checkpoint {index} reads back valid but is not what its index implies: {} bytes, \
             header {:?}; expected {} bytes, header {:?}",
            payload.len(),
            workload::checkpoint_header(&payload),
            expected.len(),
            workload::checkpoint_header(&expected)
        );
        restore_points.push(workload::checkpoint_header(&payload).unwrap());
    }
    if let Some(index) = unlisted {
        assert!(
            !checkpoints.contains(&index),
            "checkpoint {index} was killed between its file and its index entry, but is listed: \
             {checkpoints:?}"
        );
    }
    let mut expected_files: Vec<String> = checkpoints
        .iter()
        .map(|index| format!("{index:020}"))
        .collect();
    expected_files.sort();
    assert_eq!(
        checkpoint_files(path),
        expected_files,
        "the checkpoint files are not one per stored checkpoint {checkpoints:?}"
    );
    let newest = checkpoints.first().copied().unwrap_or(0);
    if acked_checkpoint > 0 {
        let newer = checkpoints
            .iter()
            .filter(|&&index| index > acked_checkpoint)
            .count();
        assert!(
            checkpoints.contains(&acked_checkpoint) || newer >= workload::KEEP_CHECKPOINTS,
            "checkpoint {acked_checkpoint} was acknowledged but is gone, and only {newer} newer \
             are stored: {checkpoints:?}"
        );
    }

    // The log: one run without gaps up to the last batch, and none of it compacted that a kept
    // checkpoint does not cover.
    let log: Vec<(u64, Vec<u8>)> = store
        .scan(workload::SITE, workload::LOG_KIND)
        .unwrap()
        .map(|item| {
            let (id, value) =
                item.unwrap_or_else(|error| panic!("corrupt log entry after kill: {error}"));
            (id.as_u64().unwrap(), value)
        })
        .collect();
    let log_begins_at = log.first().map_or(last + 1, |(seq, _)| *seq);
    for (offset, (seq, value)) in log.iter().enumerate() {
        assert_eq!(
            *seq,
            log_begins_at + offset as u64,
            "a gap in the log before entry {seq} (it begins at {log_begins_at})"
        );
        assert!(
            *value == workload::log_value(*seq),
            "log entry {seq} holds the wrong value"
        );
        large_values += large(value);
    }
    assert_eq!(
        value_files(path),
        large_values,
        "the value files are not one per stored large value (nodes and log entries up to {last})"
    );
    assert_eq!(
        log_begins_at + log.len() as u64,
        last + 1,
        "the log does not end at the last batch {last}"
    );
    if checkpoints.len() < workload::KEEP_CHECKPOINTS {
        assert_eq!(
            log_begins_at, 1,
            "the log was compacted with only {checkpoints:?} checkpoint(s)"
        );
    }
    let oldest = checkpoints.last().copied().unwrap_or(0);
    assert!(
        log_begins_at <= oldest + 1,
        "the log after the oldest stored checkpoint {oldest} is incomplete: it begins at \
         {log_begins_at} (checkpoints {checkpoints:?})"
    );
    assert!(
        log_begins_at <= newest + 1,
        "batches {}..{log_begins_at} were acknowledged but are neither in the log nor covered by a \
         checkpoint",
        newest + 1
    );
    // A restart from any stored checkpoint (the newest, or one a fallback would take) and the log after
    // it rebuilds the whole log's state.
    for (index, digest) in restore_points {
        let restored = log
            .iter()
            .filter(|(seq, _)| *seq > index)
            .fold(digest, |digest, (seq, value)| {
                workload::digest(digest, *seq, value)
            });
        assert_eq!(
            restored,
            digests.up_to(last),
            "checkpoint {index} and the log after it do not restore the log up to {last}"
        );
    }
    Verified {
        last,
        checkpoints,
        log_begins_at,
        value_files: large_values,
    }
}

/// How many files the store's value directory holds; panics on a file not named
/// `<serial, 16 hex digits>-<CRC32, 8 hex digits>.val` (temporary files of interrupted writes included:
/// opening the store deletes them).
fn value_files(db: &Path) -> usize {
    let Ok(sites) = std::fs::read_dir(db.join("values")) else {
        return 0;
    };
    let mut count = 0;
    for site in sites {
        for file in std::fs::read_dir(site.unwrap().path()).unwrap() {
            let name = file.unwrap().file_name().to_string_lossy().into_owned();
            let named = name
                .strip_suffix(".val")
                .and_then(|stem| stem.split_once('-'))
                .is_some_and(|(serial, crc)| serial.len() == 16 && crc.len() == 8);
            assert!(named, "a stray file {name:?} in the value directory");
            count += 1;
        }
    }
    count
}

/// The log indexes (20 digits) of the files in the store's checkpoint directory, sorted; panics on a
/// file not named `<log index>-<CRC32>.ckpt`.
fn checkpoint_files(db: &Path) -> Vec<String> {
    let mut indexes = Vec::new();
    let Ok(sites) = std::fs::read_dir(db.join("checkpoints")) else {
        return indexes;
    };
    for site in sites {
        for file in std::fs::read_dir(site.unwrap().path()).unwrap() {
            let name = file.unwrap().file_name().to_string_lossy().into_owned();
            let Some((index, _crc)) = name
                .strip_suffix(".ckpt")
                .and_then(|stem| stem.split_once('-'))
                .filter(|(index, crc)| index.len() == 20 && crc.len() == 8)
            else {
                panic!("a stray file {name:?} in the checkpoint directory");
            };
            let index = index.to_owned();
            indexes.push(index);
        }
    }
    indexes.sort();
    indexes
}

/// Waits for the writer's first event `wanted` accepts, keeping every event; `false` if the writer
/// stopped or was silent for [`WAIT`].
fn wait_for(
    events: &mpsc::Receiver<Event>,
    seen: &mut Vec<Event>,
    wanted: impl Fn(&Event) -> bool,
) -> bool {
    while let Ok(event) = events.recv_timeout(WAIT) {
        seen.push(event);
        if wanted(&event) {
            return true;
        }
    }
    false
}

fn torture(cycles: u64, seed: u64, budget: Duration) -> Tally {
    let binary = env!("CARGO_BIN_EXE_storage-torture");
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("db");
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut tally = Tally {
        log_begins_at: 1,
        ..Tally::default()
    };
    let mut digests = Digests(vec![0]);
    // How long the last checkpoint write and compaction took: the targeted kills' windows.
    let (mut checkpoint_micros, mut compaction_micros) = (5_000, 2_000);
    let start = Instant::now();
    while tally.cycles < cycles && start.elapsed() < budget {
        // Checkpoint writes are short (under a millisecond here, about the time the kill takes to land
        // after the writer said it began one): they get more cycles than compactions.
        let moment = match rng.random_range(0..10) {
            0 => Moment::Start,
            1 | 2 => Moment::Batches,
            3 | 4 => Moment::Checkpoint,
            5 => Moment::Compaction,
            6 => Moment::FileDurable,
            7 => Moment::IndexRemoved,
            8 => Moment::ValueFilesDurable,
            _ => Moment::ValueEntriesRemoved,
        };
        let mut child = Command::new(binary)
            .arg(&path)
            .arg(MAX_BATCHES_PER_CHILD.to_string())
            .args(moment.pause_at())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let events = spawn_reader(child.stdout.take().unwrap());
        let mut seen = Vec::new();
        let reached = match moment {
            Moment::Start => {
                thread::sleep(Duration::from_millis(rng.random_range(0..60)));
                true
            }
            Moment::Batches => wait_for(&events, &mut seen, |e| matches!(e, Event::Batch(_))),
            Moment::Checkpoint => wait_for(&events, &mut seen, |e| {
                matches!(e, Event::CheckpointBegins(_))
            }),
            Moment::Compaction => wait_for(&events, &mut seen, |e| {
                matches!(e, Event::CompactionBegins(_))
            }),
            Moment::FileDurable => {
                wait_for(&events, &mut seen, |e| matches!(e, Event::FileDurable(_)))
            }
            Moment::IndexRemoved => {
                wait_for(&events, &mut seen, |e| matches!(e, Event::IndexRemoved(_)))
            }
            Moment::ValueFilesDurable => {
                wait_for(&events, &mut seen, |e| *e == Event::ValueFilesDurable)
            }
            Moment::ValueEntriesRemoved => {
                wait_for(&events, &mut seen, |e| *e == Event::ValueEntriesRemoved)
            }
        };
        if !reached {
            let _ = child.kill();
            let output = child.wait_with_output().unwrap();
            panic!(
                "writer did not reach {moment:?} in {WAIT:?}: {}",
                String::from_utf8_lossy(&output.stderr)
            );
        }
        let delay = match moment {
            Moment::Start
            | Moment::FileDurable
            | Moment::IndexRemoved
            | Moment::ValueFilesDurable
            | Moment::ValueEntriesRemoved => 0,
            Moment::Batches => rng.random_range(0..150_000),
            Moment::Checkpoint => rng.random_range(0..=checkpoint_micros / 2),
            Moment::Compaction => rng.random_range(0..=compaction_micros / 2),
        };
        thread::sleep(Duration::from_micros(delay));
        child.kill().unwrap(); // SIGKILL on Unix
        let status = child.wait().unwrap();
        seen.extend(events.iter());
        if status.signal() == Some(9) {
            tally.killed_by_signal += 1;
        } else {
            let mut stderr = String::new();
            std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
            assert!(
                status.success(),
                "writer failed before the kill ({status}): {stderr}"
            );
        }
        // A writer that paused between a checkpoint's file and its entry was killed there: the
        // checkpoint whose entry it kept from landing, or removed, must not be listed.
        let mut unlisted = None;
        let mut unapplied_batch = false;
        match (seen.last(), moment.pause_at()) {
            (Some(Event::ValueFilesDurable), Some(_)) => {
                tally.killed_between_value_files_and_batch += 1;
                unapplied_batch = true;
            }
            (Some(Event::ValueEntriesRemoved), Some(_)) => {
                tally.killed_in_compaction += 1;
                tally.killed_between_value_entries_and_files += 1;
            }
            (Some(&Event::FileDurable(index)), Some(_)) => {
                tally.killed_in_checkpoint += 1;
                tally.killed_between_file_and_entry += 1;
                unlisted = Some(index);
            }
            (Some(&Event::IndexRemoved(index)), Some(_)) => {
                tally.killed_in_compaction += 1;
                tally.killed_between_entry_and_file_removal += 1;
                unlisted = Some(index);
            }
            (Some(Event::CheckpointBegins(_) | Event::FileDurable(_)), _) => {
                tally.killed_in_checkpoint += 1;
            }
            (
                Some(
                    Event::CompactionBegins(_)
                    | Event::IndexRemoved(_)
                    | Event::ValueEntriesRemoved,
                ),
                _,
            ) => {
                tally.killed_in_compaction += 1;
            }
            _ => {}
        }
        let mut max_acked = 0;
        for event in &seen {
            match *event {
                Event::Restored(index) => {
                    assert_eq!(
                        index, tally.newest_checkpoint,
                        "the writer restored from checkpoint {index}, not the newest stored one"
                    );
                    tally.restored_from_checkpoint += u64::from(index > 0);
                }
                Event::Batch(seq) => {
                    assert!(
                        seq > tally.last_seq.max(max_acked),
                        "acks must continue after the stored batches"
                    );
                    max_acked = seq;
                    tally.acked_batches += 1;
                }
                Event::Checkpointed { index, micros } => {
                    tally.newest_acked_checkpoint = index;
                    tally.acked_checkpoints += 1;
                    checkpoint_micros = micros.clamp(100, 200_000);
                }
                Event::CheckpointBegins(_) => tally.checkpoints_since_compaction += 1,
                Event::Compacted { micros, removed } => {
                    tally.checkpoints_since_compaction = 0;
                    tally.acked_compactions += 1;
                    tally.log_entries_removed += removed;
                    compaction_micros = micros.clamp(100, 200_000);
                }
                Event::CompactionBegins(_)
                | Event::FileDurable(_)
                | Event::IndexRemoved(_)
                | Event::ValueFilesDurable
                | Event::ValueEntriesRemoved => {}
            }
        }
        if max_acked == 0 {
            tally.killed_before_first_ack += 1;
        }
        let verified = verify(
            &path,
            max_acked.max(tally.last_seq),
            tally.newest_acked_checkpoint,
            tally.checkpoints_since_compaction,
            unlisted,
            &mut digests,
        );
        if unapplied_batch {
            assert_eq!(
                verified.last,
                max_acked.max(tally.last_seq),
                "the batch killed between its value files and its transaction was applied"
            );
        }
        tally.unacked_but_applied += verified.last - max_acked.max(tally.last_seq);
        tally.value_files = verified.value_files;
        tally.last_seq = verified.last;
        tally.newest_checkpoint = verified.checkpoints.first().copied().unwrap_or(0);
        tally.log_begins_at = verified.log_begins_at;
        tally.cycles += 1;
        if tally.cycles.is_multiple_of(50) {
            eprintln!(
                "cycle {}: {tally:?}, {:.0} s",
                tally.cycles,
                start.elapsed().as_secs_f64()
            );
        }
    }
    let size = SledStore::open_path(&path).unwrap().size_on_disk().unwrap();
    eprintln!(
        "kill -9 torture: seed {seed}, {tally:?}, {:.1} s, database {:.1} MB",
        start.elapsed().as_secs_f64(),
        size as f64 / 1e6
    );
    tally
}

fn env_u64(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|value| value.parse().ok())
        .unwrap_or(default)
}

/// What every run must have exercised.
fn assert_exercised(tally: &Tally) {
    assert!(
        tally.killed_by_signal * 10 >= tally.cycles * 9,
        "most writers must die by SIGKILL: {tally:?}"
    );
    assert!(
        tally.last_seq >= 2 * tally.cycles,
        "too few batches written to test anything: {tally:?}"
    );
    let targeted = tally.cycles / 20;
    assert!(
        tally.killed_in_checkpoint >= targeted && tally.killed_in_compaction >= targeted,
        "too few kills landed in checkpoint writes or compactions: {tally:?}"
    );
    assert!(
        tally.killed_between_file_and_entry >= 1
            && tally.killed_between_entry_and_file_removal >= 1,
        "no kill landed between a checkpoint's file and its index entry, or between an entry's \
         removal and its file's: {tally:?}"
    );
    assert!(
        tally.killed_between_value_files_and_batch >= 1
            && tally.killed_between_value_entries_and_files >= 1,
        "no kill landed between a batch's value files and the batch, or between the removal of \
         entries naming value files and the files' deletion: {tally:?}"
    );
    assert!(
        tally.restored_from_checkpoint * 2 >= tally.cycles && tally.log_begins_at > 1,
        "the writers must restore from checkpoints and compact the log: {tally:?}"
    );
}

#[test]
fn kill_nine_cycles() {
    let tally = torture(
        60,
        env_u64("EVERMAP_TORTURE_SEED", 20_250_101),
        Duration::from_secs(60),
    );
    assert!(
        tally.cycles >= 10,
        "only {} cycles ran in the time budget",
        tally.cycles
    );
    assert_exercised(&tally);
}

#[test]
#[ignore = "long: 300 kill cycles, several minutes"]
fn kill_nine_long() {
    let cycles = env_u64("EVERMAP_TORTURE_CYCLES", 300);
    let tally = torture(
        cycles,
        env_u64("EVERMAP_TORTURE_SEED", 7),
        Duration::from_secs(3600),
    );
    assert_eq!(tally.cycles, cycles, "time budget ran out: {tally:?}");
    assert_exercised(&tally);
}
