//! Which loop-closure searches GLM queues: each new node against the finished submaps near its estimate
//! (sampled), each newly finished submap against the nodes near it, and the search window, grown by the
//! drift LLO may have accumulated since the trajectory last closed a loop.

use std::sync::Arc;

use nalgebra::Point2;

use super::{GlobalSlam, NodeRecord, SubmapRecord};
use crate::geometry::Rigid2;
use crate::global_slam::{ConstraintBuilder, FixedRatioSampler, SearchJob, SearchWindow};
use crate::pose_graph::{NodeId, SubmapId, VariableId};

impl GlobalSlam {
    /// The loop-closure searches queued since the last call. Run them with
    /// [`ConstraintBuilder::run`] (from [`Self::constraint_builder`], in parallel if you like) and hand
    /// the accepted ones to [`Self::add_search_results`].
    pub fn take_search_jobs(&mut self) -> Vec<SearchJob> {
        std::mem::take(&mut self.pending_jobs)
    }

    /// The matcher that runs search jobs.
    pub fn constraint_builder(&self) -> &ConstraintBuilder {
        &self.builder
    }

    pub(super) fn queue_searches_for_node(&mut self, node: NodeId) {
        let finished: Vec<SubmapId> = self
            .submaps
            .iter()
            .filter(|(_, s)| s.grid.is_some())
            .map(|(id, _)| *id)
            .collect();
        for sid in finished {
            self.maybe_queue_search(node, sid);
        }
    }

    pub(super) fn maybe_queue_search(&mut self, node: NodeId, sid: SubmapId) {
        let (Some(record), Some(submap)) = (self.nodes.get(&node), self.submaps.get(&sid)) else {
            return;
        };
        if record.submaps.contains(&sid) {
            return;
        }
        if node.trajectory != sid.trajectory
            && (self.matched_elsewhere.contains(&node.trajectory)
                || self.matched_elsewhere.contains(&sid.trajectory))
        {
            return;
        }
        if node.trajectory != sid.trajectory
            && (self.unanchored.contains(&node.trajectory)
                || self.unanchored.contains(&sid.trajectory))
        {
            // Estimates of an unanchored trajectory mean nothing in the map frame: match its nodes
            // against whole submaps of placed trajectories, now and then, until one match places it.
            let every = self.options.unanchored_search_every_n_nodes;
            if self.unanchored.contains(&sid.trajectory)
                || every == 0
                || !(node.index as usize).is_multiple_of(every)
            {
                return;
            }
            let points = Arc::clone(&record.points);
            self.queue_search(node, sid, points, None);
            return;
        }
        let window = self.search_window(node, record, sid, submap);
        let cb = &self.options.constraint_builder;
        let growth = window.linear_m - cb.fast_correlative.linear_search_window;
        let (Some(global_node), Some(global_submap)) = (
            self.graph.pose(VariableId::Node(node)),
            self.graph.pose(VariableId::Submap(sid)),
        ) else {
            return;
        };
        let submap_from_node = global_submap.inverse() * global_node;
        if submap_from_node.translation.vector.norm() > cb.max_constraint_distance + growth {
            return;
        }
        debug_assert!(submap.grid.is_some());
        if !self
            .samplers
            .get_mut(&sid)
            .is_some_and(FixedRatioSampler::pulse)
        {
            return;
        }
        let points = Arc::clone(&record.points);
        self.queue_search(node, sid, points, Some((submap_from_node, window)));
    }

    /// Queues a search of `node`'s `points` against `sid`: near the estimate `submap_from_node` within
    /// the window, or over the whole submap (`None`).
    fn queue_search(
        &mut self,
        node: NodeId,
        sid: SubmapId,
        points: Arc<Vec<Point2<f32>>>,
        near: Option<(Rigid2, SearchWindow)>,
    ) {
        self.searches_queued += 1;
        self.pending_jobs.push(SearchJob {
            submap: sid,
            node,
            points,
            submap_from_node_estimate: near.map(|(estimate, _)| estimate),
            window: near.map(|(_, window)| window),
        });
    }

    /// The search window for `node` against `submap`: the default one grown by the drift LLO may have
    /// accumulated over the path since the node's trajectory last closed a loop (or, within one
    /// trajectory, over the path between the submap and the node, if shorter).
    pub(super) fn search_window(
        &self,
        node: NodeId,
        record: &NodeRecord,
        sid: SubmapId,
        submap: &SubmapRecord,
    ) -> SearchWindow {
        let cb = &self.options.constraint_builder;
        let drift_path = self.drift_path(node, record, sid, submap);
        let (doubt_rad, doubt_m) = self.recovery_doubt(node, record, sid, submap);
        let base = &cb.fast_correlative;
        SearchWindow {
            linear_m: (base.linear_search_window + cb.linear_window_growth * drift_path + doubt_m)
                .min(cb.max_linear_search_window.max(base.linear_search_window)),
            angular_rad: (base.angular_search_window
                + cb.angular_window_growth * drift_path
                + doubt_rad)
                .min(std::f64::consts::PI),
        }
    }

    /// The path (m) over which LLO's drift separates `node`'s estimate from `submap`'s: the path since the
    /// node's trajectory last closed a loop (or was placed by a relocalization) or, within one trajectory,
    /// the path between the submap and the node, if shorter; none for a node whose scan fitted its
    /// trajectory's placement, against another trajectory's submap (the placement pins it there: see
    /// [`Self::place_trajectory`]).
    pub(super) fn drift_path(
        &self,
        node: NodeId,
        record: &NodeRecord,
        sid: SubmapId,
        submap: &SubmapRecord,
    ) -> f64 {
        if self.fitted_by_placement(node, sid) {
            return 0.0;
        }
        let since_loop = record.path_m
            - self
                .last_loop_path
                .get(&node.trajectory)
                .copied()
                .unwrap_or(0.0);
        let mut drift_path = since_loop.max(0.0);
        if sid.trajectory == node.trajectory
            && let Some(first) = submap.nodes.first().and_then(|n| self.nodes.get(n))
        {
            drift_path = drift_path.min((record.path_m - first.path_m).abs());
        }
        drift_path
    }

    /// The doubt an LLO recovery adds between `node`'s estimate and `submap`'s: (rotation rad, translation
    /// m), zero unless the trajectory recovered since its last loop closure, at or before the node, and
    /// (within one trajectory) at or after the submap's first node: the recovery lies between the two.
    pub(super) fn recovery_doubt(
        &self,
        node: NodeId,
        record: &NodeRecord,
        sid: SubmapId,
        submap: &SubmapRecord,
    ) -> (f64, f64) {
        let doubt = self.options.constraint_builder.recovery_heading_doubt;
        let Some(&recovered) = self.recovery_path.get(&node.trajectory) else {
            return (0.0, 0.0);
        };
        let last_loop = self
            .last_loop_path
            .get(&node.trajectory)
            .copied()
            .unwrap_or(0.0);
        if doubt <= 0.0 || recovered < last_loop || record.path_m < recovered {
            return (0.0, 0.0);
        }
        if sid.trajectory == node.trajectory
            && submap
                .nodes
                .first()
                .and_then(|n| self.nodes.get(n))
                .is_some_and(|first| first.path_m > recovered)
        {
            return (0.0, 0.0);
        }
        (doubt, doubt * (record.path_m - recovered))
    }

    /// Notes that LLO placed a scan after `trajectory`'s newest node by a recovery search: until the next
    /// loop closure, its nodes carry `recovery_heading_doubt`.
    pub(super) fn note_llo_recovery(&mut self, trajectory: u32) {
        let path = self
            .last_node
            .get(&trajectory)
            .and_then(|n| self.nodes.get(n))
            .map_or(0.0, |r| r.path_m);
        let last_loop = self.last_loop_path.get(&trajectory).copied().unwrap_or(0.0);
        let entry = self.recovery_path.entry(trajectory).or_insert(path);
        if *entry < last_loop {
            *entry = path;
        }
    }
}
