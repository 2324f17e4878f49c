//! Sensor data as the algorithms see it: timestamps, laser scans, odometry and IMU readings, and the
//! conversion of a scan into range data (hits and free-space rays).

mod laser_scan;
mod odometry_clock;
mod range_data;
mod readings;
mod scan_backlog;
mod scan_period;
mod scan_stamps;
mod sensor_collator;
mod sensor_event;
#[cfg(test)]
pub(crate) mod test_support;
mod timestamp;

pub use laser_scan::{LaserScan, RangeConversionOptions, RangeStats};
pub use odometry_clock::{
    ERROR_CAP_RAD, MAX_OFFSET_S, MAX_PAIR_SPAN_S, MIN_TURN_RAD, OFFSET_STEP_S, OdometryClock,
    PAIR_SPAN_S,
};
pub use range_data::RangeData;
pub use readings::{ImuReading, OdometryReading};
pub use scan_backlog::{
    BACKLOG_GAP_PERIODS, MAX_BACKLOG_HOLD_S, MAX_ODOMETRY_SILENCE_SHARE, MIN_BACKLOG_SHARE,
    Retimed, ScanBacklog,
};
pub use scan_period::{BURST_INTERVAL_SHARE, PERIOD_WINDOW, ScanPeriod};
pub use scan_stamps::{STAMP_TOLERANCE_NS, ScanStamps, nearest_within_tolerance};
pub use sensor_collator::{LloCollator, MAX_ODOMETRY_WAIT_S, collate_for_llo};
pub use sensor_event::SensorEvent;
pub use timestamp::Timestamp;
