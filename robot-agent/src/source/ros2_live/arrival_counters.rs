//! What zenoh's receive callbacks count for each sample before it is queued for decoding: samples per
//! topic, the rmw_zenoh attachment (invalid ones, and gaps in each publisher's sequence numbers) and the
//! agent's own publications, which are not input. No network here: [`ArrivalCounters::arrive`] takes a
//! sample's topic and attachment bytes, so the fuzz harness (`tests::fuzz`, target `ros2_live`) drives it
//! as the callbacks do.

use std::collections::HashMap;

use super::super::rmw_zenoh::Attachment;

/// Publishers whose sequence numbers are followed at most; samples of further publishers are still
/// counted and decoded, only their gaps are not (a peer inventing a GID per sample cannot grow the
/// table without bound).
pub const MAX_TRACKED_PUBLISHERS: usize = 4096;

/// Counters the zenoh callbacks update, per topic index (see the module docs).
#[derive(Clone, Debug, Default)]
pub struct ArrivalCounters {
    /// Samples received (the agent's own excluded).
    pub received: Vec<u64>,
    /// Samples dropped because the queue to SLAM was full.
    pub dropped_queue_full: Vec<u64>,
    /// Messages the publishers' sequence numbers say were sent but never arrived.
    pub missed_by_sequence: Vec<u64>,
    /// Samples without a readable rmw_zenoh attachment.
    pub attachment_invalid: Vec<u64>,
    last_sequence: HashMap<(usize, [u8; 16]), i64>,
}

impl ArrivalCounters {
    /// Zero counts for `topics` topics.
    pub fn new(topics: usize) -> Self {
        Self {
            received: vec![0; topics],
            dropped_queue_full: vec![0; topics],
            missed_by_sequence: vec![0; topics],
            attachment_invalid: vec![0; topics],
            last_sequence: HashMap::new(),
        }
    }

    /// Counts one sample of topic `index` carrying `attachment` (its raw bytes, if it has one). Returns
    /// `false` for the agent's own publications (GIDs starting with `own_gid_prefix`: its `map -> odom` on
    /// `/tf`), which are not input and not counted; `true` when the sample is to be decoded. An index
    /// outside the topics is not counted (and is input: the decoder refuses it).
    pub fn arrive(
        &mut self,
        index: usize,
        attachment: Option<&[u8]>,
        own_gid_prefix: &[u8; 12],
    ) -> bool {
        let attachment = attachment.map(Attachment::decode);
        if let Some(Ok(a)) = &attachment
            && a.source_gid[..12] == own_gid_prefix[..]
        {
            return false;
        }
        let Some(received) = self.received.get_mut(index) else {
            return true;
        };
        *received += 1;
        match attachment {
            Some(Ok(a)) => {
                let key = (index, a.source_gid);
                let tracked = self.last_sequence.len() < MAX_TRACKED_PUBLISHERS
                    || self.last_sequence.contains_key(&key);
                let last = if tracked {
                    self.last_sequence.insert(key, a.sequence_number)
                } else {
                    None
                };
                if let Some(last) = last
                    && a.sequence_number > last.saturating_add(1)
                {
                    // In i128: a hostile publisher's jump from i64::MIN to i64::MAX does not overflow.
                    let gap = i128::from(a.sequence_number) - i128::from(last) - 1;
                    let gap = u64::try_from(gap).unwrap_or(u64::MAX);
                    self.missed_by_sequence[index] =
                        self.missed_by_sequence[index].saturating_add(gap);
                }
            }
            _ => self.attachment_invalid[index] += 1,
        }
        true
    }

    /// Counts a sample of topic `index` dropped because the queue to SLAM was full.
    pub fn dropped_queue_full(&mut self, index: usize) {
        if let Some(n) = self.dropped_queue_full.get_mut(index) {
            *n += 1;
        }
    }

    /// Publishers whose sequence numbers are followed.
    pub fn tracked_publishers(&self) -> usize {
        self.last_sequence.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn attachment(sequence_number: i64, gid: u8) -> Vec<u8> {
        Attachment {
            sequence_number,
            source_timestamp_ns: 0,
            source_gid: [gid; 16],
        }
        .encode()
    }

    #[test]
    fn gaps_own_samples_and_bad_attachments_are_counted() {
        let own = [7_u8; 12];
        let mut c = ArrivalCounters::new(2);
        assert!(c.arrive(0, Some(&attachment(1, 1)), &own));
        assert!(c.arrive(0, Some(&attachment(4, 1)), &own));
        assert_eq!(c.missed_by_sequence[0], 2);
        assert!(!c.arrive(1, Some(&attachment(1, 7)), &own), "our own");
        assert!(c.arrive(1, Some(b"garbage"), &own));
        assert!(c.arrive(1, None, &own));
        assert_eq!(c.received, vec![2, 2]);
        assert_eq!(c.attachment_invalid, vec![0, 2]);
        assert!(
            c.arrive(5, None, &own),
            "an unknown topic is the decoder's to refuse"
        );
    }

    /// Regression (found while writing the `ros2_live` fuzz target): a publisher jumping from a negative
    /// sequence number to `i64::MAX` overflowed `sequence_number - last - 1` (a panic on zenoh's receive
    /// thread in debug builds, a wrapped count in release), and repeated jumps overflowed the counter.
    #[test]
    fn hostile_sequence_numbers_saturate() {
        let own = [0_u8; 12];
        let mut c = ArrivalCounters::new(1);
        for _ in 0..3 {
            c.arrive(0, Some(&attachment(i64::MIN, 1)), &own);
            c.arrive(0, Some(&attachment(i64::MAX, 1)), &own);
        }
        assert_eq!(c.missed_by_sequence[0], u64::MAX);
    }

    /// Regression: a peer inventing a GID per sample grew the sequence table by one entry per sample.
    #[test]
    fn publishers_tracked_are_bounded() {
        let own = [0_u8; 12];
        let mut c = ArrivalCounters::new(1);
        for i in 0..(MAX_TRACKED_PUBLISHERS as u32 + 100) {
            let mut gid = [1_u8; 16];
            gid[12..].copy_from_slice(&i.to_le_bytes());
            let a = Attachment {
                sequence_number: 1,
                source_timestamp_ns: 0,
                source_gid: gid,
            };
            assert!(c.arrive(0, Some(&a.encode()), &own));
        }
        assert_eq!(c.tracked_publishers(), MAX_TRACKED_PUBLISHERS);
        assert_eq!(c.received[0], MAX_TRACKED_PUBLISHERS as u64 + 100);
    }
}
