//! Identifiers of pose-graph variables and constraints.

use serde::{Deserialize, Serialize};

/// A trajectory node: one scan pose, `index` counted within its trajectory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct NodeId {
    /// The trajectory (robot session) the node belongs to.
    pub trajectory: u32,
    /// Index of the node within its trajectory.
    pub index: u32,
}

/// A submap, `index` counted within its trajectory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct SubmapId {
    /// The trajectory (robot session) the submap belongs to.
    pub trajectory: u32,
    /// Index of the submap within its trajectory.
    pub index: u32,
}

/// Any optimized pose in the graph. Ordered nodes first, then submaps, each by `(trajectory, index)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub enum VariableId {
    /// A trajectory node (`world_from_node`).
    Node(NodeId),
    /// A submap origin (`world_from_submap`).
    Submap(SubmapId),
}

impl VariableId {
    /// The trajectory the node or submap belongs to.
    pub fn trajectory(&self) -> u32 {
        match self {
            Self::Node(n) => n.trajectory,
            Self::Submap(s) => s.trajectory,
        }
    }
}

impl From<NodeId> for VariableId {
    fn from(id: NodeId) -> Self {
        Self::Node(id)
    }
}

impl From<SubmapId> for VariableId {
    fn from(id: SubmapId) -> Self {
        Self::Submap(id)
    }
}

/// Handle of a constraint in a [`super::PoseGraph`]. Handles are never reused within one graph, and they
/// increase in insertion order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct ConstraintId(pub u64);
