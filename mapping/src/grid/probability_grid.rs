//! A grid of occupancy probabilities stored as 15-bit integers, as in Cartographer: value 0 means
//! "unknown", values `1..=32767` map linearly onto `[MIN_PROBABILITY, MAX_PROBABILITY]`. Integer cells make
//! hit/miss updates table lookups and keep a 1000×1000 submap at 2 MB.

use super::{CellIndex, MapLimits};

/// Smallest probability a known cell can hold (free).
pub const MIN_PROBABILITY: f32 = 0.1;
/// Largest probability a known cell can hold (occupied).
pub const MAX_PROBABILITY: f32 = 0.9;
/// Stored value of a cell never observed.
pub const UNKNOWN_VALUE: u16 = 0;
const MAX_VALUE: u16 = 32767;
/// Added to a cell's value while an insertion has already updated it, so one scan updates a cell at most
/// once per table (Cartographer's update marker).
pub(crate) const UPDATE_MARKER: u16 = 1 << 15;

/// Converts a probability (clamped to the valid range) to its stored value in `1..=32767`.
pub fn probability_to_value(p: f32) -> u16 {
    let p = p.clamp(MIN_PROBABILITY, MAX_PROBABILITY);
    1 + ((p - MIN_PROBABILITY) / (MAX_PROBABILITY - MIN_PROBABILITY) * f32::from(MAX_VALUE - 1))
        .round() as u16
}

/// Converts a stored value to a probability; [`UNKNOWN_VALUE`] reads as [`MIN_PROBABILITY`].
pub fn value_to_probability(value: u16) -> f32 {
    if value == UNKNOWN_VALUE {
        return MIN_PROBABILITY;
    }
    MIN_PROBABILITY
        + f32::from(value - 1) / f32::from(MAX_VALUE - 1) * (MAX_PROBABILITY - MIN_PROBABILITY)
}

/// Occupancy probabilities on a regular grid.
#[derive(Clone, Debug, PartialEq)]
pub struct ProbabilityGrid {
    limits: MapLimits,
    cells: Vec<u16>,
    updated: Vec<usize>,
}

impl ProbabilityGrid {
    /// A grid with every cell unknown.
    pub fn new(limits: MapLimits) -> Self {
        let cells = vec![UNKNOWN_VALUE; limits.num_cells()];
        Self {
            limits,
            cells,
            updated: Vec::new(),
        }
    }

    /// The cell geometry.
    pub fn limits(&self) -> &MapLimits {
        &self.limits
    }

    /// Raw stored values, row-major (see [`MapLimits::flat_index`]).
    pub fn values(&self) -> &[u16] {
        &self.cells
    }

    /// Mutable raw stored values, row-major.
    pub fn values_mut(&mut self) -> &mut [u16] {
        &mut self.cells
    }

    /// Occupancy probability of a cell; unknown and out-of-grid cells read as [`MIN_PROBABILITY`].
    pub fn probability(&self, index: &CellIndex) -> f32 {
        self.limits
            .flat_index(index)
            .map_or(MIN_PROBABILITY, |i| value_to_probability(self.cells[i]))
    }

    /// Whether the cell has been observed.
    pub fn is_known(&self, index: &CellIndex) -> bool {
        self.limits
            .flat_index(index)
            .is_some_and(|i| self.cells[i] != UNKNOWN_VALUE)
    }

    /// Applies an odds-update table to a cell (see [`crate::grid::RangeDataInserter`]); the cell is marked
    /// as updated until [`Self::finish_update`]. Returns `false` for a cell outside the grid or one already
    /// updated by this insertion.
    pub(crate) fn apply_lookup_table(&mut self, index: CellIndex, table: &[u16]) -> bool {
        let Some(i) = self.limits.flat_index(&index) else {
            return false;
        };
        let value = self.cells[i];
        if value >= UPDATE_MARKER {
            return false;
        }
        self.cells[i] = table[value as usize];
        self.updated.push(i);
        true
    }

    /// Clears the update markers set by [`Self::apply_lookup_table`] during one insertion.
    pub(crate) fn finish_update(&mut self) {
        for &i in &self.updated {
            self.cells[i] -= UPDATE_MARKER;
        }
        self.updated.clear();
    }

    /// Grows the grid (keeping every cell) so that all `points` fall inside it with a margin.
    pub fn grow_to_include(&mut self, points: impl IntoIterator<Item = nalgebra::Point2<f64>>) {
        let (mut min, mut max) = (
            CellIndex::new(0, 0),
            CellIndex::new(self.limits.width - 1, self.limits.height - 1),
        );
        let mut outside = false;
        for p in points {
            let c = self.limits.cell_index(&p);
            if !self.limits.contains(&c) {
                outside = true;
                min = min.inf(&c);
                max = max.sup(&c);
            }
        }
        if !outside {
            return;
        }
        // Grow by at least the current size in each direction that needs it, so growth is amortized.
        let (w, h) = (self.limits.width, self.limits.height);
        let grow_x_lo = if min.x < 0 { (-min.x).max(w / 2) } else { 0 };
        let grow_y_lo = if min.y < 0 { (-min.y).max(h / 2) } else { 0 };
        let grow_x_hi = if max.x >= w {
            (max.x - w + 1).max(w / 2)
        } else {
            0
        };
        let grow_y_hi = if max.y >= h {
            (max.y - h + 1).max(h / 2)
        } else {
            0
        };
        let new_limits = MapLimits::new(
            self.limits.resolution,
            self.limits.origin
                - nalgebra::Vector2::new(f64::from(grow_x_lo), f64::from(grow_y_lo))
                    * self.limits.resolution,
            w + grow_x_lo + grow_x_hi,
            h + grow_y_lo + grow_y_hi,
        );
        let mut cells = vec![UNKNOWN_VALUE; new_limits.num_cells()];
        for y in 0..h {
            let src = y as usize * w as usize;
            let dst = (y + grow_y_lo) as usize * new_limits.width as usize + grow_x_lo as usize;
            cells[dst..dst + w as usize].copy_from_slice(&self.cells[src..src + w as usize]);
        }
        debug_assert!(self.updated.is_empty(), "grow during an insertion");
        self.limits = new_limits;
        self.cells = cells;
    }

    /// The smallest sub-grid holding every known cell (an empty grid stays as it is).
    #[must_use]
    pub fn cropped_to_known(&self) -> Self {
        let (w, h) = (self.limits.width, self.limits.height);
        let (mut x0, mut y0, mut x1, mut y1) = (w, h, -1, -1);
        for y in 0..h {
            for x in 0..w {
                if self.cells[y as usize * w as usize + x as usize] != UNKNOWN_VALUE {
                    x0 = x0.min(x);
                    y0 = y0.min(y);
                    x1 = x1.max(x);
                    y1 = y1.max(y);
                }
            }
        }
        if x1 < 0 {
            return self.clone();
        }
        let limits = MapLimits::new(
            self.limits.resolution,
            self.limits.origin
                + nalgebra::Vector2::new(f64::from(x0), f64::from(y0)) * self.limits.resolution,
            x1 - x0 + 1,
            y1 - y0 + 1,
        );
        let mut cells = Vec::with_capacity(limits.num_cells());
        for y in y0..=y1 {
            let row = y as usize * w as usize;
            cells.extend_from_slice(&self.cells[row + x0 as usize..=row + x1 as usize]);
        }
        Self {
            limits,
            cells,
            updated: Vec::new(),
        }
    }

    /// Sets a cell's probability. Returns `false` (and changes nothing) for a cell outside the grid.
    pub fn set_probability(&mut self, index: &CellIndex, probability: f32) -> bool {
        match self.limits.flat_index(index) {
            Some(i) => {
                self.cells[i] = probability_to_value(probability);
                true
            }
            None => false,
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector2;
    use proptest::prelude::*;

    use super::*;

    proptest! {
        #[test]
        fn value_round_trip_is_within_quantization(p in 0.0..1.0f32) {
            let q = value_to_probability(probability_to_value(p));
            prop_assert!((q - p.clamp(MIN_PROBABILITY, MAX_PROBABILITY)).abs() < 1e-4);
            prop_assert!((MIN_PROBABILITY..=MAX_PROBABILITY).contains(&q));
        }
    }

    #[test]
    fn growth_keeps_cells_and_crop_keeps_known_cells() {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.5, Vector2::zeros(), 4, 4));
        let c = CellIndex::new(1, 2);
        grid.set_probability(&c, 0.8);
        let world = grid.limits().cell_center(&c);
        grid.grow_to_include([
            nalgebra::Point2::new(-3.0, 10.0),
            nalgebra::Point2::new(5.0, -1.0),
        ]);
        let limits = grid.limits().clone();
        assert!(limits.contains(&limits.cell_index(&nalgebra::Point2::new(-3.0, 10.0))));
        assert!(limits.contains(&limits.cell_index(&nalgebra::Point2::new(5.0, -1.0))));
        let moved = limits.cell_index(&world);
        assert!((grid.probability(&moved) - 0.8).abs() < 1e-4);
        let known = grid
            .values()
            .iter()
            .filter(|&&v| v != UNKNOWN_VALUE)
            .count();
        assert_eq!(known, 1);
        let cropped = grid.cropped_to_known();
        assert_eq!((cropped.limits().width, cropped.limits().height), (1, 1));
        assert!((cropped.probability(&cropped.limits().cell_index(&world)) - 0.8).abs() < 1e-4);
    }

    #[test]
    fn unknown_and_outside_read_as_min_probability() {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::zeros(), 3, 3));
        let inside = CellIndex::new(1, 1);
        assert!(!grid.is_known(&inside));
        assert!((grid.probability(&inside) - MIN_PROBABILITY).abs() < f32::EPSILON);
        assert!(grid.set_probability(&inside, 0.7));
        assert!(grid.is_known(&inside));
        assert!((grid.probability(&inside) - 0.7).abs() < 1e-4);
        assert!(!grid.set_probability(&CellIndex::new(3, 0), 0.7));
        assert!((grid.probability(&CellIndex::new(-1, 0)) - MIN_PROBABILITY).abs() < f32::EPSILON);
    }
}
