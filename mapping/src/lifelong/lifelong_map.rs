//! One site's multi-session map: sessions, trimming and sparsification around [`GlobalSlam`].

mod lifelong_map_state;

pub use lifelong_map_state::{LifelongMapState, SessionProgress};

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use thiserror::Error;

use super::{
    LifelongOptions, LifelongOptionsError, PlacedGrid, SessionStartEvent, TrimPolicy,
    covered_fraction,
};
use crate::geometry::Rigid2;
use crate::global_slam::{
    ConstraintBuilder, GlobalSlam, GlobalSlamError, GlobalSlamEvent, LoopClosure, MatchDecided,
    SearchJob,
};
use crate::grid::ProbabilityGrid;
use crate::local_slam::LloNode;
use crate::pose_graph::{
    Constraint, ConstraintId, ConstraintKind, NodeId, OptimizationSummary, PoseGraph, SubmapId,
    VariableId,
};
use crate::sensor::Timestamp;
use crate::sparsification::{self, ParallelMerge, SparsificationError};

/// Errors of [`LifelongMap`].
#[derive(Debug, Error)]
pub enum LifelongError {
    /// The options are invalid.
    #[error(transparent)]
    Options(#[from] LifelongOptionsError),
    /// Global SLAM refused a node or a session.
    #[error(transparent)]
    Global(#[from] GlobalSlamError),
    /// Sparsifying or deleting a trimmed submap failed (the graph is unchanged for that submap).
    #[error("trimming submap {submap:?}: {source}")]
    Sparsification {
        /// The submap being trimmed.
        submap: SubmapId,
        /// Why.
        source: SparsificationError,
    },
    /// The session was already started.
    #[error("session {0} was already started")]
    SessionExists(u32),
    /// The session was never started.
    #[error("session {0} was never started")]
    UnknownSession(u32),
    /// The session has ended.
    #[error("session {0} has already finished")]
    SessionFinished(u32),
}

/// Something the map did that the shell may forward, store or display.
#[derive(Clone, Debug)]
pub enum LifelongEvent {
    /// A new submap variable joined the graph.
    SubmapAdded(SubmapId),
    /// A submap was finished and can now be matched against.
    SubmapFinished(SubmapId),
    /// A GLM constraint (loop closure, or a later session's localization) was accepted.
    LoopClosureAdded(LoopClosure),
    /// A GLM match reached the acceptance rules and one of them decided it.
    MatchDecided(MatchDecided),
    /// A submap was removed from the map with the nodes only it held.
    SubmapTrimmed {
        /// The submap.
        submap: SubmapId,
        /// Whether it was dropped with its own session, which does not update the map (never placed, or
        /// any later session with `frozen`), rather than trimmed as stale.
        dropped: bool,
        /// The nodes that went with it, each at the pose the map held it at when it went (after the
        /// optimization that precedes the trim): where a trajectory's trimmed scans stay.
        removed_nodes: Vec<(NodeId, Rigid2)>,
        /// Chow–Liu tree constraints added in their place (0 for `delete` and `frozen`).
        tree_edges: usize,
        /// KL divergence (nats) of the replacement against the exact marginal: over the blanket for
        /// `clt`, over the whole remaining graph with `whole_graph_kld` (then also for `delete`);
        /// `None` when not measured.
        kld: Option<f64>,
    },
    /// The graph was optimized.
    Optimized(OptimizationSummary),
}

impl LifelongEvent {
    /// The match this event hands to `session`'s placement judge ([`super::SessionStart::add_match`]): a
    /// match of one of its nodes against another session's submap, added to the graph.
    pub fn placement_match(&self, session: u32) -> Option<&LoopClosure> {
        match self {
            Self::LoopClosureAdded(c)
                if c.node.trajectory == session && c.submap.trajectory != session =>
            {
                Some(c)
            }
            _ => None,
        }
    }
}

impl From<GlobalSlamEvent> for LifelongEvent {
    fn from(event: GlobalSlamEvent) -> Self {
        match event {
            GlobalSlamEvent::SubmapAdded(id) => Self::SubmapAdded(id),
            GlobalSlamEvent::SubmapFinished(id) => Self::SubmapFinished(id),
            GlobalSlamEvent::LoopClosureAdded(c) => Self::LoopClosureAdded(c),
            GlobalSlamEvent::MatchDecided(d) => Self::MatchDecided(d),
            GlobalSlamEvent::Optimized(s) => Self::Optimized(s),
        }
    }
}

/// Size of the map's pose graph.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct GraphCounts {
    /// Node variables.
    pub nodes: usize,
    /// Submap variables.
    pub submaps: usize,
    /// Constraints.
    pub constraints: usize,
    /// Those constraints by where they come from (what grows when the graph's size per node does).
    pub constraints_by_kind: ConstraintKindCounts,
    /// Stale submaps trimmed since the map was created (`clt`, `delete`).
    pub trimmed_total: usize,
    /// Submaps of sessions that did not update the map, dropped at their end (a session never placed;
    /// every later session with `frozen`).
    pub dropped_total: usize,
}

/// A pose graph's constraints counted by [`ConstraintKind`]. Sparsification's tree edges are node-to-node,
/// submap-to-submap or node-to-submap (`inter`, beside GLM's loop closures).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct ConstraintKindCounts {
    /// A node against a submap of its own trajectory while the submap was built (LLO).
    pub node_to_submap_intra: usize,
    /// A node against a submap by GLM, or a tree edge between a node and a submap.
    pub node_to_submap_inter: usize,
    /// Consecutive nodes' odometry.
    pub odometry: usize,
    /// Node to node (tree edges).
    pub node_to_node: usize,
    /// Submap to submap (tree edges).
    pub submap_to_submap: usize,
}

impl ConstraintKindCounts {
    /// Counts `graph`'s constraints.
    pub fn of(graph: &PoseGraph) -> Self {
        let mut counts = Self::default();
        for (_, constraint) in graph.constraints() {
            *match constraint.kind {
                ConstraintKind::NodeToSubmapIntra => &mut counts.node_to_submap_intra,
                ConstraintKind::NodeToSubmapInter => &mut counts.node_to_submap_inter,
                ConstraintKind::Odometry => &mut counts.odometry,
                ConstraintKind::NodeToNode => &mut counts.node_to_node,
                ConstraintKind::SubmapToSubmap => &mut counts.submap_to_submap,
            } += 1;
        }
        counts
    }
}

#[derive(Clone, Copy, Debug)]
struct Session {
    /// Position in start order (0 for the first session).
    order: usize,
    finished: bool,
}

/// One site's multi-session map (session id = trajectory id of the pose graph). See the module docs of
/// [`crate::lifelong`].
pub struct LifelongMap {
    options: LifelongOptions,
    global: GlobalSlam,
    sessions: BTreeMap<u32, Session>,
    /// The first session started: it maps the site and is never trimmed.
    base: Option<u32>,
    /// Sessions placed tentatively (see [`super::SessionStart`]): in the graph, matched by GLM, but their
    /// submaps stay out of [`LifelongMap::placed_submaps`] and they trim nothing.
    probation: BTreeSet<u32>,
    trimmed_total: usize,
    dropped_total: usize,
    sparsifications_since_optimization: usize,
}

impl LifelongMap {
    /// An empty map.
    pub fn new(options: LifelongOptions) -> Result<Self, LifelongError> {
        options.validate()?;
        Ok(Self {
            global: GlobalSlam::new(options.global.clone())?,
            options,
            sessions: BTreeMap::new(),
            base: None,
            probation: BTreeSet::new(),
            trimmed_total: 0,
            dropped_total: 0,
            sparsifications_since_optimization: 0,
        })
    }

    /// The options.
    pub fn options(&self) -> &LifelongOptions {
        &self.options
    }

    /// Starts a session. `global_from_local`: the relocalized prior (None for session 0 / when
    /// relocalization failed; then the session's first node is placed by the first accepted GLM match,
    /// or by identity for session 0).
    pub fn start_session(
        &mut self,
        session: u32,
        global_from_local: Option<Rigid2>,
    ) -> Result<Vec<LifelongEvent>, LifelongError> {
        if self.sessions.contains_key(&session) {
            return Err(LifelongError::SessionExists(session));
        }
        self.global.start_trajectory(session, global_from_local)?;
        let order = self.sessions.len();
        self.sessions.insert(
            session,
            Session {
                order,
                finished: false,
            },
        );
        if self.base.is_none() {
            self.base = Some(session);
        }
        Ok(Vec::new())
    }

    /// Declares that `session`'s matches against the rest of the map come from GLM on its robot (see
    /// [`GlobalSlam::set_matched_elsewhere`]); hand them in with [`Self::add_search_results`].
    pub fn set_matched_on_robot(&mut self, session: u32) {
        self.global.set_matched_elsewhere(session);
    }

    /// Whether `session` has been started (finished or not).
    pub fn is_started(&self, session: u32) -> bool {
        self.sessions.contains_key(&session)
    }

    /// Whether `session` has been finished.
    pub fn is_finished(&self, session: u32) -> bool {
        self.sessions.get(&session).is_some_and(|s| s.finished)
    }

    /// Whether `session` started without a prior and no match has placed it in the map yet.
    pub fn is_unplaced(&self, session: u32) -> bool {
        self.global.is_unanchored(session)
    }

    /// Places an unplaced session at `global_from_local` (a relocalization found after its start), fitted
    /// with the scans of its nodes `fitted` (first and last index; `None`: placed without a search); see
    /// [`GlobalSlam::place_trajectory`]. Returns false when the session was already placed.
    pub fn place_session(
        &mut self,
        session: u32,
        global_from_local: Rigid2,
        fitted: Option<(u32, u32)>,
    ) -> Result<bool, LifelongError> {
        self.active(session)?;
        Ok(self
            .global
            .place_trajectory(session, global_from_local, fitted))
    }

    /// Records that `session`, started at a prior, was placed there by a search on its robot that fitted
    /// the scans of its nodes `fitted` (first and last index); see [`GlobalSlam::set_placement_fit`].
    /// Returns false when the session is unplaced.
    pub fn set_placement_fit(
        &mut self,
        session: u32,
        fitted: (u32, u32),
    ) -> Result<bool, LifelongError> {
        self.active(session)?;
        Ok(self.global.set_placement_fit(session, fitted))
    }

    /// Puts a placed session on probation ([`super::SessionStart`]): GLM matches its nodes near their
    /// estimates as before, but its submaps leave [`Self::placed_submaps`] (what relocalization renders)
    /// and the trimmer's view, and if it ends on probation it is dropped like an unplaced session.
    pub fn begin_probation(&mut self, session: u32) -> Result<(), LifelongError> {
        self.active(session)?;
        self.probation.insert(session);
        Ok(())
    }

    /// Commits a session's placement: ends its probation. Returns whether it was on probation.
    pub fn commit_session(&mut self, session: u32) -> bool {
        self.probation.remove(&session)
    }

    /// Revokes a session's placement found wrong: removes its matches against the other sessions (and
    /// theirs against it) and makes it unplaced again (see [`GlobalSlam::unplace_trajectory`]); it can
    /// be placed again with [`Self::place_session`]. Returns false when it was not placed.
    pub fn revoke_placement(&mut self, session: u32) -> Result<bool, LifelongError> {
        self.active(session)?;
        self.probation.remove(&session);
        Ok(self.global.unplace_trajectory(session))
    }

    /// Does to the map what one of a session's [`SessionStartEvent`] decisions says: `Placed` places it
    /// on probation, `Committed` ends its probation, `Revoked` unplaces it; the other decisions change
    /// nothing in the map. Every shell that runs a [`super::SessionStart`] acts on it through this.
    pub fn apply_start_decision(
        &mut self,
        session: u32,
        decision: &SessionStartEvent,
    ) -> Result<(), LifelongError> {
        match decision {
            SessionStartEvent::Placed(placement) => {
                self.place_session(
                    session,
                    placement.global_from_local,
                    placement.fitted_nodes(),
                )?;
                self.begin_probation(session)
            }
            SessionStartEvent::Committed { .. } => {
                self.commit_session(session);
                Ok(())
            }
            SessionStartEvent::Revoked { .. } => self.revoke_placement(session).map(|_| ()),
            SessionStartEvent::Refused { .. }
            | SessionStartEvent::DockChecked { .. }
            | SessionStartEvent::GaveUp { .. } => Ok(()),
        }
    }

    /// Whether a session is placed tentatively (on probation).
    pub fn is_on_probation(&self, session: u32) -> bool {
        self.probation.contains(&session)
    }

    /// Whether a session is placed and its placement committed (not on probation): its submaps are
    /// part of the map robots relocalize against.
    pub fn is_committed(&self, session: u32) -> bool {
        self.is_placed(session) && !self.probation.contains(&session)
    }

    /// From now on the session's nodes are matched against the other sessions here again (after
    /// [`Self::set_matched_on_robot`], when the robot's placement was revoked).
    pub fn set_matched_here(&mut self, session: u32) {
        self.global.clear_matched_elsewhere(session);
    }

    /// Whether `trajectory`'s submaps belong to the map others localize against: placed, not on
    /// probation.
    fn in_map(&self, trajectory: u32) -> bool {
        !self.global.is_unanchored(trajectory) && !self.probation.contains(&trajectory)
    }

    fn active(&self, session: u32) -> Result<Session, LifelongError> {
        match self.sessions.get(&session) {
            None => Err(LifelongError::UnknownSession(session)),
            Some(s) if s.finished => Err(LifelongError::SessionFinished(session)),
            Some(s) => Ok(*s),
        }
    }

    /// Same meaning as [`GlobalSlam::add_node`], for a session.
    pub fn add_node(
        &mut self,
        session: u32,
        node: LloNode,
    ) -> Result<(NodeId, Vec<LifelongEvent>), LifelongError> {
        self.active(session)?;
        let (id, events) = self.global.add_node(session, node)?;
        Ok((id, events.into_iter().map(Into::into).collect()))
    }

    /// Finishes submaps of an active session outside [`Self::add_node`], typically LLO's submaps still
    /// active when the session ends, so that later sessions can match against them.
    pub fn finish_submaps(
        &mut self,
        session: u32,
        finished_submaps: Vec<(usize, ProbabilityGrid)>,
    ) -> Result<Vec<LifelongEvent>, LifelongError> {
        self.active(session)?;
        Ok(self
            .global
            .add_finished_submaps(session, finished_submaps)
            .into_iter()
            .map(Into::into)
            .collect())
    }

    /// The GLM searches queued since the last call: pure, run them anywhere with
    /// [`Self::constraint_builder`] and hand the accepted ones to [`Self::add_search_results`].
    pub fn take_search_jobs(&mut self) -> Vec<SearchJob> {
        self.global.take_search_jobs()
    }

    /// The matcher that runs search jobs (`Sync`).
    pub fn constraint_builder(&self) -> &ConstraintBuilder {
        self.global.constraint_builder()
    }

    /// Adds accepted matches (and optimizes every `optimize_every_n_nodes` nodes).
    pub fn add_search_results(
        &mut self,
        results: impl IntoIterator<Item = LoopClosure>,
    ) -> Vec<LifelongEvent> {
        self.global
            .add_search_results(results)
            .into_iter()
            .map(Into::into)
            .collect()
    }

    /// Runs the queued GLM searches on the calling thread and adds the accepted ones, after the matches
    /// `found_elsewhere` (GLM on a robot; see [`Self::set_matched_on_robot`]), as one node's results: the
    /// sequential, deterministic form of [`Self::take_search_jobs`] + [`Self::add_search_results`].
    pub fn run_pending_searches(
        &mut self,
        found_elsewhere: impl IntoIterator<Item = LoopClosure>,
    ) -> Vec<LifelongEvent> {
        let jobs = self.global.take_search_jobs();
        let builder = self.global.constraint_builder();
        let found: Vec<LoopClosure> = found_elsewhere
            .into_iter()
            .chain(jobs.iter().filter_map(|job| builder.run(job)))
            .collect();
        self.add_search_results(found)
    }

    /// Optimizes the whole graph now.
    pub fn optimize(&mut self) -> OptimizationSummary {
        self.global.optimize()
    }

    /// Final optimization of the session, trimming of stale submaps it overlaps, sparsification per
    /// policy.
    pub fn finish_session(&mut self, session: u32) -> Result<Vec<LifelongEvent>, LifelongError> {
        self.active(session)?;
        let mut events = vec![LifelongEvent::Optimized(self.global.optimize())];
        let is_base = self.base == Some(session);
        if !is_base && !self.in_map(session) {
            // Never placed in the map, or its placement never confirmed: its submaps are in a frame
            // nothing (trustworthy) ties to the site, so they can neither update the map nor justify
            // trimming anything. Dropped whatever the policy.
            self.probation.remove(&session);
            events.extend(self.drop_session(session)?);
            if let Some(s) = self.sessions.get_mut(&session) {
                s.finished = true;
            }
            return Ok(events);
        }
        match self.options.policy {
            TrimPolicy::Keep => {}
            TrimPolicy::Frozen => {
                if is_base {
                    self.global.set_trajectory_fixed(session, true);
                } else {
                    events.extend(self.drop_session(session)?);
                }
            }
            TrimPolicy::Clt | TrimPolicy::Delete => {
                let doomed = self.submaps_to_trim(session);
                // GLM's bends rewrite node-to-submap constraints' information: those it still may keep
                // what LLO made them and take in no tree edge. The trims change no bend.
                let rewritable = self.global.intra_submap_rewritable(session);
                for &submap in &doomed {
                    events.push(self.trim(submap, &rewritable)?);
                }
                events.extend(self.optimize_if_sparsified_enough());
            }
        }
        if let Some(s) = self.sessions.get_mut(&session) {
            s.finished = true;
        }
        // Optimized as it ended: from now on what is new moves, and it holds still (see
        // `GlobalSlamOptions::settled_region_hops`).
        self.global.set_trajectory_settled(session, true);
        Ok(events)
    }

    /// Tells the optimizer that the variables which shared a deleted constraint with `eliminated` lost it.
    fn mark_blanket_changed(
        &mut self,
        eliminated: &[VariableId],
        removed: &[(ConstraintId, Constraint)],
    ) {
        let blanket: Vec<VariableId> = removed
            .iter()
            .flat_map(|(_, c)| [c.from, c.to])
            .filter(|id| !eliminated.contains(id))
            .collect();
        self.global.mark_changed(blanket);
    }

    /// `global_from_grid` of every finished submap.
    fn placed(&self) -> Vec<(SubmapId, Rigid2, Arc<ProbabilityGrid>)> {
        self.global
            .submaps()
            .iter()
            .filter(|(id, _)| self.in_map(id.trajectory))
            .filter_map(|(id, record)| {
                let grid = record.grid.as_ref()?;
                let global = self.global.submap_pose(*id)?;
                Some((*id, global * record.local_pose.inverse(), Arc::clone(grid)))
            })
            .collect()
    }

    /// Every finished submap of a placed session not on probation, its grid placed in the map frame (what
    /// relocalization renders; an unplaced session's submaps float in a frame nothing ties to the site,
    /// and a session on probation's may be in the wrong place).
    pub fn placed_submaps(&self) -> impl Iterator<Item = PlacedGrid<'_>> + '_ {
        self.global.submaps().iter().filter_map(|(id, record)| {
            if !self.in_map(id.trajectory) {
                return None;
            }
            let grid = record.grid.as_deref()?;
            let global = self.global.submap_pose(*id)?;
            Some(PlacedGrid {
                global_from_grid: global * record.local_pose.inverse(),
                grid,
            })
        })
    }

    /// The map sessions start against: [`Self::placed_submaps`] rendered at `relocalization`'s resolution
    /// as its [`super::MapCells`] say (`None` while no placed submap knows anything).
    pub fn relocalization_map(
        &self,
        relocalization: &super::RelocalizationOptions,
    ) -> Option<ProbabilityGrid> {
        super::render_relocalization_map(
            self.placed_submaps_by_id()
                .map(|(id, grid)| (id.trajectory, grid)),
            relocalization.resolution,
            relocalization.map_cells,
        )
    }

    /// [`Self::placed_submaps`] with their ids, in id order (oldest session first).
    pub fn placed_submaps_by_id(&self) -> impl Iterator<Item = (SubmapId, PlacedGrid<'_>)> + '_ {
        self.global.submaps().iter().filter_map(|(id, record)| {
            if !self.in_map(id.trajectory) {
                return None;
            }
            let grid = record.grid.as_deref()?;
            let global = self.global.submap_pose(*id)?;
            Some((
                *id,
                PlacedGrid {
                    global_from_grid: global * record.local_pose.inverse(),
                    grid,
                },
            ))
        })
    }

    /// The stale submaps that `session`'s end trims (see the module docs), in id order.
    fn submaps_to_trim(&self, session: u32) -> Vec<SubmapId> {
        let trimmer = &self.options.trimmer;
        let placed = self.placed();
        let fresh = placed
            .iter()
            .filter(|(id, _, _)| id.trajectory == session)
            .count();
        if fresh < trimmer.min_fresh_submaps_before_trimming {
            return Vec::new();
        }
        let Some(current) = self.sessions.get(&session).map(|s| s.order) else {
            return Vec::new();
        };
        let order = |trajectory: u32| self.sessions.get(&trajectory).map(|s| s.order);
        // Only what this session's submaps overlap can have become covered since the last session ended
        // (without them the fresher submaps are the same or fewer): the rest need no coverage count.
        let fresh: Vec<PlacedGrid<'_>> = placed
            .iter()
            .filter(|(id, _, _)| id.trajectory == session)
            .map(|(_, p, g)| PlacedGrid {
                global_from_grid: *p,
                grid: g,
            })
            .collect();
        let mut doomed = Vec::new();
        for (id, pose, grid) in &placed {
            let Some(stale_order) = order(id.trajectory) else {
                continue;
            };
            // Session 0 is never trimmed, and neither is a session still running (several robots map a
            // site at once): its robot may still insert into those submaps.
            if Some(id.trajectory) == self.base
                || stale_order >= current
                || !self.is_finished(id.trajectory)
            {
                continue;
            }
            let stale = PlacedGrid {
                global_from_grid: *pose,
                grid,
            };
            if !fresh.iter().any(|f| f.overlaps(&stale)) {
                continue;
            }
            let fresher: Vec<PlacedGrid<'_>> = placed
                .iter()
                .filter(|(other, _, _)| order(other.trajectory).is_some_and(|o| o > stale_order))
                .map(|(_, p, g)| PlacedGrid {
                    global_from_grid: *p,
                    grid: g,
                })
                .collect();
            let fraction = covered_fraction(
                &stale,
                &fresher,
                trimmer.min_fresher_submaps,
                trimmer.cell_stride,
                trimmer.count_occupied_only,
            );
            if fraction > trimmer.min_covered_fraction {
                doomed.push(*id);
            }
        }
        doomed
    }

    /// `nodes` at the poses the graph holds them at now.
    fn node_poses_of(&self, nodes: &[NodeId]) -> Vec<(NodeId, Rigid2)> {
        nodes
            .iter()
            .filter_map(|&n| Some((n, self.global.node_pose(n)?)))
            .collect()
    }

    /// The nodes that go with `submap`: those all of whose insertion submaps are `submap` or gone.
    fn own_nodes(&self, submap: SubmapId) -> Vec<NodeId> {
        let Some(record) = self.global.submaps().get(&submap) else {
            return Vec::new();
        };
        record
            .nodes
            .iter()
            .filter(|n| {
                self.global.nodes().get(n).is_some_and(|r| {
                    r.submaps
                        .iter()
                        .all(|s| *s == submap || !self.global.submaps().contains_key(s))
                })
            })
            .copied()
            .collect()
    }

    /// Removes one submap and its own nodes per the policy (`clt` or `delete`); a `clt` tree's edges are
    /// summed into the plain constraints already on their pairs but those on the `rewritable` submaps
    /// (see [`GlobalSlam::intra_submap_rewritable`]).
    fn trim(
        &mut self,
        submap: SubmapId,
        rewritable: &BTreeSet<SubmapId>,
    ) -> Result<LifelongEvent, LifelongError> {
        let nodes = self.own_nodes(submap);
        let removed_nodes = self.node_poses_of(&nodes);
        let eliminate: Vec<VariableId> = std::iter::once(VariableId::Submap(submap))
            .chain(nodes.iter().map(|n| VariableId::Node(*n)))
            .collect();
        let error = |source| LifelongError::Sparsification { submap, source };
        let options = &self.options;
        let (tree_edges, kld) = if options.policy == TrimPolicy::Clt {
            let result =
                sparsification::sparsify(self.global.graph(), &eliminate, &options.sparsification)
                    .map_err(error)?;
            let kld = if options.whole_graph_kld {
                sparsification::kl_divergence(
                    self.global.graph(),
                    &eliminate,
                    &result.new_constraints,
                    &options.sparsification,
                )
                .map_err(error)?
            } else {
                result.diagnostics.kl_divergence
            };
            sparsification::apply(
                self.global.graph_mut(),
                &result,
                ParallelMerge::EveryPlainBut(rewritable),
            )
            .map_err(error)?;
            (result.new_constraints.len(), Some(kld))
        } else {
            let kld = if options.whole_graph_kld {
                Some(
                    sparsification::kl_divergence(
                        self.global.graph(),
                        &eliminate,
                        &[],
                        &options.sparsification,
                    )
                    .map_err(error)?,
                )
            } else {
                None
            };
            let removed =
                sparsification::delete(self.global.graph_mut(), &eliminate).map_err(error)?;
            self.mark_blanket_changed(&eliminate, &removed);
            (0, kld)
        };
        self.global.forget(&[submap], &nodes);
        self.trimmed_total += 1;
        self.sparsifications_since_optimization += 1;
        Ok(LifelongEvent::SubmapTrimmed {
            submap,
            dropped: false,
            removed_nodes,
            tree_edges,
            kld,
        })
    }

    /// Re-optimizes (at most `sparsification_max_iterations` steps) once `optimize_every_n_sparsifications`
    /// (≥ 1) sparsifications have accumulated: after a session's whole batch of trims, not inside it. Each tree
    /// keeps its blanket's marginal at the point it was linearized at, so the optimum hardly moves between
    /// two trims of a batch (χ² 508 → 506 and 497 → 493 in the two optimizations inside session 10's
    /// seven trims, store seed 1), while a step on a graph this size costs tens of milliseconds (a session
    /// end without trims: 170–380 ms of CPU for 2–7 steps): with the optimizations inside the batch, store
    /// seed 3's session 20 spent 18 steps and 1.8 s on its 16 trims (docs/BENCHMARK-HISTORY.md,
    /// session 18).
    fn optimize_if_sparsified_enough(&mut self) -> Option<LifelongEvent> {
        let every = self.options.optimize_every_n_sparsifications;
        if every == 0 || self.sparsifications_since_optimization < every {
            return None;
        }
        self.sparsifications_since_optimization = 0;
        Some(LifelongEvent::Optimized(
            self.global
                .optimize_capped(self.options.sparsification_max_iterations),
        ))
    }

    /// `frozen`: drops a later session's submaps and nodes from the map, replacing nothing.
    fn drop_session(&mut self, session: u32) -> Result<Vec<LifelongEvent>, LifelongError> {
        let submaps: Vec<SubmapId> = self
            .global
            .submaps()
            .keys()
            .filter(|s| s.trajectory == session)
            .copied()
            .collect();
        let mut events = Vec::new();
        for submap in submaps {
            let nodes = self.own_nodes(submap);
            let removed_nodes = self.node_poses_of(&nodes);
            let eliminate: Vec<VariableId> = std::iter::once(VariableId::Submap(submap))
                .chain(nodes.iter().map(|n| VariableId::Node(*n)))
                .collect();
            let removed = sparsification::delete(self.global.graph_mut(), &eliminate)
                .map_err(|source| LifelongError::Sparsification { submap, source })?;
            self.mark_blanket_changed(&eliminate, &removed);
            self.global.forget(&[submap], &nodes);
            self.dropped_total += 1;
            events.push(LifelongEvent::SubmapTrimmed {
                submap,
                dropped: true,
                removed_nodes,
                tree_edges: 0,
                kld: None,
            });
        }
        // Nodes inserted into no submap (none in practice) go too.
        let orphans: Vec<NodeId> = self
            .global
            .nodes()
            .keys()
            .filter(|n| n.trajectory == session)
            .copied()
            .collect();
        if !orphans.is_empty() {
            let eliminate: Vec<VariableId> = orphans.iter().map(|n| VariableId::Node(*n)).collect();
            let removed =
                sparsification::delete(self.global.graph_mut(), &eliminate).map_err(|source| {
                    LifelongError::Sparsification {
                        submap: SubmapId {
                            trajectory: session,
                            index: u32::MAX,
                        },
                        source,
                    }
                })?;
            self.mark_blanket_changed(&eliminate, &removed);
            self.global.forget(&[], &orphans);
        }
        Ok(events)
    }

    /// Every submap still in the map: id, global pose (`world_from_submap`) and its grid once finished
    /// (in its session's local frame; see [`Self::placed_submaps`] for map-frame placement).
    pub fn submaps(
        &self,
    ) -> impl Iterator<Item = (SubmapId, Rigid2, Option<&Arc<ProbabilityGrid>>)> + '_ {
        self.global.submaps().iter().filter_map(|(id, record)| {
            Some((*id, self.global.submap_pose(*id)?, record.grid.as_ref()))
        })
    }

    /// Every node still in the map: id, scan time and global pose (`world_from_tracking`).
    pub fn node_poses(&self) -> impl Iterator<Item = (NodeId, Timestamp, Rigid2)> + '_ {
        self.global
            .nodes()
            .iter()
            .filter_map(|(id, record)| Some((*id, record.time, self.global.node_pose(*id)?)))
    }

    /// Size of the graph.
    pub fn counts(&self) -> GraphCounts {
        GraphCounts {
            nodes: self.global.nodes().len(),
            submaps: self.global.submaps().len(),
            constraints: self.global.graph().num_constraints(),
            constraints_by_kind: ConstraintKindCounts::of(self.global.graph()),
            trimmed_total: self.trimmed_total,
            dropped_total: self.dropped_total,
        }
    }

    /// `global_from_local` of a session (identity until placed).
    pub fn global_from_local(&self, session: u32) -> Rigid2 {
        self.global.global_from_local(session)
    }

    /// Whether a started session has been placed in the map (by a prior or a match).
    pub fn is_placed(&self, session: u32) -> bool {
        self.sessions.contains_key(&session) && !self.global.is_unanchored(session)
    }

    /// The underlying global SLAM state (records, graph, loop-closure scores).
    pub fn global(&self) -> &GlobalSlam {
        &self.global
    }
}
