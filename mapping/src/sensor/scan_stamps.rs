//! [`ScanStamps`]: the stamps of scans [`super::ScanBacklog`] re-timed, and the times they were taken.
//!
//! A run goes by the times scans were taken; references (relations, ground truth) are keyed by the stamps
//! the scans came with. A shell that re-timed a recording's backlog uses this to write and score the run
//! at the stamps, and to ask its questions about a stamped scan at the time the run knows it by.
//! References round their stamps (the Freiburg relations to 10 µs): a time is that of a re-timed scan
//! when it is within [`STAMP_TOLERANCE_NS`] of it.

use std::collections::BTreeMap;

use super::{Retimed, Timestamp};

/// A time names a scan's stamp (or the time it was taken) when it is this close to it (ns): 0.1 ms, above
/// a reference's rounding and below the spacing of a backlog's stamps (about 0.5 ms).
pub const STAMP_TOLERANCE_NS: i64 = 100_000;

/// The value of `map`'s key nearest `time`, if within [`STAMP_TOLERANCE_NS`].
pub fn nearest_within_tolerance(
    map: &BTreeMap<Timestamp, Timestamp>,
    time: Timestamp,
) -> Option<Timestamp> {
    let window = Timestamp(time.0 - STAMP_TOLERANCE_NS)..=Timestamp(time.0 + STAMP_TOLERANCE_NS);
    map.range(window)
        .min_by_key(|(key, _)| (key.0 - time.0).abs())
        .map(|(_, value)| *value)
}

/// Both ways between the stamps of re-timed scans and the times they were taken; every other time maps
/// to itself.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ScanStamps {
    /// Taken → stamped.
    stamped: BTreeMap<Timestamp, Timestamp>,
    /// Stamped → taken (the first scan re-timed from a stamp, should two share it).
    taken: BTreeMap<Timestamp, Timestamp>,
}

impl ScanStamps {
    /// The stamps of `retimed` scans.
    pub fn new(retimed: &[Retimed]) -> Self {
        let mut stamps = Self::default();
        for r in retimed {
            stamps.stamped.insert(r.taken, r.stamped);
            stamps.taken.entry(r.stamped).or_insert(r.taken);
        }
        stamps
    }

    /// The stamp of the scan taken at `taken` (`taken` itself unless that scan was re-timed).
    pub fn stamped(&self, taken: Timestamp) -> Timestamp {
        nearest_within_tolerance(&self.stamped, taken).unwrap_or(taken)
    }

    /// When the scan stamped `stamped` was taken (`stamped` itself unless that scan was re-timed).
    pub fn taken(&self, stamped: Timestamp) -> Timestamp {
        nearest_within_tolerance(&self.taken, stamped).unwrap_or(stamped)
    }

    /// How many scans were re-timed.
    pub fn len(&self) -> usize {
        self.stamped.len()
    }

    /// Whether no scan was re-timed.
    pub fn is_empty(&self) -> bool {
        self.stamped.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn maps_re_timed_scans_both_ways_and_every_other_time_to_itself() {
        let t = Timestamp::from_secs_f64;
        let stamps = ScanStamps::new(&[
            Retimed {
                stamped: t(10.001),
                taken: t(9.5),
            },
            Retimed {
                stamped: t(10.002),
                taken: t(9.75),
            },
        ]);
        assert_eq!(stamps.len(), 2);
        assert_eq!(stamps.stamped(t(9.5)), t(10.001));
        assert_eq!(stamps.taken(t(10.002)), t(9.75));
        // A reference's rounded stamp still names its scan; one 0.2 ms off does not.
        assert_eq!(stamps.taken(t(10.00201)), t(9.75));
        assert_eq!(stamps.taken(t(10.0022)), t(10.0022));
        assert_eq!(stamps.stamped(t(3.0)), t(3.0));
        assert_eq!(stamps.taken(t(3.0)), t(3.0));
        assert!(ScanStamps::new(&[]).is_empty());
    }
}
