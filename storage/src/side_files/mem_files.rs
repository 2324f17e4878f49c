//! Files in memory: the [`crate::MemStore`]'s, so that it runs the same checkpoint and large-value code
//! as [`crate::SledStore`] (entries in the key-value map, bytes beside it).

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::sync::{Mutex, MutexGuard, PoisonError, RwLock, RwLockReadGuard, RwLockWriteGuard};

use super::SideFiles;
use crate::Result;

/// File name → bytes.
type Files = BTreeMap<String, Vec<u8>>;

/// Files held in memory; never fails.
#[derive(Debug)]
pub(crate) struct MemFiles {
    /// The directory they would be in on disk (`"checkpoints"`, `"values"`), for messages.
    dir: &'static str,
    files: Mutex<Files>,
    lock: RwLock<()>,
}

impl MemFiles {
    /// No files; `dir` names where they would be on disk, for messages.
    pub(crate) fn new(dir: &'static str) -> Self {
        Self {
            dir,
            files: Mutex::default(),
            lock: RwLock::default(),
        }
    }

    fn files(&self) -> MutexGuard<'_, Files> {
        self.files.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Test hook: gives `f` the files (name → bytes), e.g. to damage or delete one.
    #[cfg(test)]
    pub(crate) fn with_files(&self, f: impl FnOnce(&mut Files)) {
        f(&mut self.files());
    }
}

impl SideFiles for MemFiles {
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

    fn names(&self) -> Result<Vec<String>> {
        Ok(self.files().keys().cloned().collect())
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
        PathBuf::from("<memory>").join(self.dir).join(name)
    }

    fn shared(&self) -> RwLockReadGuard<'_, ()> {
        self.lock.read().unwrap_or_else(PoisonError::into_inner)
    }

    fn exclusive(&self) -> RwLockWriteGuard<'_, ()> {
        self.lock.write().unwrap_or_else(PoisonError::into_inner)
    }
}
