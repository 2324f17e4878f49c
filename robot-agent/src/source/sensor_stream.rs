//! [`SensorStream`]: what the SLAM driver reads, one event at a time, from a recording or a live robot.

use mapping::geometry::Rigid2;
use mapping::sensor::{ScanBacklog, ScanStamps, SensorEvent, Timestamp, collate_for_llo};

use super::Recording;

/// Sensor events in the order LLO takes them (stamp order, a driver's backlog of scans put back at the
/// times they were taken: `mapping::sensor::ScanBacklog`, each scan after the odometry that covers it:
/// `mapping::sensor::collate_for_llo`), and the laser's mounting pose.
pub trait SensorStream {
    /// The next event; `None` at the end of the stream. A live stream blocks until one arrives.
    fn next_event(&mut self) -> Option<SensorEvent>;

    /// `base_from_laser`: the laser's pose on the robot. Fixed before the first scan is handed on.
    fn base_from_laser(&self) -> Rigid2;

    /// The stamp a scan handed on at `time` came with (they differ where a backlog was re-timed), for
    /// scoring against references made at the stamps. The same time where not known.
    fn stamped(&self, time: Timestamp) -> Timestamp {
        time
    }

    /// How many scans so far were a driver's backlog put back at the times they were taken.
    fn scans_retimed(&self) -> usize {
        0
    }
}

/// A whole recording as a [`SensorStream`].
pub struct RecordingStream {
    order: std::vec::IntoIter<SensorEvent>,
    base_from_laser: Rigid2,
    /// Re-timed scans: the time each was given, and its stamp.
    stamps: ScanStamps,
}

impl RecordingStream {
    /// The recording's events in LLO order.
    pub fn new(recording: &Recording) -> Self {
        let (events, retimed) = ScanBacklog::retime(&recording.events);
        let order: Vec<SensorEvent> = collate_for_llo(&events).into_iter().cloned().collect();
        Self {
            order: order.into_iter(),
            base_from_laser: recording.base_from_laser,
            stamps: ScanStamps::new(&retimed),
        }
    }
}

impl SensorStream for RecordingStream {
    fn next_event(&mut self) -> Option<SensorEvent> {
        self.order.next()
    }

    fn base_from_laser(&self) -> Rigid2 {
        self.base_from_laser
    }

    fn stamped(&self, time: Timestamp) -> Timestamp {
        self.stamps.stamped(time)
    }

    fn scans_retimed(&self) -> usize {
        self.stamps.len()
    }
}
