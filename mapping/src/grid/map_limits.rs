//! Cell geometry of a grid.

use nalgebra::{Point2, Vector2};
use serde::{Deserialize, Serialize};

/// Integer cell coordinates `(ix, iy)`; `ix` grows with world x, `iy` with world y.
pub type CellIndex = Vector2<i32>;

/// `x.floor() as i32`, without the `floor` call: on the baseline x86-64 target (no SSE4.1) `f64::floor` is
/// a libm call, and it is in the correlative search's hot loop (5 % of Intel offline's samples). The
/// truncating cast rounds toward zero; one less where that rounded a negative non-integer up. Equal to
/// `x.floor() as i32` for every `f64`, NaN and beyond `i32`'s range included (both saturate).
#[inline]
fn floor_to_i32(x: f64) -> i32 {
    let t = x as i32;
    if f64::from(t) > x {
        t.saturating_sub(1)
    } else {
        t
    }
}

/// Where a grid's cells are in the world: cell `(ix, iy)` covers
/// `[origin.x + ix·r, origin.x + (ix+1)·r) × [origin.y + iy·r, origin.y + (iy+1)·r)`, r = `resolution`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MapLimits {
    /// Cell side length in metres.
    pub resolution: f64,
    /// World coordinates (metres) of the lower-left corner of cell (0, 0).
    pub origin: Vector2<f64>,
    /// Number of cells along x.
    pub width: i32,
    /// Number of cells along y.
    pub height: i32,
}

impl MapLimits {
    /// A grid of `width × height` cells of side `resolution` whose cell (0, 0) starts at `origin`.
    pub fn new(resolution: f64, origin: Vector2<f64>, width: i32, height: i32) -> Self {
        Self {
            resolution,
            origin,
            width,
            height,
        }
    }

    /// The cell containing the world point `p` (may be outside the grid).
    pub fn cell_index(&self, p: &Point2<f64>) -> CellIndex {
        let v = (p.coords - self.origin) / self.resolution;
        CellIndex::new(floor_to_i32(v.x), floor_to_i32(v.y))
    }

    /// World coordinates of the centre of a cell.
    pub fn cell_center(&self, index: &CellIndex) -> Point2<f64> {
        Point2::from(self.origin + (index.cast::<f64>() + Vector2::new(0.5, 0.5)) * self.resolution)
    }

    /// Whether the cell lies inside the grid.
    pub fn contains(&self, index: &CellIndex) -> bool {
        index.x >= 0 && index.y >= 0 && index.x < self.width && index.y < self.height
    }

    /// Row-major offset of a cell that is inside the grid.
    pub fn flat_index(&self, index: &CellIndex) -> Option<usize> {
        self.contains(index)
            .then(|| index.y as usize * self.width as usize + index.x as usize)
    }

    /// Number of cells.
    pub fn num_cells(&self) -> usize {
        self.width.max(0) as usize * self.height.max(0) as usize
    }
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    #[test]
    fn floor_to_i32_equals_floor_then_cast_at_the_edges() {
        for x in [
            0.0,
            -0.0,
            -0.5,
            -1.0,
            -2.000_001,
            -1e-300,
            2147483647.5,
            -2147483648.5,
            1e20,
            -1e20,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ] {
            assert_eq!(floor_to_i32(x), x.floor() as i32, "{x}");
        }
    }

    proptest! {
        #[test]
        fn floor_to_i32_equals_floor_then_cast(x in proptest::num::f64::ANY) {
            prop_assert_eq!(floor_to_i32(x), x.floor() as i32);
        }

        #[test]
        fn center_of_cell_maps_back_to_cell(ix in -500..500i32, iy in -500..500i32, res in 0.01..1.0f64,
                                            ox in -50.0..50.0f64, oy in -50.0..50.0f64) {
            let limits = MapLimits::new(res, Vector2::new(ox, oy), 10, 10);
            let index = CellIndex::new(ix, iy);
            prop_assert_eq!(limits.cell_index(&limits.cell_center(&index)), index);
        }

        #[test]
        fn point_lies_within_half_a_cell_of_its_cell_center(x in -100.0..100.0f64, y in -100.0..100.0f64) {
            let limits = MapLimits::new(0.05, Vector2::new(-3.0, 7.0), 10, 10);
            let p = Point2::new(x, y);
            let c = limits.cell_center(&limits.cell_index(&p));
            prop_assert!((c.x - x).abs() <= 0.025 + 1e-9 && (c.y - y).abs() <= 0.025 + 1e-9);
        }
    }

    #[test]
    fn flat_index_is_row_major_and_bounded() {
        let limits = MapLimits::new(0.1, Vector2::zeros(), 4, 3);
        assert_eq!(limits.flat_index(&CellIndex::new(1, 2)), Some(9));
        assert_eq!(limits.flat_index(&CellIndex::new(4, 0)), None);
        assert_eq!(limits.flat_index(&CellIndex::new(0, -1)), None);
        assert_eq!(limits.num_cells(), 12);
    }
}
