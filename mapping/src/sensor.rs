//! Sensor data as the algorithms see it: timestamps, laser scans, odometry and IMU readings, and the
//! conversion of a scan into range data (hits and free-space rays).

mod laser_scan;
mod range_data;
mod readings;
mod sensor_collator;
mod sensor_event;
mod timestamp;

pub use laser_scan::{LaserScan, RangeConversionOptions, RangeStats};
pub use range_data::RangeData;
pub use readings::{ImuReading, OdometryReading};
pub use sensor_collator::{LloCollator, MAX_ODOMETRY_WAIT_S, collate_for_llo};
pub use sensor_event::SensorEvent;
pub use timestamp::Timestamp;
