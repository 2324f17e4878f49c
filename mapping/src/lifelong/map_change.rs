//! Map change rate (MCR) between two maps of a site, and the per-cell classes for the diff picture.
//!
//! Both grids are compared on the first grid's cell lattice, over the union of their areas. A cell counts
//! only where both maps know it (a place one map never saw is neither removed nor added); it is
//! *occupied* when its probability exceeds [`OCCUPIED_PROBABILITY`]. Then
//!
//! ```text
//! unchanged = occupied in both,   removed = occupied before, free after,   added = free before, occupied after
//! MCR = (removed + added) / (unchanged + removed + added)
//! ```
//!
//! the share of the occupied structure, seen by both maps, that changed between them.
//!
//! Two maps of an unchanged site never agree cell for cell: submaps from different sessions are
//! registered to a few centimetres, and a thin wall lands one cell over. So an occupied cell is only
//! *removed* when the other map has no occupied cell within [`MAP_CHANGE_TOLERANCE_M`] of it (likewise
//! *added*); an occupied cell of `after` with an occupied `before` cell that close is the same structure
//! and is not counted twice. Without this, rendering one session's submaps two ways gave an MCR of 0.35 on
//! the simulated store, where nothing had changed.

use nalgebra::{Point2, Vector2};

use crate::grid::{CellIndex, MapLimits, ProbabilityGrid};

/// A cell is occupied above this probability.
pub const OCCUPIED_PROBABILITY: f32 = 0.5;

/// Registration tolerance of [`map_change_rate`], metres: an occupied cell with an occupied cell of the
/// other map this close has not changed. 0.05 m: one cell of the submaps' 0.05 m grid, which absorbs a
/// wall landing one cell over, and below the smallest change the simulator makes (goods move in 0.1 m
/// steps, which a 0.1 m tolerance hid). The simulator's own change rate is measured with it too
/// (`TruthOccupancy::surface_grid`).
pub const MAP_CHANGE_TOLERANCE_M: f64 = 0.05;

/// What happened to one cell between the two maps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CellChange {
    /// Occupied in both maps.
    Unchanged,
    /// Occupied before, free after.
    Removed,
    /// Free before, occupied after.
    Added,
}

/// The result of [`map_change_rate`].
#[derive(Clone, Debug, PartialEq)]
pub struct MapChange {
    /// MCR in `[0, 1]` (0 when no occupied cell is known to both maps).
    pub rate: f64,
    /// Cells occupied in both.
    pub unchanged: usize,
    /// Cells occupied before and free after.
    pub removed: usize,
    /// Cells free before and occupied after.
    pub added: usize,
    /// The lattice of [`Self::cells`] (the first grid's resolution, the union of both areas).
    pub limits: MapLimits,
    /// Per cell, row-major over [`Self::limits`]: its class, or `None` (free in both, or unknown to
    /// either map).
    pub cells: Vec<Option<CellChange>>,
}

pub(crate) fn state(grid: &ProbabilityGrid, p: &Point2<f64>) -> Option<bool> {
    let index = grid.limits().cell_index(p);
    grid.is_known(&index)
        .then(|| grid.probability(&index) > OCCUPIED_PROBABILITY)
}

/// Offsets (m) of the lattice points within `tolerance` of a cell centre, the centre first.
pub(crate) fn neighbourhood(resolution: f64, tolerance: f64) -> Vec<Vector2<f64>> {
    let reach = (tolerance / resolution).floor() as i32;
    let mut offsets = vec![Vector2::zeros()];
    for dy in -reach..=reach {
        for dx in -reach..=reach {
            let offset = Vector2::new(f64::from(dx), f64::from(dy)) * resolution;
            if (dx, dy) != (0, 0) && offset.norm() <= tolerance + 1e-9 {
                offsets.push(offset);
            }
        }
    }
    offsets
}

/// Whether `grid` has an occupied cell at one of `offsets` from `p`.
pub(crate) fn occupied_near(
    grid: &ProbabilityGrid,
    p: &Point2<f64>,
    offsets: &[Vector2<f64>],
) -> bool {
    offsets.iter().any(|o| state(grid, &(p + o)) == Some(true))
}

/// Compares `before` and `after` (both in the same map frame) with a registration tolerance of
/// `tolerance_m` metres (see the module docs; [`MAP_CHANGE_TOLERANCE_M`] is the one the reports use, 0
/// compares cell by cell).
pub fn map_change_rate(
    before: &ProbabilityGrid,
    after: &ProbabilityGrid,
    tolerance_m: f64,
) -> MapChange {
    let resolution = before.limits().resolution;
    let offsets = neighbourhood(resolution, tolerance_m.max(0.0));
    let corners = |l: &MapLimits| {
        (
            l.origin,
            l.origin + Vector2::new(f64::from(l.width), f64::from(l.height)) * l.resolution,
        )
    };
    let (b0, b1) = corners(before.limits());
    let (a0, a1) = corners(after.limits());
    let min = b0.inf(&a0);
    let max = b1.sup(&a1);
    // Align the lattice with `before`'s cells.
    let start = b0 - ((b0 - min) / resolution).map(f64::ceil) * resolution;
    let width = ((max.x - start.x) / resolution).ceil().max(0.0) as i32;
    let height = ((max.y - start.y) / resolution).ceil().max(0.0) as i32;
    let limits = MapLimits::new(resolution, start, width, height);
    let mut cells = vec![None; limits.num_cells()];
    let (mut unchanged, mut removed, mut added) = (0, 0, 0);
    for iy in 0..height {
        for ix in 0..width {
            let index = CellIndex::new(ix, iy);
            let p = limits.cell_center(&index);
            let class = match (state(before, &p), state(after, &p)) {
                (Some(true), Some(_)) if occupied_near(after, &p, &offsets) => {
                    unchanged += 1;
                    CellChange::Unchanged
                }
                (Some(true), Some(_)) => {
                    removed += 1;
                    CellChange::Removed
                }
                (Some(false), Some(true)) if !occupied_near(before, &p, &offsets) => {
                    added += 1;
                    CellChange::Added
                }
                _ => continue,
            };
            if let Some(flat) = limits.flat_index(&index) {
                cells[flat] = Some(class);
            }
        }
    }
    let total = unchanged + removed + added;
    MapChange {
        rate: if total == 0 {
            0.0
        } else {
            (removed + added) as f64 / total as f64
        },
        unchanged,
        removed,
        added,
        limits,
        cells,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(origin: Vector2<f64>, occupied: &[(i32, i32)], free: &[(i32, i32)]) -> ProbabilityGrid {
        let mut g = ProbabilityGrid::new(MapLimits::new(0.1, origin, 10, 10));
        for &(x, y) in free {
            g.set_probability(&CellIndex::new(x, y), 0.2);
        }
        for &(x, y) in occupied {
            g.set_probability(&CellIndex::new(x, y), 0.8);
        }
        g
    }

    #[test]
    fn classes_and_rate_match_a_hand_count() {
        let all: Vec<(i32, i32)> = (0..10).flat_map(|y| (0..10).map(move |x| (x, y))).collect();
        // before: cells (1,1), (2,2), (3,3) occupied; after: (2,2), (3,3)→free, (4,4) new; (5,5) occupied
        // after but unknown before (not counted); everything else known free in both except (5,5).
        let before_free: Vec<_> = all.iter().copied().filter(|&c| c != (5, 5)).collect();
        let before = grid(Vector2::zeros(), &[(1, 1), (2, 2), (3, 3)], &before_free);
        let after = grid(Vector2::zeros(), &[(1, 1), (2, 2), (4, 4), (5, 5)], &all);
        let change = map_change_rate(&before, &after, 0.0);
        assert_eq!((change.unchanged, change.removed, change.added), (2, 1, 1));
        assert!((change.rate - 0.5).abs() < 1e-12);
        let at = |x: i32, y: i32| {
            let p = Point2::new(0.1 * f64::from(x) + 0.05, 0.1 * f64::from(y) + 0.05);
            change.cells[change
                .limits
                .flat_index(&change.limits.cell_index(&p))
                .unwrap()]
        };
        assert_eq!(at(3, 3), Some(CellChange::Removed));
        assert_eq!(at(4, 4), Some(CellChange::Added));
        assert_eq!(at(5, 5), None);
        assert_eq!(at(0, 0), None);
    }

    #[test]
    fn offset_grids_compare_on_the_union_and_identical_maps_do_not_change() {
        let all: Vec<(i32, i32)> = (0..10).flat_map(|y| (0..10).map(move |x| (x, y))).collect();
        let before = grid(Vector2::zeros(), &[(6, 6)], &all);
        // Shifted by 5 cells: its cell (1,1) is before's (6,6).
        let after = grid(Vector2::new(0.5, 0.5), &[(1, 1)], &all);
        let change = map_change_rate(&before, &after, 0.0);
        assert_eq!(change.limits.width, 15);
        assert_eq!((change.unchanged, change.removed, change.added), (1, 0, 0));
        assert!(change.rate.abs() < 1e-12);
        let same = map_change_rate(&before, &before, MAP_CHANGE_TOLERANCE_M);
        assert!(same.rate.abs() < 1e-12);
        assert_eq!(same.unchanged, 1);
    }

    #[test]
    fn a_wall_one_cell_over_is_unchanged_within_the_tolerance_and_a_moved_one_is_not() {
        let all: Vec<(i32, i32)> = (0..10).flat_map(|y| (0..10).map(move |x| (x, y))).collect();
        let wall = |x: i32| (0..10).map(move |y| (x, y)).collect::<Vec<_>>();
        let before = grid(Vector2::zeros(), &wall(3), &all);
        // The same wall registered one cell (0.1 m) over, and a new one 0.5 m away.
        let mut after_cells = wall(4);
        after_cells.extend(wall(8));
        let after = grid(Vector2::zeros(), &after_cells, &all);
        let exact = map_change_rate(&before, &after, 0.0);
        assert_eq!((exact.unchanged, exact.removed, exact.added), (0, 10, 20));
        let tolerant = map_change_rate(&before, &after, 0.1);
        assert_eq!(
            (tolerant.unchanged, tolerant.removed, tolerant.added),
            (10, 0, 10)
        );
        assert!((tolerant.rate - 0.5).abs() < 1e-12);
    }
}
