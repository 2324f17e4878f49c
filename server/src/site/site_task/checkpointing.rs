//! Checkpoints of the site (see the module docs of `site_task`): when one is due, copying the
//! site's state in the task, encoding and writing it beside the task, and recording the outcome.

use std::sync::Arc;
use std::time::Instant;

use prost::Message as _;
use proto::pb;
use tokio::task::JoinHandle;

use super::{SITE_LOG_KIND, SiteTask};
use crate::site::maintenance_thread::run_as_maintenance;
use crate::site::{SiteError, SiteMap};

/// A checkpoint written beside the task (see [`SiteTask::checkpoint_if_due`]).
pub(super) struct CheckpointWritten {
    version: u64,
    bytes: usize,
    compaction: storage::Compaction,
    /// The summary's write, if one was stored with it.
    summary: Option<Result<(), SiteError>>,
    /// From the start of the checkpoint to its durability.
    seconds: f64,
    /// The part the task waited for: the copy of the site's state.
    copy_s: f64,
}

/// The checkpoint write in flight.
pub(super) type CheckpointWriting = JoinHandle<Result<CheckpointWritten, SiteError>>;

/// The in-flight checkpoint write's outcome (never, if there is none).
pub(super) async fn written(
    writing: &mut Option<CheckpointWriting>,
) -> Result<Result<CheckpointWritten, SiteError>, tokio::task::JoinError> {
    match writing {
        Some(handle) => handle.await,
        None => std::future::pending().await,
    }
}

impl SiteTask {
    /// Starts a checkpoint of the site when one is due and can be taken (see the module docs of `site_task`): the
    /// site's state is copied ([`SiteMap::checkpoint`]) while the task waits, then encoded, written and
    /// the log compacted on a maintenance thread beside the task, which goes on with its
    /// requests ([`Self::checkpoint_written`] records the outcome). One write at a time: a checkpoint
    /// due meanwhile starts when the write ends. A failure is logged and retried after a later change:
    /// the log stays whole until a checkpoint is durable, so nothing depends on it.
    pub(super) async fn checkpoint_if_due(&mut self) {
        if self.checkpoint_writing.is_some() {
            return;
        }
        let Ok(version) = self.map().map(SiteMap::version) else {
            return;
        };
        let options = self.checkpoints;
        let by_versions =
            version.saturating_sub(self.checkpointed_version) >= options.every_n_versions;
        if !options.enabled
            || !(self.checkpoint_due || by_versions)
            || version <= self.checkpointed_version
            || self.unflushed
            || self.store.generation() != self.generation
        {
            return;
        }
        let started = Instant::now();
        // The task waits for the copy (at the priority of the requests behind it), not for the rest.
        let copied = self.with_map_blocking(|map| map.checkpoint()).await;
        let checkpoint = match copied {
            Ok(Some(checkpoint)) => checkpoint,
            Ok(None) => return, // a session is mid-start: at a later change
            Err(e) => {
                tracing::warn!(version, "cannot checkpoint the site: {e}");
                return;
            }
        };
        let copy_s = started.elapsed().as_secs_f64();
        // Due again only if a later change makes it so (or this write fails).
        self.checkpoint_due = false;
        let (store, site) = (Arc::clone(&self.store), self.site());
        let retention = options.retention();
        // Stored only once the checkpoint at its version is durable, and only if a start could use it.
        let summary = self
            .summary()
            .filter(|s| s.info.version == version && s.info.counts.open_sessions == 0);
        let span = tracing::Span::current();
        let write = move || {
            let _entered = span.enter();
            let bytes = pb::SiteCheckpoint::from(&checkpoint).encode_to_vec();
            drop(checkpoint);
            // What the kill -9 chaos test times its kills by (`fleet-demo/tests/kill_nine_fleet.rs`).
            tracing::debug!(
                version,
                bytes = bytes.len(),
                "writing the site's checkpoint"
            );
            store.put_checkpoint(&site, version, &bytes)?;
            let compaction = store.compact(&site, SITE_LOG_KIND, &retention)?;
            let summary = summary.map(|s| s.store(store.as_ref(), &site));
            Ok(CheckpointWritten {
                version,
                bytes: bytes.len(),
                compaction,
                summary,
                seconds: started.elapsed().as_secs_f64(),
                copy_s,
            })
        };
        self.checkpoint_writing = Some(tokio::spawn(async move {
            run_as_maintenance("checkpoint", write).await?
        }));
    }

    /// Records the outcome of the checkpoint write [`Self::checkpoint_if_due`] started.
    pub(super) fn checkpoint_written(
        &mut self,
        outcome: Result<Result<CheckpointWritten, SiteError>, tokio::task::JoinError>,
    ) {
        let written = match outcome.map_err(SiteError::Worker).and_then(|w| w) {
            Ok(written) => written,
            Err(e) => {
                self.checkpoint_due = true;
                tracing::warn!("cannot store the site's checkpoint: {e}");
                return;
            }
        };
        let version = written.version;
        self.checkpointed_version = self.checkpointed_version.max(version);
        let summarized = written.summary.is_some();
        match written.summary {
            Some(Ok(())) => self.summary_version = self.summary_version.max(version),
            Some(Err(e)) => tracing::warn!(version, "cannot store the site's summary: {e}"),
            None => {}
        }
        tracing::info!(
            version,
            bytes = written.bytes,
            seconds = written.seconds,
            copy_s = written.copy_s,
            log_compacted_through = written.compaction.log_compacted_through,
            log_entries_removed = written.compaction.log_entries_removed,
            summarized,
            "site checkpointed"
        );
    }

    /// Waits for the checkpoint write in flight, if any, and records it.
    pub(super) async fn finish_checkpoint(&mut self) {
        if let Some(writing) = self.checkpoint_writing.take() {
            let outcome = writing.await;
            self.checkpoint_written(outcome);
        }
    }
}
