//! What adding a node writes into the graph: its path length, its constraints to the submaps LLO
//! inserted it into (new submaps become variables), and its odometry constraint to the trajectory's
//! previous node. [`GlobalSlam::add_node`] calls these in that order.

use super::{GlobalSlam, GlobalSlamError, GlobalSlamEvent, SubmapRecord, information, submap_bend};
use crate::geometry::Rigid2;
use crate::global_slam::FixedRatioSampler;
use crate::pose_graph::{Constraint, ConstraintKind, NodeId, RobustLoss, SubmapId, VariableId};

impl GlobalSlam {
    /// Distance (m) along `trajectory` from its first node to a new node at `local_pose`: the previous
    /// node's path plus the straight step to this one (0 for a trajectory's first node).
    pub(super) fn path_m_at(&self, trajectory: u32, local_pose: &Rigid2) -> f64 {
        self.last_node
            .get(&trajectory)
            .and_then(|p| self.nodes.get(p))
            .map_or(0.0, |previous| {
                previous.path_m
                    + (local_pose.translation.vector - previous.local_pose.translation.vector)
                        .norm()
            })
    }

    /// Ties node `id` to each submap LLO inserted it into (`(submap index, local_from_submap)`),
    /// declaring the submaps not seen before (a [`GlobalSlamEvent::SubmapAdded`] each). Returns the
    /// submaps the node is in.
    pub(super) fn insert_into_submaps(
        &mut self,
        id: NodeId,
        local_pose: Rigid2,
        path_m: f64,
        global_from_local: Rigid2,
        insertion_submaps: &[(usize, Rigid2)],
        events: &mut Vec<GlobalSlamEvent>,
    ) -> Result<Vec<SubmapId>, GlobalSlamError> {
        let graph_error = |source| GlobalSlamError::Graph { node: id, source };
        let mut node_submaps = Vec::with_capacity(insertion_submaps.len());
        for &(submap_index, local_from_submap) in insertion_submaps {
            let sid = SubmapId {
                trajectory: id.trajectory,
                index: submap_index as u32,
            };
            if !self.submaps.contains_key(&sid) {
                self.graph
                    .add_variable(
                        VariableId::Submap(sid),
                        global_from_local * local_from_submap,
                    )
                    .map_err(graph_error)?;
                self.submaps.insert(
                    sid,
                    SubmapRecord {
                        local_pose: local_from_submap,
                        grid: None,
                        nodes: Vec::new(),
                    },
                );
                self.samplers.insert(
                    sid,
                    FixedRatioSampler::new(self.options.constraint_builder.sampling_ratio),
                );
                events.push(GlobalSlamEvent::SubmapAdded(sid));
            }
            let Some(submap) = self.submaps.get_mut(&sid) else {
                continue;
            };
            // LLO drifted over the path from the submap's first node to this one, and the graph holds the
            // submap rigid: the farther along, the less the node's pose in it says about the world.
            let span_m = submap
                .nodes
                .first()
                .and_then(|n| self.nodes.get(n))
                .map_or(0.0, |first| (path_m - first.path_m).abs());
            let intra_information = submap_bend::intra_submap_information(
                &self.options,
                self.bent_submaps.get(&sid).copied(),
                span_m,
            );
            submap.nodes.push(id);
            self.graph
                .add_constraint(Constraint {
                    kind: ConstraintKind::NodeToSubmapIntra,
                    from: VariableId::Submap(sid),
                    to: VariableId::Node(id),
                    from_from_to: submap.local_pose.inverse() * local_pose,
                    information: intra_information,
                    loss: RobustLoss::Trivial,
                })
                .map_err(graph_error)?;
            node_submaps.push(sid);
        }
        Ok(node_submaps)
    }

    /// Ties node `id` at `local_pose` to its trajectory's previous node by LLO's relative motion, at the
    /// odometry sigmas of the options. Nothing for a trajectory's first node.
    pub(super) fn add_odometry_constraint(
        &mut self,
        id: NodeId,
        local_pose: Rigid2,
    ) -> Result<(), GlobalSlamError> {
        let Some((previous_id, previous_local_pose)) = self
            .last_node
            .get(&id.trajectory)
            .and_then(|p| self.nodes.get(p).map(|r| (*p, r.local_pose)))
        else {
            return Ok(());
        };
        self.graph
            .add_constraint(Constraint {
                kind: ConstraintKind::Odometry,
                from: VariableId::Node(previous_id),
                to: VariableId::Node(id),
                from_from_to: previous_local_pose.inverse() * local_pose,
                information: information(
                    self.options.odometry_translation_sigma,
                    self.options.odometry_rotation_sigma,
                ),
                loss: RobustLoss::Trivial,
            })
            .map_err(|source| GlobalSlamError::Graph { node: id, source })?;
        Ok(())
    }
}
