//! Cell-by-cell coverage of a stale submap by fresher ones, the test behind trimming.
//!
//! Like Cartographer's overlapping-submaps trimmer, coverage is counted per grid cell in the map frame:
//! a cell of the stale submap is *covered* when at least `K` fresher submaps have observed (know) the
//! point at its centre. Unlike it, the decision is a fraction of the stale submap's own cells rather than
//! an absolute area, so it does not depend on the submap's size. Each cell centre is mapped into every
//! fresher grid whose bounding box contains it; the count stops at `K`.

use nalgebra::{Point2, Vector2};

use crate::geometry::Rigid2;
use crate::grid::{CellIndex, ProbabilityGrid, value_to_probability};

/// A grid placed in the map: `global_from_grid` maps the grid's own world coordinates (for a submap, its
/// trajectory's local frame) into the map frame.
#[derive(Clone, Copy, Debug)]
pub struct PlacedGrid<'a> {
    /// `global_from_grid`.
    pub global_from_grid: Rigid2,
    /// The grid.
    pub grid: &'a ProbabilityGrid,
}

impl PlacedGrid<'_> {
    /// Axis-aligned bounds `(min, max)` of the grid's area in the map frame.
    pub fn global_bounds(&self) -> Bounds {
        let limits = self.grid.limits();
        let size =
            Vector2::new(f64::from(limits.width), f64::from(limits.height)) * limits.resolution;
        let mut min = Vector2::repeat(f64::INFINITY);
        let mut max = Vector2::repeat(f64::NEG_INFINITY);
        for corner in [
            Vector2::zeros(),
            Vector2::new(size.x, 0.0),
            Vector2::new(0.0, size.y),
            size,
        ] {
            let p = self.global_from_grid * Point2::from(limits.origin + corner);
            min = min.inf(&p.coords);
            max = max.sup(&p.coords);
        }
        (min, max)
    }

    /// Whether the two grids' map-frame bounding boxes overlap (a necessary condition for either to
    /// cover a cell of the other).
    pub fn overlaps(&self, other: &PlacedGrid<'_>) -> bool {
        overlaps(&self.global_bounds(), &other.global_bounds())
    }

    /// Whether the grid has observed the map-frame point `p`.
    pub fn knows(&self, p: &Point2<f64>) -> bool {
        let local = self.global_from_grid.inverse_transform_point(p);
        self.grid.is_known(&self.grid.limits().cell_index(&local))
    }
}

/// Axis-aligned bounds `(min, max)`, metres.
type Bounds = (Vector2<f64>, Vector2<f64>);

fn overlaps(a: &Bounds, b: &Bounds) -> bool {
    a.0.x <= b.1.x && b.0.x <= a.1.x && a.0.y <= b.1.y && b.0.y <= a.1.y
}

fn contains(bounds: &Bounds, p: &Point2<f64>) -> bool {
    p.x >= bounds.0.x && p.x <= bounds.1.x && p.y >= bounds.0.y && p.y <= bounds.1.y
}

/// The fraction of `stale`'s counted cells (known ones, or only occupied ones with
/// `count_occupied_only`; every `cell_stride`-th along each axis) whose centre at least `min_fresher`
/// grids of `fresher` know. 0 when no cell is counted.
pub fn covered_fraction(
    stale: &PlacedGrid<'_>,
    fresher: &[PlacedGrid<'_>],
    min_fresher: usize,
    cell_stride: usize,
    count_occupied_only: bool,
) -> f64 {
    let stale_bounds = stale.global_bounds();
    let candidates: Vec<(PlacedGrid<'_>, Bounds)> = fresher
        .iter()
        .map(|f| (*f, f.global_bounds()))
        .filter(|(_, b)| overlaps(b, &stale_bounds))
        .collect();
    let limits = stale.grid.limits();
    let stride = cell_stride.max(1);
    let (mut counted, mut covered) = (0usize, 0usize);
    for iy in (0..limits.height.max(0)).step_by(stride) {
        for ix in (0..limits.width.max(0)).step_by(stride) {
            let index = CellIndex::new(ix, iy);
            let Some(flat) = limits.flat_index(&index) else {
                continue;
            };
            let value = stale.grid.values()[flat];
            if value == crate::grid::UNKNOWN_VALUE
                || (count_occupied_only && value_to_probability(value) <= 0.5)
            {
                continue;
            }
            counted += 1;
            if candidates.len() < min_fresher {
                continue;
            }
            let p = stale.global_from_grid * limits.cell_center(&index);
            let mut knowing = 0;
            for (grid, bounds) in &candidates {
                if contains(bounds, &p) && grid.knows(&p) {
                    knowing += 1;
                    if knowing >= min_fresher {
                        covered += 1;
                        break;
                    }
                }
            }
        }
    }
    if counted == 0 {
        0.0
    } else {
        covered as f64 / counted as f64
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng as _, SeedableRng as _};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::geometry::rigid2;
    use crate::grid::MapLimits;

    fn random_grid(rng: &mut Pcg64) -> ProbabilityGrid {
        let limits = MapLimits::new(
            0.1,
            Vector2::new(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)),
            rng.random_range(10..40),
            rng.random_range(10..40),
        );
        let mut grid = ProbabilityGrid::new(limits.clone());
        // A random blob of known cells, some occupied.
        let (cx, cy) = (
            rng.random_range(0..limits.width),
            rng.random_range(0..limits.height),
        );
        let radius = rng.random_range(5..30);
        for iy in 0..limits.height {
            for ix in 0..limits.width {
                if (ix - cx).pow(2) + (iy - cy).pow(2) <= radius * radius {
                    let p = if rng.random_bool(0.2) { 0.8 } else { 0.2 };
                    grid.set_probability(&CellIndex::new(ix, iy), p);
                }
            }
        }
        grid
    }

    /// The oracle: every cell, every fresher grid, no bounding boxes, no early exit.
    fn brute_force(
        stale: &PlacedGrid<'_>,
        fresher: &[PlacedGrid<'_>],
        k: usize,
        occupied_only: bool,
    ) -> f64 {
        let limits = stale.grid.limits();
        let (mut counted, mut covered) = (0, 0);
        for iy in 0..limits.height {
            for ix in 0..limits.width {
                let index = CellIndex::new(ix, iy);
                if !stale.grid.is_known(&index)
                    || (occupied_only && stale.grid.probability(&index) <= 0.5)
                {
                    continue;
                }
                counted += 1;
                let p = stale.global_from_grid * limits.cell_center(&index);
                let n = fresher
                    .iter()
                    .filter(|f| {
                        let local = f.global_from_grid.inverse() * p;
                        f.grid.is_known(&f.grid.limits().cell_index(&local))
                    })
                    .count();
                if n >= k {
                    covered += 1;
                }
            }
        }
        if counted == 0 {
            0.0
        } else {
            f64::from(covered) / f64::from(counted)
        }
    }

    #[test]
    fn coverage_matches_brute_force_cell_count() {
        let mut rng = Pcg64::seed_from_u64(7);
        let mut nontrivial = 0;
        for case in 0..30 {
            let grids: Vec<ProbabilityGrid> = (0..5).map(|_| random_grid(&mut rng)).collect();
            let poses: Vec<Rigid2> = (0..5)
                .map(|_| {
                    rigid2(
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-3.0..3.0),
                    )
                })
                .collect();
            let placed: Vec<PlacedGrid<'_>> = grids
                .iter()
                .zip(&poses)
                .map(|(grid, pose)| PlacedGrid {
                    global_from_grid: *pose,
                    grid,
                })
                .collect();
            let k = 1 + case % 3;
            let occupied_only = case % 2 == 1;
            let fast = covered_fraction(&placed[0], &placed[1..], k, 1, occupied_only);
            let slow = brute_force(&placed[0], &placed[1..], k, occupied_only);
            assert!((fast - slow).abs() < 1e-12, "case {case}: {fast} vs {slow}");
            if slow > 0.05 && slow < 0.95 {
                nontrivial += 1;
            }
        }
        assert!(
            nontrivial >= 5,
            "too few partially covered cases: {nontrivial}"
        );
    }

    #[test]
    fn a_grid_covers_itself_and_a_distant_one_covers_nothing() {
        let mut rng = Pcg64::seed_from_u64(3);
        let grid = random_grid(&mut rng);
        let here = PlacedGrid {
            global_from_grid: rigid2(1.0, 2.0, 0.3),
            grid: &grid,
        };
        let far = PlacedGrid {
            global_from_grid: rigid2(100.0, 2.0, 0.3),
            grid: &grid,
        };
        assert!((covered_fraction(&here, &[here], 1, 1, false) - 1.0).abs() < 1e-12);
        assert!(covered_fraction(&here, &[here], 2, 1, false) < 1e-12);
        assert!(covered_fraction(&here, &[far], 1, 1, false) < 1e-12);
        // The stride samples: still about all covered.
        assert!(covered_fraction(&here, &[here, here], 2, 2, false) > 0.99);
    }
}
