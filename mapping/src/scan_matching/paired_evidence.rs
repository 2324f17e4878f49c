//! How much better a cloud fits a grid at one pose than at another, point by point.
//!
//! Two poses of the same cloud are compared on the same points: each point contributes the difference
//! `d` of the grid's probability under the two poses. The statistic is `Σd / √(Σd²)`: the mean difference
//! in units of its standard error if the points were independent (0 when the poses fit identically). Two
//! fits that differ by chance in a few points give a small value however many points there are; a real
//! improvement over most of the cloud gives a large one. Neighbouring points are not independent, so
//! thresholds on it are empirical, not probabilities.

use nalgebra::Point2;

use crate::geometry::Rigid2;
use crate::grid::ProbabilityGrid;

/// The probability of `grid` at point `p` (tracking frame) placed at `pose`; unknown and out-of-grid cells
/// read as the least probability, as in every search.
pub fn probability_at(grid: &ProbabilityGrid, pose: &Rigid2, p: Point2<f32>) -> f64 {
    let world = pose * Point2::new(f64::from(p.x), f64::from(p.y));
    f64::from(grid.probability(&grid.limits().cell_index(&world)))
}

/// `Σd / √(Σd²)` over `cloud`, with `d` the probability at `better` minus that at `other`: positive when
/// `better` fits better, 0 when both fit identically.
pub fn paired_z(
    grid: &ProbabilityGrid,
    cloud: &[Point2<f32>],
    better: &Rigid2,
    other: &Rigid2,
) -> f64 {
    let (mut sum, mut squares) = (0.0, 0.0);
    for p in cloud {
        let d = probability_at(grid, better, *p) - probability_at(grid, other, *p);
        sum += d;
        squares += d * d;
    }
    if squares > 0.0 {
        sum / squares.sqrt()
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;
    use crate::scan_matching::test_support::{room_grid, room_scan};

    #[test]
    fn identical_poses_give_zero_and_a_true_fit_beats_a_shifted_one() {
        let grid = room_grid();
        let truth = rigid2(2.5, 2.0, 0.3);
        let scan = room_scan(&truth);
        assert!(paired_z(&grid, &scan, &truth, &truth).abs() < 1e-12);
        let shifted = rigid2(2.8, 1.8, 0.45);
        let z = paired_z(&grid, &scan, &truth, &shifted);
        assert!(z > 5.0, "z = {z}");
        assert!((paired_z(&grid, &scan, &shifted, &truth) + z).abs() < 1e-9);
    }
}
