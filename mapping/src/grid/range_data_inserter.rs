//! Inserting range data into a probability grid: every hit makes its cell more likely occupied, every
//! cell a beam passes through (and the whole ray of a no-return reading) more likely free. Updates are
//! odds multiplications done by table lookup on the 15-bit cell values, clamped to
//! `[MIN_PROBABILITY, MAX_PROBABILITY]`, at most one hit and one miss per cell per scan.
//!
//! Rays are traversed exactly (Amanatides & Woo, "A Fast Voxel Traversal Algorithm", 1987): every cell
//! the segment crosses is visited once, which keeps thin walls from being punched through by rays that
//! graze them.

use nalgebra::{Point2, Vector2};
use serde::{Deserialize, Serialize};

use super::probability_grid::{probability_to_value, value_to_probability};
use super::{CellIndex, MAX_PROBABILITY, MIN_PROBABILITY, ProbabilityGrid};
use crate::sensor::RangeData;

/// How strongly one observation moves a cell.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RangeDataInserterOptions {
    /// Probability that a cell is occupied given one hit in it, in (0.5, 1). Default 0.7.
    /// Why: `docs/TUNING.md#rdi-hit-probability`.
    pub hit_probability: f32,
    /// Probability that a cell is occupied given one ray through it, in (0, 0.5). Default 0.45.
    /// Why: `docs/TUNING.md#rdi-miss-probability`.
    pub miss_probability: f32,
    /// Whether rays mark the cells they cross as free. Default true.
    pub insert_free_space: bool,
}

impl Default for RangeDataInserterOptions {
    fn default() -> Self {
        Self {
            hit_probability: 0.7,
            miss_probability: 0.45,
            insert_free_space: true,
        }
    }
}

/// Invalid [`RangeDataInserterOptions`].
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{0}")]
pub struct RangeDataInserterOptionsError(String);

impl RangeDataInserterOptions {
    /// Checks the probabilities.
    pub fn validate(&self) -> Result<(), RangeDataInserterOptionsError> {
        if !(self.hit_probability > 0.5 && self.hit_probability < 1.0) {
            return Err(RangeDataInserterOptionsError(format!(
                "hit_probability must be in (0.5, 1), got {}",
                self.hit_probability
            )));
        }
        if !(self.miss_probability > 0.0 && self.miss_probability < 0.5) {
            return Err(RangeDataInserterOptionsError(format!(
                "miss_probability must be in (0, 0.5), got {}",
                self.miss_probability
            )));
        }
        Ok(())
    }
}

fn odds(p: f32) -> f32 {
    p / (1.0 - p)
}

/// The table mapping each unmarked cell value to its value after one observation with `odds_factor`.
fn lookup_table(odds_factor: f32) -> Vec<u16> {
    (0..super::probability_grid::UPDATE_MARKER)
        .map(|value| {
            let updated = if value == super::UNKNOWN_VALUE {
                // An unknown cell takes the observation's own probability.
                odds_factor / (1.0 + odds_factor)
            } else {
                let o = odds(value_to_probability(value)) * odds_factor;
                o / (1.0 + o)
            };
            probability_to_value(updated.clamp(MIN_PROBABILITY, MAX_PROBABILITY))
                + super::probability_grid::UPDATE_MARKER
        })
        .collect()
}

/// Inserts range data into grids; holds the two lookup tables.
#[derive(Clone, Debug)]
pub struct RangeDataInserter {
    options: RangeDataInserterOptions,
    hit_table: Vec<u16>,
    miss_table: Vec<u16>,
}

impl RangeDataInserter {
    /// Builds the lookup tables.
    pub fn new(options: RangeDataInserterOptions) -> Self {
        let hit_table = lookup_table(odds(options.hit_probability));
        let miss_table = lookup_table(odds(options.miss_probability));
        Self {
            options,
            hit_table,
            miss_table,
        }
    }

    /// Inserts `range_data` (in the grid's frame), growing the grid as needed.
    pub fn insert(&self, range_data: &RangeData, grid: &mut ProbabilityGrid) {
        let origin = Point2::from(range_data.origin);
        grid.grow_to_include(
            std::iter::once(origin).chain(
                range_data
                    .returns
                    .iter()
                    .chain(&range_data.misses)
                    .map(|p| p.cast::<f64>()),
            ),
        );
        // Hits first, so a cell both hit and crossed in one scan counts as hit (as in Cartographer).
        for p in &range_data.returns {
            let cell = grid.limits().cell_index(&p.cast::<f64>());
            grid.apply_lookup_table(cell, &self.hit_table);
        }
        if self.options.insert_free_space {
            for p in &range_data.returns {
                self.cast_ray(grid, &origin, &p.cast::<f64>(), false);
            }
            for p in &range_data.misses {
                self.cast_ray(grid, &origin, &p.cast::<f64>(), true);
            }
        }
        grid.finish_update();
    }

    fn cast_ray(
        &self,
        grid: &mut ProbabilityGrid,
        from: &Point2<f64>,
        to: &Point2<f64>,
        include_end: bool,
    ) {
        let table = &self.miss_table;
        let (resolution, origin) = (grid.limits().resolution, grid.limits().origin);
        traverse(resolution, &origin, from, to, |cell, is_end| {
            if !is_end || include_end {
                grid.apply_lookup_table(cell, table);
            }
        });
    }
}

/// Visits every cell crossed by the segment `from → to`, in order; `visit(cell, is_last)`.
pub(crate) fn traverse(
    resolution: f64,
    grid_origin: &Vector2<f64>,
    from: &Point2<f64>,
    to: &Point2<f64>,
    mut visit: impl FnMut(CellIndex, bool),
) {
    let a = (from.coords - grid_origin) / resolution;
    let b = (to.coords - grid_origin) / resolution;
    let mut cell = CellIndex::new(a.x.floor() as i32, a.y.floor() as i32);
    let end = CellIndex::new(b.x.floor() as i32, b.y.floor() as i32);
    let d = b - a;
    let step = CellIndex::new(
        if d.x > 0.0 { 1 } else { -1 },
        if d.y > 0.0 { 1 } else { -1 },
    );
    let t_delta = Vector2::new(
        if d.x == 0.0 {
            f64::INFINITY
        } else {
            1.0 / d.x.abs()
        },
        if d.y == 0.0 {
            f64::INFINITY
        } else {
            1.0 / d.y.abs()
        },
    );
    let boundary = |coord: f64, c: i32, s: i32| {
        if s > 0 {
            f64::from(c + 1) - coord
        } else {
            coord - f64::from(c)
        }
    };
    let mut t_max = Vector2::new(
        boundary(a.x, cell.x, step.x) * t_delta.x,
        boundary(a.y, cell.y, step.y) * t_delta.y,
    );
    // At most |Δx| + |Δy| + 2 steps: a hard bound that also protects against NaN input.
    let max_steps = ((end.x - cell.x).abs() + (end.y - cell.y).abs()) as usize + 2;
    for _ in 0..max_steps {
        if cell == end {
            break;
        }
        visit(cell, false);
        if t_max.x < t_max.y {
            cell.x += step.x;
            t_max.x += t_delta.x;
        } else {
            cell.y += step.y;
            t_max.y += t_delta.y;
        }
    }
    visit(end, true);
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;
    use crate::grid::MapLimits;

    #[test]
    fn hits_raise_and_rays_lower_probability() {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.1, Vector2::new(-1.0, -1.0), 20, 20));
        let inserter = RangeDataInserter::new(RangeDataInserterOptions::default());
        let data = RangeData {
            origin: Vector2::new(0.05, 0.05),
            returns: vec![Point2::new(0.55f32, 0.05)],
            misses: vec![Point2::new(0.05f32, 0.55)],
        };
        let options = RangeDataInserterOptions::default();
        inserter.insert(&data, &mut grid);
        let hit = grid.limits().cell_index(&Point2::new(0.55, 0.05));
        assert!((grid.probability(&hit) - options.hit_probability).abs() < 1e-3);
        for x in [0.05, 0.25, 0.45] {
            let c = grid.limits().cell_index(&Point2::new(x, 0.05));
            assert!(
                (grid.probability(&c) - options.miss_probability).abs() < 1e-3,
                "x = {x}"
            );
        }
        let miss_end = grid.limits().cell_index(&Point2::new(0.05, 0.55));
        assert!(grid.is_known(&miss_end));
        let untouched = grid.limits().cell_index(&Point2::new(0.55, 0.55));
        assert!(!grid.is_known(&untouched));
        for _ in 0..200 {
            inserter.insert(&data, &mut grid);
        }
        assert!((grid.probability(&hit) - MAX_PROBABILITY).abs() < 1e-4);
    }

    #[test]
    fn grows_for_far_points() {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.1, Vector2::zeros(), 4, 4));
        let inserter = RangeDataInserter::new(RangeDataInserterOptions::default());
        let data = RangeData {
            origin: Vector2::new(0.2, 0.2),
            returns: vec![Point2::new(5.0f32, -3.0)],
            misses: vec![],
        };
        inserter.insert(&data, &mut grid);
        let hit = grid.limits().cell_index(&Point2::new(5.0, -3.0));
        assert!(grid.limits().contains(&hit) && grid.probability(&hit) > 0.5);
    }

    fn brute_force_cells(a: Point2<f64>, b: Point2<f64>) -> Vec<CellIndex> {
        // Dense sampling along the segment; cells touched by a sample, in order.
        let mut out: Vec<CellIndex> = Vec::new();
        for k in 0..=200_000 {
            let p = a + (b - a) * (f64::from(k) / 200_000.0);
            let c = CellIndex::new(p.x.floor() as i32, p.y.floor() as i32);
            if out.last() != Some(&c) {
                out.push(c);
            }
        }
        out
    }

    proptest! {
        #[test]
        fn traversal_matches_dense_sampling(ax in -5.0..5.0f64, ay in -5.0..5.0f64, bx in -5.0..5.0f64, by in -5.0..5.0f64) {
            let (a, b) = (Point2::new(ax, ay), Point2::new(bx, by));
            let mut visited = Vec::new();
            traverse(1.0, &Vector2::zeros(), &a, &b, |c, _| visited.push(c));
            let expected = brute_force_cells(a, b);
            // Dense sampling can skip a cell only when the segment passes within 5e-5 of a corner;
            // then the exact traversal has one extra cell. Every sampled cell must be visited in order.
            let mut it = visited.iter();
            for c in &expected {
                prop_assert!(it.any(|v| v == c), "missing {:?} in {:?}", c, visited);
            }
            prop_assert!(visited.len() <= expected.len() + 2);
        }

        #[test]
        fn probabilities_stay_clamped(n_hits in 0usize..300, n_misses in 0usize..300) {
            let inserter = RangeDataInserter::new(RangeDataInserterOptions::default());
            let mut v = crate::grid::UNKNOWN_VALUE;
            for _ in 0..n_hits { v = inserter.hit_table[v as usize] - super::super::probability_grid::UPDATE_MARKER; }
            for _ in 0..n_misses { v = inserter.miss_table[v as usize] - super::super::probability_grid::UPDATE_MARKER; }
            let p = value_to_probability(v);
            prop_assert!((MIN_PROBABILITY..=MAX_PROBABILITY).contains(&p));
        }
    }
}
