//! Durable, exactly-once uploading of one robot's batches, and the end of sessions an agent restart
//! interrupted.
//!
//! A restarted agent does not resume its interrupted session: it ends it and starts a new one. The
//! session's LLO state (active submaps, the local frame, the pose extrapolator) died with the process, so
//! a resumed session would add nodes in a fresh local frame to a trajectory whose submaps it can no
//! longer insert into. Ending it keeps everything the server acknowledged (its nodes and finished
//! submaps, and its place in the map); the submaps that were still active are lost with their grids.
//! The [`Uploader`] of the new session therefore first delivers what the outbox still holds of every
//! other unfinished session (see [`crate::outbox`]) and ends each one with `CloseSession` (unless its
//! own `SessionEnd` was delivered), before any batch of its own session.
//!
//! A full disk does not end the session: a batch the outbox cannot store (`ENOSPC`) is kept in memory,
//! numbered, and stored — then sent — once the disk has room again (at most
//! [`MAX_UNSTORED_BATCHES`]; past that the session fails with the storage error). Such a batch is not
//! durable: it would die with the process, which is all a full disk leaves.

use std::collections::{BTreeSet, VecDeque};

use mapping::geometry::Rigid2;
use proto::{FORMAT_VERSION, UploadItem, pb};

use super::{MapUplink, UplinkError};
use crate::outbox::Outbox;

/// Batches kept in memory while the outbox's disk is full, at most (about as many minutes of mapping
/// at the default batch size and scan rate).
pub const MAX_UNSTORED_BATCHES: usize = 1024;

/// What one [`Uploader::flush`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FlushStats {
    /// Batches the server applied.
    pub applied: usize,
    /// Batches the server already had (their ack had been lost).
    pub duplicates: usize,
    /// Batches dropped from the outbox because re-opening the session showed the server had them.
    pub already_acked: usize,
    /// Interrupted sessions (of an earlier run of the agent) ended on the server.
    pub interrupted_ended: usize,
    /// Batches of interrupted sessions the server refused because it had already ended the session
    /// (its robot was silent past the server's idle timeout): they cannot be applied and were dropped.
    pub dropped_after_server_end: usize,
    /// Site version after the last ack.
    pub map_version: u64,
}

/// What the server's ack of a session's end said.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SessionEnded {
    /// Where the server put the session's last node in the site map after the end (`site_from_tracking`);
    /// `None` when the session ended unplaced.
    pub pose: Option<Rigid2>,
}

/// Whether a batch carries its session's end.
fn ends_session(batch: &pb::UploadBatch) -> bool {
    batch
        .items
        .iter()
        .any(|item| matches!(item.item, Some(pb::upload_item::Item::SessionEnd(_))))
}

/// The server refused a batch because its session is closed (`SiteError::SessionClosed`; a sequence gap,
/// the other failed precondition, arrives as [`UplinkError::SequenceGap`]).
fn session_closed(error: &UplinkError) -> bool {
    matches!(
        error,
        UplinkError::Rejected {
            code: tonic::Code::FailedPrecondition,
            ..
        }
    )
}

/// Numbers one session's batches, keeps them in the outbox until acknowledged, and sends them in order.
pub struct Uploader<U> {
    uplink: U,
    outbox: Outbox,
    site: String,
    robot_id: String,
    session_uuid: String,
    next_seq: u64,
    /// Sessions opened on the current connection (cleared when the link fails).
    opened: BTreeSet<String>,
    last_version: u64,
    trajectory: Option<u32>,
    /// Batches made while the outbox's disk was full, in sequence order, not yet stored.
    unstored: VecDeque<pb::UploadBatch>,
    /// The last outbox write failed for lack of space.
    outbox_full: bool,
    /// Set when the server acknowledged this session's end.
    session_end: Option<SessionEnded>,
}

impl<U: MapUplink> Uploader<U> {
    /// An uploader for a session; continues the session's numbering from the outbox (a fresh session
    /// starts at 1). Batches of older sessions still in the outbox are sent too.
    pub fn new(
        uplink: U,
        outbox: Outbox,
        site: &str,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<Self, UplinkError> {
        let next_seq = outbox.last_seq(session_uuid)?.map_or(1, |s| s + 1);
        Ok(Self {
            uplink,
            outbox,
            site: site.to_owned(),
            robot_id: robot_id.to_owned(),
            session_uuid: session_uuid.to_owned(),
            next_seq,
            opened: BTreeSet::new(),
            last_version: 0,
            session_end: None,
            trajectory: None,
            unstored: VecDeque::new(),
            outbox_full: false,
        })
    }

    /// The span this session runs in ([`super::session_span`] of its site, robot and session).
    pub fn session_span(&self) -> tracing::Span {
        super::session_span(&self.site, &self.robot_id, &self.session_uuid)
    }

    /// The trajectory the server gave this uploader's session, once it has been opened.
    pub fn trajectory(&self) -> Option<u32> {
        self.trajectory
    }

    /// The uplink (e.g. for map queries).
    pub fn uplink_mut(&mut self) -> &mut U {
        &mut self.uplink
    }

    /// The outbox.
    pub fn outbox(&self) -> &Outbox {
        &self.outbox
    }

    /// The sequence number the next batch gets.
    pub fn next_seq(&self) -> u64 {
        self.next_seq
    }

    /// Site version of the last acknowledgement seen.
    pub fn last_version(&self) -> u64 {
        self.last_version
    }

    /// Batches kept in memory because the outbox's disk was full.
    pub fn unstored(&self) -> usize {
        self.unstored.len()
    }

    /// Stores the batches kept in memory, in order, as far as the disk allows. `Err` on any other
    /// storage failure, or when more than [`MAX_UNSTORED_BATCHES`] are waiting.
    fn store_unstored(&mut self) -> Result<(), UplinkError> {
        while let Some(batch) = self.unstored.front() {
            match self.outbox.push(batch) {
                Ok(()) => {
                    self.unstored.pop_front();
                }
                Err(e) if e.is_out_of_space() && self.unstored.len() <= MAX_UNSTORED_BATCHES => {
                    if !self.outbox_full {
                        self.outbox_full = true;
                        tracing::warn!(
                            seq = batch.seq,
                            "the outbox cannot store a batch ({e}): keeping batches in memory (at \
                             most {MAX_UNSTORED_BATCHES}) until the disk has room"
                        );
                    }
                    return Ok(());
                }
                Err(e) => return Err(e.into()),
            }
        }
        if self.outbox_full {
            self.outbox_full = false;
            tracing::info!("the outbox has room again");
        }
        Ok(())
    }

    /// Makes a batch of `items` with the next sequence number and stores it in the outbox (durably) —
    /// or, while the outbox's disk is full, keeps it in memory (see the module docs).
    pub fn enqueue(&mut self, items: &[UploadItem]) -> Result<u64, UplinkError> {
        let seq = self.next_seq;
        let batch = pb::UploadBatch {
            format_version: FORMAT_VERSION,
            site: self.site.clone(),
            robot_id: self.robot_id.clone(),
            session_uuid: self.session_uuid.clone(),
            seq,
            items: items.iter().map(pb::UploadItem::from).collect(),
        };
        self.unstored.push_back(batch);
        self.next_seq += 1;
        self.store_unstored()?;
        Ok(seq)
    }

    /// The server's acknowledgement of this session's end, once it came.
    pub fn session_end(&self) -> Option<SessionEnded> {
        self.session_end
    }

    /// Sends every pending batch in order (opening each session first on a new connection, and dropping
    /// what the server already has). Stops at the first failure; a transient one ([`UplinkError::is_transient`])
    /// leaves everything in the outbox for the next flush.
    pub async fn flush(&mut self) -> Result<FlushStats, UplinkError> {
        self.store_unstored()?;
        let result = self.try_flush().await;
        if result.is_err() {
            self.opened.clear();
        }
        result
    }

    /// Sessions of earlier runs still unfinished in the outbox (not yet ended on the server), as
    /// (session uuid, robot id).
    pub fn interrupted_sessions(&self) -> Result<Vec<(String, String)>, UplinkError> {
        let mut sessions: BTreeSet<(String, String)> =
            self.outbox.unfinished_sessions()?.into_iter().collect();
        // Batches without a marker (an outbox written before markers existed) are interrupted too.
        for batch in self.outbox.pending()? {
            if !sessions.iter().any(|(s, _)| *s == batch.session_uuid) {
                sessions.insert((batch.session_uuid, batch.robot_id));
            }
        }
        Ok(sessions
            .into_iter()
            .filter(|(s, _)| *s != self.session_uuid)
            .collect())
    }

    async fn try_flush(&mut self) -> Result<FlushStats, UplinkError> {
        let mut stats = FlushStats {
            map_version: self.last_version,
            ..FlushStats::default()
        };
        for (session, robot) in self.interrupted_sessions()? {
            self.end_interrupted(&session, &robot, &mut stats).await?;
        }
        let pending: Vec<pb::UploadBatch> = self
            .outbox
            .pending()?
            .into_iter()
            .filter(|b| b.session_uuid == self.session_uuid)
            .collect();
        if self.deliver(pending, &mut stats).await? {
            self.outbox.finish_session(&self.session_uuid)?;
        }
        Ok(stats)
    }

    /// Delivers what is left of interrupted `session` and ends it on the server.
    async fn end_interrupted(
        &mut self,
        session: &str,
        robot: &str,
        stats: &mut FlushStats,
    ) -> Result<(), UplinkError> {
        let pending: Vec<pb::UploadBatch> = self
            .outbox
            .pending()?
            .into_iter()
            .filter(|b| b.session_uuid == session)
            .collect();
        let ended = match self.deliver(pending, stats).await {
            Ok(ended) => ended,
            Err(e) if session_closed(&e) => {
                // The server ended the session itself (silent past its idle timeout): what is left
                // can never be applied.
                let dropped = self.outbox.finish_session(session)?;
                tracing::warn!(
                    interrupted_session = session,
                    dropped,
                    "the server had already ended this interrupted session: dropping its undelivered batches"
                );
                stats.dropped_after_server_end += dropped;
                stats.interrupted_ended += 1;
                return Ok(());
            }
            Err(e) => return Err(e),
        };
        if !ended {
            match self.uplink.close_session(robot, session).await {
                Ok(version) => {
                    self.last_version = self.last_version.max(version);
                    stats.map_version = self.last_version;
                }
                // Never opened on the server (nothing of it was ever delivered): nothing to end.
                Err(UplinkError::Rejected {
                    code: tonic::Code::NotFound,
                    ..
                }) => {}
                Err(e) => return Err(e),
            }
        }
        self.outbox.finish_session(session)?;
        stats.interrupted_ended += 1;
        tracing::info!(interrupted_session = session, "interrupted session ended");
        Ok(())
    }

    /// Sends `batches` (of one session, in order), opening their session first on a new connection and
    /// dropping what the server already has. Returns whether the session's end was among them.
    async fn deliver(
        &mut self,
        batches: Vec<pb::UploadBatch>,
        stats: &mut FlushStats,
    ) -> Result<bool, UplinkError> {
        let mut ended = false;
        let mut skip_through: Option<(String, u64)> = None;
        for batch in batches {
            if !self.opened.contains(&batch.session_uuid) {
                let opened = self
                    .uplink
                    .open_session(&batch.robot_id, &batch.session_uuid)
                    .await?;
                stats.already_acked += self
                    .outbox
                    .remove_through(&batch.session_uuid, opened.last_acked_seq)?;
                skip_through = Some((batch.session_uuid.clone(), opened.last_acked_seq));
                if batch.session_uuid == self.session_uuid {
                    self.trajectory = Some(opened.trajectory);
                }
                self.opened.insert(batch.session_uuid.clone());
            }
            ended |= ends_session(&batch);
            if skip_through
                .as_ref()
                .is_some_and(|(s, seq)| *s == batch.session_uuid && batch.seq <= *seq)
            {
                continue;
            }
            let ack = self.uplink.upload(&batch).await?;
            if batch.session_uuid == self.session_uuid && ends_session(&batch) {
                self.session_end = Some(SessionEnded {
                    pose: ack.session_end_pose,
                });
            }
            if ack.duplicate {
                stats.duplicates += 1;
            } else {
                stats.applied += 1;
            }
            self.outbox.remove_through(&batch.session_uuid, batch.seq)?;
            self.last_version = self.last_version.max(ack.map_version);
            stats.map_version = self.last_version;
        }
        Ok(ended)
    }
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;
    use mapping::sensor::Timestamp;
    use proto::NodeAdded;

    use super::*;
    use crate::uplink::InMemoryUplink;

    fn items(i: i64) -> Vec<UploadItem> {
        vec![UploadItem::NodeAdded(NodeAdded {
            time: Timestamp(i),
            local_pose: rigid2(0.0, 0.0, 0.0),
            points: vec![],
            insertion_submaps: vec![(0, rigid2(0.0, 0.0, 0.0))],
            recovered: false,
        })]
    }

    #[tokio::test]
    async fn the_acknowledged_end_of_the_session_is_kept_and_only_its_own() {
        let server = InMemoryUplink::new("s");
        let outbox = Outbox::in_memory("s");
        let mut uploader = Uploader::new(server.clone(), outbox.clone(), "s", "r", "sess").unwrap();
        uploader.enqueue(&items(1)).unwrap();
        uploader.flush().await.unwrap();
        assert_eq!(uploader.session_end(), None, "not ended yet");
        uploader.enqueue(&[UploadItem::SessionEnd]).unwrap();
        uploader.flush().await.unwrap();
        // The in-memory server places nothing: the end is acknowledged, with no pose.
        assert_eq!(uploader.session_end(), Some(SessionEnded { pose: None }));
        // An interrupted session's end, delivered by the next run's uploader, is not that run's own.
        let mut interrupted =
            Uploader::new(server.clone(), outbox.clone(), "s", "r", "old").unwrap();
        interrupted.enqueue(&items(2)).unwrap();
        interrupted.enqueue(&[UploadItem::SessionEnd]).unwrap();
        let mut next = Uploader::new(server.clone(), outbox, "s", "r", "next").unwrap();
        next.enqueue(&items(3)).unwrap();
        let stats = next.flush().await.unwrap();
        assert_eq!(stats.interrupted_ended, 1);
        let ends = server
            .applied()
            .iter()
            .filter(|b| b.session_uuid == "old" && ends_session(b))
            .count();
        assert_eq!(ends, 1, "the interrupted session's end reached the server");
        assert_eq!(next.session_end(), None);
    }

    #[test]
    fn an_ack_with_a_malformed_end_pose_is_refused() {
        let ack = |theta: f64| pb::Ack {
            format_version: FORMAT_VERSION,
            session_uuid: "sess".into(),
            seq: 2,
            map_version: 7,
            duplicate: false,
            session_end_pose: Some(pb::Pose2 {
                x: 1.0,
                y: 2.0,
                theta,
            }),
        };
        let acked = super::super::Acked::from_wire(&ack(0.5)).unwrap();
        assert_eq!(acked.session_end_pose, Some(rigid2(1.0, 2.0, 0.5)));
        assert!(matches!(
            super::super::Acked::from_wire(&ack(f64::NAN)),
            Err(UplinkError::Malformed(_))
        ));
    }

    #[tokio::test]
    async fn a_dead_link_loses_nothing_and_duplicates_nothing() {
        let server = InMemoryUplink::new("s");
        let mut uploader =
            Uploader::new(server.clone(), Outbox::in_memory("s"), "s", "r", "sess").unwrap();
        uploader.enqueue(&items(1)).unwrap();
        assert_eq!(uploader.flush().await.unwrap().applied, 1);
        server.set_online(false);
        for i in 2..=4 {
            uploader.enqueue(&items(i)).unwrap();
            assert!(uploader.flush().await.unwrap_err().is_transient());
        }
        assert_eq!(uploader.outbox().len().unwrap(), 3);
        server.set_online(true);
        let stats = uploader.flush().await.unwrap();
        assert_eq!((stats.applied, stats.duplicates), (3, 0));
        assert!(uploader.outbox().is_empty().unwrap());
        let seqs: Vec<u64> = server.applied().iter().map(|b| b.seq).collect();
        assert_eq!(seqs, [1, 2, 3, 4]);
    }

    #[tokio::test]
    async fn a_restarted_agent_resumes_from_its_outbox_and_the_servers_last_ack() {
        let server = InMemoryUplink::new("s");
        let outbox = Outbox::in_memory("s");
        {
            let mut first =
                Uploader::new(server.clone(), outbox.clone(), "s", "r", "sess").unwrap();
            first.enqueue(&items(1)).unwrap();
            first.enqueue(&items(2)).unwrap();
            first.flush().await.unwrap();
            // Batch 3 reaches the server but the agent dies before removing it from the outbox.
            first.enqueue(&items(3)).unwrap();
            let pending = outbox.pending().unwrap();
            server.clone().upload(&pending[0]).await.unwrap();
            first.enqueue(&items(4)).unwrap();
        }
        let mut second = Uploader::new(server.clone(), outbox.clone(), "s", "r", "sess").unwrap();
        assert_eq!(second.next_seq(), 5);
        let stats = second.flush().await.unwrap();
        assert_eq!(
            (stats.already_acked, stats.applied, stats.duplicates),
            (1, 1, 0)
        );
        let seqs: Vec<u64> = server.applied().iter().map(|b| b.seq).collect();
        assert_eq!(seqs, [1, 2, 3, 4]);
        assert_eq!(server.duplicates(), 0);
    }

    fn end_batch(i: i64) -> Vec<UploadItem> {
        let mut items = items(i);
        items.push(UploadItem::SessionEnd);
        items
    }

    #[tokio::test]
    async fn a_restarted_agent_ends_its_interrupted_session_and_starts_a_new_one() {
        let server = InMemoryUplink::new("s");
        let outbox = Outbox::in_memory("s");
        {
            let mut first = Uploader::new(server.clone(), outbox.clone(), "s", "r", "old").unwrap();
            first.enqueue(&items(1)).unwrap();
            first.flush().await.unwrap();
            // Killed with one batch not yet delivered.
            first.enqueue(&items(2)).unwrap();
        }
        let mut second = Uploader::new(server.clone(), outbox.clone(), "s", "r", "new").unwrap();
        assert_eq!(second.next_seq(), 1, "a new session numbers from 1");
        assert_eq!(
            second.interrupted_sessions().unwrap(),
            [("old".to_owned(), "r".to_owned())]
        );
        // The link is down at first: nothing is ended, nothing lost.
        server.set_online(false);
        assert!(second.flush().await.unwrap_err().is_transient());
        assert!(!server.is_closed("old"));
        server.set_online(true);
        let stats = second.flush().await.unwrap();
        assert_eq!((stats.applied, stats.interrupted_ended), (1, 1));
        assert!(server.is_closed("old"));
        assert!(second.interrupted_sessions().unwrap().is_empty());
        assert!(outbox.is_empty().unwrap());

        second.enqueue(&items(3)).unwrap();
        second.enqueue(&end_batch(4)).unwrap();
        let stats = second.flush().await.unwrap();
        assert_eq!((stats.applied, stats.interrupted_ended), (2, 0));
        assert!(
            outbox.unfinished_sessions().unwrap().is_empty(),
            "the new session's end was delivered: nothing is unfinished"
        );
        let sent: Vec<(String, u64)> = server
            .applied()
            .iter()
            .map(|b| (b.session_uuid.clone(), b.seq))
            .collect();
        assert_eq!(
            sent,
            [("old", 1), ("old", 2), ("new", 1), ("new", 2)].map(|(s, n)| (s.to_owned(), n))
        );
        assert_eq!(server.duplicates(), 0);
    }

    #[tokio::test]
    async fn an_interrupted_session_with_everything_delivered_is_ended_too() {
        let server = InMemoryUplink::new("s");
        let outbox = Outbox::in_memory("s");
        {
            let mut first = Uploader::new(server.clone(), outbox.clone(), "s", "r", "old").unwrap();
            first.enqueue(&items(1)).unwrap();
            first.flush().await.unwrap();
            assert!(outbox.is_empty().unwrap());
        }
        let mut second = Uploader::new(server.clone(), outbox.clone(), "s", "r", "new").unwrap();
        assert!(!server.is_closed("old"));
        let stats = second.flush().await.unwrap();
        assert_eq!((stats.applied, stats.interrupted_ended), (0, 1));
        assert!(server.is_closed("old"));

        // A session whose end was delivered before the kill is finished: nothing to end.
        let mut third = Uploader::new(server.clone(), outbox.clone(), "s", "r", "third").unwrap();
        second.enqueue(&end_batch(2)).unwrap();
        second.flush().await.unwrap();
        assert!(third.interrupted_sessions().unwrap().is_empty());
        assert_eq!(third.flush().await.unwrap().interrupted_ended, 0);
    }

    #[tokio::test]
    async fn batches_of_a_session_the_server_ended_are_dropped_not_retried_for_ever() {
        let server = InMemoryUplink::new("s");
        let outbox = Outbox::in_memory("s");
        {
            let mut first = Uploader::new(server.clone(), outbox.clone(), "s", "r", "old").unwrap();
            first.enqueue(&items(1)).unwrap();
            first.flush().await.unwrap();
            first.enqueue(&items(2)).unwrap();
            first.enqueue(&items(3)).unwrap();
        }
        server.close_as_server("old");
        let mut second = Uploader::new(server.clone(), outbox.clone(), "s", "r", "new").unwrap();
        let stats = second.flush().await.unwrap();
        assert_eq!(
            (
                stats.applied,
                stats.dropped_after_server_end,
                stats.interrupted_ended
            ),
            (0, 2, 1)
        );
        assert!(outbox.is_empty().unwrap());
        assert!(outbox.unfinished_sessions().unwrap().is_empty());
        // The current session is not excused: a refusal of its own batch is an error.
        second.enqueue(&items(4)).unwrap();
        server.clone().open_session("r", "new").await.unwrap();
        server.close_as_server("new");
        assert!(!second.flush().await.unwrap_err().is_transient());
    }

    /// Issue 16 §1, disk full on the agent: batches made while the outbox cannot store them are kept
    /// in memory, the session goes on, and once space returns every batch reaches the server exactly
    /// once, in order — whether the full disk fails the write or only its flush.
    #[tokio::test]
    async fn a_full_outbox_disk_keeps_the_session_going_and_loses_nothing() {
        use std::sync::Arc;

        use storage::{DiskFullStore, FailAt, MemStore};

        for fail_at in [FailAt::Apply, FailAt::Flush] {
            let server = InMemoryUplink::new("s");
            let disk = Arc::new(DiskFullStore::new(Arc::new(MemStore::new()), fail_at));
            let outbox = Outbox::with_store(Arc::clone(&disk) as Arc<dyn storage::MapStore>, "s");
            let mut uploader = Uploader::new(server.clone(), outbox, "s", "r", "sess").unwrap();
            uploader.enqueue(&items(1)).unwrap();
            uploader.flush().await.unwrap();
            disk.fill();
            for i in 2..=4 {
                uploader.enqueue(&items(i)).unwrap();
                assert_eq!(uploader.unstored(), (i - 1) as usize, "{fail_at:?}");
                // Whatever reaches the server meanwhile is acknowledged; nothing is lost.
                if let Err(e) = uploader.flush().await {
                    assert!(e.is_transient(), "{fail_at:?}: {e}");
                }
            }
            uploader.enqueue(&end_batch(5)).unwrap();
            assert!(disk.failures() > 0, "{fail_at:?}: the full disk was felt");
            disk.free();
            let mut rounds = 0;
            while uploader.unstored() > 0 || !uploader.outbox().is_empty().unwrap() {
                rounds += 1;
                assert!(rounds <= 5, "{fail_at:?}: the outbox does not drain");
                uploader.flush().await.unwrap();
            }
            let seqs: Vec<u64> = server.applied().iter().map(|b| b.seq).collect();
            assert_eq!(
                seqs,
                [1, 2, 3, 4, 5],
                "{fail_at:?}: each batch once, in order"
            );
            assert!(
                uploader.outbox().unfinished_sessions().unwrap().is_empty(),
                "{fail_at:?}: the session's end was delivered"
            );
        }
    }

    #[tokio::test]
    async fn another_outbox_failure_still_ends_the_session() {
        use std::sync::Arc;

        use storage::{DiskFullStore, FailAt, MemStore};

        // More than MAX_UNSTORED_BATCHES waiting: the storage error is returned, not swallowed.
        let server = InMemoryUplink::new("s");
        let disk = Arc::new(DiskFullStore::new(Arc::new(MemStore::new()), FailAt::Apply));
        let outbox = Outbox::with_store(Arc::clone(&disk) as Arc<dyn storage::MapStore>, "s");
        let mut uploader = Uploader::new(server, outbox, "s", "r", "sess").unwrap();
        disk.fill();
        for i in 0..MAX_UNSTORED_BATCHES {
            uploader.enqueue(&items(i as i64)).unwrap();
        }
        let error = uploader.enqueue(&items(-1)).unwrap_err();
        assert!(
            matches!(&error, UplinkError::Outbox(e) if e.is_out_of_space()),
            "{error}"
        );
    }
}
