//! Durable, exactly-once uploading of one robot's batches.

use std::collections::BTreeSet;

use proto::{FORMAT_VERSION, UploadItem, pb};

use super::{MapUplink, UplinkError};
use crate::outbox::Outbox;

/// What one [`Uploader::flush`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FlushStats {
    /// Batches the server applied.
    pub applied: usize,
    /// Batches the server already had (their ack had been lost).
    pub duplicates: usize,
    /// Batches dropped from the outbox because re-opening the session showed the server had them.
    pub already_acked: usize,
    /// Site version after the last ack.
    pub map_version: u64,
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
            trajectory: None,
        })
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

    /// Makes a batch of `items` with the next sequence number and stores it in the outbox (durably).
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
        self.outbox.push(&batch)?;
        self.next_seq += 1;
        Ok(seq)
    }

    /// Sends every pending batch in order (opening each session first on a new connection, and dropping
    /// what the server already has). Stops at the first failure; a transient one ([`UplinkError::is_transient`])
    /// leaves everything in the outbox for the next flush.
    pub async fn flush(&mut self) -> Result<FlushStats, UplinkError> {
        let result = self.try_flush().await;
        if result.is_err() {
            self.opened.clear();
        }
        result
    }

    async fn try_flush(&mut self) -> Result<FlushStats, UplinkError> {
        let mut stats = FlushStats {
            map_version: self.last_version,
            ..FlushStats::default()
        };
        let pending = self.outbox.pending()?;
        let mut skip_through: Option<(String, u64)> = None;
        for batch in pending {
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
            if skip_through
                .as_ref()
                .is_some_and(|(s, seq)| *s == batch.session_uuid && batch.seq <= *seq)
            {
                continue;
            }
            let ack = self.uplink.upload(&batch).await?;
            if ack.duplicate {
                stats.duplicates += 1;
            } else {
                stats.applied += 1;
            }
            self.outbox.remove_through(&batch.session_uuid, batch.seq)?;
            self.last_version = self.last_version.max(ack.map_version);
            stats.map_version = self.last_version;
        }
        Ok(stats)
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
        })]
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
}
