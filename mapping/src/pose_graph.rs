//! The pose graph and its sparse robust Levenberg–Marquardt optimizer.
//!
//! Variables are `world_from_node` and `world_from_submap` poses ([`VariableId`]); constraints are
//! measured relative poses with an information matrix and a robust loss ([`Constraint`]). The error of a
//! constraint follows g2o's convention (see [`Constraint`]), so [`PoseGraph::chi2`] is
//! directly comparable with published χ² values.
//!
//! ```
//! use mapping::geometry::rigid2;
//! use mapping::pose_graph::{Constraint, ConstraintKind, NodeId, Optimizer, OptimizerOptions, PoseGraph, RobustLoss, VariableId};
//! use nalgebra::Matrix3;
//!
//! let node = |index| VariableId::Node(NodeId { trajectory: 0, index });
//! let mut graph = PoseGraph::new();
//! graph.add_variable(node(0), rigid2(0.0, 0.0, 0.0)).unwrap();
//! graph.add_variable(node(1), rigid2(0.5, 0.2, 0.1)).unwrap();
//! graph.add_constraint(Constraint {
//!     kind: ConstraintKind::Odometry,
//!     from: node(0),
//!     to: node(1),
//!     from_from_to: rigid2(1.0, 0.0, 0.0),
//!     information: Matrix3::identity(),
//!     loss: RobustLoss::Trivial,
//! }).unwrap();
//! let summary = Optimizer::new(OptimizerOptions::default()).unwrap().optimize(&mut graph);
//! assert!(summary.termination.is_converged() && summary.final_chi2 < 1e-12);
//! ```

mod constraint;
mod constraint_merge;
mod graph;
mod ids;
mod linear_system;
mod optimizer;
mod robust_optimizer;
#[cfg(test)]
mod tests;

pub(crate) use constraint::PreparedMeasurement;
pub use constraint::{Constraint, ConstraintKind, RobustLoss};
pub(crate) use constraint_merge::merged;
pub use graph::{PoseGraph, PoseGraphError};
pub use ids::{ConstraintId, NodeId, SubmapId, VariableId};
pub use optimizer::{
    ConvergenceCriterion, FailureReason, OptimizationSummary, Optimizer, OptimizerOptions,
    OptimizerOptionsError, Termination,
};
pub use robust_optimizer::{
    RobustOptimizationSummary, RobustOptimizer, RobustOptimizerOptions,
    RobustOptimizerOptionsError, RobustTrack,
};
