//! [`GlobalSlam`] as plain data, and back: what a checkpoint of a site stores of global SLAM.
//!
//! The state holds every field whose value a replay of the same inputs would rebuild and that changes
//! what the map does later; the rest is rebuilt deterministically from it (see ARCHITECTURE.md,
//! "Checkpoints: what a site's state is"):
//!
//! - stored: the pose graph (variables with poses and fixed flags, constraints under their ids, the
//!   next id), node and submap records (grids included), the per-submap samplers' counts, each
//!   trajectory's `global_from_local` and last node, the queued searches, the accepted loop closures
//!   with how they were accepted and where each stands, the matches waiting for agreement, the
//!   unanchored, matched-elsewhere and settled trajectories, each trajectory's last loop's path and the
//!   nodes that fitted its placement, the
//!   corrections on probation or kept, the bends confirmed corrections granted, the optimization bookkeeping (nodes since the last optimization, the first constraint new to the next
//!   one, the variables changed since) and the counters;
//! - rebuilt: which submaps a bend holds loosely now (from the bends and the closures' states; their
//!   constraints in the graph already carry it), the branch-and-bound matchers of the constraint builder (from the finished submaps' grids
//!   and local poses, as [`GlobalSlam`] built them), the optimizers (from the options; their cached
//!   symbolic factorization is keyed by the block pattern and rebuilt on first use, their work buffers
//!   are overwritten every step), and the options themselves (the caller's: a state restored with other
//!   options than it was taken with is not what a replay with either would give).
//!
//! Maps are ordered (`BTreeMap`/`BTreeSet`), so iteration order round-trips; every value is copied, so
//! `f32`/`f64` values and ids round-trip bit for bit.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use super::{
    Acceptance, BendGrowth, ClosureState, CorrectionProbation, GlobalSlam, GlobalSlamError,
    NodeRecord, SubmapBend, SubmapRecord, closure_refs, submap_bend,
};
use crate::geometry::Rigid2;
use crate::global_slam::{
    ConstraintBuilder, FixedRatioSampler, GlobalSlamOptions, GlobalSlamOptionsError, LoopClosure,
    SearchJob,
};
use crate::pose_graph::{ConstraintId, NodeId, Optimizer, PoseGraph, SubmapId, VariableId};

/// Everything [`GlobalSlam`] holds that is not rebuilt from the options or from the rest (see the module
/// docs). Take it with [`GlobalSlam::to_state`], restore it with [`GlobalSlam::from_state`]. The fields
/// mirror [`GlobalSlam`]'s private ones and carry their meaning.
#[derive(Clone, Debug, PartialEq)]
pub struct GlobalSlamState {
    /// The pose graph.
    pub graph: PoseGraph,
    /// Node records, by id.
    pub nodes: BTreeMap<NodeId, NodeRecord>,
    /// Submap records (finished grids included), by id.
    pub submaps: BTreeMap<SubmapId, SubmapRecord>,
    /// The per-submap loop-closure samplers (which later searches are queued depends on their counts).
    pub samplers: BTreeMap<SubmapId, FixedRatioSampler>,
    /// `global_from_local` per trajectory (absent: identity).
    pub global_from_local: BTreeMap<u32, Rigid2>,
    /// The newest node per trajectory (kept after the node itself is trimmed: indices continue).
    pub last_node: BTreeMap<u32, NodeId>,
    /// Searches queued and not yet taken (their points are the node's: shared again on restore).
    pub pending_jobs: Vec<SearchJob>,
    /// Nodes added since the last periodic optimization.
    pub nodes_since_optimization: usize,
    /// Accepted loop closures whose node and submap are still known, in acceptance order.
    pub accepted_loop_closures: Vec<LoopClosure>,
    /// Loop closures accepted so far, forgotten ones included.
    pub loop_closures_accepted: usize,
    /// How each accepted closure was accepted (parallel to `accepted_loop_closures`).
    pub acceptances: Vec<Acceptance>,
    /// Where each accepted closure stands (parallel to `accepted_loop_closures`).
    pub closure_states: Vec<ClosureState>,
    /// Searches queued so far.
    pub searches_queued: usize,
    /// Trajectories not placed in the map yet.
    pub unanchored: BTreeSet<u32>,
    /// Trajectories whose cross-trajectory matches are found elsewhere (GLM on the robot).
    pub matched_elsewhere: BTreeSet<u32>,
    /// Per trajectory, the path (m) of its latest node that closed a loop.
    pub last_loop_path: BTreeMap<u32, f64>,
    /// Per trajectory, the path (m) of the node before its first LLO recovery since its last loop.
    pub recovery_path: BTreeMap<u32, f64>,
    /// Per trajectory placed by a search, the first and last index of the nodes whose scans fitted the
    /// placement.
    pub placement_fits: BTreeMap<u32, (u32, u32)>,
    /// Matches refused as beyond drift, still counted.
    pub closures_beyond_drift: usize,
    /// Matches beyond drift waiting for others to agree, in arrival order.
    pub pending_beyond_drift: Vec<(LoopClosure, Acceptance)>,
    /// Matches outvoted so far.
    pub closures_outvoted: usize,
    /// Matches far from the estimate waiting for another to agree, in arrival order.
    pub pending_unconfirmed: Vec<(LoopClosure, Acceptance)>,
    /// Trajectories an optimization holds still away from what is new.
    pub settled: BTreeSet<u32>,
    /// The first constraint new to the next optimization.
    pub new_constraints_from: ConstraintId,
    /// Variables whose constraints changed since the last optimization other than by an addition.
    pub changed: BTreeSet<VariableId>,
    /// Confirmed corrections on probation or kept, in confirmation order.
    pub correction_probations: Vec<CorrectionProbation>,
    /// The bends confirmed corrections granted, in confirmation order.
    pub submap_bends: Vec<SubmapBend>,
}

impl GlobalSlam {
    /// Everything needed to rebuild this map exactly with [`Self::from_state`] (grids and scan points are
    /// shared, not copied).
    pub fn to_state(&self) -> GlobalSlamState {
        GlobalSlamState {
            graph: self.graph.clone(),
            nodes: self.nodes.clone(),
            submaps: self.submaps.clone(),
            samplers: self.samplers.clone(),
            global_from_local: self.global_from_local.clone(),
            last_node: self.last_node.clone(),
            pending_jobs: self.pending_jobs.clone(),
            nodes_since_optimization: self.nodes_since_optimization,
            accepted_loop_closures: self.accepted_loop_closures.clone(),
            loop_closures_accepted: self.loop_closures_accepted,
            acceptances: self.acceptances.clone(),
            closure_states: self.closure_states.clone(),
            searches_queued: self.searches_queued,
            unanchored: self.unanchored.clone(),
            matched_elsewhere: self.matched_elsewhere.clone(),
            last_loop_path: self.last_loop_path.clone(),
            recovery_path: self.recovery_path.clone(),
            placement_fits: self.placement_fits.clone(),
            closures_beyond_drift: self.closures_beyond_drift,
            pending_beyond_drift: self.pending_beyond_drift.clone(),
            closures_outvoted: self.closures_outvoted,
            pending_unconfirmed: self.pending_unconfirmed.clone(),
            settled: self.settled.clone(),
            new_constraints_from: self.new_constraints_from,
            changed: self.changed.clone(),
            correction_probations: self.probations.clone(),
            submap_bends: self.submap_bends.clone(),
        }
    }

    /// The map `state` was taken from, with `options` (which must be those it ran with: see the module
    /// docs). Rebuilds the branch-and-bound matchers of every finished submap. Fails on invalid options
    /// and on a state that contradicts itself (records without their graph variable, queued searches or
    /// closures of unknown nodes or submaps, parallel lists of different lengths).
    pub fn from_state(
        options: GlobalSlamOptions,
        state: GlobalSlamState,
    ) -> Result<Self, GlobalSlamError> {
        validate(&state)?;
        options.validate()?;
        let optimizer =
            Optimizer::new(options.optimizer.clone()).map_err(GlobalSlamOptionsError::from)?;
        let mut builder = ConstraintBuilder::new(options.constraint_builder.clone());
        for (id, record) in &state.submaps {
            if let Some(grid) = &record.grid {
                builder.add_finished_submap(*id, record.local_pose, Arc::clone(grid));
            }
        }
        let GlobalSlamState {
            graph,
            nodes,
            submaps,
            samplers,
            global_from_local,
            last_node,
            mut pending_jobs,
            nodes_since_optimization,
            accepted_loop_closures,
            loop_closures_accepted,
            acceptances,
            closure_states,
            searches_queued,
            unanchored,
            matched_elsewhere,
            last_loop_path,
            recovery_path,
            placement_fits,
            closures_beyond_drift,
            pending_beyond_drift,
            closures_outvoted,
            pending_unconfirmed,
            settled,
            new_constraints_from,
            changed,
            correction_probations,
            mut submap_bends,
        } = state;
        // A checkpoint written before bends stored their growth holds none: those bends grew at the fixed
        // rates, and go on doing so.
        for bend in &mut submap_bends {
            if bend.growth == BendGrowth::default() {
                bend.growth = submap_bend::fixed_growth(&options);
            }
        }
        // A queued search matches its node's points: share them again (a decoded state has copies).
        for job in &mut pending_jobs {
            if let Some(record) = nodes.get(&job.node) {
                job.points = Arc::clone(&record.points);
            }
        }
        let mut global = Self {
            options,
            graph,
            optimizer,
            builder,
            nodes,
            submaps,
            samplers,
            global_from_local,
            last_node,
            pending_jobs,
            nodes_since_optimization,
            accepted_loop_closures,
            loop_closures_accepted,
            acceptances,
            closure_states,
            searches_queued,
            unanchored,
            capped_optimizer: None,
            matched_elsewhere,
            last_loop_path,
            recovery_path,
            placement_fits,
            closures_beyond_drift,
            pending_beyond_drift,
            closures_outvoted,
            probations: correction_probations,
            pending_unconfirmed,
            settled,
            new_constraints_from,
            changed,
            submap_bends,
            bent_submaps: BTreeMap::new(),
        };
        global.bent_submaps = global.bent_by_evidence();
        Ok(global)
    }
}

fn validate(state: &GlobalSlamState) -> Result<(), GlobalSlamError> {
    let inconsistent = |what: String| Err(GlobalSlamError::InconsistentState(what));
    if let Some(id) = state
        .nodes
        .keys()
        .find(|id| !state.graph.contains_variable(VariableId::Node(**id)))
    {
        return inconsistent(format!("node {id:?} has no graph variable"));
    }
    if let Some(id) = state
        .submaps
        .keys()
        .find(|id| !state.graph.contains_variable(VariableId::Submap(**id)))
    {
        return inconsistent(format!("submap {id:?} has no graph variable"));
    }
    if let Some(job) = state
        .pending_jobs
        .iter()
        .find(|j| !state.nodes.contains_key(&j.node) || !state.submaps.contains_key(&j.submap))
    {
        return inconsistent(format!(
            "queued search of node {:?} against submap {:?}: unknown",
            job.node, job.submap
        ));
    }
    let closures = state.accepted_loop_closures.len();
    if state.acceptances.len() != closures || state.closure_states.len() != closures {
        return inconsistent(format!(
            "{closures} accepted loop closures, {} acceptances, {} closure states",
            state.acceptances.len(),
            state.closure_states.len()
        ));
    }
    let accepted = closure_refs(&state.accepted_loop_closures);
    let held = [
        (
            "correction on probation holds",
            state
                .correction_probations
                .iter()
                .flat_map(|p| &p.closures)
                .collect::<Vec<_>>(),
        ),
        (
            "submap bend granted by",
            state
                .submap_bends
                .iter()
                .flat_map(|b| &b.closures)
                .collect(),
        ),
    ];
    for (holder, closures) in held {
        if let Some((node, submap)) = closures.into_iter().find(|c| !accepted.contains(c)) {
            return inconsistent(format!(
                "{holder} the match of node {node:?} against submap {submap:?}, not an accepted closure"
            ));
        }
    }
    if state.new_constraints_from > state.graph.next_constraint_id() {
        return inconsistent(format!(
            "first new constraint {:?} beyond the next id {:?}",
            state.new_constraints_from,
            state.graph.next_constraint_id()
        ));
    }
    Ok(())
}
