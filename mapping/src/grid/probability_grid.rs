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
}

impl ProbabilityGrid {
    /// A grid with every cell unknown.
    pub fn new(limits: MapLimits) -> Self {
        let cells = vec![UNKNOWN_VALUE; limits.num_cells()];
        Self { limits, cells }
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
