//! The map's worker thread: it runs each session through the lifelong map as LLO's nodes arrive,
//! and notes what happened in the session's summary and record.

use std::collections::BTreeMap;
use std::sync::mpsc;
use std::time::Instant;

use mapping::geometry::Rigid2;
use mapping::grid::ProbabilityGrid;
use mapping::lifelong::{
    LifelongEvent, LifelongMap, LiveAnchor, LiveAnchorNoise, SessionStart, SessionStartEvent,
    StartSearch, render_submaps_max,
};
use mapping::local_slam::LloNode;
use mapping::metrics::MatchScorer;
use mapping::pose_graph::NodeId;
use mapping::sensor::Timestamp;

use super::act_on_start::act_on_start;
use super::carried_nodes::{CarriedNode, carry};
use super::{
    OptimizationFigures, ProbationStepFigures, ScanAnchor, SessionEnd, SessionRecord,
    SessionSummary, SessionsConfig, SessionsError,
};
use crate::map_probes::MapProbes;
use crate::offline_slam::run_searches;
use crate::process_stats::thread_cpu_ms;

pub(super) enum Message {
    Start {
        session: u32,
        /// The session's first event.
        start_time: Timestamp,
        /// See [`SessionInput::from_dock`].
        ///
        /// [`SessionInput::from_dock`]: super::SessionInput::from_dock
        from_dock: bool,
    },
    Node {
        session: u32,
        node: LloNode,
    },
    Finish {
        session: u32,
        active_submaps: Vec<(usize, ProbabilityGrid)>,
        /// Every matched scan of the session, in time order.
        scans: Vec<ScanAnchor>,
    },
}

pub(super) struct WorkerOutput {
    pub(super) map: LifelongMap,
    pub(super) sessions: Vec<SessionSummary>,
    /// Every node's pose when the last session that saw it in the map ended.
    pub(super) retired: BTreeMap<NodeId, Rigid2>,
    /// Every trimmed node, in the order they went, tied to the nearest node the map kept.
    pub(super) carried: Vec<CarriedNode>,
    pub(super) records: Vec<SessionRecord>,
    pub(super) probe_poses: Vec<Option<Rigid2>>,
}

/// `map_from_base` of each scan whose node has a pose in `node_poses`: the node's pose composed with
/// LLO's motion from the node to the scan.
fn poses_of_scans(
    scans: &[ScanAnchor],
    node_local: &BTreeMap<NodeId, Rigid2>,
    node_poses: &BTreeMap<NodeId, Rigid2>,
) -> Vec<(Timestamp, Rigid2)> {
    scans
        .iter()
        .filter_map(|a| {
            let node = a.node?;
            let global = node_poses.get(&node)?;
            let local = node_local.get(&node)?;
            Some((a.time, global * local.inverse() * a.local_pose))
        })
        .collect()
}

pub(super) fn worker(
    map: LifelongMap,
    dock: Option<Rigid2>,
    config: &SessionsConfig,
    probes: MapProbes,
    receiver: &mpsc::Receiver<Message>,
    on_session_end: &mut (dyn FnMut(&SessionEnd<'_>) + Send),
) -> Result<WorkerOutput, SessionsError> {
    let mut worker = MapWorker::new(map, dock, config, probes);
    for message in receiver {
        match message {
            Message::Start {
                session,
                start_time,
                from_dock,
            } => worker.start(session, start_time, from_dock)?,
            Message::Node { session, node } => worker.node(session, node)?,
            Message::Finish {
                session,
                active_submaps,
                scans,
            } => worker.finish(session, active_submaps, &scans, on_session_end)?,
        }
    }
    Ok(worker.into_output())
}

/// The worker's state: the map, what it noted of every session so far, and the current session's books.
/// One method per [`Message`].
struct MapWorker<'a> {
    map: LifelongMap,
    config: &'a SessionsConfig,
    probes: MapProbes,
    sessions: Vec<SessionSummary>,
    retired: BTreeMap<NodeId, Rigid2>,
    carried: Vec<CarriedNode>,
    records: Vec<SessionRecord>,
    // The current session's: node local poses, node poses as the robot had them when each was added,
    // and the map of the finished sessions as it was at its start (for the match scores).
    node_local: BTreeMap<NodeId, Rigid2>,
    online_nodes: BTreeMap<NodeId, Rigid2>,
    /// Where the robot was at the end of its last session, as it had it then: its dock (a resumed run's
    /// from its resume point).
    dock: Option<Rigid2>,
    map_at_start: Option<MatchScorer>,
    priors: BTreeMap<u32, (Rigid2, Rigid2)>,
    scores: Vec<f32>,
    // The current session's start (none for session 0, which defines the map) and its nodes' times.
    start: Option<SessionStart>,
    node_times: Vec<Timestamp>,
    // The current session's pose as the robot has it: each node's best match against the earlier
    // sessions' map fused in, the graph's after each optimization or start decision.
    live: Option<LiveAnchor>,
}

impl<'a> MapWorker<'a> {
    fn new(
        map: LifelongMap,
        dock: Option<Rigid2>,
        config: &'a SessionsConfig,
        probes: MapProbes,
    ) -> Self {
        Self {
            map,
            config,
            probes,
            sessions: Vec::new(),
            retired: BTreeMap::new(),
            carried: Vec::new(),
            records: Vec::new(),
            node_local: BTreeMap::new(),
            online_nodes: BTreeMap::new(),
            dock,
            map_at_start: None,
            priors: BTreeMap::new(),
            scores: Vec::new(),
            start: None,
            node_times: Vec::new(),
            live: None,
        }
    }

    /// Acts on session `session`'s start decisions `decisions` with this worker's books
    /// (`first_search`: they come from its first whole-map search); see [`act_on_start`].
    fn act_on_start(
        &mut self,
        session: u32,
        first_search: bool,
        decisions: &[SessionStartEvent],
    ) -> Result<(), SessionsError> {
        act_on_start(
            &mut self.map,
            session,
            first_search,
            decisions,
            &self.node_times,
            &self.node_local,
            self.sessions.last_mut(),
            self.records.last_mut(),
            &mut self.priors,
        )
    }

    /// [`Message::Start`]: a new session, its books cleared; every session after the first gets its start.
    fn start(
        &mut self,
        session: u32,
        start_time: Timestamp,
        from_dock: bool,
    ) -> Result<(), SessionsError> {
        let relocalization = &self.config.lifelong.relocalization;
        self.scores.clear();
        self.node_local.clear();
        self.live = None;
        let dock = self.dock;
        self.online_nodes.clear();
        self.node_times.clear();
        self.map_at_start = None;
        self.start = None;
        if session > 0 {
            // AMS scores every scan against everything the map holds (each cell at the
            // highest value any submap gives it: the definition every earlier figure used);
            // the session start searches the map as `map_cells` renders it.
            self.map_at_start =
                render_submaps_max(self.map.placed_submaps(), relocalization.resolution)
                    .map(|grid| MatchScorer::new(&grid, self.config.scoring.match_window));
            self.start = Some(session_start(
                &self.map,
                self.config,
                dock.filter(|_| from_dock),
            )?);
        }
        // Every later session starts unplaced; its `SessionStart` places it.
        self.map.start_session(session, None)?;
        self.sessions.push(SessionSummary {
            session,
            ..SessionSummary::default()
        });
        self.records.push(SessionRecord {
            session,
            start_time,
            ..SessionRecord::default()
        });
        Ok(())
    }

    /// [`Message::Node`]: the node into the map and the session start, its matches judged, its pose as
    /// the robot has it and its match score noted.
    fn node(&mut self, session: u32, node: LloNode) -> Result<(), SessionsError> {
        let (time, local_pose) = (node.time, node.local_pose);
        // The scans before this node were estimated from the map as it stands now.
        self.probes
            .answer_before(time, |id| self.map.global().node_pose(id));
        let scored_points = (session > 0).then(|| node.points.clone());
        let start_points = self.start.as_ref().map(|_| node.points.clone());
        let (id, events) = self.map.add_node(session, node)?;
        self.node_local.insert(id, local_pose);
        self.node_times.push(time);
        let mut decisions = Vec::new();
        let mut first_search = false;
        if let (Some(start), Some(points)) = (self.start.as_mut(), start_points) {
            let began = Instant::now();
            let searches = start.searches();
            decisions = start.add_node(local_pose, points);
            if let Some(summary) = self.sessions.last_mut() {
                summary.first_node_time = self.node_times.first().copied();
                if start.searches() > searches {
                    let ms = began.elapsed().as_secs_f64() * 1e3;
                    first_search = searches == 0;
                    if first_search {
                        summary.relocalization_ms = ms;
                    }
                    summary.relocalization_ms_total += ms;
                    summary.relocalization_retries = start.searches() - 1;
                }
            }
        }
        self.act_on_start(session, first_search, &decisions)?;
        let mut events_after = run_search_jobs(&mut self.map);
        events_after.extend(events);
        // The matches of this session's nodes against the existing map judge its placement.
        let mut later_decisions = Vec::new();
        if let Some(start) = self.start.as_mut() {
            later_decisions = start.add_matches_from(&self.map, session, &events_after);
            self.act_on_start(session, false, &later_decisions)?;
        }
        if let Some(summary) = self.sessions.last_mut() {
            summary.nodes_added += 1;
            count_closures(summary, &events_after, &mut self.scores);
        }
        // What the robot has now, at this scan: placed (on probation or committed) or not, and
        // where.
        let decided = !decisions.is_empty() || !later_decisions.is_empty();
        let online = self.map.is_placed(session).then(|| {
            let anchor = live_anchor(
                &self.map,
                session,
                self.live,
                decided,
                &events_after,
                &self.node_local,
                &local_pose,
            );
            self.live = Some(anchor);
            anchor.pose(&local_pose)
        });
        if let Some(pose) = online {
            self.online_nodes.insert(id, pose);
        }
        if let (Some(points), Some(record)) = (scored_points, self.records.last_mut()) {
            let score = match (online, &self.map_at_start) {
                (Some(pose), Some(scorer)) => scorer.score(&points, &pose),
                _ => 0.0,
            };
            record.match_scores.push(score);
        }
        Ok(())
    }

    /// [`Message::Finish`]: the session's last submaps in and the session finished (pose graph
    /// refinement, trimming), its summary and record completed and handed to `on_session_end`.
    fn finish(
        &mut self,
        session: u32,
        active_submaps: Vec<(usize, ProbabilityGrid)>,
        scans: &[ScanAnchor],
        on_session_end: &mut (dyn FnMut(&SessionEnd<'_>) + Send),
    ) -> Result<(), SessionsError> {
        if let Some(last) = scans.last() {
            self.probes.answer_before(Timestamp(last.time.0 + 1), |id| {
                self.map.global().node_pose(id)
            });
        }
        self.map.finish_submaps(session, active_submaps)?;
        let events = run_search_jobs(&mut self.map);
        // Every node's pose before pose graph refinement: what a node `finish_session` removes
        // (trimmed, or its session dropped) keeps; the rest are updated after it.
        let mut at_session_end = BTreeMap::new();
        note_poses(&self.map, session, &mut self.retired, &mut at_session_end);
        // What the session's end decides of its start (a dock placement never disputed).
        // (Taken out while `act_on_start` borrows the worker, and put back.)
        if let Some(mut start) = self.start.take() {
            let decisions = start.finish();
            self.act_on_start(session, false, &decisions)?;
            if let (Some(summary), Some(record)) = (self.sessions.last_mut(), self.records.last()) {
                summary.probation_timeline = ProbationStepFigures::timed(
                    start.probation_timeline(),
                    &self.node_times,
                    record.start_time,
                );
            }
            self.start = Some(start);
        }
        let on_probation = self.map.is_on_probation(session);
        let start_ms = Instant::now();
        let start_cpu_ms = thread_cpu_ms();
        let events_finish = self.map.finish_session(session)?;
        let finish_ms = start_ms.elapsed().as_secs_f64() * 1e3;
        let finish_cpu_ms = thread_cpu_ms()
            .zip(start_cpu_ms)
            .map(|(end, start)| end - start);
        // The trims freed grids and nodes: hand the pages back as the server's sites do, so that resident
        // memory follows the map and not the largest the allocator ever held. Here at once, not on a
        // thread of its own: the resident memory reported below is then the map's.
        proto::memory_release::release_freed_memory();
        note_poses(&self.map, session, &mut self.retired, &mut at_session_end);
        // A node trimmed or dropped keeps the pose the map held it at when it went: after the session's
        // final optimization, not before it.
        note_removed_poses(
            &events_finish,
            session,
            &mut self.retired,
            &mut at_session_end,
        );
        self.carried.extend(carry(
            &trimmed_nodes(&events_finish),
            &self
                .map
                .node_poses()
                .map(|(id, _, pose)| (id, pose))
                .collect::<Vec<_>>(),
        ));
        let placed = self.map.is_placed(session) && !on_probation;
        let counts = self.map.counts();
        let offset = relocalization_offset(&self.priors, &self.retired, session);
        if let Some(summary) = self.sessions.last_mut() {
            count_closures(summary, &events, &mut self.scores);
            count_trims(summary, &events_finish);
            summary.placed = placed;
            summary.ended_on_probation = on_probation;
            summary.counts = counts;
            summary.finish_ms = finish_ms;
            summary.finish_cpu_ms = finish_cpu_ms;
            summary.finish_optimizations = optimization_figures(&events_finish);
            summary.relocalization_offset_m = offset;
            summary.peak_rss_mb = crate::process_stats::peak_rss_mb();
            summary.rss_mb = crate::process_stats::current_rss_mb();
        }
        self.probes.add_ended_session(scans, &self.node_local);
        // Where the robot ends this session, as it has it: the next session's dock.
        self.dock = self.online_nodes.values().next_back().copied();
        if let (Some(summary), Some(record)) = (self.sessions.last(), self.records.last_mut()) {
            record.online = poses_of_scans(scans, &self.node_local, &self.online_nodes);
            record.smoothed = poses_of_scans(scans, &self.node_local, &at_session_end);
            on_session_end(&SessionEnd {
                summary,
                record,
                map: &self.map,
                dock: self.dock,
            });
        }
        Ok(())
    }

    /// What the worker hands back when the channel closes. Nodes still in the map report their final
    /// pose; `retired` keeps the rest.
    fn into_output(self) -> WorkerOutput {
        WorkerOutput {
            map: self.map,
            sessions: self.sessions,
            retired: self.retired,
            carried: self.carried,
            records: self.records,
            probe_poses: self.probes.into_answers(),
        }
    }
}

/// Notes every node's pose in `map` in `retired`, and those of `session`'s nodes in `at_session_end`.
fn note_poses(
    map: &LifelongMap,
    session: u32,
    retired: &mut BTreeMap<NodeId, Rigid2>,
    at_session_end: &mut BTreeMap<NodeId, Rigid2>,
) {
    for (id, _, pose) in map.node_poses() {
        retired.insert(id, pose);
        if id.trajectory == session {
            at_session_end.insert(id, pose);
        }
    }
}

/// Notes the pose each node removed by `events` (trimmed, or dropped with its session) had when it went,
/// in `retired`, and those of `session`'s nodes in `at_session_end`.
fn note_removed_poses(
    events: &[LifelongEvent],
    session: u32,
    retired: &mut BTreeMap<NodeId, Rigid2>,
    at_session_end: &mut BTreeMap<NodeId, Rigid2>,
) {
    for event in events {
        if let LifelongEvent::SubmapTrimmed { removed_nodes, .. } = event {
            for &(id, pose) in removed_nodes {
                retired.insert(id, pose);
                if id.trajectory == session {
                    at_session_end.insert(id, pose);
                }
            }
        }
    }
}

/// The nodes `events` trimmed as stale (not those dropped with their own session, whose frame nothing
/// ties to the site), at their poses when they went.
fn trimmed_nodes(events: &[LifelongEvent]) -> Vec<(NodeId, Rigid2)> {
    events
        .iter()
        .filter_map(|e| match e {
            LifelongEvent::SubmapTrimmed {
                dropped: false,
                removed_nodes,
                ..
            } => Some(removed_nodes.iter().copied()),
            _ => None,
        })
        .flatten()
        .collect()
}

/// The session start of a session after the first: the whole-map search over the map as it stands
/// (rendered as `map_cells` says), from the robot's `dock` when there is one.
fn session_start(
    map: &LifelongMap,
    config: &SessionsConfig,
    dock: Option<Rigid2>,
) -> Result<SessionStart, SessionsError> {
    let relocalization = &config.lifelong.relocalization;
    let rendered = map.relocalization_map(relocalization);
    let search = rendered
        .as_ref()
        .map(|grid| StartSearch::new(grid, relocalization));
    let options = config.lifelong.session_start.clone();
    match dock {
        Some(dock) => SessionStart::from_dock(options, search, dock),
        None => SessionStart::new(options, search),
    }
    .map_err(|e| SessionsError::Options(e.into()))
}

/// `session`'s pose as the robot has it after its node at `local_pose` whose events were `events` (see
/// [`LiveAnchor`]): the graph's `global_from_local` where the session was just placed or its placement
/// decided (`decided`), or nothing was anchored yet (the next match overrules it), or the graph optimized
/// (trusted as one match); else the anchor carried to the node, with the best-scoring match of the
/// session's nodes against an earlier session's submap, if any, fused in.
fn live_anchor(
    map: &LifelongMap,
    session: u32,
    live: Option<LiveAnchor>,
    decided: bool,
    events: &[LifelongEvent],
    node_local: &BTreeMap<NodeId, Rigid2>,
    local_pose: &Rigid2,
) -> LiveAnchor {
    let optimized = events
        .iter()
        .any(|e| matches!(e, LifelongEvent::Optimized(_)));
    let noise = LiveAnchorNoise::from_constraint_builder(map.constraint_builder().options());
    let graph = map.global().global_from_local(session);
    let mut anchor = match live {
        Some(anchor) if !decided && !optimized => anchor,
        Some(_) if !decided => LiveAnchor::new(graph, noise),
        _ => LiveAnchor::placed(graph, noise),
    };
    anchor.advance(local_pose);
    if decided || optimized {
        return anchor;
    }
    let best = events
        .iter()
        .filter_map(|e| match e {
            LifelongEvent::LoopClosureAdded(c)
                if c.node.trajectory == session && c.submap.trajectory != session =>
            {
                Some(c)
            }
            _ => None,
        })
        .max_by(|a, b| a.score.total_cmp(&b.score));
    if let Some(closure) = best
        && let (Some(global_from_submap), Some(node_pose)) = (
            map.global().submap_pose(closure.submap),
            node_local.get(&closure.node),
        )
    {
        anchor.anchor_on_match(
            &global_from_submap,
            &closure.submap_from_node,
            node_pose,
            closure.information.as_ref(),
        );
    }
    anchor
}

/// Runs the GLM searches the map queued ([`run_searches`]: on two threads) and adds the accepted ones.
fn run_search_jobs(map: &mut LifelongMap) -> Vec<LifelongEvent> {
    let jobs = map.take_search_jobs();
    let results = run_searches(map.constraint_builder(), &jobs);
    map.add_search_results(results)
}

/// How far `session`'s placement put its first node from that node's last known pose (`retired`),
/// metres; `None` without a placement (`priors`) or that pose.
fn relocalization_offset(
    priors: &BTreeMap<u32, (Rigid2, Rigid2)>,
    retired: &BTreeMap<NodeId, Rigid2>,
    session: u32,
) -> Option<f64> {
    let first_node = NodeId {
        trajectory: session,
        index: 0,
    };
    priors.get(&session).and_then(|(prior, first_local)| {
        let last = retired.get(&first_node)?;
        Some(((prior * first_local).translation.vector - last.translation.vector).norm())
    })
}

/// Counts the submap trims among a session end's `events` in `summary`: submaps trimmed or dropped,
/// nodes removed, tree edges added, and the mean KL divergence of the trims that measured one.
fn count_trims(summary: &mut SessionSummary, events: &[LifelongEvent]) {
    let mut klds = Vec::new();
    for event in events {
        if let LifelongEvent::SubmapTrimmed {
            dropped,
            removed_nodes,
            tree_edges,
            kld,
            ..
        } = event
        {
            if *dropped {
                summary.dropped += 1;
                continue;
            }
            summary.trimmed += 1;
            summary.nodes_trimmed += removed_nodes.len();
            summary.tree_edges += tree_edges;
            klds.extend(*kld);
        }
    }
    summary.trim_kld_mean =
        (!klds.is_empty()).then(|| klds.iter().sum::<f64>() / klds.len() as f64);
}

/// The figures of each optimization among `events`, in order.
fn optimization_figures(events: &[LifelongEvent]) -> Vec<OptimizationFigures> {
    events
        .iter()
        .filter_map(|e| match e {
            LifelongEvent::Optimized(o) => Some(OptimizationFigures {
                iterations: o.iterations,
                accepted_steps: o.accepted_steps,
                chi2: [o.initial_chi2, o.final_chi2],
                termination: o.termination.to_string(),
                free_variables: o.free_variables,
                factor_nonzeros: o.factor_nonzeros,
            }),
            _ => None,
        })
        .collect()
}

fn count_closures(summary: &mut SessionSummary, events: &[LifelongEvent], scores: &mut Vec<f32>) {
    for event in events {
        if let LifelongEvent::LoopClosureAdded(closure) = event
            && closure.node.trajectory == summary.session
        {
            summary.closures += 1;
            scores.push(closure.score);
            if closure.submap.trajectory != summary.session {
                let n = summary.cross_session_closures as f64;
                let mean = summary.cross_session_ams.unwrap_or(0.0);
                summary.cross_session_ams = Some((mean * n + f64::from(closure.score)) / (n + 1.0));
                summary.cross_session_closures += 1;
            }
        }
    }
    summary.ams = if scores.is_empty() {
        0.0
    } else {
        scores.iter().map(|&s| f64::from(s)).sum::<f64>() / scores.len() as f64
    };
}
