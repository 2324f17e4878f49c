//! `storage-torture DB_PATH MAX_BATCHES`: the writer of the kill -9 test (`tests/kill_nine.rs`).
//!
//! Opens a `SledStore` at `DB_PATH`, resumes after the torture session's last applied sequence number, and
//! applies up to `MAX_BATCHES` batches of the shared workload durably, printing each sequence number on its own
//! line on stdout only after `apply_durable` returned (the acknowledgement). The test SIGKILLs it at random.

mod workload;

use std::io::Write as _;
use std::process::ExitCode;

use storage::{BatchOutcome, MapStore as _, SledStore};

fn run(path: &str, max_batches: u64) -> Result<(), Box<dyn std::error::Error>> {
    let store = SledStore::open_path(path)?;
    let first = store
        .last_applied_seq(workload::SITE, workload::SESSION)?
        .unwrap_or(0)
        + 1;
    let mut stdout = std::io::stdout().lock();
    for seq in first..first + max_batches {
        match store.apply_durable(&workload::batch(seq))? {
            BatchOutcome::Applied { .. } => writeln!(stdout, "{seq}")?,
            BatchOutcome::Duplicate { last_applied } => {
                return Err(format!(
                    "batch {seq} reported duplicate (last applied {last_applied})"
                )
                .into());
            }
        }
        stdout.flush()?;
    }
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().collect();
    let (Some(path), Some(max_batches)) = (args.get(1), args.get(2).and_then(|n| n.parse().ok()))
    else {
        eprintln!("usage: storage-torture DB_PATH MAX_BATCHES");
        return ExitCode::from(2);
    };
    match run(path, max_batches) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("storage-torture: {error}");
            ExitCode::FAILURE
        }
    }
}
