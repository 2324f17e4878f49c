//! Renders a site's submaps into one grid in the site frame.
//!
//! Each output cell looks up, in every submap whose footprint covers it, the submap cell under its centre
//! (nearest neighbour, after mapping the centre through `grid_from_global`), and fuses the known ones by
//! adding their log-odds, clamped to the grid's probability range. Pulling from the output side leaves no
//! holes when submaps are rotated; the cost is the sum of the submaps' footprint areas in output cells.

use std::sync::{Arc, OnceLock};

use mapping::geometry::Rigid2;
use mapping::grid::{
    CellIndex, MAX_PROBABILITY, MIN_PROBABILITY, MapLimits, ProbabilityGrid, UNKNOWN_VALUE,
    value_to_probability,
};
use nalgebra::{Point2, Vector2};

fn logit(p: f32) -> f32 {
    (p / (1.0 - p)).ln()
}

/// `logit(value_to_probability(v))` for every stored value `v`, computed once: the logarithm per cell
/// was most of a render's time (the console renders a map per version).
fn logit_of_value() -> &'static [f32] {
    static TABLE: OnceLock<Vec<f32>> = OnceLock::new();
    TABLE.get_or_init(|| {
        (0..=u16::MAX)
            .map(|v| logit(value_to_probability(v)))
            .collect()
    })
}

/// Fuses `grids` (each with `global_from_grid`, the pose of its frame in the site frame) into one grid of
/// cell side `resolution` (m; 0 or less: the first grid's). `None` when there is nothing to draw.
pub fn render_submaps(
    grids: &[(Rigid2, Arc<ProbabilityGrid>)],
    resolution: f64,
) -> Option<ProbabilityGrid> {
    let first = grids.first()?;
    let resolution = if resolution > 0.0 && resolution.is_finite() {
        resolution
    } else {
        first.1.limits().resolution
    };
    let footprint = |(pose, grid): &(Rigid2, Arc<ProbabilityGrid>)| {
        let l = grid.limits();
        let size = Vector2::new(f64::from(l.width), f64::from(l.height)) * l.resolution;
        let corners = [
            Vector2::zeros(),
            Vector2::new(size.x, 0.0),
            Vector2::new(0.0, size.y),
            size,
        ]
        .map(|c| pose * Point2::from(l.origin + c));
        let min = corners
            .iter()
            .fold(Vector2::repeat(f64::INFINITY), |m, c| m.inf(&c.coords));
        let max = corners
            .iter()
            .fold(Vector2::repeat(f64::NEG_INFINITY), |m, c| m.sup(&c.coords));
        (min, max)
    };
    let (mut min, mut max) = (
        Vector2::repeat(f64::INFINITY),
        Vector2::repeat(f64::NEG_INFINITY),
    );
    for g in grids {
        let (lo, hi) = footprint(g);
        min = min.inf(&lo);
        max = max.sup(&hi);
    }
    let cells = ((max - min) / resolution).map(|v| v.ceil().max(1.0) as i32);
    let limits = MapLimits::new(resolution, min, cells.x, cells.y);
    let mut log_odds = vec![0.0_f32; limits.num_cells()];
    let mut known = vec![false; limits.num_cells()];
    let logits = logit_of_value();
    for g in grids {
        let (pose, grid) = g;
        let grid_from_global = pose.inverse();
        let (lo, hi) = footprint(g);
        let (a, b) = (
            limits.cell_index(&Point2::from(lo)),
            limits.cell_index(&Point2::from(hi)),
        );
        for iy in a.y.max(0)..=b.y.min(limits.height - 1) {
            for ix in a.x.max(0)..=b.x.min(limits.width - 1) {
                let cell = CellIndex::new(ix, iy);
                let source = grid
                    .limits()
                    .cell_index(&(grid_from_global * limits.cell_center(&cell)));
                let Some(value) = grid
                    .limits()
                    .flat_index(&source)
                    .and_then(|s| grid.values().get(s).copied())
                    .filter(|v| *v != UNKNOWN_VALUE)
                else {
                    continue;
                };
                if let (Some(i), Some(l)) =
                    (limits.flat_index(&cell), logits.get(usize::from(value)))
                {
                    log_odds[i] += l;
                    known[i] = true;
                }
            }
        }
    }
    let mut out = ProbabilityGrid::new(limits);
    let (lo, hi) = (logit(MIN_PROBABILITY), logit(MAX_PROBABILITY));
    for (i, value) in out.values_mut().iter_mut().enumerate() {
        if known[i] {
            let l = log_odds[i].clamp(lo, hi);
            *value = mapping::grid::probability_to_value(1.0 / (1.0 + (-l).exp()));
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;

    use super::*;

    /// A 20×10 grid at 0.1 m with an occupied column at ix = 15 and free cells elsewhere.
    fn wall_grid() -> ProbabilityGrid {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.1, Vector2::new(-1.0, -0.5), 20, 10));
        for iy in 0..10 {
            for ix in 0..20 {
                let p = if ix == 15 { 0.9 } else { 0.2 };
                grid.set_probability(&CellIndex::new(ix, iy), p);
            }
        }
        grid
    }

    #[test]
    fn an_unmoved_grid_renders_as_itself() {
        let grid = Arc::new(wall_grid());
        let out = render_submaps(&[(Rigid2::identity(), Arc::clone(&grid))], 0.0).unwrap();
        assert_eq!(out.limits().width, 20);
        assert_eq!(out.limits().height, 10);
        for iy in 0..10 {
            for ix in 0..20 {
                let c = CellIndex::new(ix, iy);
                assert!(
                    (out.probability(&c) - grid.probability(&c)).abs() < 1e-3,
                    "{c:?}"
                );
            }
        }
    }

    #[test]
    fn a_moved_grid_puts_its_wall_where_the_pose_says() {
        // The wall is at local x = 0.55; rotated by 90° and shifted by (5, 0) it is at global y = 0.55.
        let pose = rigid2(5.0, 0.0, std::f64::consts::FRAC_PI_2);
        let out = render_submaps(&[(pose, Arc::new(wall_grid()))], 0.1).unwrap();
        let wall = out.limits().cell_index(&Point2::new(5.0, 0.55));
        let free = out.limits().cell_index(&Point2::new(5.0, 0.0));
        assert!(out.probability(&wall) > 0.85, "{}", out.probability(&wall));
        assert!(out.probability(&free) < 0.3);
        assert!(!out.is_known(&out.limits().cell_index(&Point2::new(0.0, 0.0))));
        assert!(render_submaps(&[], 0.1).is_none());
    }

    #[test]
    fn overlapping_observations_reinforce() {
        let grid = Arc::new(wall_grid());
        let one = render_submaps(&[(Rigid2::identity(), Arc::clone(&grid))], 0.1).unwrap();
        let two = render_submaps(
            &[
                (Rigid2::identity(), Arc::clone(&grid)),
                (Rigid2::identity(), grid),
            ],
            0.1,
        )
        .unwrap();
        let free = CellIndex::new(3, 3);
        assert!(two.probability(&free) < one.probability(&free));
    }
}
