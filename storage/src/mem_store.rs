//! In-memory [`crate::MapStore`] for tests and simulations.

use std::collections::BTreeMap;
use std::sync::{Mutex, MutexGuard, PoisonError};

use crate::Result;
use crate::file_step::{FileStep, StepHook};
use crate::raw_kv::{RawIter, RawKv, RawTxn, impl_map_store_via_raw_kv};
use crate::side_files::{MemFiles, SideFiles};
use crate::value_files::ValueFiles;

type Map = BTreeMap<Vec<u8>, Vec<u8>>;

/// A [`crate::MapStore`] in memory, with exactly the semantics of [`crate::SledStore`] except durability
/// ([`crate::MapStore::flush`] makes nothing more durable and everything is lost on drop). Values are
/// sealed and verified like on disk, and checkpoints and large values are entries in the map with their
/// bytes beside it, as sled's are with their bytes in files (a replaced large value's bytes go at the
/// next flush). Transactions run under one mutex; scans return a copy taken when they start.
#[derive(Debug)]
pub struct MemStore {
    map: Mutex<Map>,
    checkpoint_files: MemFiles,
    value_files: ValueFiles<MemFiles>,
    hook: StepHook,
}

impl Default for MemStore {
    fn default() -> Self {
        Self {
            map: Mutex::default(),
            checkpoint_files: MemFiles::new("checkpoints"),
            value_files: ValueFiles::new(MemFiles::new("values")),
            hook: StepHook::default(),
        }
    }
}

impl MemStore {
    /// An empty store.
    pub fn new() -> Self {
        Self::default()
    }

    fn lock(&self) -> MutexGuard<'_, Map> {
        // A panic while holding the lock cannot leave a half-applied transaction: writes are staged first.
        self.map.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Test hook: gives `f` the raw stored map (keys and sealed values), e.g. to corrupt a byte.
    #[cfg(test)]
    pub(crate) fn with_raw(&self, f: impl FnOnce(&mut Map)) {
        f(&mut self.lock());
    }

    /// Test hook: the checkpoint files, e.g. to damage or delete one.
    #[cfg(test)]
    pub(crate) fn files(&self) -> &MemFiles {
        &self.checkpoint_files
    }

    /// Test hook: the value files, e.g. to damage or delete one.
    #[cfg(test)]
    pub(crate) fn values(&self) -> &MemFiles {
        self.value_files.files()
    }

    /// Test hook: sets the hook [`RawKv::step`] calls.
    #[cfg(test)]
    pub(crate) fn hook(&self) -> &StepHook {
        &self.hook
    }
}

struct MemTxn<'a> {
    base: &'a Map,
    staged: BTreeMap<Vec<u8>, Option<Vec<u8>>>,
}

impl RawTxn for MemTxn<'_> {
    fn get(&mut self, key: &[u8]) -> Result<Option<Vec<u8>>> {
        Ok(match self.staged.get(key) {
            Some(staged) => staged.clone(),
            None => self.base.get(key).cloned(),
        })
    }

    fn insert(&mut self, key: &[u8], value: Vec<u8>) -> Result<Option<Vec<u8>>> {
        let old = self.get(key)?;
        self.staged.insert(key.to_vec(), Some(value));
        Ok(old)
    }

    fn remove(&mut self, key: &[u8]) -> Result<Option<Vec<u8>>> {
        let old = self.get(key)?;
        self.staged.insert(key.to_vec(), None);
        Ok(old)
    }
}

impl RawKv for MemStore {
    fn checkpoint_files(&self) -> &dyn SideFiles {
        &self.checkpoint_files
    }

    fn value_files(&self) -> &ValueFiles {
        &self.value_files
    }

    fn step(&self, step: FileStep) {
        self.hook.call(step);
    }

    fn raw_get(&self, key: &[u8]) -> Result<Option<Vec<u8>>> {
        Ok(self.lock().get(key).cloned())
    }

    fn raw_scan(&self, prefix: &[u8]) -> RawIter<'_> {
        let entries: Vec<_> = self
            .lock()
            .range(prefix.to_vec()..)
            .take_while(|(key, _)| key.starts_with(prefix))
            .map(|(key, value)| Ok((key.clone(), value.clone())))
            .collect();
        Box::new(entries.into_iter())
    }

    fn transact<T>(&self, body: &dyn Fn(&mut dyn RawTxn) -> Result<T>) -> Result<T> {
        let mut map = self.lock();
        let mut txn = MemTxn {
            base: &map,
            staged: BTreeMap::new(),
        };
        let value = body(&mut txn)?;
        let staged = txn.staged;
        for (key, value) in staged {
            match value {
                Some(value) => map.insert(key, value),
                None => map.remove(&key),
            };
        }
        Ok(value)
    }

    fn raw_flush(&self) -> Result<()> {
        Ok(())
    }
}

impl_map_store_via_raw_kv!(MemStore);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{MapStore as _, RecordId, RecordKind, StorageError, WriteBatch, conformance, key};

    #[test]
    fn conformance_suite() {
        let cases = conformance::run_all(&|| MemStore::new());
        assert!(
            cases >= conformance::MIN_CASES,
            "only {cases} conformance cases ran"
        );
    }

    #[test]
    fn failure_inside_a_transaction_writes_nothing() {
        let store = MemStore::new();
        let mut batch = WriteBatch::new("depot");
        batch.bump_map_version();
        store.apply(&batch).unwrap();
        let version_key = key::record_key("depot", key::KIND_MAP_VERSION, &[]);
        store.with_raw(|map| map.get_mut(&version_key).unwrap()[5] ^= 0x01);
        batch
            .put(RecordKind::Node, 1, b"staged".to_vec())
            .for_session("robot", 1);
        assert!(matches!(
            store.apply(&batch),
            Err(StorageError::Corrupt { .. })
        ));
        assert_eq!(
            store
                .get("depot", RecordKind::Node, &RecordId::from(1))
                .unwrap(),
            None
        );
        assert_eq!(store.last_applied_seq("depot", "robot").unwrap(), None);
    }

    #[test]
    fn corrupt_value_is_reported_not_returned() {
        let store = MemStore::new();
        let id = RecordId::from("s1");
        store
            .put("depot", RecordKind::Submap, &id, b"grid bytes")
            .unwrap();
        store.with_raw(|map| {
            let value = map
                .values_mut()
                .find(|value| value.ends_with(b"grid bytes"))
                .unwrap();
            let last = value.len() - 1;
            value[last] ^= 0x01;
        });
        assert!(matches!(
            store.get("depot", RecordKind::Submap, &id),
            Err(StorageError::Corrupt { .. })
        ));
        let scanned: Vec<_> = store.scan("depot", RecordKind::Submap).unwrap().collect();
        assert!(matches!(
            scanned.as_slice(),
            [Err(StorageError::Corrupt { .. })]
        ));
        assert!(matches!(
            store.export_site("depot", &mut Vec::new()),
            Err(StorageError::Corrupt { .. })
        ));
    }
}
