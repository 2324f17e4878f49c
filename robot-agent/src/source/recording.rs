//! A whole recording in memory, in time order, with an account of what was read and what was not.

use mapping::geometry::Rigid2;
use mapping::sensor::SensorEvent;
use serde::Serialize;

/// What a reader found, so a user can see what was used and what was skipped.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct ReadReport {
    /// Laser scans kept.
    pub scans: usize,
    /// Odometry readings kept.
    pub odometry: usize,
    /// IMU readings kept.
    pub imu: usize,
    /// TF messages read (for the laser's mounting pose).
    pub tf: usize,
    /// Messages of other types, or lines of other kinds, skipped.
    pub skipped_other: usize,
    /// Messages that could not be decoded, skipped (each is also counted by kind in `problems`).
    pub skipped_malformed: usize,
    /// Messages whose stamp is earlier than the previous message of the same stream (kept, re-sorted).
    pub out_of_order: usize,
    /// Messages identical to the previous one of the same stream (same stamp and payload), dropped.
    pub duplicates_dropped: usize,
    /// Messages with the same stamp as the previous one of the same stream but a different payload,
    /// dropped (the first one wins: the estimators need strictly increasing time per stream).
    pub same_stamp_dropped: usize,
    /// Where the laser's mounting pose came from.
    pub extrinsic_source: String,
    /// The first few problems seen, as human-readable lines.
    pub problems: Vec<String>,
}

impl ReadReport {
    /// Records a problem (keeps only the first 20 lines).
    pub fn problem(&mut self, line: String) {
        if self.problems.len() < 20 {
            self.problems.push(line);
        }
    }
}

/// A recording: sensor events in time order and the laser's mounting pose.
#[derive(Clone, Debug)]
pub struct Recording {
    /// Events sorted by stamp (stable: equal stamps keep file order).
    pub events: Vec<SensorEvent>,
    /// `base_from_laser`: the laser's pose on the robot.
    pub base_from_laser: Rigid2,
    /// What was read and skipped.
    pub report: ReadReport,
}

fn stream(event: &SensorEvent) -> usize {
    match event {
        SensorEvent::Scan(_) => 0,
        SensorEvent::Odometry(_) => 1,
        SensorEvent::Imu(_) => 2,
    }
}

impl Recording {
    /// Orders events by stamp, drops exact and same-stamp duplicates per stream, and counts what it did.
    pub fn from_unsorted(
        mut events: Vec<SensorEvent>,
        base_from_laser: Rigid2,
        mut report: ReadReport,
    ) -> Self {
        let mut last: [Option<usize>; 3] = [None; 3];
        for (i, e) in events.iter().enumerate() {
            let s = stream(e);
            if let Some(j) = last[s]
                && e.time() < events[j].time()
            {
                report.out_of_order += 1;
            }
            last[s] = Some(i);
        }
        events.sort_by_key(SensorEvent::time);
        let mut kept: Vec<SensorEvent> = Vec::with_capacity(events.len());
        let mut last_kept: [Option<usize>; 3] = [None; 3];
        for e in events {
            let s = stream(&e);
            if let Some(j) = last_kept[s]
                && kept[j].time() == e.time()
            {
                if kept[j] == e {
                    report.duplicates_dropped += 1;
                } else {
                    report.same_stamp_dropped += 1;
                }
                continue;
            }
            last_kept[s] = Some(kept.len());
            kept.push(e);
        }
        report.scans = kept
            .iter()
            .filter(|e| matches!(e, SensorEvent::Scan(_)))
            .count();
        report.odometry = kept
            .iter()
            .filter(|e| matches!(e, SensorEvent::Odometry(_)))
            .count();
        report.imu = kept
            .iter()
            .filter(|e| matches!(e, SensorEvent::Imu(_)))
            .count();
        Self {
            events: kept,
            base_from_laser,
            report,
        }
    }
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;
    use mapping::sensor::{OdometryReading, Timestamp};

    use super::*;

    fn odom(t: i64, x: f64) -> SensorEvent {
        SensorEvent::Odometry(OdometryReading {
            time: Timestamp(t),
            pose: rigid2(x, 0.0, 0.0),
        })
    }

    #[test]
    fn sorts_and_drops_duplicates_with_counts() {
        let events = vec![
            odom(2, 2.0),
            odom(1, 1.0),
            odom(3, 3.0),
            odom(3, 3.0),
            odom(3, 9.0),
        ];
        let r = Recording::from_unsorted(events, Rigid2::identity(), ReadReport::default());
        let times: Vec<i64> = r.events.iter().map(|e| e.time().0).collect();
        assert_eq!(times, vec![1, 2, 3]);
        assert_eq!(r.report.out_of_order, 1);
        assert_eq!(r.report.duplicates_dropped, 1);
        assert_eq!(r.report.same_stamp_dropped, 1);
        assert_eq!(r.report.odometry, 3);
    }
}
