//! How much better a cloud fits a grid at one pose than at another, point by point.
//!
//! Two poses of the same cloud are compared on the same points: each point contributes the difference
//! `d` of the grid's probability under the two poses. The statistic is `Σd / √(Σd²)`: the mean difference
//! in units of its standard error if the points were independent (0 when the poses fit identically). Two
//! fits that differ by chance in a few points give a small value however many points there are; a real
//! improvement over most of the cloud gives a large one. Neighbouring points are not independent, so
//! thresholds on it are empirical, not probabilities.
//!
//! [`blocked_paired_z`] sums the differences per block of the cloud first (squares of a given size in
//! the cloud's own frame) and takes the statistic over the blocks: points that move, vanish or fit by
//! chance together — a shelf section's goods, a parked cart — count as one piece of evidence, so the
//! statistic does not grow merely because a growing cloud holds more points of the same chance fit.

use std::collections::BTreeMap;

use nalgebra::Point2;

use crate::geometry::Rigid2;
use crate::grid::ProbabilityGrid;

/// The probability of `grid` at point `p` (tracking frame) placed at `pose`; unknown and out-of-grid cells
/// read as the least probability, as in every search.
pub fn probability_at(grid: &ProbabilityGrid, pose: &Rigid2, p: Point2<f32>) -> f64 {
    let world = pose * Point2::new(f64::from(p.x), f64::from(p.y));
    f64::from(grid.probability(&grid.limits().cell_index(&world)))
}

/// The score of `points` (tracking frame) placed at `grid_from_tracking`: the mean of
/// [`probability_at`] over them, in their order (unknown and out-of-grid cells read as the least
/// probability). 0 for no points. Searches maximize it; the paper's AMS averages it.
pub fn mean_probability(
    grid: &ProbabilityGrid,
    points: &[Point2<f32>],
    grid_from_tracking: &Rigid2,
) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let sum: f64 = points
        .iter()
        .map(|&p| probability_at(grid, grid_from_tracking, p))
        .sum();
    sum / points.len() as f64
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

/// [`paired_z`] over blocks: the differences `d` summed per `block_m` × `block_m` square of the cloud's
/// frame into `D`, then `ΣD / √(ΣD²)`. `block_m` ≤ 0 gives [`paired_z`] (every point its own block).
pub fn blocked_paired_z(
    grid: &ProbabilityGrid,
    cloud: &[Point2<f32>],
    better: &Rigid2,
    other: &Rigid2,
    block_m: f64,
) -> f64 {
    if block_m <= 0.0 {
        return paired_z(grid, cloud, better, other);
    }
    let mut blocks = PairedBlocks::new(block_m);
    blocks.add(grid, cloud, better, other);
    blocks.z()
}

/// The block sums of [`blocked_paired_z`], gathered piece by piece: each piece of one cloud (points in the
/// cloud's frame) is compared at its own pair of poses, and its differences are added to the same
/// `block_m` squares of the cloud's frame (`block_m` ≤ 0: every point its own block, as in [`paired_z`]).
/// One piece is [`blocked_paired_z`] itself.
#[derive(Clone, Debug)]
pub struct PairedBlocks {
    block_m: f64,
    /// Ordered, so that the sums, and every decision on them, are the same in every run.
    blocks: BTreeMap<(i64, i64), f64>,
    /// Points added so far (the blocks' keys when `block_m` ≤ 0).
    points: i64,
}

impl PairedBlocks {
    /// No evidence yet, blocks of `block_m` metres.
    pub fn new(block_m: f64) -> Self {
        Self {
            block_m,
            blocks: BTreeMap::new(),
            points: 0,
        }
    }

    /// Adds the differences of `piece` (points in the cloud's frame) between `better` and `other`.
    pub fn add(
        &mut self,
        grid: &ProbabilityGrid,
        piece: &[Point2<f32>],
        better: &Rigid2,
        other: &Rigid2,
    ) {
        for p in piece {
            let d = probability_at(grid, better, *p) - probability_at(grid, other, *p);
            let key = if self.block_m > 0.0 {
                (
                    (f64::from(p.x) / self.block_m).floor() as i64,
                    (f64::from(p.y) / self.block_m).floor() as i64,
                )
            } else {
                (self.points, 0)
            };
            self.points += 1;
            *self.blocks.entry(key).or_default() += d;
        }
    }

    /// `ΣD / √(ΣD²)` over the blocks: positive when `better` fits better (0 without evidence).
    pub fn z(&self) -> f64 {
        let (sum, squares) = self
            .blocks
            .values()
            .fold((0.0, 0.0), |(sum, squares), d| (sum + d, squares + d * d));
        if squares > 0.0 {
            sum / squares.sqrt()
        } else {
            0.0
        }
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

    #[test]
    fn blocks_count_a_chance_fit_once_and_tiny_blocks_are_points() {
        let grid = room_grid();
        let truth = rigid2(2.5, 2.0, 0.3);
        let scan = room_scan(&truth);
        let shifted = rigid2(2.8, 1.8, 0.45);
        let points = paired_z(&grid, &scan, &truth, &shifted);
        // Blocks smaller than the points' spacing hold one point each: the per-point statistic.
        let tiny = blocked_paired_z(&grid, &scan, &truth, &shifted, 1e-3);
        assert!((tiny - points).abs() < 1e-9, "{tiny} vs {points}");
        let zero = blocked_paired_z(&grid, &scan, &truth, &shifted, 0.0);
        assert!((zero - points).abs() < 1e-12, "{zero} vs {points}");
        // Brute force: the same statistic over 1 m blocks summed by hand.
        let mut sums = std::collections::BTreeMap::<(i64, i64), f64>::new();
        for p in &scan {
            let d = probability_at(&grid, &truth, *p) - probability_at(&grid, &shifted, *p);
            *sums
                .entry((f64::from(p.x).floor() as i64, f64::from(p.y).floor() as i64))
                .or_default() += d;
        }
        let expected =
            sums.values().sum::<f64>() / sums.values().map(|d| d * d).sum::<f64>().sqrt();
        let blocked = blocked_paired_z(&grid, &scan, &truth, &shifted, 1.0);
        assert!((blocked - expected).abs() < 1e-9, "{blocked} vs {expected}");
        // Fewer, larger pieces of evidence: a smaller statistic than per point.
        assert!(blocked > 0.0 && blocked < points, "{blocked} vs {points}");
    }
}
