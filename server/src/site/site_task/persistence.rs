//! Writing changes to the site log, and keeping the map equal to the stored log: writes not yet
//! flushed, and a store reopened after a failed write.

use std::sync::Arc;
use std::time::Instant;

use prost::Message as _;
use proto::{FORMAT_VERSION, pb};
use storage::{BatchOutcome, WriteBatch};

use super::{SITE_LOG_KIND, SiteTask};
use crate::site::SiteError;

impl SiteTask {
    /// Writes log entry `version` with the version bump and the session's sequence number, and flushes
    /// it. A failed write stores nothing (`Err`); a write applied but not flushed is `Ok` with
    /// [`Self::unflushed`] set: the caller applies it to the map, and [`Self::durable`] refuses to
    /// acknowledge it until a flush succeeds.
    pub(super) async fn persist(
        &mut self,
        version: u64,
        entry: pb::site_log_entry::Entry,
        session_seq: Option<(String, u64)>,
    ) -> Result<(), SiteError> {
        let bytes = pb::SiteLogEntry {
            format_version: FORMAT_VERSION,
            map_version: version,
            entry: Some(entry),
        }
        .encode_to_vec();
        let mut batch = WriteBatch::new(self.site());
        batch.put(SITE_LOG_KIND, version, bytes).bump_map_version();
        if let Some((session, seq)) = session_seq {
            batch.for_session(session, seq);
        }
        let store = Arc::clone(&self.store);
        let (outcome, flushed) =
            tokio::task::spawn_blocking(move || store.apply(&batch).map(|o| (o, store.flush())))
                .await
                .map_err(SiteError::Worker)??;
        match outcome {
            BatchOutcome::Applied { map_version } if map_version == version => {}
            other => {
                return Err(SiteError::Internal(format!(
                    "store disagrees on the site version: expected to write {version}, got {other:?}"
                )));
            }
        }
        if let Err(e) = flushed {
            tracing::warn!(
                version,
                "change stored but not durable ({e}): not acknowledged until a flush succeeds"
            );
            self.unflushed = true;
        } else if self.store.generation() != self.generation {
            // Reopened between the write and the flush: the flush may not have covered the write.
            self.unflushed = true;
        }
        Ok(())
    }

    /// Before any change: if the store was reopened since the map was built and the map may differ
    /// from it, rebuilds the map from the store (see the module docs of `site_task`). `Err` while that fails (nothing
    /// may be changed on a map that may not equal the store).
    pub(super) async fn check_store(&mut self) -> Result<(), SiteError> {
        let generation = self.store.generation();
        if generation == self.generation {
            return Ok(());
        }
        let stored = {
            let (store, site) = (Arc::clone(&self.store), self.site());
            tokio::task::spawn_blocking(move || store.map_version(&site))
                .await
                .map_err(SiteError::Worker)??
        };
        if !self.unflushed && stored == self.map()?.version() {
            self.generation = generation;
            return Ok(());
        }
        self.rebuild(generation).await
    }

    /// Replays the store's log into a new map, which replaces the current one.
    async fn rebuild(&mut self, generation: u64) -> Result<(), SiteError> {
        let before = self.map()?.version();
        let started = Instant::now();
        let loaded = self
            .load_from_store("after the store was reopened its log")
            .await?;
        let version = loaded.map.version();
        tracing::warn!(
            from_version = before,
            to_version = version,
            seconds = started.elapsed().as_secs_f64(),
            "the store was reopened after a failed write: site map rebuilt from its log"
        );
        self.install(loaded, generation);
        self.publish();
        Ok(())
    }

    /// Flushes a change [`Self::persist`] could not; `Err` while the store still cannot (nothing may
    /// be acknowledged or published before), and publishes the version once it can.
    pub(super) async fn durable(&mut self) -> Result<(), SiteError> {
        if !self.unflushed {
            return Ok(());
        }
        let store = Arc::clone(&self.store);
        tokio::task::spawn_blocking(move || store.flush())
            .await
            .map_err(SiteError::Worker)??;
        if self.store.generation() != self.generation {
            // The store was reopened: the unflushed change may be gone. Rebuild, and let the robot
            // retry (its batch is then applied once, or acknowledged as a duplicate).
            let generation = self.store.generation();
            self.rebuild(generation).await?;
            return Err(SiteError::Storage(storage::StorageError::Wedged {
                cause: "the store was reopened before the change was durable".into(),
                source: None,
                out_of_space: false,
            }));
        }
        self.unflushed = false;
        tracing::info!("stored changes are durable again");
        self.publish();
        Ok(())
    }
}
