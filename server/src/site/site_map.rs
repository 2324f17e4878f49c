//! The site map: a multi-session pose graph plus the bookkeeping that makes versions and deltas.
//!
//! An adapter over [`mapping::lifelong::LifelongMap`] (one trajectory per session): the same multi-session
//! map, trimming and Chow–Liu sparsification as the offline `lifelong` and `sessions` commands. Everything
//! here is synchronous and deterministic: replaying the same opens, uploads and closes in the same order
//! gives the same map, which is how the server rebuilds a site after a restart.
//!
//! A session joins the lifelong map at its first node, with the agent's `SessionStartPrior`
//! (`global_from_local`, found on the robot by the same [`SessionStart`] against its cache) when it sent
//! one. Every session after the first has a [`SessionStart`] here too — the one session-start mechanism
//! of `mapping::lifelong` —, fed each node and each accepted match of its nodes against the other
//! sessions: a robot's prior is on probation until independent matches along the route agree with it
//! (disagreement revokes it: the robot's matches are ignored from then on and the server searches for
//! the session itself); without a prior the server holds the session unplaced and searches the whole
//! map for it (hold-back, retries), then puts the placement on probation. Only committed sessions'
//! submaps are published (an unplaced session's float in a frame nothing ties to the site; a session on
//! probation's may be in the wrong place), and a session that ends unplaced or on probation is dropped. Closing a session trims the stale submaps it overlaps (per the configured policy); trimmed
//! submaps leave the map at that version and deltas list them.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use mapping::geometry::{Rigid2, Rigid2Ext as _, normalize_angle};
use mapping::global_slam::LoopClosure;
use mapping::grid::ProbabilityGrid;
use mapping::lifelong::{
    LifelongError, LifelongEvent, LifelongMap, LifelongOptions, SessionStart, SessionStartEvent,
    StartSearch,
};
use mapping::pose_graph::{NodeId, SubmapId};
pub use proto::SessionStartCounts;
use proto::{
    MapDelta, NodeAdded, PublishedSubmapState, RobotPrior, SiteSessionState, SubmapSnapshot,
    UploadBatch, UploadItem,
};

use super::map_history::{HistoryEntry, MapHistory};
use super::published_submaps::{PublishedSubmap, PublishedSubmaps};
use super::session_view::{PlacementState, SessionView, thin_poses};
use super::{SiteError, SiteView};

/// Two poses closer than this (m, rad) are the same pose for delta purposes.
const POSE_EPSILON: f64 = 1e-9;

/// What opening a session gave.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SessionOpened {
    /// The session's trajectory in the site map.
    pub trajectory: u32,
    /// Last applied sequence number (0: none).
    pub last_seq: u64,
    /// Whether this open created the session (a re-open of a known session changes nothing).
    pub created: bool,
}

/// Whether an upload should be applied.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UploadCheck {
    /// Apply it: it is the session's next batch and fits the session.
    Apply,
    /// Its sequence number was already applied; acknowledge without applying.
    Duplicate {
        /// The session's last applied sequence number.
        last_seq: u64,
    },
}

/// Sizes of a site map, and what it counted since the site began (rebuilt by replay, like the map).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MapCounts {
    /// Sessions ever opened.
    pub sessions: u64,
    /// Nodes.
    pub nodes: u64,
    /// Submaps (finished or not).
    pub submaps: u64,
    /// Finished submaps (with grids).
    pub finished_submaps: u64,
    /// Pose-graph constraints.
    pub constraints: u64,
    /// Published submaps trimmed from the map since the site began.
    pub trimmed_submaps: u64,
    /// Sessions dropped because they ended without ever being placed in the map.
    pub dropped_sessions: u64,
    /// Loop closures accepted since the site began (those of trimmed submaps included).
    pub loop_closures: u64,
    /// Loop-closure searches queued since the site began (`GlobalSlam::searches_queued`).
    pub loop_closure_searches: u64,
    /// Matches refused since the site began because other matches of their node disagreed
    /// (`GlobalSlam::closures_outvoted`).
    pub loop_closures_outvoted: u64,
    /// Matches refused because they moved their node farther than the drift since its last loop
    /// explains, and not confirmed by others since (`GlobalSlam::closures_beyond_drift`: it falls when a
    /// chorus confirms them).
    pub loop_closures_beyond_drift: u64,
    /// Accepted loop closures out of the graph now because the optimized graph refuses them
    /// (`GlobalSlam::closures_retracted`: it falls when one fits again or is trimmed).
    pub loop_closures_retracted: u64,
    /// What the sessions' starts decided since the site began.
    pub session_starts: SessionStartCounts,
    /// Sessions opened and not ended yet.
    pub open_sessions: u64,
}

/// A struct literal of type `$to` with the counts every form of a site's counts carries ([`MapCounts`],
/// the wire's `MapCounts`, the stored summary's `SiteCounts`) copied from `$from`, then `$rest`: the
/// fields only some forms have. The shared fields are listed here once.
macro_rules! copy_counts {
    ($from:expr => $to:path { $($rest:tt)* }) => {{
        let from = &$from;
        $to {
            sessions: from.sessions,
            nodes: from.nodes,
            submaps: from.submaps,
            finished_submaps: from.finished_submaps,
            constraints: from.constraints,
            trimmed_submaps: from.trimmed_submaps,
            dropped_sessions: from.dropped_sessions,
            loop_closures: from.loop_closures,
            open_sessions: from.open_sessions,
            $($rest)*
        }
    }};
}
pub(crate) use copy_counts;

/// One site's map, its sessions and its version history.
pub struct SiteMap {
    site: String,
    map: LifelongMap,
    sessions: BTreeMap<String, SiteSessionState>,
    submap_versions: BTreeMap<SubmapId, PublishedSubmapState>,
    /// Every submap trimmed so far and the version that trimmed it (shared with the published versions).
    trimmed: Arc<BTreeMap<SubmapId, u64>>,
    version: u64,
    optimizations: u64,
    dropped_sessions: u64,
    /// Each running session's start (every session but the first), by trajectory.
    starts: BTreeMap<u32, SessionStart>,
    /// Sessions whose robot's placement was revoked: their robot's matches are ignored.
    robot_revoked: BTreeSet<u32>,
    /// The published map at past versions (the console's slider).
    history: MapHistory,
    /// The session that started the map (its frame is the site's).
    base: Option<u32>,
    /// What the session starts decided so far.
    session_starts: SessionStartCounts,
    /// Running sessions the server has searched for at least once (a later search is a retry).
    searched: BTreeSet<u32>,
}

impl SiteMap {
    /// An empty site map at version 0.
    pub fn new(site: impl Into<String>, options: LifelongOptions) -> Result<Self, LifelongError> {
        Ok(Self {
            site: site.into(),
            map: LifelongMap::new(options)?,
            sessions: BTreeMap::new(),
            submap_versions: BTreeMap::new(),
            trimmed: Arc::default(),
            version: 0,
            optimizations: 0,
            dropped_sessions: 0,
            starts: BTreeMap::new(),
            robot_revoked: BTreeSet::new(),
            history: MapHistory::default(),
            base: None,
            session_starts: SessionStartCounts::default(),
            searched: BTreeSet::new(),
        })
    }

    /// The site id.
    pub fn site(&self) -> &str {
        &self.site
    }

    /// The current version: how many changes have been applied.
    pub fn version(&self) -> u64 {
        self.version
    }

    /// What opening `session_uuid` for `robot_id` would give, without changing anything: the existing
    /// session, or the trajectory a new one would get.
    pub fn check_open(
        &self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<SessionOpened, SiteError> {
        match self.sessions.get(session_uuid) {
            Some(s) if s.robot_id != robot_id => Err(SiteError::WrongRobot {
                session: session_uuid.to_owned(),
                owner: s.robot_id.clone(),
                robot: robot_id.to_owned(),
            }),
            Some(s) => Ok(SessionOpened {
                trajectory: s.trajectory,
                last_seq: s.last_seq,
                created: false,
            }),
            None => Ok(SessionOpened {
                trajectory: self.sessions.len() as u32,
                last_seq: 0,
                created: true,
            }),
        }
    }

    /// Opens a new session as change number `version` (a no-op for a known session).
    pub fn open_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
        trajectory: u32,
        version: u64,
    ) -> Result<(), SiteError> {
        if self.sessions.contains_key(session_uuid) {
            return Ok(());
        }
        if trajectory != self.sessions.len() as u32 {
            return Err(SiteError::Internal(format!(
                "session {session_uuid:?} recorded as trajectory {trajectory}, expected {}",
                self.sessions.len()
            )));
        }
        self.sessions.insert(
            session_uuid.to_owned(),
            SiteSessionState {
                robot_id: robot_id.to_owned(),
                trajectory,
                last_seq: 0,
                closed: false,
                prior: None,
                glm_on_robot: false,
                nodes: 0,
                dropped: false,
            },
        );
        self.version = version;
        Ok(())
    }

    fn session(&self, robot_id: &str, session_uuid: &str) -> Result<&SiteSessionState, SiteError> {
        let session = self
            .sessions
            .get(session_uuid)
            .ok_or_else(|| SiteError::UnknownSession(session_uuid.to_owned()))?;
        if session.robot_id != robot_id {
            return Err(SiteError::WrongRobot {
                session: session_uuid.to_owned(),
                owner: session.robot_id.clone(),
                robot: robot_id.to_owned(),
            });
        }
        Ok(session)
    }

    /// Decides whether `batch` is the session's next one and fits it. Changes nothing.
    pub fn check_upload(&self, batch: &UploadBatch) -> Result<UploadCheck, SiteError> {
        let session = self.session(&batch.robot_id, &batch.session_uuid)?;
        if batch.seq <= session.last_seq {
            return Ok(UploadCheck::Duplicate {
                last_seq: session.last_seq,
            });
        }
        if batch.seq != session.last_seq + 1 {
            return Err(SiteError::SequenceGap {
                session: batch.session_uuid.clone(),
                expected: session.last_seq + 1,
                got: batch.seq,
            });
        }
        if session.closed {
            return Err(SiteError::SessionClosed(batch.session_uuid.clone()));
        }
        // The wire conversion refuses empty batches, so a stored one could never be replayed.
        if batch.items.is_empty() {
            return Err(SiteError::InvalidBatch(
                "a batch needs at least one item".into(),
            ));
        }
        let mut nodes = session.nodes;
        let mut at_dock = session.prior.is_some_and(|p| p.at_dock);
        let mut last_insertion: &[(u32, Rigid2)] = &[];
        let mut ended = false;
        for (i, item) in batch.items.iter().enumerate() {
            if ended {
                return Err(SiteError::InvalidBatch(format!(
                    "item {i} follows SessionEnd"
                )));
            }
            match item {
                UploadItem::NodeAdded(node) => {
                    nodes += 1;
                    last_insertion = &node.insertion_submaps;
                }
                UploadItem::SubmapFinished { index, .. } => {
                    if !last_insertion.iter().any(|(s, _)| s == index) {
                        return Err(SiteError::InvalidBatch(format!(
                            "item {i} finishes submap {index}, which the node before it was not inserted into"
                        )));
                    }
                }
                UploadItem::SessionStartPrior { at_dock: dock, .. } => {
                    if nodes > 0 {
                        return Err(SiteError::InvalidBatch(format!(
                            "item {i}: SessionStartPrior after the session's first node"
                        )));
                    }
                    at_dock = *dock;
                }
                UploadItem::DockPlacementKept => {
                    if !at_dock {
                        return Err(SiteError::InvalidBatch(format!(
                            "item {i}: DockPlacementKept in a session whose prior is not a dock placement"
                        )));
                    }
                }
                UploadItem::SessionEnd => ended = true,
                // The conversion checked that it follows a node's items.
                UploadItem::GlobalMatch { .. } => {}
            }
        }
        Ok(UploadCheck::Apply)
    }

    /// Applies a batch that [`Self::check_upload`] accepted, as change number `version`: adds its nodes and
    /// finished submaps, runs the loop-closure searches they allow, and optimizes when due (and at the end
    /// of a session). Returns the number of optimizations run. This is the heavy part: call it off the
    /// async runtime.
    pub fn apply_upload(&mut self, batch: &UploadBatch, version: u64) -> Result<usize, SiteError> {
        let session = self
            .sessions
            .get(&batch.session_uuid)
            .ok_or_else(|| SiteError::UnknownSession(batch.session_uuid.clone()))?;
        let (trajectory, mut prior, mut glm_on_robot) =
            (session.trajectory, session.prior, session.glm_on_robot);
        let mut optimizations = 0;
        let mut nodes = 0;
        let mut ended = false;
        let mut items = batch.items.iter().peekable();
        while let Some(item) = items.next() {
            match item {
                UploadItem::SessionStartPrior {
                    global_from_local,
                    glm_on_robot: on_robot,
                    at_dock,
                    fitted,
                } => {
                    prior = Some(RobotPrior {
                        global_from_local: *global_from_local,
                        at_dock: *at_dock,
                        fitted: *fitted,
                    });
                    glm_on_robot = *on_robot;
                }
                UploadItem::DockPlacementKept => self.keep_dock_placement(trajectory)?,
                UploadItem::SessionEnd => ended = true,
                // check_upload guarantees these follow a node; they were handed over with it.
                UploadItem::SubmapFinished { .. } | UploadItem::GlobalMatch { .. } => {}
                UploadItem::NodeAdded(node) => {
                    let mut finished = Vec::new();
                    while let Some(UploadItem::SubmapFinished { index, grid }) = items.peek() {
                        finished.push((*index as usize, grid.clone()));
                        items.next();
                    }
                    let mut matches = Vec::new();
                    while let Some(UploadItem::GlobalMatch {
                        submap,
                        submap_from_node,
                        score,
                    }) = items.peek()
                    {
                        matches.push((*submap, *submap_from_node, *score));
                        items.next();
                    }
                    if !self.map.is_started(trajectory) {
                        self.start_session(trajectory, prior, glm_on_robot)?;
                    }
                    optimizations += self.add_node(trajectory, node, finished, &matches)?;
                    nodes += 1;
                }
            }
        }
        if let Some(session) = self.sessions.get_mut(&batch.session_uuid) {
            session.prior = prior;
            session.glm_on_robot = glm_on_robot;
            session.last_seq = batch.seq;
            session.nodes += nodes;
        }
        let mut events = Vec::new();
        if ended {
            events = self.end_session(&batch.session_uuid)?;
        }
        self.optimizations += optimizations as u64;
        self.finish_change(version, &events);
        Ok(optimizations + count_optimizations(&events))
    }

    /// Starts a session in the lifelong map. Every session but the first gets a [`SessionStart`]: on
    /// probation at the robot's `prior` (its dock placement or a search's), or searching the map for
    /// itself without one.
    fn start_session(
        &mut self,
        trajectory: u32,
        prior: Option<RobotPrior>,
        glm_on_robot: bool,
    ) -> Result<(), SiteError> {
        let is_first = self.map.counts().nodes == 0;
        self.map
            .start_session(trajectory, prior.map(|p| p.global_from_local))
            .map_err(SiteError::Rejected)?;
        if let Some(fitted) = prior.and_then(|p| p.fitted) {
            // The robot's search fitted those nodes' scans to the map at the prior.
            self.map
                .set_placement_fit(trajectory, fitted)
                .map_err(SiteError::Rejected)?;
        }
        // Only a placed session can be matched on the robot: it needs the prior.
        if glm_on_robot && prior.is_some() {
            self.map.set_matched_on_robot(trajectory);
        }
        if is_first {
            self.base = Some(trajectory);
            return Ok(());
        }
        let options = self.map.options().session_start.clone();
        let start = match prior {
            Some(prior) => {
                self.session_starts.priors += 1;
                // The robot decided at its last held-back node.
                let decided_at = options.hold_back_nodes.saturating_sub(1);
                self.map
                    .begin_probation(trajectory)
                    .map_err(SiteError::Rejected)?;
                let RobotPrior {
                    global_from_local,
                    at_dock,
                    ..
                } = prior;
                let (start, events) = if at_dock {
                    SessionStart::with_dock_placement(options, None, global_from_local, decided_at)
                } else {
                    SessionStart::with_placement(options, None, global_from_local, decided_at)
                }
                .map_err(SiteError::Options)?;
                self.starts.insert(trajectory, start);
                self.act_on_start(trajectory, &events)?;
                return Ok(());
            }
            None => SessionStart::new(options, self.start_search()).map_err(SiteError::Options)?,
        };
        self.starts.insert(trajectory, start);
        Ok(())
    }

    /// The committed map prepared for whole-map searches (`None` while it is empty).
    fn start_search(&self) -> Option<StartSearch> {
        let relocalization = &self.map.options().relocalization;
        self.map
            .relocalization_map(relocalization)
            .map(|grid| StartSearch::new(&grid, relocalization))
    }

    /// Acts on `trajectory`'s session-start decisions: places, commits or revokes it in the map.
    fn act_on_start(
        &mut self,
        trajectory: u32,
        decisions: &[SessionStartEvent],
    ) -> Result<(), SiteError> {
        for decision in decisions {
            self.count_start_decision(trajectory, decision);
            self.map
                .apply_start_decision(trajectory, decision)
                .map_err(SiteError::Map)?;
            match decision {
                SessionStartEvent::Revoked { .. } => {
                    // The robot's frame is wrong: its matches say nothing more; search here.
                    self.map.set_matched_here(trajectory);
                    self.robot_revoked.insert(trajectory);
                    let needs_search = self
                        .starts
                        .get(&trajectory)
                        .is_some_and(|s| !s.has_search());
                    if needs_search
                        && let Some(search) = self.start_search()
                        && let Some(start) = self.starts.get_mut(&trajectory)
                    {
                        start.set_search(search);
                    }
                }
                SessionStartEvent::Committed { .. } | SessionStartEvent::GaveUp { .. } => {
                    self.drop_final_start(trajectory);
                }
                SessionStartEvent::Placed(_)
                | SessionStartEvent::Refused { .. }
                | SessionStartEvent::DockChecked { .. } => {}
            }
        }
        Ok(())
    }

    /// The robot says its dock placement stands at the session's end (`UploadItem::DockPlacementKept`):
    /// [`SessionStart::finish`] commits it where this server's judging agrees (the placement is still the
    /// robot's, on probation, and no match disputed it).
    fn keep_dock_placement(&mut self, trajectory: u32) -> Result<(), SiteError> {
        let Some(start) = self.starts.get_mut(&trajectory) else {
            return Ok(());
        };
        let decisions = start.finish();
        self.act_on_start(trajectory, &decisions)
    }

    /// Drops `trajectory`'s start once it has decided for good (committed, or gave up): a final
    /// [`SessionStart`] ignores every node and match and decides nothing more, so keeping it changes no
    /// output, and with no start left mid-way the site can be checkpointed (see `site_map_checkpoint`).
    fn drop_final_start(&mut self, trajectory: u32) {
        self.starts.remove(&trajectory);
        self.searched.remove(&trajectory);
    }

    /// Counts one of `trajectory`'s session-start decisions.
    fn count_start_decision(&mut self, trajectory: u32, decision: &SessionStartEvent) {
        let counts = &mut self.session_starts;
        let searched = match decision {
            SessionStartEvent::Placed(_) => {
                counts.placed += 1;
                true
            }
            SessionStartEvent::Refused { .. } => {
                counts.refused += 1;
                true
            }
            SessionStartEvent::Committed { .. } => {
                counts.committed += 1;
                false
            }
            SessionStartEvent::Revoked { .. } => {
                counts.revoked += 1;
                false
            }
            SessionStartEvent::GaveUp { .. } => {
                counts.gave_up += 1;
                false
            }
            // The server's sessions start from a robot's prior or a search, never from a dock.
            SessionStartEvent::DockChecked { .. } => false,
        };
        if searched && !self.searched.insert(trajectory) {
            self.session_starts.retries += 1;
        }
    }

    /// Ends a session in the lifelong map (final optimization, trimming) and marks it closed.
    fn end_session(&mut self, session_uuid: &str) -> Result<Vec<LifelongEvent>, SiteError> {
        let Some(session) = self.sessions.get(session_uuid) else {
            return Err(SiteError::UnknownSession(session_uuid.to_owned()));
        };
        let trajectory = session.trajectory;
        let mut events = Vec::new();
        let mut dropped = false;
        // A dock placement is kept only on the robot's word (`keep_dock_placement`), before this.
        self.starts.remove(&trajectory);
        self.searched.remove(&trajectory);
        if self.map.is_started(trajectory) && !self.map.is_finished(trajectory) {
            let unplaced = self.map.is_unplaced(trajectory) || self.map.is_on_probation(trajectory);
            dropped = unplaced;
            events =
                self.map
                    .finish_session(trajectory)
                    .map_err(|source| SiteError::EndSession {
                        session: session_uuid.to_owned(),
                        source,
                    })?;
            if unplaced {
                self.dropped_sessions += 1;
            }
            // The trims freed the stale submaps' grids and matchers: give the pages back.
            proto::memory_release::release_freed_memory_in_background();
        }
        if let Some(session) = self.sessions.get_mut(session_uuid) {
            session.closed = true;
            session.dropped = dropped;
        }
        self.optimizations += count_optimizations(&events) as u64;
        Ok(events)
    }

    fn add_node(
        &mut self,
        trajectory: u32,
        node: &NodeAdded,
        finished: Vec<(usize, ProbabilityGrid)>,
        matches: &[(SubmapId, Rigid2, f32)],
    ) -> Result<usize, SiteError> {
        let (id, _) = self
            .map
            .add_node(trajectory, node.to_llo_node(finished))
            .map_err(SiteError::Rejected)?;
        // A session started on an empty committed map searches once there is one.
        let needs_search = self
            .starts
            .get(&trajectory)
            .is_some_and(|s| !s.has_search() && s.placement().is_none());
        if needs_search
            && let Some(search) = self.start_search()
            && let Some(start) = self.starts.get_mut(&trajectory)
        {
            start.set_search(search);
        }
        let decisions = self
            .starts
            .get_mut(&trajectory)
            .map(|start| start.add_node(node.local_pose, node.points.clone()))
            .unwrap_or_default();
        self.act_on_start(trajectory, &decisions)?;
        // The robot's GLM matches while its placement stands (a submap trimmed since the robot matched
        // it is skipped by the map), then what the server's own searches found.
        let robot_trusted =
            self.map.is_placed(trajectory) && !self.robot_revoked.contains(&trajectory);
        let events = self
            .map
            .run_pending_searches(matches.iter().filter(|_| robot_trusted).map(
                |(submap, submap_from_node, score)| LoopClosure {
                    submap: *submap,
                    node: id,
                    submap_from_node: *submap_from_node,
                    score: *score,
                    runner_up_score: None,
                    information: None,
                },
            ));
        // Its matches against the other sessions judge its placement.
        let decisions = self
            .starts
            .get_mut(&trajectory)
            .map(|start| start.add_matches_from(&self.map, trajectory, &events))
            .unwrap_or_default();
        self.act_on_start(trajectory, &decisions)?;
        Ok(count_optimizations(&events))
    }

    /// Closes a session as change number `version`, with a final optimization (idempotent: closing a
    /// closed session changes nothing and returns `false`).
    pub fn close_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
        version: u64,
    ) -> Result<bool, SiteError> {
        if self.session(robot_id, session_uuid)?.closed {
            return Ok(false);
        }
        let events = self.end_session(session_uuid)?;
        self.finish_change(version, &events);
        Ok(true)
    }

    /// The robot of a known session.
    pub fn session_robot(&self, session_uuid: &str) -> Option<&str> {
        self.sessions.get(session_uuid).map(|s| s.robot_id.as_str())
    }

    /// Every session not ended yet, as (session uuid, robot id), ordered by session uuid.
    pub fn open_sessions(&self) -> Vec<(String, String)> {
        self.sessions
            .iter()
            .filter(|(_, s)| !s.closed)
            .map(|(uuid, s)| (uuid.clone(), s.robot_id.clone()))
            .collect()
    }

    /// Where a session's last node is in the site map (`site_from_tracking`), if the session is placed
    /// and still has nodes: what a robot keeps as its dock when its session ends.
    pub fn session_end_pose(&self, session_uuid: &str) -> Option<Rigid2> {
        let trajectory = self.sessions.get(session_uuid)?.trajectory;
        if !self.map.is_placed(trajectory) {
            return None;
        }
        let (last, _) = self.map.global().trajectory_nodes(trajectory).next_back()?;
        self.map.global().node_pose(*last)
    }

    /// Whether the session is known and closed.
    pub fn is_closed(&self, session_uuid: &str) -> bool {
        self.sessions.get(session_uuid).is_some_and(|s| s.closed)
    }

    /// Records the submaps trimmed by `events`, the revisions of newly finished (and placed) submaps and
    /// which submap poses moved.
    fn finish_change(&mut self, version: u64, events: &[LifelongEvent]) {
        self.version = version;
        let mut changed = false;
        for event in events {
            if let LifelongEvent::SubmapTrimmed { submap, .. } = event {
                // Only published submaps are news to a client; a dropped unplaced session's never were.
                if self.submap_versions.remove(submap).is_some() {
                    Arc::make_mut(&mut self.trimmed).insert(*submap, version);
                    changed = true;
                }
            }
        }
        for (id, pose, grid) in self.map.submaps() {
            if grid.is_none() || !self.map.is_committed(id.trajectory) {
                continue;
            }
            match self.submap_versions.get_mut(&id) {
                None => {
                    self.submap_versions.insert(
                        id,
                        PublishedSubmapState {
                            revision: version,
                            pose_version: version,
                            pose,
                        },
                    );
                    changed = true;
                }
                Some(v) => {
                    let moved = (v.pose.translation.vector - pose.translation.vector).norm()
                        > POSE_EPSILON
                        || normalize_angle(v.pose.theta() - pose.theta()).abs() > POSE_EPSILON;
                    if moved {
                        v.pose_version = version;
                        v.pose = pose;
                        changed = true;
                    }
                }
            }
        }
        if changed {
            self.history.record(HistoryEntry {
                version,
                counts: self.counts(),
                grids: Arc::new(self.grids_for_render()),
            });
        }
    }

    /// The published map at past versions.
    pub fn history(&self) -> &MapHistory {
        &self.history
    }

    /// The site as read-only front ends see it now.
    pub fn view(&self) -> SiteView {
        SiteView {
            version: self.version,
            sessions: Arc::new(self.session_views()),
            history: Arc::new(self.history.entries().cloned().collect()),
            submaps: Some(Arc::new(self.published_submaps())),
            unloaded: false,
        }
    }

    /// Every session, in the order they were opened, with its placement state and (while placed) its
    /// trajectory in the site frame.
    pub fn session_views(&self) -> Vec<SessionView> {
        let mut poses: BTreeMap<u32, Vec<Rigid2>> = BTreeMap::new();
        for (id, _, pose) in self.map.node_poses() {
            poses.entry(id.trajectory).or_default().push(pose);
        }
        let mut views: Vec<SessionView> = self
            .sessions
            .iter()
            .map(|(uuid, s)| {
                let t = s.trajectory;
                let started = self.map.is_started(t);
                let state = if s.dropped {
                    PlacementState::Dropped
                } else if !started {
                    PlacementState::Waiting
                } else if self.base == Some(t) {
                    PlacementState::Base
                } else if !self.map.is_placed(t) {
                    PlacementState::Searching
                } else if self.map.is_on_probation(t) {
                    PlacementState::Probation
                } else {
                    PlacementState::Committed
                };
                let placed = matches!(
                    state,
                    PlacementState::Base | PlacementState::Probation | PlacementState::Committed
                );
                let trajectory_poses = if placed {
                    thin_poses(
                        poses.remove(&t).unwrap_or_default(),
                        SessionView::MAX_TRAJECTORY_POINTS,
                    )
                } else {
                    Vec::new()
                };
                SessionView {
                    session: uuid.clone(),
                    robot_id: s.robot_id.clone(),
                    trajectory: t,
                    closed: s.closed,
                    nodes: s.nodes,
                    state,
                    prior_from_robot: s.prior.is_some(),
                    robot_prior_revoked: self.robot_revoked.contains(&t),
                    global_from_local: placed.then(|| self.map.global_from_local(t)),
                    latest_pose: trajectory_poses.last().copied(),
                    trajectory_poses,
                }
            })
            .collect();
        views.sort_by_key(|v| v.trajectory);
        views
    }

    /// The sizes of the map.
    pub fn counts(&self) -> MapCounts {
        let graph = self.map.counts();
        let global = self.map.global();
        MapCounts {
            sessions: self.sessions.len() as u64,
            nodes: graph.nodes as u64,
            submaps: graph.submaps as u64,
            finished_submaps: self.submap_versions.len() as u64,
            constraints: graph.constraints as u64,
            trimmed_submaps: self.trimmed.len() as u64,
            dropped_sessions: self.dropped_sessions,
            loop_closures: global.loop_closures_accepted() as u64,
            loop_closure_searches: global.searches_queued() as u64,
            loop_closures_outvoted: global.closures_outvoted() as u64,
            loop_closures_beyond_drift: global.closures_beyond_drift() as u64,
            loop_closures_retracted: global.closures_retracted() as u64,
            session_starts: self.session_starts,
            open_sessions: self.sessions.values().filter(|s| !s.closed).count() as u64,
        }
    }

    /// Optimizations run so far.
    pub fn optimizations(&self) -> u64 {
        self.optimizations
    }

    fn snapshot(&self, id: SubmapId, versions: &PublishedSubmapState) -> Option<SubmapSnapshot> {
        let global = self.map.global();
        let record = global.submaps().get(&id)?;
        Some(SubmapSnapshot {
            id,
            revision: versions.revision,
            global_pose: global.submap_pose(id)?,
            local_pose: record.local_pose,
            grid: Arc::clone(record.grid.as_ref()?),
        })
    }

    /// The finished submaps of this version as robots fetch them ([`PublishedSubmaps`]).
    pub fn published_submaps(&self) -> PublishedSubmaps {
        let submaps = self
            .submap_versions
            .iter()
            .filter_map(|(id, versions)| {
                Some((
                    *id,
                    PublishedSubmap {
                        revision: versions.revision,
                        pose_version: versions.pose_version,
                        snapshot: self.snapshot(*id, versions)?,
                    },
                ))
            })
            .collect();
        PublishedSubmaps::new(&self.site, self.version, submaps, Arc::clone(&self.trimmed))
    }

    /// What changed after version `since` (0: the whole map): see [`PublishedSubmaps::delta_since`].
    pub fn delta_since(&self, since: u64) -> Result<MapDelta, SiteError> {
        self.published_submaps().delta_since(since)
    }

    /// One finished submap; `revision` 0 means the current one.
    pub fn submap(&self, id: SubmapId, revision: u64) -> Result<SubmapSnapshot, SiteError> {
        self.published_submaps().submap(id, revision)
    }

    /// Every finished submap as (`global_from_grid`, grid), where the grid frame is its session's local
    /// frame: what rendering needs.
    pub fn grids_for_render(&self) -> Vec<(Rigid2, Arc<ProbabilityGrid>)> {
        self.submap_versions
            .keys()
            .filter_map(|id| {
                let record = self.map.global().submaps().get(id)?;
                let global = self.map.global().submap_pose(*id)?;
                Some((
                    global * record.local_pose.inverse(),
                    Arc::clone(record.grid.as_ref()?),
                ))
            })
            .collect()
    }

    /// Current global pose of every node, by id.
    pub fn node_poses(&self) -> BTreeMap<NodeId, Rigid2> {
        self.map
            .node_poses()
            .map(|(id, _, pose)| (id, pose))
            .collect()
    }
}

#[cfg(test)]
impl SiteMap {
    /// GLM searches the server has queued so far.
    fn searches_queued(&self) -> usize {
        self.map.global().searches_queued()
    }
}

fn count_optimizations(events: &[LifelongEvent]) -> usize {
    events
        .iter()
        .filter(|e| matches!(e, LifelongEvent::Optimized(_)))
        .count()
}

mod site_map_checkpoint;
#[cfg(test)]
mod tests;
