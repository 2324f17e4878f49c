//! The site's submaps painted into one grid in the map frame, three ways. Where several submaps know a
//! cell, the painters differ in how they combine them:
//!
//! - [`render_submaps_max`]: the highest probability any submap gives the cell (every wall and goods
//!   arrangement ever seen; the agent's maps: the offline map, the `/map` it publishes to ROS 2, the
//!   map AMS scores scans against).
//! - [`render_submaps_newest`]: the last submap's value, submaps taken oldest first (the site as its
//!   latest sessions saw it; the map change rate and its pictures).
//! - [`render_submaps_log_odds`]: the sum of the submaps' log-odds, clamped to the grid's probability
//!   range (every observation counts; the server's `GetMapImage` and the web console's map).
//!
//! The first two are [`render_relocalization_map`] with [`MapCells::Highest`] and [`MapCells::Newest`]
//! (one session for all grids), cropped to the known cells.
//!
//! The log-odds painter looks up, for each output cell, in every submap whose footprint covers it, the
//! submap cell under its centre (nearest neighbour, after mapping the centre through `grid_from_global`).
//! Pulling from the output side leaves no holes when submaps are rotated. The source cell is affine in
//! the output cell's index, so each output row is walked only where it crosses a submap, with one
//! fixed-point add per coordinate and cell: the cost is the sum of the submaps' areas in output cells, a
//! few nanoseconds each (the web console renders a map per version).

use std::sync::{Arc, OnceLock};

use nalgebra::{Point2, Vector2};

use super::{MapCells, PlacedGrid, render_relocalization_map};
use crate::geometry::Rigid2;
use crate::grid::{
    CellIndex, MAX_PROBABILITY, MIN_PROBABILITY, MapLimits, ProbabilityGrid, UNKNOWN_VALUE,
    probability_to_value, value_to_probability,
};

/// Renders placed grids into one map-frame grid of cell size `resolution`: each cell takes the highest
/// probability among the grids that know its centre ([`MapCells::Highest`], for pictures of everything
/// ever seen). `None` when no grid knows anything.
pub fn render_submaps_max<'a>(
    grids: impl IntoIterator<Item = PlacedGrid<'a>>,
    resolution: f64,
) -> Option<ProbabilityGrid> {
    render_as_one_session(grids, resolution, MapCells::Highest)
}

/// Like [`render_submaps_max`], but each cell takes the value of the *last* grid (in iteration order)
/// that knows its centre: with grids ordered oldest first, the map as the newest observations describe
/// it ([`MapCells::Newest`], for the map change rate).
pub fn render_submaps_newest<'a>(
    grids: impl IntoIterator<Item = PlacedGrid<'a>>,
    resolution: f64,
) -> Option<ProbabilityGrid> {
    render_as_one_session(grids, resolution, MapCells::Newest)
}

/// [`render_relocalization_map`] with every grid in one session.
fn render_as_one_session<'a>(
    grids: impl IntoIterator<Item = PlacedGrid<'a>>,
    resolution: f64,
    cells: MapCells,
) -> Option<ProbabilityGrid> {
    render_relocalization_map(grids.into_iter().map(|g| (0, g)), resolution, cells)
}

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

/// Where a grid placed at `global_from_grid` lies in the site frame: the lower and upper corners of
/// its axis-aligned bounding box, m.
fn footprint(global_from_grid: &Rigid2, grid: &ProbabilityGrid) -> (Vector2<f64>, Vector2<f64>) {
    PlacedGrid {
        global_from_grid: *global_from_grid,
        grid,
    }
    .global_bounds()
}

/// Fuses `grids` (each with `global_from_grid`, the pose of its frame in the site frame) into one grid of
/// cell side `resolution` (m; 0 or less: the first grid's) by adding their log-odds. `None` when there is
/// nothing to draw.
pub fn render_submaps_log_odds(
    grids: &[(Rigid2, Arc<ProbabilityGrid>)],
    resolution: f64,
) -> Option<ProbabilityGrid> {
    let first = grids.first()?;
    let resolution = if resolution > 0.0 && resolution.is_finite() {
        resolution
    } else {
        first.1.limits().resolution
    };
    let (mut min, mut max) = (
        Vector2::repeat(f64::INFINITY),
        Vector2::repeat(f64::NEG_INFINITY),
    );
    for (global_from_grid, grid) in grids {
        let (lo, hi) = footprint(global_from_grid, grid);
        min = min.inf(&lo);
        max = max.sup(&hi);
    }
    let cells = ((max - min) / resolution).map(|v| v.ceil().max(1.0) as i32);
    let limits = MapLimits::new(resolution, min, cells.x, cells.y);
    let mut log_odds = vec![0.0_f32; limits.num_cells()];
    let mut known = vec![false; limits.num_cells()];
    for (global_from_grid, grid) in grids {
        add_grid(&limits, global_from_grid, grid, &mut log_odds, &mut known);
    }
    let mut out = ProbabilityGrid::new(limits);
    let (lo, hi) = (logit(MIN_PROBABILITY), logit(MAX_PROBABILITY));
    for ((value, l), known) in out.values_mut().iter_mut().zip(&log_odds).zip(&known) {
        if *known {
            let l = l.clamp(lo, hi);
            *value = probability_to_value(1.0 / (1.0 + (-l).exp()));
        }
    }
    Some(out)
}

/// Fraction bits of the fixed-point source indices: steps exact to 2^-40 cells, so a 2000-cell row drifts
/// by less than 1e-9 cells, and indices up to 2^23 cells fit an `i64`.
const FRACTION_BITS: u32 = 40;

/// `x` in fixed point with [`FRACTION_BITS`] (saturating far outside any grid).
fn to_fixed(x: f64) -> i64 {
    (x * (1_u64 << FRACTION_BITS) as f64).round() as i64
}

/// The real `ix` for which `start + ix * step` lies in `[0, size)`, as `(lowest, highest)` (either may
/// be infinite); `None` when there is none.
fn span(start: f64, step: f64, size: f64) -> Option<(f64, f64)> {
    if step == 0.0 {
        return (0.0..size)
            .contains(&start)
            .then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let (a, b) = (-start / step, (size - start) / step);
    Some((a.min(b), a.max(b)))
}

/// Adds the log-odds of `grid`'s known cells, placed at `global_from_grid`, to the cells of `limits`
/// (`log_odds`, `known`: one entry per cell, row-major) whose centres fall in them.
///
/// The (continuous) source cell under an output cell's centre is affine in the output cell's index, so
/// each output row is one straight line through the source grid: the stretch of the row inside the
/// source grid is solved for, then walked with one fixed-point add per coordinate. (The direct lookup — an
/// isometry, two `floor`s and two bounds checks per cell over the grid's whole bounding box — was nearly
/// all of a render's time: 0.5 s for the README demo's 40 submaps.)
fn add_grid(
    limits: &MapLimits,
    global_from_grid: &Rigid2,
    grid: &ProbabilityGrid,
    log_odds: &mut [f32],
    known: &mut [bool],
) {
    let source = grid.limits();
    let (Ok(source_width), Ok(source_height), Ok(width)) = (
        usize::try_from(source.width),
        usize::try_from(source.height),
        usize::try_from(limits.width),
    ) else {
        return;
    };
    if source_width == 0 || source_height == 0 || width == 0 {
        return;
    }
    let values = grid.values();
    let logits = logit_of_value();
    let grid_from_global = global_from_grid.inverse();
    // Continuous source index of output cell (ix, iy)'s centre: start + ix * step_x + iy * step_y.
    let to_source =
        |p: Point2<f64>| (grid_from_global * p - source.origin).coords / source.resolution;
    let start = to_source(limits.cell_center(&CellIndex::new(0, 0)));
    let step_x =
        grid_from_global.rotation * Vector2::new(limits.resolution, 0.0) / source.resolution;
    let step_y =
        grid_from_global.rotation * Vector2::new(0.0, limits.resolution) / source.resolution;
    let (lo, hi) = footprint(global_from_grid, grid);
    let (a, b) = (
        limits.cell_index(&Point2::from(lo)),
        limits.cell_index(&Point2::from(hi)),
    );
    let last_column = limits.width - 1;
    for iy in a.y.max(0)..=b.y.min(limits.height - 1) {
        let row_start = start + f64::from(iy) * step_y;
        let (Some((u_lo, u_hi)), Some((v_lo, v_hi))) = (
            span(row_start.x, step_x.x, source_width as f64),
            span(row_start.y, step_x.y, source_height as f64),
        ) else {
            continue;
        };
        // One cell of margin each side: the exact test is per cell below.
        let first = (u_lo.max(v_lo).floor() - 1.0).max(f64::from(a.x.max(0)));
        let last = (u_hi.min(v_hi).ceil() + 1.0).min(f64::from(b.x.min(last_column)));
        if first.is_nan() || last.is_nan() || first > last {
            continue;
        }
        let (first, last) = (first as usize, last as usize);
        let row = iy as usize * width;
        let (Some(row_log_odds), Some(row_known)) = (
            log_odds.get_mut(row + first..=row + last),
            known.get_mut(row + first..=row + last),
        ) else {
            continue;
        };
        // Fixed point from here: the walk is integer adds and shifts, no float-to-integer conversions.
        let (mut u, mut v) = (
            to_fixed(row_start.x + first as f64 * step_x.x),
            to_fixed(row_start.y + first as f64 * step_x.y),
        );
        let (du, dv) = (to_fixed(step_x.x), to_fixed(step_x.y));
        for (l, k) in row_log_odds.iter_mut().zip(row_known) {
            // An arithmetic shift floors; a negative index becomes huge as u64 and fails the test.
            let (iu, iv) = ((u >> FRACTION_BITS) as u64, (v >> FRACTION_BITS) as u64);
            (u, v) = (u.wrapping_add(du), v.wrapping_add(dv));
            if iu >= source_width as u64 || iv >= source_height as u64 {
                continue;
            }
            let Some(&value) = values.get(iv as usize * source_width + iu as usize) else {
                continue;
            };
            if value == UNKNOWN_VALUE {
                continue;
            }
            if let Some(logit) = logits.get(usize::from(value)) {
                *l += logit;
                *k = true;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::geometry::rigid2;

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
        let out = render_submaps_log_odds(&[(Rigid2::identity(), Arc::clone(&grid))], 0.0).unwrap();
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
        let out = render_submaps_log_odds(&[(pose, Arc::new(wall_grid()))], 0.1).unwrap();
        let wall = out.limits().cell_index(&Point2::new(5.0, 0.55));
        let free = out.limits().cell_index(&Point2::new(5.0, 0.0));
        assert!(out.probability(&wall) > 0.85, "{}", out.probability(&wall));
        assert!(out.probability(&free) < 0.3);
        assert!(!out.is_known(&out.limits().cell_index(&Point2::new(0.0, 0.0))));
        assert!(render_submaps_log_odds(&[], 0.1).is_none());
    }

    /// The direct lookup the renderer walks rows for: per output cell, the isometry and `floor` of its
    /// centre into every grid whose bounding box covers it (the renderer before rows were walked).
    fn render_directly(grids: &[(Rigid2, Arc<ProbabilityGrid>)], resolution: f64) -> Vec<u16> {
        let out = render_submaps_log_odds(grids, resolution).unwrap();
        let limits = out.limits().clone();
        let mut log_odds = vec![0.0_f32; limits.num_cells()];
        let mut known = vec![false; limits.num_cells()];
        for (pose, grid) in grids {
            let grid_from_global = pose.inverse();
            for iy in 0..limits.height {
                for ix in 0..limits.width {
                    let cell = CellIndex::new(ix, iy);
                    let source = grid
                        .limits()
                        .cell_index(&(grid_from_global * limits.cell_center(&cell)));
                    let Some(s) = grid.limits().flat_index(&source) else {
                        continue;
                    };
                    let value = grid.values()[s];
                    if value != UNKNOWN_VALUE {
                        let i = limits.flat_index(&cell).unwrap();
                        log_odds[i] += logit(value_to_probability(value));
                        known[i] = true;
                    }
                }
            }
        }
        let (lo, hi) = (logit(MIN_PROBABILITY), logit(MAX_PROBABILITY));
        log_odds
            .iter()
            .zip(&known)
            .map(|(l, k)| {
                if *k {
                    probability_to_value(1.0 / (1.0 + (-l.clamp(lo, hi)).exp()))
                } else {
                    UNKNOWN_VALUE
                }
            })
            .collect()
    }

    #[test]
    fn walking_rows_gives_the_direct_lookup_cell_for_cell() {
        use rand::{Rng as _, SeedableRng as _};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let mut compared = 0;
        for case in 0..12 {
            let grids: Vec<(Rigid2, Arc<ProbabilityGrid>)> = (0..=(case % 4))
                .map(|_| {
                    let (w, h) = (rng.random_range(1..30), rng.random_range(1..30));
                    let origin =
                        Vector2::new(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0));
                    let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, origin, w, h));
                    for iy in 0..h {
                        for ix in 0..w {
                            // Some cells stay unknown.
                            if rng.random_range(0..4) > 0 {
                                let p = rng.random_range(0.1..0.9);
                                grid.set_probability(&CellIndex::new(ix, iy), p);
                            }
                        }
                    }
                    let pose = rigid2(
                        rng.random_range(-3.0..3.0),
                        rng.random_range(-3.0..3.0),
                        rng.random_range(-4.0..4.0),
                    );
                    (pose, Arc::new(grid))
                })
                .collect();
            // Coarser, equal and finer output cells than the grids'.
            let resolution = [0.11, 0.05, 0.03][case % 3];
            let fast = render_submaps_log_odds(&grids, resolution).unwrap();
            let direct = render_directly(&grids, resolution);
            assert_eq!(fast.values(), &direct[..], "case {case}");
            compared += direct.iter().filter(|v| **v != UNKNOWN_VALUE).count();
        }
        assert!(compared > 1000, "{compared} known cells compared");
    }

    #[test]
    fn overlapping_observations_reinforce() {
        let grid = Arc::new(wall_grid());
        let one = render_submaps_log_odds(&[(Rigid2::identity(), Arc::clone(&grid))], 0.1).unwrap();
        let two = render_submaps_log_odds(
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
