//! Sensor events for unit tests: a small scan and an odometry reading driving along x at 1 m/s.

use super::{LaserScan, OdometryReading, SensorEvent, Timestamp};
use crate::geometry::rigid2;

/// A four-beam scan stamped `t` seconds.
pub(crate) fn scan_event(t: f64) -> SensorEvent {
    SensorEvent::Scan(LaserScan {
        time: Timestamp::from_secs_f64(t),
        angle_min: 0.0,
        angle_increment: 0.1,
        time_increment: 0.0,
        range_min: 0.1,
        range_max: 10.0,
        ranges: vec![1.0; 4],
    })
}

/// An odometry reading stamped `t` seconds, at x = `t` m.
pub(crate) fn odometry_event(t: f64) -> SensorEvent {
    SensorEvent::Odometry(OdometryReading {
        time: Timestamp::from_secs_f64(t),
        pose: rigid2(t, 0.0, 0.0),
    })
}
