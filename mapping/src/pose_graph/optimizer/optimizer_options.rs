//! [`OptimizerOptions`]: when Levenberg–Marquardt stops, its damping bounds, and what it prunes.

use serde::Deserialize;
use thiserror::Error;

#[cfg(doc)]
use super::Optimizer;

/// Options of the [`Optimizer`].
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OptimizerOptions {
    /// Maximum number of Levenberg–Marquardt steps tried (accepted or rejected; each costs one numeric
    /// factorization). Count.
    pub max_iterations: usize,
    /// Converged when an accepted step lowers the cost by less than this fraction of the cost. Unitless.
    pub function_tolerance: f64,
    /// Converged when `‖h‖ ≤ parameter_tolerance · (‖x‖ + parameter_tolerance)`. Unitless.
    pub parameter_tolerance: f64,
    /// Converged when the largest gradient entry `|g_k|` is at most this. Cost units per metre or radian.
    pub gradient_tolerance: f64,
    /// Initial damping `λ` (relative to `diag(H)`). Unitless.
    pub initial_lambda: f64,
    /// Give up when `λ` exceeds this (no step lowers the cost). Unitless.
    pub max_lambda: f64,
    /// Lower clamp of the damping diagonal `D`. Cost units per metre² or radian².
    pub min_diagonal: f64,
    /// Upper clamp of the damping diagonal `D`. Cost units per metre² or radian².
    pub max_diagonal: f64,
    /// Before iterating, compute a rotation-first initial guess (orientations, then positions, by linear
    /// least squares) and start from it when its χ² (robust losses ignored) is lower. Default false.
    /// Why: `docs/TUNING.md#opt-rotation-first-initialization`.
    pub rotation_first_initialization: bool,
    /// A constraint whose robust weight `ρ'(s)` falls below this is left out of the linear system until it
    /// rises above ten times this (its cost still counts). Unitless, in `[0, 0.1)`; `0` keeps every
    /// constraint. Default 1e-4. Why: `docs/TUNING.md#opt-prune-weight`.
    pub prune_weight: f64,
}

impl OptimizerOptions {
    /// The defaults: on the benchmark graphs (ring, CSAIL, Intel, M3500, City10000) they stop within
    /// 2e-5 relative of the optimum, the looser GTSAM default (1e-5 relative decrease) within ~1e-4.
    pub const DEFAULT: Self = Self {
        max_iterations: 100,
        function_tolerance: 1e-6,
        parameter_tolerance: 1e-10,
        gradient_tolerance: 1e-10,
        initial_lambda: 1e-8,
        max_lambda: 1e16,
        min_diagonal: 1e-6,
        max_diagonal: 1e32,
        rotation_first_initialization: false,
        prune_weight: 1e-4,
    };

    /// Checks that every field is usable.
    pub fn validate(&self) -> Result<(), OptimizerOptionsError> {
        let positive = [
            ("function_tolerance", self.function_tolerance),
            ("parameter_tolerance", self.parameter_tolerance),
            ("gradient_tolerance", self.gradient_tolerance),
            ("initial_lambda", self.initial_lambda),
            ("max_lambda", self.max_lambda),
            ("min_diagonal", self.min_diagonal),
            ("max_diagonal", self.max_diagonal),
        ];
        for (field, value) in positive {
            if !(value.is_finite() && value >= 0.0) {
                return Err(OptimizerOptionsError::Negative { field, value });
            }
        }
        if self.initial_lambda <= 0.0 || self.initial_lambda > self.max_lambda {
            return Err(OptimizerOptionsError::Lambda);
        }
        if self.min_diagonal <= 0.0 || self.min_diagonal > self.max_diagonal {
            return Err(OptimizerOptionsError::Diagonal);
        }
        if !(0.0..0.1).contains(&self.prune_weight) {
            return Err(OptimizerOptionsError::PruneWeight(self.prune_weight));
        }
        Ok(())
    }
}

impl Default for OptimizerOptions {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Invalid [`OptimizerOptions`].
#[derive(Debug, Error, Clone, PartialEq)]
pub enum OptimizerOptionsError {
    /// A tolerance or bound is negative, NaN or infinite.
    #[error("{field} must be finite and non-negative, got {value}")]
    Negative {
        /// The offending field.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// Needs `0 < initial_lambda ≤ max_lambda`.
    #[error("need 0 < initial_lambda <= max_lambda")]
    Lambda,
    /// Needs `0 < min_diagonal ≤ max_diagonal`.
    #[error("need 0 < min_diagonal <= max_diagonal")]
    Diagonal,
    /// Needs `0 ≤ prune_weight < 0.1`.
    #[error("prune_weight must be in [0, 0.1), got {0}")]
    PruneWeight(f64),
}
