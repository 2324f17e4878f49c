//! Regular 2D grids: the cell geometry ([`MapLimits`]) and the occupancy-probability grid that submaps
//! are made of.

mod map_limits;
mod probability_grid;
mod range_data_inserter;

pub use map_limits::{CellIndex, MapLimits};
pub use probability_grid::{
    MAX_PROBABILITY, MIN_PROBABILITY, ProbabilityGrid, UNKNOWN_VALUE, probability_to_value,
    value_to_probability,
};
pub use range_data_inserter::{
    RangeDataInserter, RangeDataInserterOptions, RangeDataInserterOptionsError,
};
