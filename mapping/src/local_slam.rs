//! LLO, local LiDAR odometry: scan-to-submap matching into probability-grid submaps, fused with wheel
//! odometry and IMU yaw rate (Cartographer's `LocalTrajectoryBuilder2D`).

mod active_submaps;
mod llo_driver;
mod local_trajectory_builder;
mod motion_filter;
mod pose_extrapolator;
mod submap;
#[cfg(test)]
mod test_support;
mod voxel_filter;

pub use active_submaps::{ActiveSubmaps, SubmapsOptions};
pub use llo_driver::{LloDriver, LloEvent};
pub use local_trajectory_builder::{
    CorrelativeBranch, InsertionResult, LloNode, LocalTrajectoryBuilder,
    LocalTrajectoryBuilderOptions, LocalTrajectoryBuilderOptionsError, MatchingResult,
    TrajectoryNodeData,
};
pub use motion_filter::{MotionFilter, MotionFilterOptions};
pub use pose_extrapolator::{PoseExtrapolator, PoseExtrapolatorOptions};
pub use submap::{Submap, SubmapRef};
pub use voxel_filter::{AdaptiveVoxelFilterOptions, adaptive_voxel_filter, voxel_filter};
