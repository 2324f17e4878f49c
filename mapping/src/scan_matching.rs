//! Scan matching: finding the pose at which a scan best fits a probability grid.
//!
//! Three matchers, from coarse-and-global to fine-and-local:
//!
//! * [`FastCorrelativeScanMatcher`] — branch-and-bound search over a large window (or the whole grid and all
//!   rotations) on precomputed multi-resolution max grids (Hess et al., ICRA 2016). Used for loop closure and
//!   relocalization; its grids are built once per submap.
//! * [`RealTimeCorrelativeScanMatcher`] — exhaustive correlative search over a small window around a prior
//!   (Olson, ICRA 2009). Optional front end of local SLAM when odometry is poor.
//! * [`LeastSquaresScanMatcher`] — Levenberg–Marquardt refinement against a bicubically interpolated grid,
//!   run on every scan by local SLAM and to refine loop-closure matches.
//!
//! Conventions shared by all matchers: `points` are scan points in the frame being localized (the robot's
//! tracking frame); the grid's world coordinates are the map (submap-local) frame; every returned pose is
//! `grid_from_tracking`, mapping scan points into grid coordinates. A *score* is the mean grid probability at
//! the transformed points, with unknown and out-of-grid cells reading as
//! [`MIN_PROBABILITY`](crate::grid::MIN_PROBABILITY).

mod branch_and_bound;
mod correlative;
mod interpolated_grid;
mod least_squares;
mod paired_evidence;
mod precomputation_grid;
mod real_time_correlative;
mod relocalizer;
#[cfg(test)]
pub(crate) mod test_support;

use thiserror::Error;

pub use branch_and_bound::{
    DISTINCT_ROTATION_RAD, DISTINCT_TRANSLATION_CELLS, FastCorrelativeScanMatcher,
    FastCorrelativeScanMatcherOptions, MAX_BRANCH_AND_BOUND_DEPTH, Match,
};
pub use interpolated_grid::InterpolatedGrid;
pub use least_squares::{
    LeastSquaresScanMatcher, LeastSquaresScanMatcherOptions, LeastSquaresSummary,
};
pub use paired_evidence::{
    PairedBlocks, blocked_paired_z, mean_probability, paired_z, probability_at,
};
pub use real_time_correlative::{
    RealTimeCorrelativeScanMatcher, RealTimeCorrelativeScanMatcherOptions,
};
pub use relocalizer::{
    Relocalization, Relocalizer, RelocalizerOptions, clearly_different, max_downsampled,
    max_filtered,
};

/// Errors of the scan matching module.
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum MatchError {
    /// An options field is outside its valid range.
    #[error("invalid scan matching option `{field}`: {reason}")]
    InvalidOption {
        /// Name of the offending field.
        field: &'static str,
        /// What the field must satisfy.
        reason: &'static str,
    },
}

/// Checks that `value` is finite and `>= 0`.
fn check_non_negative(field: &'static str, value: f64) -> Result<(), MatchError> {
    if value.is_finite() && value >= 0.0 {
        Ok(())
    } else {
        Err(MatchError::InvalidOption {
            field,
            reason: "must be finite and non-negative",
        })
    }
}

/// Checks that `value` is finite and `> 0`.
fn check_positive(field: &'static str, value: f64) -> Result<(), MatchError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(MatchError::InvalidOption {
            field,
            reason: "must be finite and positive",
        })
    }
}
