//! A planar laser scan (the fields of `sensor_msgs/LaserScan` that matter in 2D) and its conversion to
//! [`RangeData`], following the ROS REP 117 conventions for special range values.

use nalgebra::{Point2, Vector2};
use serde::{Deserialize, Serialize};

use super::{RangeData, Timestamp};

/// One laser scan in the laser frame.
#[derive(Clone, Debug, PartialEq)]
pub struct LaserScan {
    /// Acquisition time of the first beam.
    pub time: Timestamp,
    /// Angle of the first beam in radians, counter-clockwise from the laser's x axis.
    pub angle_min: f32,
    /// Angle between consecutive beams in radians.
    pub angle_increment: f32,
    /// Time between consecutive beams in seconds (0 when unknown).
    pub time_increment: f32,
    /// Smallest valid range in metres.
    pub range_min: f32,
    /// Largest valid range in metres.
    pub range_max: f32,
    /// Measured ranges in metres, one per beam.
    pub ranges: Vec<f32>,
}

/// How raw ranges become hits and misses.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RangeConversionOptions {
    /// Readings closer than this (metres) are dropped, in addition to the scan's own `range_min`
    /// (robot body, bumper). Default 0.1 m.
    pub min_range: f32,
    /// Hits farther than this (metres) are not trusted as obstacles and become free-space rays instead.
    /// Default 30 m.
    pub max_range: f32,
    /// Length in metres of the free-space ray inserted for a no-return reading (`+inf`, or at/above the
    /// scan's `range_max`). 0 disables free-space rays. Default 5 m.
    pub missing_data_ray_length: f32,
}

impl Default for RangeConversionOptions {
    fn default() -> Self {
        Self {
            min_range: 0.1,
            max_range: 30.0,
            missing_data_ray_length: 5.0,
        }
    }
}

/// What happened to each beam of a scan, for diagnostics and reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RangeStats {
    /// Beams that became obstacle hits.
    pub hits: u64,
    /// Beams that became free-space rays (no return or beyond `max_range`).
    pub no_return: u64,
    /// NaN readings (ROS: measurement failed), dropped.
    pub nan: u64,
    /// `−inf` readings or readings below the minimum range (ROS: too close), dropped.
    pub too_close: u64,
}

impl std::ops::AddAssign for RangeStats {
    fn add_assign(&mut self, o: Self) {
        self.hits += o.hits;
        self.no_return += o.no_return;
        self.nan += o.nan;
        self.too_close += o.too_close;
    }
}

impl LaserScan {
    /// Angle of beam `i` in radians.
    pub fn beam_angle(&self, i: usize) -> f32 {
        self.angle_min + i as f32 * self.angle_increment
    }

    /// Converts the scan into range data in the laser frame.
    ///
    /// Per REP 117: NaN is an erroneous reading and `−inf` is "too close": both are dropped; `+inf`, and
    /// any value at or above the scan's `range_max` (these data sets write 81.91 m or exactly `range_max`
    /// for no return), is "no return" and becomes a free-space ray of `missing_data_ray_length`.
    pub fn to_range_data(&self, options: &RangeConversionOptions) -> (RangeData, RangeStats) {
        let mut data = RangeData {
            origin: Vector2::zeros(),
            ..RangeData::default()
        };
        let mut stats = RangeStats::default();
        let min_range = options.min_range.max(self.range_min);
        for (i, &r) in self.ranges.iter().enumerate() {
            let angle = self.beam_angle(i);
            let direction = Point2::new(angle.cos(), angle.sin());
            if r.is_nan() {
                stats.nan += 1;
            } else if r < min_range {
                stats.too_close += 1;
            } else if r >= self.range_max || r > options.max_range {
                stats.no_return += 1;
                if options.missing_data_ray_length > 0.0 {
                    let len = options.missing_data_ray_length.min(r);
                    data.misses.push(Point2::from(direction.coords * len));
                }
            } else {
                stats.hits += 1;
                data.returns.push(Point2::from(direction.coords * r));
            }
        }
        (data, stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan(ranges: Vec<f32>) -> LaserScan {
        LaserScan {
            time: Timestamp(0),
            angle_min: -std::f32::consts::FRAC_PI_2,
            angle_increment: std::f32::consts::FRAC_PI_2,
            time_increment: 0.0,
            range_min: 0.0,
            range_max: 80.0,
            ranges,
        }
    }

    #[test]
    fn special_values_follow_rep117() {
        let s = scan(vec![
            f32::NAN,
            f32::NEG_INFINITY,
            2.0,
            f32::INFINITY,
            81.91,
            0.05,
            50.0,
        ]);
        let (data, stats) = s.to_range_data(&RangeConversionOptions::default());
        assert_eq!(
            stats,
            RangeStats {
                hits: 1,
                no_return: 3,
                nan: 1,
                too_close: 2
            }
        );
        assert_eq!(data.returns.len(), 1);
        // Beam 2 points along +y with angle_min = −π/2 and increment π/2.
        assert!(data.returns[0].x.abs() < 1e-6 && (data.returns[0].y - 2.0).abs() < 1e-6);
        assert_eq!(data.misses.len(), 3);
        for m in &data.misses {
            assert!((m.coords.norm() - 5.0).abs() < 1e-5);
        }
    }

    #[test]
    fn no_rays_when_disabled() {
        let s = scan(vec![f32::INFINITY]);
        let options = RangeConversionOptions {
            missing_data_ray_length: 0.0,
            ..Default::default()
        };
        let (data, stats) = s.to_range_data(&options);
        assert!(data.misses.is_empty());
        assert_eq!(stats.no_return, 1);
    }
}
