//! Odometry and IMU readings.

use super::Timestamp;
use crate::geometry::Rigid2;

/// A wheel-odometry reading: the pose of the robot base in the odometry frame.
#[derive(Clone, Debug, PartialEq)]
pub struct OdometryReading {
    /// When the pose was measured.
    pub time: Timestamp,
    /// `odom_from_base`.
    pub pose: Rigid2,
}

/// An IMU reading; only the yaw rate is used in 2D.
#[derive(Clone, Debug, PartialEq)]
pub struct ImuReading {
    /// When the rate was measured.
    pub time: Timestamp,
    /// Angular velocity about the vertical axis in rad/s (counter-clockwise positive).
    pub yaw_rate: f64,
}
