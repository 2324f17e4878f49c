//! What one [`Optimizer::optimize`](super::Optimizer::optimize) call did, and why it stopped.

use std::fmt;

#[cfg(doc)]
use super::{Optimizer, OptimizerOptions};

/// Which convergence test stopped the optimizer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConvergenceCriterion {
    /// The relative cost decrease fell below `function_tolerance`.
    FunctionTolerance,
    /// The step fell below `parameter_tolerance`.
    ParameterTolerance,
    /// The gradient fell below `gradient_tolerance` (includes an already-optimal start).
    GradientTolerance,
}

/// Why the optimizer gave up.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FailureReason {
    /// The initial cost is NaN or infinite.
    NonFiniteCost,
    /// The linear system could not be analysed (out of memory).
    SymbolicFactorization,
    /// `λ` exceeded `max_lambda` without finding a step that lowers the cost.
    DampingExhausted,
}

/// How an optimization ended. The graph always holds the best estimate found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Termination {
    /// A convergence test passed.
    Converged(ConvergenceCriterion),
    /// `max_iterations` steps were tried.
    MaxIterations,
    /// The optimizer could not continue.
    Failed(FailureReason),
}

impl Termination {
    /// Whether a convergence test passed.
    pub fn is_converged(&self) -> bool {
        matches!(self, Self::Converged(_))
    }
}

impl fmt::Display for Termination {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Converged(ConvergenceCriterion::FunctionTolerance) => {
                f.write_str("converged: function tolerance")
            }
            Self::Converged(ConvergenceCriterion::ParameterTolerance) => {
                f.write_str("converged: parameter tolerance")
            }
            Self::Converged(ConvergenceCriterion::GradientTolerance) => {
                f.write_str("converged: gradient tolerance")
            }
            Self::MaxIterations => f.write_str("max iterations"),
            Self::Failed(FailureReason::NonFiniteCost) => {
                f.write_str("failed: non-finite initial cost")
            }
            Self::Failed(FailureReason::SymbolicFactorization) => {
                f.write_str("failed: symbolic factorization")
            }
            Self::Failed(FailureReason::DampingExhausted) => {
                f.write_str("failed: damping exhausted, no step lowers the cost")
            }
        }
    }
}

/// What one [`Optimizer::optimize`] call did.
#[derive(Clone, Debug, PartialEq)]
pub struct OptimizationSummary {
    /// χ² before (robust losses ignored).
    pub initial_chi2: f64,
    /// χ² after.
    pub final_chi2: f64,
    /// Σ ρ(eᵀΩe) before.
    pub initial_cost: f64,
    /// Σ ρ(eᵀΩe) after.
    pub final_cost: f64,
    /// Steps tried (each one numeric factorization).
    pub iterations: usize,
    /// Steps accepted (each one relinearization).
    pub accepted_steps: usize,
    /// Constraints left out of the linear system at the end (robust weight below
    /// [`OptimizerOptions::prune_weight`]).
    pub pruned_constraints: usize,
    /// Why it stopped.
    pub termination: Termination,
    /// Poses the optimization moved (free variables). Count.
    pub free_variables: usize,
    /// Values stored for the last factorization's Cholesky factor, fill-in included (0 if none ran):
    /// with `free_variables`, what each step costs. Count.
    pub factor_nonzeros: usize,
}
