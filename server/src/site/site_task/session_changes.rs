//! The robots' session changes: opening a session, uploading a batch, closing a session, each
//! logged before it is applied.

use std::time::Instant;

use proto::{UploadBatch, UploadItem, pb};

use super::SiteTask;
use crate::site::{SessionOpened, SiteError, SiteMap, UploadAck, UploadCheck};

impl SiteTask {
    pub(super) async fn open_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<(SessionOpened, u64), SiteError> {
        storage::validate_session_id(session_uuid)?;
        self.check_store().await?;
        let opened = self.map()?.check_open(robot_id, session_uuid)?;
        if !opened.created {
            self.durable().await?;
            return Ok((opened, self.map()?.version()));
        }
        let version = self.map()?.version() + 1;
        self.persist(
            version,
            pb::site_log_entry::Entry::SessionOpened(pb::SessionOpened {
                robot_id: robot_id.to_owned(),
                session_uuid: session_uuid.to_owned(),
                trajectory: opened.trajectory,
            }),
            None,
        )
        .await?;
        if let Some(map) = self.map.as_mut() {
            map.open_session(robot_id, session_uuid, opened.trajectory, version)?;
        }
        self.metrics.session_opened();
        self.durable().await?;
        self.publish();
        Ok((opened, version))
    }

    pub(super) async fn upload(
        &mut self,
        batch: UploadBatch,
        sent: Instant,
    ) -> Result<UploadAck, SiteError> {
        self.check_store().await?;
        let map = self.map()?;
        if let UploadCheck::Duplicate { .. } = map.check_upload(&batch)? {
            self.durable().await?;
            self.metrics.upload_duplicate();
            let map = self.map()?;
            return Ok(UploadAck {
                seq: batch.seq,
                map_version: map.version(),
                duplicate: true,
                session_end_pose: batch
                    .ends_session()
                    .then(|| map.session_end_pose(&batch.session_uuid))
                    .flatten(),
            });
        }
        let version = map.version() + 1;
        let received = Instant::now();
        // The map applies exactly what replay will: the batch decoded from its stored form (a pose's
        // angle goes through `atan2` and `sin`/`cos` once more, which can move its last bit), so a
        // restart rebuilds this map bit for bit. A batch whose stored form does not decode is refused
        // before anything is stored.
        let entry = pb::UploadBatch::from(&batch);
        let batch = UploadBatch::try_from(&entry).map_err(SiteError::Unstorable)?;
        self.persist(
            version,
            pb::site_log_entry::Entry::Upload(entry),
            Some((batch.session_uuid.clone(), batch.seq)),
        )
        .await?;
        let (seq, session) = (batch.seq, batch.session_uuid.clone());
        let (nodes, submaps_finished) =
            batch.items.iter().fold((0, 0), |(n, s), item| match item {
                UploadItem::NodeAdded(_) => (n + 1, s),
                UploadItem::SubmapFinished { .. } => (n, s + 1),
                _ => (n, s),
            });
        let started = Instant::now();
        let ends_session = batch.ends_session();
        let apply = move |map: &mut SiteMap| map.apply_upload(&batch, version);
        let applied = if ends_session {
            self.with_map_in_maintenance("session end", apply).await?
        } else {
            self.with_map_blocking(apply).await?
        };
        let applying = started.elapsed();
        self.metrics.record_pgr(applying);
        tracing::debug!(
            version,
            nodes,
            submaps_finished,
            ends_session,
            optimizations = applied.as_ref().ok(),
            queue_seconds = (received - sent).as_secs_f64(),
            store_seconds = (started - received).as_secs_f64(),
            apply_seconds = applying.as_secs_f64(),
            "upload applied"
        );
        if let Err(e) = applied {
            // Stored but not fully applied: a bug (check_upload accepted it). Replay will hit it again.
            tracing::error!(version, "stored upload failed to apply: {e}");
            return Err(e);
        }
        self.metrics.upload_applied();
        if self.map()?.is_closed(&session) {
            self.last_heard.remove(&session);
            self.checkpoint_due = true;
        }
        self.durable().await?;
        self.publish();
        let session_end_pose = ends_session
            .then(|| self.map().ok()?.session_end_pose(&session))
            .flatten();
        Ok(UploadAck {
            seq,
            map_version: version,
            duplicate: false,
            session_end_pose,
        })
    }

    pub(super) async fn close_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<u64, SiteError> {
        self.check_store().await?;
        let map = self.map()?;
        map.check_open(robot_id, session_uuid)?;
        if map.is_closed(session_uuid) {
            self.durable().await?;
            return Ok(self.map()?.version());
        }
        if map.check_open(robot_id, session_uuid)?.created {
            return Err(SiteError::UnknownSession(session_uuid.to_owned()));
        }
        let version = map.version() + 1;
        self.persist(
            version,
            pb::site_log_entry::Entry::SessionClosed(pb::SessionClosed {
                session_uuid: session_uuid.to_owned(),
            }),
            None,
        )
        .await?;
        let (robot, session) = (robot_id.to_owned(), session_uuid.to_owned());
        let started = Instant::now();
        self.with_map_in_maintenance("session end", move |map| {
            map.close_session(&robot, &session, version)
        })
        .await??;
        self.last_heard.remove(session_uuid);
        self.checkpoint_due = true;
        let closing = started.elapsed();
        self.metrics.record_pgr(closing);
        tracing::info!(
            version,
            seconds = closing.as_secs_f64(),
            "session closed: trimmed, sparsified and optimized"
        );
        self.durable().await?;
        self.publish();
        Ok(version)
    }
}
