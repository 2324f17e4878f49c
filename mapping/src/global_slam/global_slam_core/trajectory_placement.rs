//! Where each trajectory sits in the map frame: a trajectory that starts unanchored is placed by a
//! relocalization or anchored by its first cross-trajectory closure, and unplaced when its placement is
//! found wrong.

use super::{ClosureState, GlobalSlam};
use crate::geometry::Rigid2;
#[cfg(doc)]
use crate::global_slam::ConstraintBuilderOptions;
use crate::global_slam::LoopClosure;
use crate::pose_graph::{NodeId, SubmapId, VariableId};

impl GlobalSlam {
    /// Declares that `trajectory`'s matches against other trajectories are computed elsewhere (by GLM on
    /// its robot, handed in with [`Self::add_search_results`]): no search pairs one of its nodes with
    /// another trajectory's submap, or one of its submaps with another trajectory's node. Searches within
    /// the trajectory (its own loop closures) still run here.
    pub fn set_matched_elsewhere(&mut self, trajectory: u32) {
        self.matched_elsewhere.insert(trajectory);
    }

    /// Whether a trajectory still waits for its first cross-trajectory match to be placed in the map.
    pub fn is_unanchored(&self, trajectory: u32) -> bool {
        self.unanchored.contains(&trajectory)
    }

    /// Moves an unanchored trajectory so that `closure` holds exactly, and queues the searches its nodes
    /// can now make near their estimates.
    pub(super) fn anchor(&mut self, closure: &LoopClosure) {
        let trajectory = closure.node.trajectory;
        let (Some(submap_pose), Some(node_pose)) = (
            self.graph.pose(VariableId::Submap(closure.submap)),
            self.graph.pose(VariableId::Node(closure.node)),
        ) else {
            return;
        };
        let correction = submap_pose * closure.submap_from_node * node_pose.inverse();
        self.move_trajectory(trajectory, correction);
    }

    /// Places an unanchored trajectory (see [`Self::start_trajectory`]) at `global_from_local`, found by
    /// relocalization after it started: moves its nodes and submaps there and queues the searches its nodes
    /// can now make near their estimates. The placement ties the trajectory's newest node to the map as a
    /// loop closure would: drift, and with it the search windows and the drift bound of its matches, grows
    /// from that node again (as from the node of the first closure that anchors a trajectory).
    ///
    /// `fitted`: the first and last index of the nodes whose scans, merged in their local frame, the
    /// search fitted to the map at this placement (`None`: a placement given without a search). The
    /// placement pins those nodes to the other trajectories' submaps, and vouches for LLO between them: a
    /// slip there would have spoiled the fit. So no drift separates them from those submaps, and a chorus
    /// of matches beyond that bound (what [`ConstraintBuilderOptions::beyond_drift_confirmations`] lets
    /// repair a slip) is never confirmed: it contradicts the placement, and only the session start, which
    /// counts such matches against it, may overturn that. Returns false (and changes nothing) when the
    /// trajectory is not unanchored.
    pub fn place_trajectory(
        &mut self,
        trajectory: u32,
        global_from_local: Rigid2,
        fitted: Option<(u32, u32)>,
    ) -> bool {
        if !self.unanchored.contains(&trajectory) {
            return false;
        }
        if let Some(newest) = self
            .last_node
            .get(&trajectory)
            .and_then(|n| self.nodes.get(n))
        {
            self.last_loop_path.insert(trajectory, newest.path_m);
        }
        match fitted {
            Some(fitted) => self.placement_fits.insert(trajectory, fitted),
            None => self.placement_fits.remove(&trajectory),
        };
        let correction = global_from_local * self.global_from_local(trajectory).inverse();
        self.move_trajectory(trajectory, correction);
        true
    }

    /// Undoes a placement (see [`Self::place_trajectory`]) found wrong: removes every constraint between
    /// `trajectory` and the other trajectories (its matches against their submaps and theirs against its
    /// own), forgets its queued and pending cross-trajectory matches, and makes it unanchored again (its
    /// estimates keep their values, which mean nothing in the map frame until it is placed again).
    /// Returns false (and changes nothing) when it is unanchored already or unknown.
    pub fn unplace_trajectory(&mut self, trajectory: u32) -> bool {
        if self.unanchored.contains(&trajectory) || !self.last_node.contains_key(&trajectory) {
            return false;
        }
        let crossing: Vec<_> = self
            .graph
            .constraints()
            .filter(|(_, c)| {
                let (a, b) = (c.from.trajectory(), c.to.trajectory());
                a != b && (a == trajectory || b == trajectory)
            })
            .map(|(id, _)| id)
            .collect();
        for id in crossing {
            if let Ok(c) = self.graph.remove_constraint(id) {
                self.changed.extend([c.from, c.to]);
            }
        }
        let crosses = |node: NodeId, submap: SubmapId| {
            node.trajectory != submap.trajectory
                && (node.trajectory == trajectory || submap.trajectory == trajectory)
        };
        // Its cross-trajectory closures are gone for good, retracted ones included (never put back).
        for (closure, state) in self
            .accepted_loop_closures
            .iter()
            .zip(&mut self.closure_states)
        {
            if crosses(closure.node, closure.submap) {
                *state = ClosureState::Gone;
            }
        }
        self.pending_jobs.retain(|j| !crosses(j.node, j.submap));
        self.probations
            .retain(|p| !p.closures.iter().any(|&(n, s)| crosses(n, s)));
        self.pending_unconfirmed
            .retain(|(c, _)| !crosses(c.node, c.submap));
        self.pending_beyond_drift
            .retain(|(c, _)| !crosses(c.node, c.submap));
        self.sync_bends();
        self.last_loop_path.remove(&trajectory);
        self.recovery_path.remove(&trajectory);
        self.placement_fits.remove(&trajectory);
        self.unanchored.insert(trajectory);
        true
    }

    /// Whether `node`'s scan fitted its trajectory's placement (see [`Self::place_trajectory`]) and
    /// `submap` is another trajectory's: what the placement fitted it to.
    pub(super) fn fitted_by_placement(&self, node: NodeId, submap: SubmapId) -> bool {
        node.trajectory != submap.trajectory
            && self
                .placement_fits
                .get(&node.trajectory)
                .is_some_and(|&(first, last)| (first..=last).contains(&node.index))
    }

    /// Records that `trajectory`, started at a prior ([`Self::start_trajectory`]), was placed there by a
    /// search made elsewhere (on its robot) that fitted the scans of its nodes `fitted` (first and last
    /// index), as [`Self::place_trajectory`]'s `fitted` does for a search made here. Returns false (and
    /// changes nothing) when the trajectory is unanchored.
    pub fn set_placement_fit(&mut self, trajectory: u32, fitted: (u32, u32)) -> bool {
        if self.unanchored.contains(&trajectory) {
            return false;
        }
        self.placement_fits.insert(trajectory, fitted);
        true
    }

    /// Stops treating `trajectory`'s cross-trajectory matches as found elsewhere (see
    /// [`Self::set_matched_elsewhere`]): its nodes are searched here again from now on.
    pub fn clear_matched_elsewhere(&mut self, trajectory: u32) {
        self.matched_elsewhere.remove(&trajectory);
    }

    /// Applies `correction` (new global from old global) to every variable of `trajectory`, anchors it and
    /// queues its nodes' searches.
    fn move_trajectory(&mut self, trajectory: u32, correction: Rigid2) {
        let variables: Vec<(VariableId, Rigid2)> = self
            .graph
            .variables()
            .filter(|(id, _, _)| id.trajectory() == trajectory)
            .map(|(id, pose, _)| (id, pose))
            .collect();
        for (id, pose) in variables {
            // Cannot fail: the variable exists and a rigid motion keeps poses finite.
            let _ = self.graph.set_pose(id, correction * pose);
        }
        let global_from_local = correction * self.global_from_local(trajectory);
        self.global_from_local.insert(trajectory, global_from_local);
        self.unanchored.remove(&trajectory);
        let nodes: Vec<NodeId> = self
            .trajectory_nodes(trajectory)
            .map(|(id, _)| *id)
            .collect();
        for node in nodes {
            self.queue_searches_for_node(node);
        }
    }
}
