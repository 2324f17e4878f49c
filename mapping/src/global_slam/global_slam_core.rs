//! The global SLAM state machine.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use nalgebra::{Matrix3, Point2};

use super::{
    ConstraintBuilder, FixedRatioSampler, GlobalSlamOptions, GlobalSlamOptionsError, LoopClosure,
    SearchJob,
};
use crate::geometry::Rigid2;
use crate::grid::ProbabilityGrid;
use crate::pose_graph::{
    Constraint, ConstraintKind, NodeId, OptimizationSummary, Optimizer, PoseGraph, PoseGraphError,
    RobustLoss, SubmapId, VariableId,
};
use crate::sensor::Timestamp;

/// What global SLAM knows about a node.
#[derive(Clone, Debug)]
pub struct NodeRecord {
    /// When the node's scan was taken.
    pub time: Timestamp,
    /// `local_from_tracking` from LLO.
    pub local_pose: Rigid2,
    /// The node's filtered scan points in its tracking frame (what GLM matches).
    pub points: Arc<Vec<Point2<f32>>>,
    /// Submaps the node was inserted into.
    pub submaps: Vec<SubmapId>,
}

/// What global SLAM knows about a submap.
#[derive(Clone, Debug)]
pub struct SubmapRecord {
    /// `local_from_submap` from LLO.
    pub local_pose: Rigid2,
    /// The finished grid (in the trajectory's local frame); `None` while LLO still inserts into it.
    pub grid: Option<Arc<ProbabilityGrid>>,
    /// Nodes inserted into the submap.
    pub nodes: Vec<NodeId>,
}

/// Something global SLAM did that the shell may want to forward, store or display.
#[derive(Clone, Debug)]
pub enum GlobalSlamEvent {
    /// A new submap variable joined the graph.
    SubmapAdded(SubmapId),
    /// A submap was finished and can now be matched against.
    SubmapFinished(SubmapId),
    /// A loop closure (GLM constraint) was accepted.
    LoopClosureAdded(LoopClosure),
    /// The graph was optimized.
    Optimized(OptimizationSummary),
}

/// Errors of [`GlobalSlam`].
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GlobalSlamError {
    /// The options are invalid.
    #[error(transparent)]
    Options(#[from] GlobalSlamOptionsError),
    /// The trajectory already has nodes, so it cannot be started (again).
    #[error("trajectory {0} has already started")]
    TrajectoryStarted(u32),
    /// A node or constraint was refused by the pose graph (non-finite pose, bad information matrix).
    #[error("pose graph refused node {node:?}: {source}")]
    Graph {
        /// The node being added.
        node: NodeId,
        /// Why.
        source: PoseGraphError,
    },
}

/// Pose graph, loop-closure search and optimization over LLO's output.
pub struct GlobalSlam {
    options: GlobalSlamOptions,
    graph: PoseGraph,
    optimizer: Optimizer,
    builder: ConstraintBuilder,
    nodes: BTreeMap<NodeId, NodeRecord>,
    submaps: BTreeMap<SubmapId, SubmapRecord>,
    samplers: BTreeMap<SubmapId, FixedRatioSampler>,
    global_from_local: BTreeMap<u32, Rigid2>,
    last_node: BTreeMap<u32, NodeId>,
    pending_jobs: Vec<SearchJob>,
    nodes_since_optimization: usize,
    loop_closure_scores: Vec<f32>,
    searches_queued: usize,
    /// Trajectories started without a prior while the map already had other trajectories: their
    /// estimates are in an arbitrary frame until a full-submap match places them (see
    /// [`GlobalSlam::start_trajectory`]).
    unanchored: BTreeSet<u32>,
    /// A second optimizer with a capped number of iterations (see [`GlobalSlam::optimize_capped`]).
    capped_optimizer: Option<Optimizer>,
    /// Trajectories whose cross-trajectory matches are found elsewhere (GLM on the robot; see
    /// [`GlobalSlam::set_matched_elsewhere`]).
    matched_elsewhere: BTreeSet<u32>,
}

fn information(translation_sigma: f64, rotation_sigma: f64) -> Matrix3<f64> {
    let t = 1.0 / (translation_sigma * translation_sigma);
    Matrix3::from_diagonal(&nalgebra::Vector3::new(
        t,
        t,
        1.0 / (rotation_sigma * rotation_sigma),
    ))
}

impl GlobalSlam {
    /// An empty map.
    pub fn new(options: GlobalSlamOptions) -> Result<Self, GlobalSlamError> {
        options.validate()?;
        let optimizer = Optimizer::new(options.optimizer.clone())
            .map_err(|e| GlobalSlamOptionsError::Invalid(e.to_string()))?;
        Ok(Self {
            graph: PoseGraph::new(),
            optimizer,
            builder: ConstraintBuilder::new(options.constraint_builder.clone()),
            options,
            nodes: BTreeMap::new(),
            submaps: BTreeMap::new(),
            samplers: BTreeMap::new(),
            global_from_local: BTreeMap::new(),
            last_node: BTreeMap::new(),
            pending_jobs: Vec::new(),
            nodes_since_optimization: 0,
            loop_closure_scores: Vec::new(),
            searches_queued: 0,
            unanchored: BTreeSet::new(),
            capped_optimizer: None,
            matched_elsewhere: BTreeSet::new(),
        })
    }

    /// Declares a new trajectory before its first node. With `Some(global_from_local)` (a relocalized
    /// prior) its nodes are placed there and searched near their estimates like any other. With `None`
    /// the trajectory is *unanchored* if the map already holds another trajectory: its nodes are matched
    /// against the other trajectories' finished submaps with no prior (every
    /// `unanchored_search_every_n_nodes`-th node, over whole submaps), and the first accepted match moves
    /// the whole trajectory into place. A trajectory never declared (or the first one) starts at
    /// identity, as before.
    pub fn start_trajectory(
        &mut self,
        trajectory: u32,
        global_from_local: Option<Rigid2>,
    ) -> Result<(), GlobalSlamError> {
        if self.last_node.contains_key(&trajectory) {
            return Err(GlobalSlamError::TrajectoryStarted(trajectory));
        }
        if let Some(prior) = global_from_local {
            self.global_from_local.insert(trajectory, prior);
            self.unanchored.remove(&trajectory);
        } else {
            self.global_from_local.remove(&trajectory);
            if !self.nodes.is_empty() {
                self.unanchored.insert(trajectory);
            }
        }
        Ok(())
    }

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

    /// Adds a node that LLO inserted into the submaps `insertion_submaps` (`(index, local_from_submap)`
    /// per submap, indices per trajectory), together with the submaps this insertion finished
    /// (`(index, grid)`). Queues the loop-closure searches it makes possible (see
    /// [`Self::take_search_jobs`]).
    pub fn add_node(
        &mut self,
        trajectory: u32,
        time: Timestamp,
        local_pose: Rigid2,
        points: Vec<Point2<f32>>,
        insertion_submaps: &[(usize, Rigid2)],
        finished_submaps: Vec<(usize, ProbabilityGrid)>,
    ) -> Result<(NodeId, Vec<GlobalSlamEvent>), GlobalSlamError> {
        let mut events = Vec::new();
        let index = self.last_node.get(&trajectory).map_or(0, |n| n.index + 1);
        let id = NodeId { trajectory, index };
        let graph_error = |source| GlobalSlamError::Graph { node: id, source };
        let global_from_local = self.global_from_local(trajectory);
        self.graph
            .add_variable(VariableId::Node(id), global_from_local * local_pose)
            .map_err(graph_error)?;
        if self.nodes.is_empty() {
            self.graph
                .set_fixed(VariableId::Node(id), true)
                .map_err(graph_error)?;
        }

        let mut node_submaps = Vec::with_capacity(insertion_submaps.len());
        for &(submap_index, local_from_submap) in insertion_submaps {
            let sid = SubmapId {
                trajectory,
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
            submap.nodes.push(id);
            self.graph
                .add_constraint(Constraint {
                    kind: ConstraintKind::NodeToSubmapIntra,
                    from: VariableId::Submap(sid),
                    to: VariableId::Node(id),
                    from_from_to: submap.local_pose.inverse() * local_pose,
                    information: information(
                        self.options.intra_submap_translation_sigma,
                        self.options.intra_submap_rotation_sigma,
                    ),
                    loss: RobustLoss::Trivial,
                })
                .map_err(graph_error)?;
            node_submaps.push(sid);
        }

        if let Some(previous) = self
            .last_node
            .get(&trajectory)
            .and_then(|p| self.nodes.get(p).map(|r| (*p, r)))
        {
            let (previous_id, previous_record) = previous;
            self.graph
                .add_constraint(Constraint {
                    kind: ConstraintKind::Odometry,
                    from: VariableId::Node(previous_id),
                    to: VariableId::Node(id),
                    from_from_to: previous_record.local_pose.inverse() * local_pose,
                    information: information(
                        self.options.odometry_translation_sigma,
                        self.options.odometry_rotation_sigma,
                    ),
                    loss: RobustLoss::Trivial,
                })
                .map_err(graph_error)?;
        }
        self.nodes.insert(
            id,
            NodeRecord {
                time,
                local_pose,
                points: Arc::new(points),
                submaps: node_submaps,
            },
        );
        self.last_node.insert(trajectory, id);

        events.extend(self.add_finished_submaps(trajectory, finished_submaps));
        self.queue_searches_for_node(id);
        self.nodes_since_optimization += 1;
        Ok((id, events))
    }

    /// Finishes submaps of a trajectory outside [`Self::add_node`] (e.g. the submaps still active when a
    /// session ends) and queues the searches they make possible. Unknown submaps are ignored.
    pub fn add_finished_submaps(
        &mut self,
        trajectory: u32,
        finished_submaps: Vec<(usize, ProbabilityGrid)>,
    ) -> Vec<GlobalSlamEvent> {
        let mut events = Vec::new();
        for (submap_index, grid) in finished_submaps {
            let sid = SubmapId {
                trajectory,
                index: submap_index as u32,
            };
            if self.submaps.contains_key(&sid) {
                self.finish_submap(sid, grid);
                events.push(GlobalSlamEvent::SubmapFinished(sid));
            }
        }
        events
    }

    fn finish_submap(&mut self, sid: SubmapId, grid: ProbabilityGrid) {
        let Some(submap) = self.submaps.get_mut(&sid) else {
            return;
        };
        let grid = Arc::new(grid);
        submap.grid = Some(Arc::clone(&grid));
        let local_pose = submap.local_pose;
        self.builder.add_finished_submap(sid, local_pose, grid);
        let node_ids: Vec<NodeId> = self.nodes.keys().copied().collect();
        for node in node_ids {
            self.maybe_queue_search(node, sid);
        }
    }

    fn queue_searches_for_node(&mut self, node: NodeId) {
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

    fn maybe_queue_search(&mut self, node: NodeId, sid: SubmapId) {
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
            self.searches_queued += 1;
            self.pending_jobs.push(SearchJob {
                submap: sid,
                node,
                points: Arc::clone(&record.points),
                submap_from_node_estimate: None,
            });
            return;
        }
        let (Some(global_node), Some(global_submap)) = (
            self.graph.pose(VariableId::Node(node)),
            self.graph.pose(VariableId::Submap(sid)),
        ) else {
            return;
        };
        let submap_from_node = global_submap.inverse() * global_node;
        if submap_from_node.translation.vector.norm()
            > self.options.constraint_builder.max_constraint_distance
        {
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
        self.searches_queued += 1;
        self.pending_jobs.push(SearchJob {
            submap: sid,
            node,
            points: Arc::clone(&record.points),
            submap_from_node_estimate: Some(submap_from_node),
        });
    }

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

    /// Adds accepted loop closures as robust node-to-submap constraints, then optimizes if
    /// `optimize_every_n_nodes` nodes arrived since the last optimization.
    pub fn add_search_results(
        &mut self,
        results: impl IntoIterator<Item = LoopClosure>,
    ) -> Vec<GlobalSlamEvent> {
        let mut events = Vec::new();
        let cb = &self.options.constraint_builder;
        let loop_closure_information = information(
            cb.loop_closure_translation_sigma,
            cb.loop_closure_rotation_sigma,
        );
        let loss = RobustLoss::Huber {
            delta: cb.huber_scale,
        };
        for closure in results {
            if !self.nodes.contains_key(&closure.node)
                || !self.submaps.contains_key(&closure.submap)
            {
                continue;
            }
            if closure.node.trajectory != closure.submap.trajectory
                && self.unanchored.contains(&closure.submap.trajectory)
            {
                continue; // never queued: an unplaced submap says nothing about placed nodes yet
            }
            if self.unanchored.contains(&closure.node.trajectory)
                && closure.node.trajectory != closure.submap.trajectory
            {
                self.anchor(&closure);
            }
            let added = self.graph.add_constraint(Constraint {
                kind: ConstraintKind::NodeToSubmapInter,
                from: VariableId::Submap(closure.submap),
                to: VariableId::Node(closure.node),
                from_from_to: closure.submap_from_node,
                information: loop_closure_information,
                loss,
            });
            if added.is_err() {
                continue; // a non-finite match; nothing to learn from it
            }
            self.loop_closure_scores.push(closure.score);
            events.push(GlobalSlamEvent::LoopClosureAdded(closure));
        }
        let n = self.options.optimize_every_n_nodes;
        if n > 0 && self.nodes_since_optimization >= n {
            events.push(GlobalSlamEvent::Optimized(self.optimize()));
        }
        events
    }

    /// Moves an unanchored trajectory so that `closure` holds exactly, and queues the searches its nodes
    /// can now make near their estimates.
    fn anchor(&mut self, closure: &LoopClosure) {
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
    /// can now make near their estimates. Returns false (and changes nothing) when the trajectory is not
    /// unanchored.
    pub fn place_trajectory(&mut self, trajectory: u32, global_from_local: Rigid2) -> bool {
        if !self.unanchored.contains(&trajectory) {
            return false;
        }
        let correction = global_from_local * self.global_from_local(trajectory).inverse();
        self.move_trajectory(trajectory, correction);
        true
    }

    /// Applies `correction` (new global from old global) to every variable of `trajectory`, anchors it and
    /// queues its nodes' searches.
    fn move_trajectory(&mut self, trajectory: u32, correction: Rigid2) {
        let variables: Vec<(VariableId, Rigid2)> = self
            .graph
            .variables()
            .filter(|(id, _, _)| match id {
                VariableId::Node(n) => n.trajectory == trajectory,
                VariableId::Submap(s) => s.trajectory == trajectory,
            })
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
            .nodes
            .range(
                NodeId {
                    trajectory,
                    index: 0,
                }..=NodeId {
                    trajectory,
                    index: u32::MAX,
                },
            )
            .map(|(id, _)| *id)
            .collect();
        for node in nodes {
            self.queue_searches_for_node(node);
        }
    }

    /// Runs every queued search on this thread and adds the results.
    pub fn run_pending_searches(&mut self) -> Vec<GlobalSlamEvent> {
        let jobs = self.take_search_jobs();
        let results: Vec<LoopClosure> = jobs.iter().filter_map(|j| self.builder.run(j)).collect();
        self.add_search_results(results)
    }

    /// Optimizes the whole graph now and updates each trajectory's `global_from_local`.
    pub fn optimize(&mut self) -> OptimizationSummary {
        let summary = self.optimizer.optimize(&mut self.graph);
        self.nodes_since_optimization = 0;
        self.update_global_from_local();
        summary
    }

    /// Re-derives each trajectory's `global_from_local` from its last node's optimized pose.
    fn update_global_from_local(&mut self) {
        for (&trajectory, last) in &self.last_node {
            if let (Some(global), Some(record)) = (
                self.graph.pose(VariableId::Node(*last)),
                self.nodes.get(last),
            ) {
                self.global_from_local
                    .insert(trajectory, global * record.local_pose.inverse());
            }
        }
    }

    /// Optimizes with at most `max_iterations` Levenberg–Marquardt steps (the same options otherwise), as
    /// after a batch of sparsifications; does not reset the periodic-optimization counter.
    pub fn optimize_capped(&mut self, max_iterations: usize) -> OptimizationSummary {
        let stale = self
            .capped_optimizer
            .as_ref()
            .is_none_or(|o| o.options().max_iterations != max_iterations);
        if stale {
            let options = crate::pose_graph::OptimizerOptions {
                max_iterations,
                ..self.options.optimizer.clone()
            };
            // The options were validated at construction and max_iterations is not checked.
            self.capped_optimizer = Optimizer::new(options).ok();
        }
        let summary = match self.capped_optimizer.as_mut() {
            Some(optimizer) => optimizer.optimize(&mut self.graph),
            None => self.optimizer.optimize(&mut self.graph),
        };
        self.update_global_from_local();
        summary
    }

    /// Holds every variable of a trajectory fixed (or frees it) in later optimizations.
    pub fn set_trajectory_fixed(&mut self, trajectory: u32, fixed: bool) {
        let ids: Vec<VariableId> = self
            .graph
            .variables()
            .filter(|(id, _, _)| match id {
                VariableId::Node(n) => n.trajectory == trajectory,
                VariableId::Submap(s) => s.trajectory == trajectory,
            })
            .map(|(id, _, _)| id)
            .collect();
        for id in ids {
            // Cannot fail: the id came from the graph.
            let _ = self.graph.set_fixed(id, fixed);
        }
    }

    /// Forgets submaps and nodes whose variables the caller has removed from (or is about to remove
    /// from) [`Self::graph_mut`]: their records, branch-and-bound matchers, samplers and queued searches.
    pub fn forget(&mut self, submaps: &[SubmapId], nodes: &[NodeId]) {
        for sid in submaps {
            self.submaps.remove(sid);
            self.samplers.remove(sid);
            self.builder.remove_submap(*sid);
        }
        for node in nodes {
            self.nodes.remove(node);
        }
        let submaps: BTreeSet<SubmapId> = submaps.iter().copied().collect();
        let nodes: BTreeSet<NodeId> = nodes.iter().copied().collect();
        self.pending_jobs
            .retain(|j| !submaps.contains(&j.submap) && !nodes.contains(&j.node));
    }

    /// The pose graph, for editing by trimming and sparsification. Keep it consistent with the records:
    /// remove variables only together with [`Self::forget`].
    pub fn graph_mut(&mut self) -> &mut PoseGraph {
        &mut self.graph
    }

    /// `global_from_local` of a trajectory: where its LLO frame sits in the map (identity before its first
    /// optimization).
    pub fn global_from_local(&self, trajectory: u32) -> Rigid2 {
        self.global_from_local
            .get(&trajectory)
            .copied()
            .unwrap_or_else(Rigid2::identity)
    }

    /// Current global pose of a node.
    pub fn node_pose(&self, id: NodeId) -> Option<Rigid2> {
        self.graph.pose(VariableId::Node(id))
    }

    /// Current global pose of a submap.
    pub fn submap_pose(&self, id: SubmapId) -> Option<Rigid2> {
        self.graph.pose(VariableId::Submap(id))
    }

    /// All nodes, by id.
    pub fn nodes(&self) -> &BTreeMap<NodeId, NodeRecord> {
        &self.nodes
    }

    /// All submaps, by id.
    pub fn submaps(&self) -> &BTreeMap<SubmapId, SubmapRecord> {
        &self.submaps
    }

    /// The pose graph.
    pub fn graph(&self) -> &PoseGraph {
        &self.graph
    }

    /// Loop-closure searches queued so far.
    pub fn searches_queued(&self) -> usize {
        self.searches_queued
    }

    /// Scores of every accepted loop closure, in acceptance order (their mean is the paper's AMS).
    pub fn loop_closure_scores(&self) -> &[f32] {
        &self.loop_closure_scores
    }
}
