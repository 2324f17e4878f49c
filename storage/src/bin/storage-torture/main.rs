//! `storage-torture DB_PATH MAX_BATCHES [PAUSE_AT]`: the writer of the kill -9 test (`tests/kill_nine.rs`).
//!
//! Opens a `SledStore` at `DB_PATH` and restores the torture site as a server does: from the newest
//! checkpoint that reads back (a corrupt one is skipped for the one before it) plus the log after it,
//! folding the stored log entries into the running [`workload::digest`]. Then it resumes after the
//! session's last applied sequence number and applies up to `MAX_BATCHES` batches of the shared workload
//! durably; after each batch that [`workload::checkpoint_due`] names (and at the start, when the last
//! applied batch's checkpoint is due and missing) it writes the checkpoint with `put_checkpoint` and
//! compacts the log with `compact`, keeping [`workload::KEEP_CHECKPOINTS`].
//!
//! It reports on stdout, one line each, flushed, only after the step returned:
//! - `r INDEX` restored from the checkpoint at INDEX (0: none) and the log after it;
//! - `b SEQ` batch SEQ applied durably (the acknowledgement);
//! - `C INDEX` a checkpoint write begins, `c INDEX MICROS` it is durable (acknowledged);
//! - `K INDEX` a compaction begins, `k INDEX MICROS LOG_ENTRIES_REMOVED` it returned;
//! - `F INDEX` the file of the checkpoint at INDEX is durable, its index entry not stored yet;
//! - `D INDEX` the index entry of the checkpoint at INDEX is removed durably, its file not deleted yet;
//! - `V FILES` the value files of the next batch are durable, the batch not applied yet;
//! - `U FILES` the removal of entries naming FILES value files is durable (a compaction's), the files not
//!   deleted yet.
//!
//! With `PAUSE_AT` `file-durable`, `index-removed`, `value-files-durable` or `value-entries-removed` it
//! stops for good after the first `F`, `D`, `V` or `U` line, for the kill to land exactly between the two
//! steps. The test SIGKILLs it at random, just after a `C` or a `K`, or in such a pause.

mod workload;

use std::io::Write as _;
use std::process::ExitCode;
use std::time::Instant;

use storage::{
    BatchOutcome, CheckpointRetention, FileStep, MapStore as _, SledStore, StorageError,
};

type Error = Box<dyn std::error::Error>;

/// The site's state: the newest checkpoint that reads back and the digest of the log up to `last`.
fn restore(store: &SledStore, last: u64) -> Result<(u64, u64), Error> {
    let mut from = (0, 0);
    for index in store.checkpoint_indexes(workload::SITE)? {
        match store.checkpoint(workload::SITE, index) {
            Ok(Some(payload)) => {
                let Some((stated, digest)) = workload::checkpoint_header(&payload) else {
                    return Err(format!("checkpoint {index} has no header").into());
                };
                if stated != index {
                    return Err(format!("checkpoint {index} says it covers {stated}").into());
                }
                from = (index, digest);
                break;
            }
            Ok(None) => {}
            Err(error @ StorageError::Corrupt { .. }) => {
                eprintln!("storage-torture: skipping checkpoint {index}: {error}");
            }
            Err(error) => return Err(error.into()),
        }
    }
    let (index, mut digest) = from;
    if index > last {
        return Err(format!("checkpoint {index} is beyond the last batch {last}").into());
    }
    for seq in index + 1..=last {
        let Some(value) = store.get(
            workload::SITE,
            workload::LOG_KIND,
            &storage::RecordId::from(seq),
        )?
        else {
            return Err(format!("log entry {seq} after checkpoint {index} is missing").into());
        };
        digest = workload::digest(digest, seq, &value);
    }
    Ok((index, digest))
}

fn checkpoint_and_compact(
    store: &SledStore,
    stdout: &mut impl std::io::Write,
    index: u64,
    digest: u64,
) -> Result<(), Error> {
    let payload = workload::checkpoint_payload(index, digest);
    writeln!(stdout, "C {index}")?;
    stdout.flush()?;
    let started = Instant::now();
    store.put_checkpoint(workload::SITE, index, &payload)?;
    writeln!(stdout, "c {index} {}", started.elapsed().as_micros())?;
    writeln!(stdout, "K {index}")?;
    stdout.flush()?;
    let started = Instant::now();
    let retention = CheckpointRetention {
        checkpoints: workload::KEEP_CHECKPOINTS,
        log_entries: 0,
    };
    let compaction = store.compact(workload::SITE, workload::LOG_KIND, &retention)?;
    writeln!(
        stdout,
        "k {index} {} {}",
        started.elapsed().as_micros(),
        compaction.log_entries_removed
    )?;
    stdout.flush()?;
    Ok(())
}

/// The `PAUSE_AT` names, one per [`FileStep`].
const PAUSE_POINTS: [&str; 4] = [
    "file-durable",
    "index-removed",
    "value-files-durable",
    "value-entries-removed",
];

/// Reports each step between a file and its entry (`F`, `D`, `V`, `U`), and stops for good at the first
/// one `pause_at` names.
fn report_file_steps(store: &SledStore, pause_at: Option<&str>) {
    let pause_at = pause_at.map(str::to_owned);
    store.on_file_step(move |step| {
        let (tag, index, name) = match step {
            FileStep::CheckpointFileDurable { log_index } => ('F', log_index, PAUSE_POINTS[0]),
            FileStep::CheckpointIndexRemoved { log_index } => ('D', log_index, PAUSE_POINTS[1]),
            FileStep::ValueFilesDurable { files } => ('V', files as u64, PAUSE_POINTS[2]),
            FileStep::ValueEntriesRemoved { files } => ('U', files as u64, PAUSE_POINTS[3]),
        };
        let mut stdout = std::io::stdout().lock();
        let _ = writeln!(stdout, "{tag} {index}").and_then(|()| stdout.flush());
        if pause_at.as_deref() == Some(name) {
            loop {
                std::thread::sleep(std::time::Duration::from_secs(3600));
            }
        }
    });
}

fn run(path: &str, max_batches: u64, pause_at: Option<&str>) -> Result<(), Error> {
    let store = SledStore::open_path(path)?;
    report_file_steps(&store, pause_at);
    let last = store
        .last_applied_seq(workload::SITE, workload::SESSION)?
        .unwrap_or(0);
    let (restored_from, mut digest) = restore(&store, last)?;
    let mut stdout = std::io::stdout().lock();
    writeln!(stdout, "r {restored_from}")?;
    stdout.flush()?;
    // A checkpoint due at the last batch that a kill interrupted: written now, as a server retries one.
    let newest = store.checkpoint_indexes(workload::SITE)?.first().copied();
    if last > 0 && workload::checkpoint_due(last) && newest < Some(last) {
        checkpoint_and_compact(&store, &mut stdout, last, digest)?;
    }
    for seq in last + 1..=last + max_batches {
        match store.apply_durable(&workload::batch(seq))? {
            BatchOutcome::Applied { .. } => writeln!(stdout, "b {seq}")?,
            BatchOutcome::Duplicate { last_applied } => {
                return Err(format!(
                    "batch {seq} reported duplicate (last applied {last_applied})"
                )
                .into());
            }
        }
        stdout.flush()?;
        digest = workload::digest(digest, seq, &workload::log_value(seq));
        if workload::checkpoint_due(seq) {
            checkpoint_and_compact(&store, &mut stdout, seq, digest)?;
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().collect();
    let (Some(path), Some(max_batches)) = (args.get(1), args.get(2).and_then(|n| n.parse().ok()))
    else {
        eprintln!(
            "usage: storage-torture DB_PATH MAX_BATCHES [{}]",
            PAUSE_POINTS.join("|")
        );
        return ExitCode::from(2);
    };
    let pause_at = args.get(3).map(String::as_str);
    if pause_at.is_some_and(|at| !PAUSE_POINTS.contains(&at)) {
        eprintln!(
            "storage-torture: PAUSE_AT is one of {}",
            PAUSE_POINTS.join(", ")
        );
        return ExitCode::from(2);
    }
    match run(path, max_batches, pause_at) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("storage-torture: {error}");
            ExitCode::FAILURE
        }
    }
}
