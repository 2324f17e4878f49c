//! Motion filter: a scan becomes a node only if the robot moved or time passed enough since the last
//! node, so a parked robot does not fill the graph.

use serde::{Deserialize, Serialize};

use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle};
use crate::sensor::Timestamp;

/// Thresholds; a scan passes when any one is exceeded.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionFilterOptions {
    /// Seconds. Default 5 s.
    pub max_time_seconds: f64,
    /// Metres. Default 0.2 m.
    pub max_distance_meters: f64,
    /// Radians. Default 1°.
    pub max_angle_radians: f64,
}

impl Default for MotionFilterOptions {
    fn default() -> Self {
        Self {
            max_time_seconds: 5.0,
            max_distance_meters: 0.2,
            max_angle_radians: 1f64.to_radians(),
        }
    }
}

/// Remembers the last accepted pose.
#[derive(Clone, Debug)]
pub struct MotionFilter {
    options: MotionFilterOptions,
    last: Option<(Timestamp, Rigid2)>,
}

impl MotionFilter {
    /// A filter that accepts the first pose.
    pub fn new(options: MotionFilterOptions) -> Self {
        Self {
            options,
            last: None,
        }
    }

    /// Makes `pose` at `time` the last accepted one (a scan inserted whatever the filter says).
    pub fn accept(&mut self, time: Timestamp, pose: &Rigid2) {
        self.last = Some((time, *pose));
    }

    /// Whether `pose` at `time` is too close to the last accepted one; if not, it becomes the last one.
    pub fn is_similar(&mut self, time: Timestamp, pose: &Rigid2) -> bool {
        if let Some((t, p)) = &self.last {
            let moved = (pose.translation.vector - p.translation.vector).norm();
            let turned = normalize_angle(pose.theta() - p.theta()).abs();
            if time.seconds_since(*t) <= self.options.max_time_seconds
                && moved <= self.options.max_distance_meters
                && turned <= self.options.max_angle_radians
            {
                return true;
            }
        }
        self.last = Some((time, *pose));
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;

    #[test]
    fn passes_on_distance_angle_or_time() {
        let mut f = MotionFilter::new(MotionFilterOptions::default());
        let s = |secs: f64| Timestamp::from_secs_f64(secs);
        assert!(!f.is_similar(s(0.0), &rigid2(0.0, 0.0, 0.0)));
        assert!(f.is_similar(s(1.0), &rigid2(0.1, 0.0, 0.0)));
        assert!(!f.is_similar(s(1.1), &rigid2(0.3, 0.0, 0.0)));
        assert!(!f.is_similar(s(1.2), &rigid2(0.3, 0.0, 0.05)));
        assert!(!f.is_similar(s(6.3), &rigid2(0.3, 0.0, 0.05)));
    }
}
