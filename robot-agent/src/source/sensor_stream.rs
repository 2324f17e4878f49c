//! [`SensorStream`]: what the SLAM driver reads, one event at a time, from a recording or a live robot.

use mapping::geometry::Rigid2;
use mapping::sensor::SensorEvent;

use super::Recording;

/// Sensor events in the order LLO takes them (stamp order, each scan after the odometry that covers it:
/// `mapping::sensor::collate_for_llo`), and the laser's mounting pose.
pub trait SensorStream {
    /// The next event; `None` at the end of the stream. A live stream blocks until one arrives.
    fn next_event(&mut self) -> Option<SensorEvent>;

    /// `base_from_laser`: the laser's pose on the robot. Fixed before the first scan is handed on.
    fn base_from_laser(&self) -> Rigid2;
}

/// A whole recording as a [`SensorStream`].
pub struct RecordingStream<'a> {
    order: std::vec::IntoIter<&'a SensorEvent>,
    base_from_laser: Rigid2,
}

impl<'a> RecordingStream<'a> {
    /// The recording's events in LLO order.
    pub fn new(recording: &'a Recording) -> Self {
        Self {
            order: mapping::sensor::collate_for_llo(&recording.events).into_iter(),
            base_from_laser: recording.base_from_laser,
        }
    }
}

impl SensorStream for RecordingStream<'_> {
    fn next_event(&mut self) -> Option<SensorEvent> {
        self.order.next().cloned()
    }

    fn base_from_laser(&self) -> Rigid2 {
        self.base_from_laser
    }
}
