//! The agent's durable outbox: every upload batch from the moment it is made until the server
//! acknowledges it, so a dead link or a dead server (or a restarted agent) loses nothing.
//!
//! Batches are stored (encoded `UploadBatch` messages) as `RecordKind::Outbox` records of the agent's
//! site in a [`storage::MapStore`] — sled on disk, or in memory for tests — keyed by session then
//! sequence number, and written with a durable flush before [`Outbox::push`] returns. Calls block for a
//! disk flush (milliseconds).
//!
//! Beside the batches, every session the robot has not finished yet has a marker (a
//! `RecordKind::Session` record: session uuid → robot id), written in the same atomic write as the
//! session's batches and removed only once the server has the session's end ([`Outbox::finish_session`]).
//! A marker that survives a restart of the agent is an interrupted session: its acknowledged batches may
//! all be gone from the outbox, but the server still holds it open, and the restarted agent ends it
//! (see `uplink::Uploader`).
//!
//! The same store keeps the robot's dock in the site (a `RecordKind::SiteMeta` record `dock`): where its
//! last session ended, as it estimated it then, which the next session checks first
//! ([`Outbox::dock`], [`Outbox::set_dock`]).

use std::path::Path;
use std::sync::Arc;

use mapping::geometry::Rigid2;
use prost::Message as _;
use proto::pb;
use storage::{MapStore, MemStore, RecordId, RecordKind, SledStore, SledStoreOptions, WriteBatch};

/// Outbox failures.
#[derive(Debug, thiserror::Error)]
pub enum OutboxError {
    /// The store failed.
    #[error("outbox storage: {0}")]
    Storage(#[from] storage::StorageError),
    /// A stored batch cannot be decoded.
    #[error("corrupt outbox entry {id}: {reason}")]
    Corrupt {
        /// The record id.
        id: String,
        /// Why (with the text of `source`, when there is one).
        reason: String,
        /// The decoder's or the conversion's error, kept for `source()`.
        source: Option<Box<dyn std::error::Error + Send + Sync>>,
    },
}

impl OutboxError {
    /// Whether the disk is full: the write failed, nothing of it was stored, and it may succeed once
    /// space returns.
    pub fn is_out_of_space(&self) -> bool {
        matches!(self, Self::Storage(e) if e.is_out_of_space())
    }
}

/// Batches not yet acknowledged by the server, for one site.
#[derive(Clone)]
pub struct Outbox {
    store: Arc<dyn MapStore>,
    site: String,
}

/// The `RecordKind::SiteMeta` record of the robot's dock: an encoded `ExactPose2`, as checkpoints store
/// poses.
const DOCK_RECORD: &str = "dock";

fn record_id(session: &str, seq: u64) -> RecordId {
    // Session ids contain no control characters, so the NUL separator keeps sessions apart and the
    // big-endian sequence number sorts numerically.
    let mut id = session.as_bytes().to_vec();
    id.push(0);
    id.extend_from_slice(&seq.to_be_bytes());
    RecordId::new(id)
}

fn session_prefix(id: &RecordId) -> Option<(&[u8], u64)> {
    let bytes = id.as_bytes();
    let (session, rest) = bytes.split_at(bytes.len().checked_sub(9)?);
    let (nul, seq) = rest.split_first()?;
    (*nul == 0).then(|| {
        (
            session,
            u64::from_be_bytes(seq.try_into().unwrap_or_default()),
        )
    })
}

impl Outbox {
    /// An outbox on disk in `dir` (created if missing) for `site`.
    pub fn open(dir: &Path, site: &str) -> Result<Self, OutboxError> {
        let store = SledStore::open(&SledStoreOptions::at(dir))?;
        Ok(Self {
            store: Arc::new(store),
            site: site.to_owned(),
        })
    }

    /// An outbox in `store` (e.g. a `storage::DiskFullStore` in tests) for `site`.
    pub fn with_store(store: Arc<dyn MapStore>, site: &str) -> Self {
        Self {
            store,
            site: site.to_owned(),
        }
    }

    /// An outbox in memory (tests).
    pub fn in_memory(site: &str) -> Self {
        Self {
            store: Arc::new(MemStore::new()),
            site: site.to_owned(),
        }
    }

    /// Stores a batch durably (replacing one with the same session and sequence number), marking its
    /// session unfinished in the same atomic write.
    pub fn push(&self, batch: &pb::UploadBatch) -> Result<(), OutboxError> {
        let mut write = WriteBatch::new(&self.site);
        write
            .put(
                RecordKind::Outbox,
                record_id(&batch.session_uuid, batch.seq),
                batch.encode_to_vec(),
            )
            .put(
                RecordKind::Session,
                batch.session_uuid.as_str(),
                batch.robot_id.as_bytes(),
            );
        self.store.apply_durable(&write)?;
        Ok(())
    }

    /// Every session with a batch pushed and no [`Self::finish_session`] since, as (session uuid, robot
    /// id), ordered by session uuid.
    pub fn unfinished_sessions(&self) -> Result<Vec<(String, String)>, OutboxError> {
        self.store
            .scan(&self.site, RecordKind::Session)?
            .map(|record| {
                let (id, robot) = record?;
                let corrupt = |what: &str, e: std::string::FromUtf8Error| OutboxError::Corrupt {
                    id: id.to_string(),
                    reason: format!("the session marker's {what} is not UTF-8"),
                    source: Some(e.into()),
                };
                let session = String::from_utf8(id.as_bytes().to_vec())
                    .map_err(|e| corrupt("session uuid", e))?;
                let robot = String::from_utf8(robot).map_err(|e| corrupt("robot id", e))?;
                Ok((session, robot))
            })
            .collect()
    }

    /// Marks `session` finished (the server has its end) and removes whatever of it is still pending,
    /// durably and atomically. Returns how many batches were removed.
    pub fn finish_session(&self, session: &str) -> Result<usize, OutboxError> {
        let mut write = WriteBatch::new(&self.site);
        for record in self.store.scan(&self.site, RecordKind::Outbox)? {
            let (id, _) = record?;
            if let Some((s, _)) = session_prefix(&id)
                && s == session.as_bytes()
            {
                write.delete(RecordKind::Outbox, id);
            }
        }
        let removed = write.len();
        write.delete(RecordKind::Session, session);
        self.store.apply_durable(&write)?;
        Ok(removed)
    }

    /// The robot's dock in the site (`map_from_tracking` where its last session ended, as it estimated it
    /// then), if one was stored.
    pub fn dock(&self) -> Result<Option<Rigid2>, OutboxError> {
        let Some(bytes) = self.store.get(
            &self.site,
            RecordKind::SiteMeta,
            &RecordId::from(DOCK_RECORD),
        )?
        else {
            return Ok(None);
        };
        let corrupt = |source: Box<dyn std::error::Error + Send + Sync>| OutboxError::Corrupt {
            id: DOCK_RECORD.into(),
            reason: format!("{} bytes: {source}", bytes.len()),
            source: Some(source),
        };
        let exact = pb::ExactPose2::decode(bytes.as_slice()).map_err(|e| corrupt(e.into()))?;
        proto::pose_from_exact(Some(&exact), "ExactPose2", "dock")
            .map(Some)
            .map_err(|e| corrupt(e.into()))
    }

    /// Stores the robot's dock in the site, durably, or removes it (`None`: the robot does not know where
    /// it is, e.g. while a session runs or after one that was never placed). A non-finite pose is
    /// removed too: it is no place to check.
    pub fn set_dock(&self, dock: Option<Rigid2>) -> Result<(), OutboxError> {
        let mut write = WriteBatch::new(&self.site);
        let finite = |d: &Rigid2| {
            let (t, r) = (d.translation.vector, d.rotation);
            [t.x, t.y, r.re, r.im].iter().all(|v| v.is_finite())
        };
        match dock.filter(finite) {
            Some(dock) => {
                write.put(
                    RecordKind::SiteMeta,
                    DOCK_RECORD,
                    proto::pose_to_exact(&dock).encode_to_vec(),
                );
            }
            None => {
                write.delete(RecordKind::SiteMeta, DOCK_RECORD);
            }
        }
        self.store.apply_durable(&write)?;
        Ok(())
    }

    /// Every pending batch, ordered by session then sequence number.
    pub fn pending(&self) -> Result<Vec<pb::UploadBatch>, OutboxError> {
        self.store
            .scan(&self.site, RecordKind::Outbox)?
            .map(|record| {
                let (id, bytes) = record?;
                pb::UploadBatch::decode(bytes.as_slice()).map_err(|e| OutboxError::Corrupt {
                    id: id.to_string(),
                    reason: e.to_string(),
                    source: Some(e.into()),
                })
            })
            .collect()
    }

    /// Highest pending sequence number of `session`, if any.
    pub fn last_seq(&self, session: &str) -> Result<Option<u64>, OutboxError> {
        let mut last = None;
        for record in self.store.scan(&self.site, RecordKind::Outbox)? {
            let (id, _) = record?;
            if let Some((s, seq)) = session_prefix(&id)
                && s == session.as_bytes()
            {
                last = Some(seq);
            }
        }
        Ok(last)
    }

    /// Removes (durably) every batch of `session` with a sequence number up to `seq`: the server has them.
    /// Returns how many were removed.
    pub fn remove_through(&self, session: &str, seq: u64) -> Result<usize, OutboxError> {
        let mut write = WriteBatch::new(&self.site);
        for record in self.store.scan(&self.site, RecordKind::Outbox)? {
            let (id, _) = record?;
            if let Some((s, n)) = session_prefix(&id)
                && s == session.as_bytes()
                && n <= seq
            {
                write.delete(RecordKind::Outbox, id);
            }
        }
        let removed = write.len();
        if removed > 0 {
            self.store.apply_durable(&write)?;
        }
        Ok(removed)
    }

    /// Number of pending batches.
    pub fn len(&self) -> Result<usize, OutboxError> {
        Ok(self.store.scan(&self.site, RecordKind::Outbox)?.count())
    }

    /// Whether nothing is pending.
    pub fn is_empty(&self) -> Result<bool, OutboxError> {
        Ok(self.len()? == 0)
    }
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;

    use super::*;

    fn batch(session: &str, seq: u64) -> pb::UploadBatch {
        pb::UploadBatch {
            format_version: proto::FORMAT_VERSION,
            site: "s".into(),
            robot_id: "r".into(),
            session_uuid: session.into(),
            seq,
            items: vec![],
        }
    }

    #[test]
    fn the_dock_is_kept_per_site_until_replaced_or_removed() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let here = Outbox::with_store(Arc::clone(&store), "store-1");
        let elsewhere = Outbox::with_store(store, "store-2");
        assert_eq!(here.dock().unwrap(), None);
        here.set_dock(Some(rigid2(1.5, -2.0, 0.75))).unwrap();
        assert_eq!(here.dock().unwrap(), Some(rigid2(1.5, -2.0, 0.75)));
        assert_eq!(elsewhere.dock().unwrap(), None);
        here.set_dock(Some(rigid2(f64::NAN, 0.0, 0.0))).unwrap();
        assert_eq!(here.dock().unwrap(), None);
        here.set_dock(Some(rigid2(1.0, 1.0, 0.0))).unwrap();
        here.set_dock(None).unwrap();
        assert_eq!(here.dock().unwrap(), None);
    }

    #[test]
    fn a_damaged_dock_record_is_an_error_not_a_place() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let mut write = WriteBatch::new("store-1");
        write.put(RecordKind::SiteMeta, DOCK_RECORD, vec![0u8; 17]);
        store.apply_durable(&write).unwrap();
        let error = Outbox::with_store(store, "store-1").dock().unwrap_err();
        assert!(error.to_string().contains("17 bytes"), "{error}");
        // The decoder's error is kept as the source (issue 35).
        let source = std::error::Error::source(&error).expect("the decoder's error");
        assert!(
            source.downcast_ref::<prost::DecodeError>().is_some(),
            "{source:?}"
        );
    }

    #[test]
    fn batches_wait_until_acknowledged_in_order() {
        let outbox = Outbox::in_memory("s");
        for seq in [3, 1, 2, 300] {
            outbox.push(&batch("a", seq)).unwrap();
        }
        outbox.push(&batch("ab", 1)).unwrap();
        let seqs: Vec<(String, u64)> = outbox
            .pending()
            .unwrap()
            .into_iter()
            .map(|b| (b.session_uuid, b.seq))
            .collect();
        assert_eq!(
            seqs,
            [("a", 1), ("a", 2), ("a", 3), ("a", 300), ("ab", 1)].map(|(s, n)| (s.to_owned(), n))
        );
        assert_eq!(outbox.last_seq("a").unwrap(), Some(300));
        assert_eq!(outbox.last_seq("zz").unwrap(), None);
        assert_eq!(outbox.remove_through("a", 2).unwrap(), 2);
        assert_eq!(outbox.len().unwrap(), 3);
        assert_eq!(outbox.remove_through("a", 1000).unwrap(), 2);
        assert_eq!(outbox.pending().unwrap()[0].session_uuid, "ab");
    }

    #[test]
    fn a_session_stays_unfinished_until_finished_even_with_nothing_pending() {
        let outbox = Outbox::in_memory("s");
        assert!(outbox.unfinished_sessions().unwrap().is_empty());
        outbox.push(&batch("a", 1)).unwrap();
        outbox.push(&batch("b", 1)).unwrap();
        outbox.push(&batch("b", 2)).unwrap();
        assert_eq!(outbox.remove_through("a", 1).unwrap(), 1);
        let unfinished = |o: &Outbox| {
            o.unfinished_sessions()
                .unwrap()
                .into_iter()
                .map(|(s, r)| format!("{s}/{r}"))
                .collect::<Vec<_>>()
        };
        assert_eq!(unfinished(&outbox), ["a/r", "b/r"], "acked is not finished");
        assert_eq!(outbox.finish_session("b").unwrap(), 2);
        assert_eq!(unfinished(&outbox), ["a/r"]);
        assert!(outbox.is_empty().unwrap());
        assert_eq!(outbox.finish_session("a").unwrap(), 0);
        assert!(outbox.unfinished_sessions().unwrap().is_empty());
    }

    #[test]
    fn a_sled_outbox_survives_reopening() {
        let dir = tempfile::tempdir().unwrap();
        {
            let outbox = Outbox::open(dir.path(), "s").unwrap();
            outbox.push(&batch("a", 1)).unwrap();
            outbox.push(&batch("a", 2)).unwrap();
            outbox.remove_through("a", 1).unwrap();
            outbox.push(&batch("b", 1)).unwrap();
            outbox.remove_through("b", 1).unwrap();
        }
        let outbox = Outbox::open(dir.path(), "s").unwrap();
        let pending = outbox.pending().unwrap();
        assert_eq!(pending.len(), 1);
        assert_eq!(pending[0].seq, 2);
        assert_eq!(
            outbox.unfinished_sessions().unwrap(),
            [
                ("a".to_owned(), "r".to_owned()),
                ("b".to_owned(), "r".to_owned())
            ]
        );
    }
}
