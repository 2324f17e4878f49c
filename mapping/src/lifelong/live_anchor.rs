//! [`LiveAnchor`]: the pose a placed robot navigates on, between optimizations.
//!
//! A session's nodes are placed in the map by its `global_from_local`, which the pose graph re-derives only
//! when it optimizes (every `optimize_every_n_nodes` nodes, or when matches confirm a correction). Between
//! optimizations LLO's drift since then goes straight into the robot's pose, although GLM keeps matching
//! its nodes against the map. The anchor takes each node's best accepted match against the map as the
//! session's `global_from_local` (the paper's agents localize so), and the graph's own once it optimizes.
//! Right after a session's start in the map this halves what the robot's estimate is off at the time on
//! ACES and MIT CSAIL cut into sessions (docs/BENCHMARK-HISTORY.md, "Session 70").

use crate::geometry::Rigid2;

/// A session's `global_from_local` as the robot has it (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LiveAnchor {
    global_from_local: Rigid2,
}

impl LiveAnchor {
    /// Anchored at `global_from_local` (a placement, or the graph's after an optimization).
    pub fn new(global_from_local: Rigid2) -> Self {
        Self { global_from_local }
    }

    /// The session's `global_from_local` as the robot has it.
    pub fn global_from_local(&self) -> Rigid2 {
        self.global_from_local
    }

    /// Where the robot is at `local_pose` (LLO's frame).
    pub fn pose(&self, local_pose: &Rigid2) -> Rigid2 {
        self.global_from_local * local_pose
    }

    /// Re-anchors on a match of the node at `local_pose` (LLO's frame): the node is at `submap_from_node`
    /// in the submap whose pose in the map is `global_from_submap`.
    pub fn anchor_on_match(
        &mut self,
        global_from_submap: &Rigid2,
        submap_from_node: &Rigid2,
        local_pose: &Rigid2,
    ) {
        self.global_from_local = global_from_submap * submap_from_node * local_pose.inverse();
    }
}

#[cfg(test)]
mod tests {
    use approx::assert_relative_eq;

    use super::*;
    use crate::geometry::{Rigid2Ext as _, rigid2};

    #[test]
    fn a_match_moves_the_robot_to_where_it_puts_the_node_and_carries_later_nodes_along() {
        let mut anchor = LiveAnchor::new(rigid2(1.0, 0.0, 0.0));
        let node = rigid2(2.0, 0.0, 0.0);
        assert_relative_eq!(anchor.pose(&node).translation.x, 3.0);
        // The map says the node is 0.3 m farther and turned 0.1 rad: LLO drifted.
        let submap = rigid2(0.0, 1.0, 0.0);
        let submap_from_node = rigid2(3.3, -1.0, 0.1);
        anchor.anchor_on_match(&submap, &submap_from_node, &node);
        let at_node = anchor.pose(&node);
        assert_relative_eq!(at_node.translation.x, 3.3, epsilon = 1e-12);
        assert_relative_eq!(at_node.translation.y, 0.0, epsilon = 1e-12);
        assert_relative_eq!(at_node.theta(), 0.1, epsilon = 1e-12);
        // One metre on in LLO's frame is one metre on along the corrected heading.
        let later = anchor.pose(&rigid2(3.0, 0.0, 0.0));
        assert_relative_eq!(later.translation.x, 3.3 + 0.1f64.cos(), epsilon = 1e-12);
        assert_relative_eq!(later.translation.y, 0.1f64.sin(), epsilon = 1e-12);
    }
}
