//! Range data: the points of one scan, split into hits and misses, in some frame.

use nalgebra::{Point2, Vector2};

use crate::geometry::Rigid2;

/// One scan's points, all in the same frame.
///
/// `returns` are obstacle hits. `misses` are end points of free-space rays (no-return or max-range readings
/// shortened to a configured length): the ray from `origin` to them is free, the end point is not an obstacle.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RangeData {
    /// Sensor origin in this frame, metres.
    pub origin: Vector2<f64>,
    /// Obstacle hits, metres.
    pub returns: Vec<Point2<f32>>,
    /// Free-space ray end points, metres.
    pub misses: Vec<Point2<f32>>,
}

impl RangeData {
    /// Expresses the range data in another frame: `target_from_self * self`.
    #[must_use]
    pub fn transformed(&self, target_from_source: &Rigid2) -> Self {
        let t: nalgebra::Isometry2<f32> = nalgebra::convert_ref(target_from_source);
        Self {
            origin: (target_from_source * Point2::from(self.origin)).coords,
            returns: self.returns.iter().map(|p| t * p).collect(),
            misses: self.misses.iter().map(|p| t * p).collect(),
        }
    }
}
