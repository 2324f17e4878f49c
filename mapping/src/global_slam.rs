//! Global SLAM: the back end that turns LLO's nodes and submaps into a loop-closed pose graph.
//!
//! This is the synchronous core of Cartographer's `PoseGraph2D`: every node LLO inserts becomes a
//! variable with an intra-submap constraint to each submap it was inserted into and an odometry
//! constraint to its predecessor; finished submaps get a branch-and-bound matcher, and the constraint
//! builder searches loop closures between nodes and finished submaps nearby (GLM). The graph is
//! optimized every `optimize_every_n_nodes` nodes and on demand. Nothing here does I/O or reads a
//! clock: callers feed nodes in and read [`GlobalSlamEvent`]s out.

mod constraint_builder;
mod fixed_ratio_sampler;
mod global_slam_core;
mod global_slam_options;
mod loop_closure_check;
mod optimization_region;

pub use constraint_builder::{
    ConstraintBuilder, ConstraintBuilderOptions, LoopClosure, SearchJob, SearchWindow,
};
pub use fixed_ratio_sampler::FixedRatioSampler;
pub use global_slam_core::{
    Acceptance, BendGrowth, ClosureState, CorrectionProbation, GlobalSlam, GlobalSlamError,
    GlobalSlamEvent, GlobalSlamState, MatchDecided, MatchDecision, NodeRecord, SubmapBend,
    SubmapRecord,
};
pub use global_slam_options::{GlobalSlamOptions, GlobalSlamOptionsError};
pub use loop_closure_check::{
    LoopClosureCheck, LoopClosurePrecision, TRUE_CLOSURE_ROTATION_RAD, TRUE_CLOSURE_TRANSLATION_M,
    loop_closure_precision,
};
pub use optimization_region::optimization_region;

/// [`GlobalSlam`]'s test fixtures, for the tests of what reads it (`metrics::judge_matches`).
#[cfg(test)]
pub(crate) use global_slam_core::tests::{straight_run, wide_closure};
