//! Checkpoint files in memory: the [`crate::MemStore`]'s, so that it runs the same checkpoint code as
//! [`crate::SledStore`] (index entries in the key-value map, bytes beside it).

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::sync::{Mutex, MutexGuard, PoisonError};

use super::{CheckpointFiles, CheckpointStep, StepHook};
use crate::Result;

/// File name → bytes.
type Files = BTreeMap<String, Vec<u8>>;

/// Checkpoint files held in memory; never fails.
#[derive(Debug, Default)]
pub(crate) struct MemCheckpointFiles {
    files: Mutex<Files>,
    lock: Mutex<()>,
    hook: StepHook,
}

impl MemCheckpointFiles {
    fn files(&self) -> MutexGuard<'_, Files> {
        self.files.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Test hook: gives `f` the files (name → bytes), e.g. to damage or delete one.
    #[cfg(test)]
    pub(crate) fn with_files(&self, f: impl FnOnce(&mut Files)) {
        f(&mut self.files());
    }

    /// Test hook: sets the hook [`CheckpointFiles::step`] calls.
    #[cfg(test)]
    pub(crate) fn hook(&self) -> &StepHook {
        &self.hook
    }
}

impl CheckpointFiles for MemCheckpointFiles {
    fn write(&self, _site: &str, name: &str, bytes: &[u8]) -> Result<()> {
        self.files().insert(name.to_owned(), bytes.to_vec());
        Ok(())
    }

    fn read(&self, _site: &str, name: &str) -> Result<Option<Vec<u8>>> {
        Ok(self.files().get(name).cloned())
    }

    fn remove(&self, _site: &str, name: &str) -> Result<()> {
        self.files().remove(name);
        Ok(())
    }

    fn remove_dir(&self, _site: &str, dir: &str) -> Result<()> {
        let prefix = format!("{dir}/");
        self.files().retain(|name, _| !name.starts_with(&prefix));
        Ok(())
    }

    fn retain(&self, keep: &BTreeSet<String>) -> Result<u64> {
        let mut files = self.files();
        let before = files.len();
        files.retain(|name, _| keep.contains(name));
        Ok((before - files.len()) as u64)
    }

    fn total_bytes(&self) -> Result<u64> {
        Ok(self.files().values().map(|bytes| bytes.len() as u64).sum())
    }

    fn path(&self, name: &str) -> PathBuf {
        PathBuf::from("<memory>/checkpoints").join(name)
    }

    fn lock(&self) -> MutexGuard<'_, ()> {
        self.lock.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn step(&self, step: CheckpointStep) {
        self.hook.call(step);
    }
}
