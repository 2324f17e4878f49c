//! The score of a scan at a pose in a map: what branch and bound maximizes (the mean occupancy
//! probability of the cells the scan's points fall in), evaluated at one pose. The paper's AMS averages
//! it over the scans of a session against the map as it was then.

use nalgebra::Point2;

use crate::geometry::Rigid2;
use crate::grid::ProbabilityGrid;

/// Mean probability of `map`'s cells at `points` (tracking frame) placed at `map_from_tracking`; unknown
/// and out-of-map cells read as the least probability, as in branch and bound. 0 for no points.
pub fn match_score(
    map: &ProbabilityGrid,
    points: &[Point2<f32>],
    map_from_tracking: &Rigid2,
) -> f64 {
    if points.is_empty() {
        return 0.0;
    }
    let sum: f64 = points
        .iter()
        .map(|p| {
            let world = map_from_tracking * Point2::new(f64::from(p.x), f64::from(p.y));
            f64::from(map.probability(&map.limits().cell_index(&world)))
        })
        .sum();
    sum / points.len() as f64
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector2;

    use super::*;
    use crate::geometry::rigid2;
    use crate::grid::{CellIndex, MIN_PROBABILITY, MapLimits};

    #[test]
    fn scores_the_cells_the_points_land_in() {
        // 10 × 10 cells of 0.1 m from (0, 0); a wall of 0.9 along x = 0.55.
        let mut map = ProbabilityGrid::new(MapLimits::new(0.1, Vector2::zeros(), 10, 10));
        for y in 0..10 {
            map.set_probability(&CellIndex::new(5, y), 0.9);
            map.set_probability(&CellIndex::new(2, y), 0.2);
        }
        let points: Vec<Point2<f32>> = (0..4).map(|k| Point2::new(0.5, 0.1 * k as f32)).collect();
        // Placed with the points on the wall (x 0.55).
        let on_wall = match_score(&map, &points, &rigid2(0.05, 0.25, 0.0));
        assert!((on_wall - 0.9).abs() < 1e-3, "{on_wall}");
        // Three cells to the left: the 0.2 cells.
        let off = match_score(&map, &points, &rigid2(-0.25, 0.25, 0.0));
        assert!((off - 0.2).abs() < 1e-3, "{off}");
        // Outside the map: the least probability.
        let outside = match_score(&map, &points, &rigid2(5.0, 5.0, 0.0));
        assert!((outside - f64::from(MIN_PROBABILITY)).abs() < 1e-6);
        // Half on the wall, half out of the map.
        let half = match_score(&map, &points, &rigid2(0.05, 0.85, 0.0));
        assert!(
            (half - 0.5 * (0.9 + f64::from(MIN_PROBABILITY))).abs() < 1e-3,
            "{half}"
        );
        assert!(match_score(&map, &[], &Rigid2::identity()).abs() < f64::EPSILON);
    }
}
