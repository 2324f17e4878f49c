//! Conversions between wire messages and `mapping` types, one file per family.

pub(crate) mod constraint;
mod geometry;
mod grid;
mod node;

pub(crate) use geometry::{check_finite, points_from_pb, points_to_pb};
pub use geometry::{check_format_version, pose_from_pb, pose_to_pb};
pub use grid::{grid_from_pb, grid_to_pb, grid_to_pb_with};
pub use node::NodeSnapshot;
