//! The score of a scan in a map, as the paper's AMS averages it: the branch-and-bound score (the mean
//! occupancy probability of the cells the scan's points fall in, maximized over poses) of the scan
//! searched within a small window around where the robot believed it was. The window is the tolerance of
//! correct localization by default ([`ScoringOptions::match_window`](super::ScoringOptions)): a scan
//! scores well when the map, near the robot's own estimate, still looks like what it sees.

use nalgebra::Point2;

use super::PoseTolerance;
use crate::geometry::Rigid2;
use crate::grid::ProbabilityGrid;
use crate::scan_matching::{FastCorrelativeScanMatcher, FastCorrelativeScanMatcherOptions};

/// Scores scans against one map by branch and bound within a window around an estimate. Building it
/// precomputes the map's bound grids once (a few bytes per cell); scoring is then a small search.
#[derive(Clone, Debug)]
pub struct MatchScorer {
    matcher: FastCorrelativeScanMatcher,
    window: PoseTolerance,
}

impl MatchScorer {
    /// A scorer of scans against `map` within `window` (metres, degrees) of the estimate.
    pub fn new(map: &ProbabilityGrid, window: PoseTolerance) -> Self {
        // Depth: the coarsest bound grid spans about the window.
        let cells = (2.0 * window.translation_m / map.limits().resolution).max(1.0);
        let depth = (cells.log2().ceil() as u32).clamp(1, 8);
        let options = FastCorrelativeScanMatcherOptions {
            linear_search_window: window.translation_m,
            angular_search_window: window.rotation_deg.to_radians(),
            branch_and_bound_depth: depth,
        };
        Self {
            matcher: FastCorrelativeScanMatcher::new(map, options),
            window,
        }
    }

    /// The best [`mean_probability`](crate::scan_matching::mean_probability) of `points` (tracking
    /// frame) within the window around `map_from_tracking`. 0 for no points.
    pub fn score(&self, points: &[Point2<f32>], map_from_tracking: &Rigid2) -> f64 {
        if points.is_empty() {
            return 0.0;
        }
        self.matcher
            .match_within(
                map_from_tracking,
                points,
                0.0,
                self.window.translation_m,
                self.window.rotation_deg.to_radians(),
            )
            .map_or(0.0, |m| f64::from(m.score))
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector2;

    use super::*;
    use crate::geometry::rigid2;
    use crate::grid::{CellIndex, MIN_PROBABILITY, MapLimits};
    use crate::scan_matching::mean_probability;

    /// 10 × 10 cells of 0.1 m from (0, 0); a wall of 0.9 along x = 0.55 and cells of 0.2 at x = 0.25.
    fn map() -> ProbabilityGrid {
        let mut map = ProbabilityGrid::new(MapLimits::new(0.1, Vector2::zeros(), 10, 10));
        for y in 0..10 {
            map.set_probability(&CellIndex::new(5, y), 0.9);
            map.set_probability(&CellIndex::new(2, y), 0.2);
        }
        map
    }

    fn points() -> Vec<Point2<f32>> {
        (0..4).map(|k| Point2::new(0.5, 0.1 * k as f32)).collect()
    }

    #[test]
    fn scores_the_cells_the_points_land_in() {
        let (map, points) = (map(), points());
        // Placed with the points on the wall (x 0.55).
        let on_wall = mean_probability(&map, &points, &rigid2(0.05, 0.25, 0.0));
        assert!((on_wall - 0.9).abs() < 1e-3, "{on_wall}");
        // Three cells to the left: the 0.2 cells.
        let off = mean_probability(&map, &points, &rigid2(-0.25, 0.25, 0.0));
        assert!((off - 0.2).abs() < 1e-3, "{off}");
        // Outside the map: the least probability.
        let outside = mean_probability(&map, &points, &rigid2(5.0, 5.0, 0.0));
        assert!((outside - f64::from(MIN_PROBABILITY)).abs() < 1e-6);
        // Half on the wall, half out of the map.
        let half = mean_probability(&map, &points, &rigid2(0.05, 0.85, 0.0));
        assert!(
            (half - 0.5 * (0.9 + f64::from(MIN_PROBABILITY))).abs() < 1e-3,
            "{half}"
        );
        assert!(mean_probability(&map, &[], &Rigid2::identity()).abs() < f64::EPSILON);
    }

    #[test]
    fn the_scorer_finds_the_best_pose_within_its_window_only() {
        let (map, points) = (map(), points());
        let window = PoseTolerance {
            translation_m: 0.15,
            rotation_deg: 2.0,
        };
        let scorer = MatchScorer::new(&map, window);
        // The estimate one cell off the wall: the search finds the wall.
        let near = scorer.score(&points, &rigid2(-0.05, 0.25, 0.0));
        assert!((near - 0.9).abs() < 1e-3, "{near}");
        // At the wall it is the plain score.
        let at = scorer.score(&points, &rigid2(0.05, 0.25, 0.0));
        let plain = mean_probability(&map, &points, &rigid2(0.05, 0.25, 0.0));
        assert!((at - plain).abs() < 1e-3, "{at} {plain}");
        // Three cells off: the wall is out of reach, and the best within reach is below it (a brute-force
        // oracle over the window's whole-cell shifts agrees).
        let estimate = rigid2(-0.25, 0.25, 0.0);
        let far = scorer.score(&points, &estimate);
        let oracle = (-1..=1)
            .flat_map(|dx| (-1..=1).map(move |dy| (dx, dy)))
            .map(|(dx, dy)| {
                let shifted = rigid2(-0.25 + 0.1 * f64::from(dx), 0.25 + 0.1 * f64::from(dy), 0.0);
                mean_probability(&map, &points, &shifted)
            })
            .fold(f64::MIN, f64::max);
        assert!(far < 0.9 - 0.1, "{far}");
        assert!(far + 1e-3 >= oracle, "{far} vs {oracle}");
        assert!(scorer.score(&[], &estimate).abs() < f64::EPSILON);
    }
}
