//! Sensor data as the algorithms see it: timestamps, laser scans, odometry and IMU readings, and the
//! conversion of a scan into range data (hits and free-space rays).

mod laser_scan;
mod range_data;
mod readings;
mod scan_backlog;
mod sensor_collator;
mod sensor_event;
#[cfg(test)]
pub(crate) mod test_support;
mod timestamp;

pub use laser_scan::{LaserScan, RangeConversionOptions, RangeStats};
pub use range_data::RangeData;
pub use readings::{ImuReading, OdometryReading};
pub use scan_backlog::{
    BACKLOG_GAP_PERIODS, BURST_INTERVAL_SHARE, MAX_BACKLOG_HOLD_S, MAX_ODOMETRY_SILENCE_SHARE,
    MIN_BACKLOG_SHARE, PERIOD_WINDOW, Retimed, ScanBacklog,
};
pub use sensor_collator::{LloCollator, MAX_ODOMETRY_WAIT_S, collate_for_llo};
pub use sensor_event::SensorEvent;
pub use timestamp::Timestamp;
