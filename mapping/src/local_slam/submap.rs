//! A submap: a probability grid built from a fixed number of consecutive scans.

use crate::geometry::Rigid2;
use crate::grid::ProbabilityGrid;

/// One submap of a trajectory. Its grid is in the trajectory's local frame; `local_pose` is
/// `local_from_submap`, the pose of the submap's origin (the first inserted scan's origin, unrotated).
#[derive(Clone, Debug)]
pub struct Submap {
    /// `local_from_submap`.
    pub local_pose: Rigid2,
    /// Occupancy probabilities, in the local frame.
    pub grid: ProbabilityGrid,
    /// Scans inserted so far.
    pub num_range_data: usize,
    /// Whether the submap will receive no more scans.
    pub finished: bool,
}

/// A submap a node was inserted into.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SubmapRef {
    /// Per-trajectory submap index.
    pub index: usize,
    /// `local_from_submap`.
    pub local_pose: Rigid2,
}
