//! Voxel filters: thin a point cloud to one point per square cell, and the adaptive variant that picks
//! the largest cell size still leaving enough points (Cartographer's `AdaptiveVoxelFilter`), so the
//! matchers see an even, bounded number of points whatever the scanner's density.

use std::collections::HashSet;

use nalgebra::Point2;
use serde::{Deserialize, Serialize};

/// Keeps the first point of every `size × size` cell, in input order.
pub fn voxel_filter(points: &[Point2<f32>], size: f32) -> Vec<Point2<f32>> {
    if size <= 0.0 {
        return points.to_vec();
    }
    let mut seen = HashSet::with_capacity(points.len());
    points
        .iter()
        .filter(|p| seen.insert(((p.x / size).floor() as i32, (p.y / size).floor() as i32)))
        .copied()
        .collect()
}

/// Adaptive voxel filter settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AdaptiveVoxelFilterOptions {
    /// Largest cell size tried, metres. Default 0.5 m.
    pub max_length: f32,
    /// The filter shrinks cells until at least this many points remain (if the input has them).
    /// Default 200.
    pub min_num_points: usize,
    /// Points farther than this from the sensor are dropped first, metres. Default 50 m.
    pub max_range: f32,
}

impl Default for AdaptiveVoxelFilterOptions {
    fn default() -> Self {
        Self {
            max_length: 0.5,
            min_num_points: 200,
            max_range: 50.0,
        }
    }
}

/// Range-limits the points, then voxel-filters them with the largest cell size (≤ `max_length`) that
/// keeps at least `min_num_points` points, found by bisection.
pub fn adaptive_voxel_filter(
    points: &[Point2<f32>],
    options: &AdaptiveVoxelFilterOptions,
) -> Vec<Point2<f32>> {
    let in_range: Vec<Point2<f32>> = points
        .iter()
        .filter(|p| p.coords.norm_squared() <= options.max_range * options.max_range)
        .copied()
        .collect();
    if in_range.len() <= options.min_num_points {
        return in_range;
    }
    let coarse = voxel_filter(&in_range, options.max_length);
    if coarse.len() >= options.min_num_points {
        return coarse;
    }
    // Bisect on the cell size: `high` keeps too few points, `low` enough.
    let (mut low, mut high) = (0.0f32, options.max_length);
    let mut best = in_range.clone();
    for _ in 0..12 {
        let mid = 0.5 * (low + high);
        let candidate = voxel_filter(&in_range, mid);
        if candidate.len() >= options.min_num_points {
            low = mid;
            best = candidate;
        } else {
            high = mid;
        }
        if high - low < 0.005 {
            break;
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(n: usize, step: f32) -> Vec<Point2<f32>> {
        (0..n).map(|i| Point2::new(i as f32 * step, 0.0)).collect()
    }

    #[test]
    fn one_point_per_cell() {
        let pts = line(100, 0.01); // 1 m of points every cm
        assert_eq!(voxel_filter(&pts, 0.1).len(), 10);
        assert_eq!(voxel_filter(&pts, 0.0).len(), 100);
    }

    #[test]
    fn adaptive_keeps_enough_points() {
        let pts = line(2000, 0.01); // 20 m
        let options = AdaptiveVoxelFilterOptions {
            max_length: 0.5,
            min_num_points: 200,
            max_range: 50.0,
        };
        let out = adaptive_voxel_filter(&pts, &options);
        // 0.5 m cells would leave 40 points: the filter must shrink the cells to keep ≥ 200.
        assert!(out.len() >= 200 && out.len() < 400, "{}", out.len());
        let sparse = line(50, 1.0);
        assert_eq!(adaptive_voxel_filter(&sparse, &options).len(), 50);
        let far = vec![Point2::new(60.0f32, 0.0)];
        assert!(adaptive_voxel_filter(&far, &options).is_empty());
    }
}
