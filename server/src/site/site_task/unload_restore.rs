//! Idle sites leave memory: unloading a site once a durable checkpoint covers it, and restoring it
//! at its next request.

use std::sync::Arc;
use std::time::Instant;

use super::SiteTask;
use crate::site::{SiteError, VersionInfo};

impl SiteTask {
    /// Unloads the site if it has been idle long enough (see the module docs of `site_task`).
    pub(super) async fn unload_if_idle(&mut self) {
        let Some(after) = self.unload_after else {
            return;
        };
        if self.unloaded || self.last_request.idle() < after {
            return;
        }
        if !self.unload().await {
            // Not now (a session open, no checkpoint possible): look again after another idle period.
            self.last_request.touch();
        }
    }

    /// Drops the map from memory if no session is open and a durable checkpoint covers its version
    /// (written now if needed); `true` if the site is unloaded now.
    pub(super) async fn unload(&mut self) -> bool {
        if self.unloaded {
            return true;
        }
        let Ok(map) = self.map() else {
            return false;
        };
        let version = map.version();
        if !self.checkpoints.enabled || !map.open_sessions().is_empty() {
            return false;
        }
        self.finish_checkpoint().await;
        if self.checkpointed_version != version {
            self.checkpoint_due = true;
            self.checkpoint_if_due().await;
            self.finish_checkpoint().await;
        }
        if self.checkpointed_version != version
            || self.unflushed
            || self.store.generation() != self.generation
        {
            tracing::debug!(
                version,
                checkpointed = self.checkpointed_version,
                "site idle but not unloaded: no durable checkpoint covers its version"
            );
            return false;
        }
        if self.summary_version != version {
            // Checkpointed while a session was open, or the summary's write failed: without one
            // the next start loads the site.
            if let Some(summary) = self.summary() {
                let (store, site) = (Arc::clone(&self.store), self.site());
                match tokio::task::spawn_blocking(move || summary.store(store.as_ref(), &site))
                    .await
                {
                    Ok(Ok(())) => self.summary_version = version,
                    Ok(Err(e)) => tracing::warn!(version, "cannot store the site's summary: {e}"),
                    Err(e) => tracing::warn!(version, "cannot store the site's summary: {e}"),
                }
            }
        }
        let Some(map) = self.map.take() else {
            return false;
        };
        self.unloaded = true;
        self.last_heard.clear();
        let view = self.views.borrow().unloaded();
        self.views.send_replace(Arc::new(view));
        self.metrics.site_unloaded();
        tracing::info!(
            version,
            idle_s = self.last_request.idle().as_secs_f64(),
            "site unloaded: its map dropped from memory until the next request"
        );
        // Freeing a big map takes a while: beside the task, then the pages go back to the system.
        drop(tokio::task::spawn_blocking(move || {
            drop(map);
            proto::memory_release::release_all_freed_memory_in_background();
        }));
        true
    }

    /// Restores an unloaded site from its store (its checkpoint and the log after it) and publishes
    /// its view again; `Err` leaves it unloaded.
    pub(super) async fn restore(&mut self) -> Result<(), SiteError> {
        let started = Instant::now();
        let generation = self.store.generation();
        let loaded = self.load_from_store("the unloaded site's store").await?;
        let seconds = started.elapsed();
        self.metrics.site_restored(seconds);
        tracing::info!(
            version = loaded.map.version(),
            checkpoint = loaded.checkpoint,
            replayed = loaded.replayed,
            seconds = seconds.as_secs_f64(),
            read_s = loaded.times.read.as_secs_f64(),
            decode_s = loaded.times.decode.as_secs_f64(),
            rebuild_s = loaded.times.rebuild.as_secs_f64(),
            replay_s = loaded.times.replay.as_secs_f64(),
            "unloaded site restored"
        );
        self.install(loaded, generation);
        self.unloaded = false;
        // The view comes back with the map; the version is only announced if it moved.
        if let Ok(map) = self.map() {
            let info = VersionInfo {
                version: map.version(),
                counts: map.counts(),
            };
            self.views.send_replace(Arc::new(map.view()));
            self.versions.send_if_modified(|current| {
                let moved = *current != info;
                *current = info;
                moved
            });
        }
        Ok(())
    }
}
