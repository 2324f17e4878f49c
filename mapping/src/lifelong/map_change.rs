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

use nalgebra::{Point2, Vector2};

use crate::grid::{CellIndex, MapLimits, ProbabilityGrid};

/// A cell is occupied above this probability.
pub const OCCUPIED_PROBABILITY: f32 = 0.5;

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

fn state(grid: &ProbabilityGrid, p: &Point2<f64>) -> Option<bool> {
    let index = grid.limits().cell_index(p);
    grid.is_known(&index)
        .then(|| grid.probability(&index) > OCCUPIED_PROBABILITY)
}

/// Compares `before` and `after` (both in the same map frame); see the module docs.
pub fn map_change_rate(before: &ProbabilityGrid, after: &ProbabilityGrid) -> MapChange {
    let resolution = before.limits().resolution;
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
                (Some(true), Some(true)) => {
                    unchanged += 1;
                    CellChange::Unchanged
                }
                (Some(true), Some(false)) => {
                    removed += 1;
                    CellChange::Removed
                }
                (Some(false), Some(true)) => {
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
        let change = map_change_rate(&before, &after);
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
        let change = map_change_rate(&before, &after);
        assert_eq!(change.limits.width, 15);
        assert_eq!((change.unchanged, change.removed, change.added), (1, 0, 0));
        assert!(change.rate.abs() < 1e-12);
        let same = map_change_rate(&before, &before);
        assert!(same.rate.abs() < 1e-12);
        assert_eq!(same.unchanged, 1);
    }
}
