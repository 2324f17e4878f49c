//! The steps between a file beside the database (a checkpoint's, a large record value's) and the entry
//! naming it, reported to a hook so that crash tests can stop the process exactly there.

use std::sync::{PoisonError, RwLock};

/// A step of storing or removing a file and the entry naming it, reported to the hook set with
/// [`crate::SledStore::on_file_step`] (crash tests stop the process there). Each is a point where a crash
/// leaves an orphan file, deleted when the store next opens, and nothing else.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileStep {
    /// The checkpoint's file is durable (written, fsynced, renamed, its directory fsynced); its index
    /// entry is not stored yet.
    CheckpointFileDurable {
        /// The log index the checkpoint covers.
        log_index: u64,
    },
    /// The checkpoint's index entry was removed durably (by a compaction, or replaced by a rewrite at the
    /// same log index); its file is not deleted yet.
    CheckpointIndexRemoved {
        /// The log index the removed checkpoint covered.
        log_index: u64,
    },
    /// The files of a batch's large values are durable; the batch (with the entries naming them) is not
    /// applied yet.
    ValueFilesDurable {
        /// How many files the batch wrote.
        files: usize,
    },
    /// A flush made durable the removal (an overwrite, a delete, a compaction) of entries naming value
    /// files; the files are not deleted yet.
    ValueEntriesRemoved {
        /// How many files are to be deleted.
        files: usize,
    },
}

/// The hook [`StepHook::call`] calls.
type Hook = Box<dyn Fn(FileStep) + Send + Sync>;

/// A settable [`FileStep`] hook, one per store.
#[derive(Default)]
pub(crate) struct StepHook(RwLock<Option<Hook>>);

impl StepHook {
    /// Sets the hook (replacing any).
    pub(crate) fn set(&self, hook: Hook) {
        *self.0.write().unwrap_or_else(PoisonError::into_inner) = Some(hook);
    }

    /// Calls the hook, if set.
    pub(crate) fn call(&self, step: FileStep) {
        if let Some(hook) = self
            .0
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .as_ref()
        {
            hook(step);
        }
    }
}

impl std::fmt::Debug for StepHook {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let set = self
            .0
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .is_some();
        f.debug_tuple("StepHook").field(&set).finish()
    }
}
