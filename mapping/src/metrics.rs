//! Accuracy measures of SLAM results.

mod relations_metric;
mod trajectory_metric;

pub use relations_metric::{RelationError, RelationsErrorStats, relation_errors, relations_error};
pub use trajectory_metric::{
    MRCL_ROTATION_DEG, MRCL_TRANSLATION_M, TrajectoryAccuracy, rigid_alignment, trajectory_accuracy,
};
