//! One timestamped sensor message of any kind.

use super::{ImuReading, LaserScan, OdometryReading, Timestamp};

/// A sensor message as recordings and simulators deliver them, in time order.
#[derive(Clone, Debug, PartialEq)]
pub enum SensorEvent {
    /// A laser scan, in the laser frame.
    Scan(LaserScan),
    /// A wheel-odometry pose.
    Odometry(OdometryReading),
    /// An IMU yaw rate.
    Imu(ImuReading),
}

impl SensorEvent {
    /// The message's timestamp.
    pub fn time(&self) -> Timestamp {
        match self {
            Self::Scan(s) => s.time,
            Self::Odometry(o) => o.time,
            Self::Imu(i) => i.time,
        }
    }
}
