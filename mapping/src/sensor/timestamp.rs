//! Exact timestamps.

use std::fmt;

/// A point in time, in integer nanoseconds since the Unix epoch (ROS and CARMEN stamps both map to it).
///
/// Integer nanoseconds keep equality and ordering exact, which matters for matching relation files and
/// for detecting duplicated or out-of-order messages.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    serde::Serialize,
    serde::Deserialize,
)]
pub struct Timestamp(pub i64);

impl Timestamp {
    /// From ROS `(sec, nsec)`.
    pub fn from_sec_nsec(sec: u32, nsec: u32) -> Self {
        Self(i64::from(sec) * 1_000_000_000 + i64::from(nsec))
    }

    /// From floating-point seconds (CARMEN logs), rounded to the nearest nanosecond.
    pub fn from_secs_f64(seconds: f64) -> Self {
        Self((seconds * 1e9).round() as i64)
    }

    /// Seconds since the epoch as `f64`.
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 * 1e-9
    }

    /// `self − earlier` in seconds (negative when `self` is before `earlier`).
    pub fn seconds_since(self, earlier: Timestamp) -> f64 {
        (self.0 - earlier.0) as f64 * 1e-9
    }

    /// This time shifted by `seconds`.
    #[must_use]
    pub fn offset_by(self, seconds: f64) -> Self {
        Self(self.0 + (seconds * 1e9).round() as i64)
    }
}

impl fmt::Display for Timestamp {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}.{:09}",
            self.0.div_euclid(1_000_000_000),
            self.0.rem_euclid(1_000_000_000)
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ros_and_float_stamps_agree() {
        let a = Timestamp::from_sec_nsec(1_000_000_000, 500_000_000);
        let b = Timestamp::from_secs_f64(1_000_000_000.5);
        assert_eq!(a, b);
        assert_eq!(a.to_string(), "1000000000.500000000");
        assert!((b.seconds_since(Timestamp::from_sec_nsec(1_000_000_000, 0)) - 0.5).abs() < 1e-12);
    }
}
