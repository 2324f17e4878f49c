//! The global SLAM state machine.

mod closure_acceptance;
mod correction_probation;
mod global_slam_state;
mod match_decision;
mod node_insertion;
mod optimization;
mod search_queue;
mod submap_bend;
mod trajectory_placement;

pub use global_slam_state::GlobalSlamState;
pub use match_decision::{MatchDecided, MatchDecision};

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use nalgebra::{Matrix3, Point2};

use super::{
    ConstraintBuilder, FixedRatioSampler, GlobalSlamOptions, GlobalSlamOptionsError, LoopClosure,
    LoopClosureCheck, SearchJob,
};
use crate::geometry::Rigid2;
use crate::grid::ProbabilityGrid;
use crate::local_slam::LloNode;
use crate::pose_graph::{
    Constraint, ConstraintId, NodeId, OptimizationSummary, Optimizer, PoseGraph, PoseGraphError,
    SubmapId, VariableId,
};
use crate::sensor::Timestamp;
pub use correction_probation::CorrectionProbation;
pub use submap_bend::{BendGrowth, SubmapBend};

/// What global SLAM knows about a node.
#[derive(Clone, Debug, PartialEq)]
pub struct NodeRecord {
    /// When the node's scan was taken.
    pub time: Timestamp,
    /// `local_from_tracking` from LLO.
    pub local_pose: Rigid2,
    /// The node's filtered scan points in its tracking frame (what GLM matches).
    pub points: Arc<Vec<Point2<f32>>>,
    /// Submaps the node was inserted into.
    pub submaps: Vec<SubmapId>,
    /// Distance (m) travelled along the trajectory from its first node to this one.
    pub path_m: f64,
}

/// What global SLAM knows about a submap.
#[derive(Clone, Debug, PartialEq)]
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
    /// A search's match reached the acceptance rules and one of them decided it (one event per match).
    MatchDecided(MatchDecided),
    /// The graph was optimized.
    Optimized(OptimizationSummary),
}

/// How a loop closure was accepted: how far it moved its node from the estimate of the moment, and
/// whether it waited for another match to agree with it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Acceptance {
    /// Translation (m) between the match and the node's estimate in the submap's frame when it arrived.
    pub innovation_translation_m: f64,
    /// Absolute rotation (rad) between the two.
    pub innovation_rotation_rad: f64,
    /// Whether it was held until a match of another node agreed with it.
    pub confirmed_by_agreement: bool,
}

impl Acceptance {
    /// How far a match moves its node: `innovation` is the match's pose of the node relative to the
    /// node's estimate (`None` for unknown nodes or submaps, which move nothing).
    pub fn of_innovation(innovation: Option<&Rigid2>) -> Self {
        innovation.map_or_else(Self::default, |innovation| Self {
            innovation_translation_m: innovation.translation.vector.norm(),
            innovation_rotation_rad: innovation.rotation.angle().abs(),
            confirmed_by_agreement: false,
        })
    }
}

/// Where an accepted loop closure stands.
#[derive(Clone, Debug, PartialEq)]
pub enum ClosureState {
    /// In the graph as this constraint.
    InGraph(ConstraintId),
    /// Taken out because the optimized graph refused it; put back once the graph fits it again.
    Retracted(Constraint),
    /// Its node or submap was trimmed.
    Gone,
}

/// Errors of [`GlobalSlam`].
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GlobalSlamError {
    /// The options are invalid.
    #[error(transparent)]
    Options(#[from] GlobalSlamOptionsError),
    /// A state to restore ([`GlobalSlam::from_state`]) contradicts itself.
    #[error("inconsistent global SLAM state: {0}")]
    InconsistentState(String),
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
    /// The accepted loop closures whose node and submap are still known (see [`GlobalSlam::forget`]).
    accepted_loop_closures: Vec<LoopClosure>,
    /// Loop closures accepted so far, forgotten ones included.
    loop_closures_accepted: usize,
    /// How each accepted loop closure was accepted, parallel to `accepted_loop_closures`.
    acceptances: Vec<Acceptance>,
    /// Where each accepted loop closure stands, parallel to `accepted_loop_closures`.
    closure_states: Vec<ClosureState>,
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
    /// Per trajectory, the path length (m) of its latest node with an accepted loop closure that closed a
    /// loop (see `min_loop_length`): drift, and so the search window, grows from there.
    last_loop_path: BTreeMap<u32, f64>,
    /// Per trajectory, the path length (m) of the node before its first LLO recovery since its last loop
    /// closure (see `recovery_heading_doubt`).
    recovery_path: BTreeMap<u32, f64>,
    /// Per trajectory placed by a search ([`GlobalSlam::place_trajectory`], or on its robot:
    /// [`GlobalSlam::set_placement_fit`]): the first and last index of the nodes whose scans the search
    /// fitted to the map at the placement. No drift separates them from other trajectories' submaps, and
    /// no chorus of matches beyond that bound moves them (see [`GlobalSlam::fitted_by_placement`]).
    placement_fits: BTreeMap<u32, (u32, u32)>,
    /// Matches refused because they moved their node farther than drift can explain: those still waiting
    /// for a chorus or given up, not those a chorus confirmed later.
    closures_beyond_drift: usize,
    /// Those matches, waiting for enough others to agree with them (`beyond_drift_confirmations`).
    pending_beyond_drift: Vec<(LoopClosure, Acceptance)>,
    /// Matches refused because other matches of their node disagreed with them.
    closures_outvoted: usize,
    /// Matches that would move their node far from its estimate, waiting for another to agree with them.
    pending_unconfirmed: Vec<(LoopClosure, Acceptance)>,
    /// Trajectories an optimization holds still away from what is new (see
    /// [`GlobalSlam::set_trajectory_settled`]).
    settled: BTreeSet<u32>,
    /// The first constraint added after the last optimization: those from here on are new to it.
    new_constraints_from: ConstraintId,
    /// Variables whose constraints changed since the last optimization other than by an addition (a
    /// retracted closure, a deleted neighbour): optimizations move them and their neighbourhood.
    changed: BTreeSet<VariableId>,
    /// Confirmed corrections the nodes after them are judging, or have kept (see
    /// [`CorrectionProbation`]).
    probations: Vec<CorrectionProbation>,
    /// The bends confirmed corrections granted (see [`SubmapBend`]), in confirmation order.
    submap_bends: Vec<SubmapBend>,
    /// The submaps a bend holds loosely now (rebuilt from `submap_bends` and the closures' states).
    bent_submaps: BTreeMap<SubmapId, BendGrowth>,
}

/// The (node, submap) pair of each of `closures`: how corrections and bends name the matches they hold.
pub(super) fn closure_refs<'a>(
    closures: impl IntoIterator<Item = &'a LoopClosure>,
) -> BTreeSet<(NodeId, SubmapId)> {
    closures.into_iter().map(|c| (c.node, c.submap)).collect()
}

pub(super) fn information(translation_sigma: f64, rotation_sigma: f64) -> Matrix3<f64> {
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
        let optimizer =
            Optimizer::new(options.optimizer.clone()).map_err(GlobalSlamOptionsError::from)?;
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
            accepted_loop_closures: Vec::new(),
            loop_closures_accepted: 0,
            acceptances: Vec::new(),
            closure_states: Vec::new(),
            searches_queued: 0,
            unanchored: BTreeSet::new(),
            capped_optimizer: None,
            matched_elsewhere: BTreeSet::new(),
            last_loop_path: BTreeMap::new(),
            recovery_path: BTreeMap::new(),
            placement_fits: BTreeMap::new(),
            pending_unconfirmed: Vec::new(),
            closures_beyond_drift: 0,
            pending_beyond_drift: Vec::new(),
            settled: BTreeSet::new(),
            new_constraints_from: ConstraintId(0),
            changed: BTreeSet::new(),
            closures_outvoted: 0,
            probations: Vec::new(),
            submap_bends: Vec::new(),
            bent_submaps: BTreeMap::new(),
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

    /// Adds a node of `trajectory` as LLO inserted it, together with the submaps its insertion finished.
    /// Queues the loop-closure searches it makes possible (see [`Self::take_search_jobs`]).
    pub fn add_node(
        &mut self,
        trajectory: u32,
        node: LloNode,
    ) -> Result<(NodeId, Vec<GlobalSlamEvent>), GlobalSlamError> {
        let LloNode {
            time,
            local_pose,
            points,
            insertion_submaps,
            finished_submaps,
            recovered,
        } = node;
        if recovered {
            self.note_llo_recovery(trajectory);
        }
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

        let path_m = self.path_m_at(trajectory, &local_pose);
        let node_submaps = self.insert_into_submaps(
            id,
            local_pose,
            path_m,
            global_from_local,
            &insertion_submaps,
            &mut events,
        )?;
        self.add_odometry_constraint(id, local_pose)?;
        self.nodes.insert(
            id,
            NodeRecord {
                time,
                local_pose,
                points: Arc::new(points),
                submaps: node_submaps,
                path_m,
            },
        );
        self.last_node.insert(trajectory, id);
        self.judge_corrections_by_node(id);

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

    /// Runs every queued search on this thread and adds the results.
    pub fn run_pending_searches(&mut self) -> Vec<GlobalSlamEvent> {
        let jobs = self.take_search_jobs();
        let results: Vec<LoopClosure> = jobs.iter().filter_map(|j| self.builder.run(j)).collect();
        self.add_search_results(results)
    }

    /// Forgets submaps and nodes whose variables the caller has removed from (or is about to remove
    /// from) [`Self::graph_mut`]: their records, branch-and-bound matchers, samplers and queued searches,
    /// and the accepted loop closures (and matches still waiting for agreement) of either. A lifelong
    /// map trims submaps session after session, so what it remembers of them must go with them: kept,
    /// the record of every closure ever accepted grows with the site's life (issue 16 §5).
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
        let gone = |c: &LoopClosure| submaps.contains(&c.submap) || nodes.contains(&c.node);
        self.pending_beyond_drift.retain(|(c, _)| !gone(c));
        self.pending_unconfirmed.retain(|(c, _)| !gone(c));
        if self.accepted_loop_closures.iter().any(gone) {
            let kept: Vec<_> = std::mem::take(&mut self.accepted_loop_closures)
                .into_iter()
                .zip(std::mem::take(&mut self.acceptances))
                .zip(std::mem::take(&mut self.closure_states))
                .filter(|((closure, _), _)| !gone(closure))
                .collect();
            for ((closure, acceptance), state) in kept {
                self.accepted_loop_closures.push(closure);
                self.acceptances.push(acceptance);
                self.closure_states.push(state);
            }
            self.forget_probations();
        }
        self.forget_bends();
        self.sync_bends();
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

    /// The nodes of one trajectory, in index order.
    pub fn trajectory_nodes(
        &self,
        trajectory: u32,
    ) -> std::collections::btree_map::Range<'_, NodeId, NodeRecord> {
        self.nodes.range(
            NodeId {
                trajectory,
                index: 0,
            }..=NodeId {
                trajectory,
                index: u32::MAX,
            },
        )
    }

    /// All submaps, by id.
    pub fn submaps(&self) -> &BTreeMap<SubmapId, SubmapRecord> {
        &self.submaps
    }

    /// The pose graph.
    pub fn graph(&self) -> &PoseGraph {
        &self.graph
    }

    /// Matches refused so far because they moved their node farther from its estimate than the drift since
    /// the last loop can explain (`max_innovation_translation`, `max_innovation_rotation`).
    pub fn closures_beyond_drift(&self) -> usize {
        self.closures_beyond_drift
    }

    /// Matches refused so far because other matches of their node, handed in together, disagreed with them
    /// (see `add_search_results`).
    pub fn closures_outvoted(&self) -> usize {
        self.closures_outvoted
    }

    /// Loop-closure searches queued so far.
    pub fn searches_queued(&self) -> usize {
        self.searches_queued
    }

    /// The accepted loop closures, in acceptance order (the mean of their scores is the paper's AMS),
    /// but those whose node or submap was forgotten since ([`Self::forget`]: trimmed or dropped); a map
    /// that forgets nothing (a single-session run) keeps every one.
    pub fn accepted_loop_closures(&self) -> &[LoopClosure] {
        &self.accepted_loop_closures
    }

    /// How many loop closures were accepted so far, those forgotten since included.
    pub fn loop_closures_accepted(&self) -> usize {
        self.loop_closures_accepted
    }

    /// Every accepted loop closure whose node and submap are still in the graph (and whose trajectory was
    /// not unplaced since), judged against the current (optimized) poses: how far the optimized graph
    /// violates it (retracted ones included, marked).
    pub fn loop_closure_checks(&self) -> Vec<LoopClosureCheck> {
        self.accepted_loop_closures
            .iter()
            .zip(&self.acceptances)
            .zip(&self.closure_states)
            .filter(|(_, state)| !matches!(state, ClosureState::Gone))
            .filter_map(|((closure, acceptance), state)| {
                let submap = self.submap_pose(closure.submap)?;
                let node = self.node_pose(closure.node)?;
                let residual = closure.submap_from_node.inverse() * submap.inverse() * node;
                Some(LoopClosureCheck {
                    closure: closure.clone(),
                    acceptance: *acceptance,
                    residual_translation_m: residual.translation.vector.norm(),
                    residual_rotation_rad: residual.rotation.angle().abs(),
                    retracted: matches!(state, ClosureState::Retracted(_)),
                })
            })
            .collect()
    }
}

#[cfg(test)]
pub(crate) mod tests;
