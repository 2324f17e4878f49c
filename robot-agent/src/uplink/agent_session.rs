//! One mapping session of a robot: LLO on a recording, batched into the durable uploader; and following
//! the site's versions into the global submap cache.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mapping::geometry::Rigid2;
use mapping::global_slam::{ConstraintBuilderOptions, GlobalSlamOptions};
use mapping::lifelong::{
    LifelongOptionsError, PlacedGrid, RelocalizationOptions, SessionStart as StartDecision,
    SessionStartEvent, SessionStartOptions, StartSearch, render_relocalization_map,
};
use mapping::local_slam::LocalTrajectoryBuilderOptions;
use mapping::metrics::StartRecord;
use mapping::sensor::Timestamp;
use nalgebra::Point2;
use proto::UploadItem;
use tokio::sync::{mpsc, watch};
use tokio_stream::StreamExt as _;

use super::robot_glm::RobotGlm;
use super::{
    GlobalSubmapCache, LloStats, MapUplink, UplinkError, Uploader, run_llo, run_llo_stream,
};
use crate::source::{Recording, SensorStream};

/// How a session streams.
#[derive(Clone, Debug)]
pub struct SessionOptions {
    /// Nodes per upload batch (at least 1).
    pub nodes_per_batch: usize,
    /// Recording pace: multiple of real time; 0 = as fast as possible.
    pub replay_speed: f64,
    /// Stop after this many scans (all when `None`).
    pub max_scans: Option<usize>,
    /// Pause between flush attempts while the server is unreachable.
    pub retry_interval: Duration,
    /// After the recording ends, how long to keep retrying until everything is acknowledged.
    pub final_flush_timeout: Duration,
    /// LLO settings.
    pub local: LocalTrajectoryBuilderOptions,
    /// Run GLM on the robot once the session's start is relocalized: match each node against the cached
    /// site submaps and send the accepted matches with it, so the server searches only within the
    /// session. Default true.
    pub glm_on_robot: bool,
    /// The robot's GLM settings. Default: the server's (`GlobalSlamOptions::default().constraint_builder`).
    pub glm: ConstraintBuilderOptions,
    /// Where to send each node's global pose as the robot estimates it when the node is made
    /// (`(stamp, map_from_base)`; the live ROS 2 publisher): sent without waiting, dropped when the
    /// receiver lags. Default none.
    pub node_poses: Option<tokio::sync::mpsc::Sender<(mapping::sensor::Timestamp, Rigid2)>>,
}

impl Default for SessionOptions {
    fn default() -> Self {
        Self {
            nodes_per_batch: 10,
            replay_speed: 1.0,
            max_scans: None,
            retry_interval: Duration::from_millis(500),
            final_flush_timeout: Duration::from_secs(60),
            local: LocalTrajectoryBuilderOptions::default(),
            glm_on_robot: true,
            glm: GlobalSlamOptions::default().constraint_builder,
            node_poses: None,
        }
    }
}

/// What a session did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SessionReport {
    /// LLO's figures.
    pub llo: LloStats,
    /// Batches made.
    pub batches: u64,
    /// Flushes that failed transiently (link or server down) and were retried.
    pub failed_flushes: u64,
    /// Batches applied by the server.
    pub applied: usize,
    /// Site version after the last acknowledgement.
    pub map_version: u64,
    /// Batches still in the outbox (or held in memory while its disk was full) at the end (0 unless
    /// the final flush timed out).
    pub left_in_outbox: usize,
}

/// Why a session stopped early.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The server refused something for good.
    #[error(transparent)]
    Uplink(#[from] UplinkError),
    /// The LLO thread panicked.
    #[error("LLO thread: {0}")]
    Llo(String),
    /// The LLO thread could not be started.
    #[error("LLO thread: {0}")]
    LloSpawn(#[source] std::io::Error),
}

/// How a session finds its place in the site map before its first upload, through
/// `mapping::lifelong::SessionStart` (the session start every shell uses) against the agent's cache of the
/// site's submaps: its nodes are held back while it searches (the first search after
/// `session_start.hold_back_nodes`, retries on its schedule), and the session opens with the placement as
/// its `SessionStartPrior`. The robot holds at most `session_start.max_search_nodes` nodes back (it gives
/// up searching there when `give_up_after_nodes` is 0 or larger): a session it cannot place streams
/// without a prior and the server searches for it. The robot's GLM matches then judge the placement on
/// probation (the server judges it the same way); a revoked placement stops GLM on the robot. With a
/// `dock`, the session is first checked there (`mapping::lifelong::SessionStart::from_dock`): placed at
/// once where its first nodes agree, else searched for as without one; a dock placement nothing
/// disputed is kept at the session's end (`UploadItem::DockPlacementKept`).
pub struct SessionStart<'a> {
    /// The agent's cache of the site's global submaps.
    pub cache: &'a Mutex<GlobalSubmapCache>,
    /// The whole-map search.
    pub relocalization: RelocalizationOptions,
    /// Hold-back, retries and probation.
    pub session_start: SessionStartOptions,
    /// The robot's dock: where its last session in the site ended, as it estimated it then
    /// (`map_from_tracking`; see [`SessionTrace::end_pose`]). `None`: search the whole map.
    pub dock: Option<Rigid2>,
}

/// What a session's start relocalization found and which nodes the session made.
#[derive(Clone, Debug, Default)]
pub struct SessionTrace {
    /// Whether relocalization ran (a [`SessionStart`] was given and the cache held finished submaps).
    pub relocalization_attempted: bool,
    /// `global_from_local` sent as the session's prior.
    pub prior: Option<Rigid2>,
    /// The nodes whose scans the search that placed it fitted, first and last index (sent with the
    /// prior: the placement vouches for their LLO).
    pub fitted: Option<(u32, u32)>,
    /// Its branch-and-bound score.
    pub score: Option<f32>,
    /// Wall time of the first whole-map search, milliseconds.
    pub relocalization_ms: f64,
    /// Whole-map searches made.
    pub searches: usize,
    /// What its session start decided: every placement the robot acted on (its tentative start
    /// placements), the one it committed to (probation passed on its own GLM matches), each search's
    /// best, and whether a placement was revoked (its GLM stopped then).
    pub start: StartRecord,
    /// Scan time of every node, in node order (node `i` of the session has `node_times[i]`).
    pub node_times: Vec<Timestamp>,
    /// The robot's own estimate of every node's global pose (`world_from_tracking`) at the time of the
    /// node, in node order: the prior, with GLM's matches on the robot fused in as it matches; `None` before the
    /// start was decided (the held-back nodes but the last) and when the start was not relocalized.
    pub node_estimates: Vec<Option<Rigid2>>,
    /// The first node's local pose (`local_from_tracking`).
    pub first_local_pose: Option<Rigid2>,
    /// What became of [`SessionStart::dock`].
    pub dock: DockOutcome,
    /// Whether GLM ran on the robot for this session.
    pub glm_on_robot: bool,
    /// GLM matches the robot sent.
    pub glm_matches: u64,
}

/// What became of a session's dock ([`SessionStart::dock`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DockOutcome {
    /// No dock, or its check disagreed (the session searched instead).
    #[default]
    NotPlaced,
    /// Placed at the dock; committed by matches, or dropped with the session if still on probation.
    Placed,
    /// Placed at the dock and kept at the session's end (sent as `UploadItem::DockPlacementKept`).
    Kept,
}

impl SessionTrace {
    /// Where the session ended, as the robot estimated it at its last node (`map_from_tracking`): the
    /// next session's dock. `None` when the robot did not know its place then (never placed, or its
    /// placement revoked).
    pub fn end_pose(&self) -> Option<Rigid2> {
        self.node_estimates.last().copied().flatten()
    }
}

/// The span a robot session runs in, `session{site, robot, session}`: the shell that runs a session
/// (`evermap-agent run`, the demo's robots) enters it, so every line the session's uploader, GLM and
/// shell log names the session. At ERROR level so that it is on whenever any event is: a filter at WARN
/// still shows whose session a warning is about.
pub fn session_span(site: &str, robot_id: &str, session_uuid: &str) -> tracing::Span {
    tracing::error_span!("session", site = %site, robot = %robot_id, session = %session_uuid)
}

/// Runs LLO over `recording` on a named thread and streams its output through `uploader` in batches of
/// `nodes_per_batch` nodes, ending with `SessionEnd`. Transient failures are retried while LLO goes on
/// (the outbox keeps everything); after the recording, flushing is retried for up to
/// `final_flush_timeout`. A permanent refusal stops the session with an error.
pub async fn stream_recording<U: MapUplink>(
    recording: Arc<Recording>,
    options: &SessionOptions,
    uploader: &mut Uploader<U>,
) -> Result<SessionReport, SessionError> {
    stream_session(recording, options, uploader, None)
        .await
        .map(|(report, _)| report)
}

/// The local pose of the node of a node's items.
fn node_local_pose(items: &[UploadItem]) -> Option<Rigid2> {
    items.iter().find_map(|item| match item {
        UploadItem::NodeAdded(node) => Some(node.local_pose),
        _ => None,
    })
}

/// The estimates of the held-back nodes once the start is decided: none for those before the
/// decision, the prior for the node it was decided at (the last).
fn push_held_estimates(trace: &mut SessionTrace, held: &[Vec<UploadItem>]) {
    for (i, items) in held.iter().enumerate() {
        let decided = i + 1 == held.len();
        let local = node_local_pose(items);
        trace.node_estimates.push(
            trace
                .prior
                .zip(local)
                .filter(|_| decided)
                .map(|(p, l)| p * l),
        );
    }
}

/// The session's `SessionStartPrior`, when its start was placed: where, whether GLM runs on the robot,
/// and whether the placement is its dock's.
fn start_prior(trace: &SessionTrace, glm_on_robot: bool) -> Option<UploadItem> {
    Some(UploadItem::SessionStartPrior {
        global_from_local: trace.prior?,
        glm_on_robot,
        at_dock: trace.dock == DockOutcome::Placed,
        fitted: trace.fitted,
    })
}

/// Starts GLM on the robot when the session was relocalized (and GLM is on), matching the held-back
/// nodes right away.
async fn begin_glm(
    start: &SessionStart<'_>,
    options: &SessionOptions,
    held: &mut [Vec<UploadItem>],
    trace: &SessionTrace,
) -> Option<RobotGlm> {
    let prior = trace.prior.filter(|_| options.glm_on_robot)?;
    let mut glm = RobotGlm::new(&options.glm, prior)?;
    for items in held.iter_mut() {
        glm.match_items(start.cache, None, items).await;
    }
    Some(glm)
}

/// The cache rendered and prepared for whole-map searches (on a blocking thread); `None` when it holds
/// no submaps.
async fn prepare_search(
    cache: &Mutex<GlobalSubmapCache>,
    options: &RelocalizationOptions,
) -> Option<StartSearch> {
    let submaps = cached_grids(cache);
    if submaps.is_empty() {
        return None;
    }
    let options = options.clone();
    tokio::task::spawn_blocking(move || {
        let grid = render_cached(&submaps, &options)?;
        Some(StartSearch::new(&grid, &options))
    })
    .await
    .ok()
    .flatten()
}

/// The cached submaps (their session, `global_from_grid`, grid; oldest first) rendered into the
/// relocalization map (blocking: call off the async threads).
fn render_cached(
    submaps: &[(u32, Rigid2, Arc<mapping::grid::ProbabilityGrid>)],
    options: &RelocalizationOptions,
) -> Option<mapping::grid::ProbabilityGrid> {
    render_relocalization_map(
        submaps.iter().map(|(session, global_from_grid, grid)| {
            (
                *session,
                PlacedGrid {
                    global_from_grid: *global_from_grid,
                    grid,
                },
            )
        }),
        options.resolution,
        options.map_cells,
    )
}

/// The session, `global_from_grid` and grid of every cached submap, oldest first (by id).
fn cached_grids(
    cache: &Mutex<GlobalSubmapCache>,
) -> Vec<(u32, Rigid2, Arc<mapping::grid::ProbabilityGrid>)> {
    cache
        .lock()
        .map(|cache| {
            cache
                .submaps()
                .iter()
                .map(|(id, s)| {
                    (
                        id.trajectory,
                        s.global_pose * s.local_pose.inverse(),
                        Arc::clone(&s.grid),
                    )
                })
                .collect()
        })
        .unwrap_or_default()
}

/// Feeds the node of `items` to the session start (on a blocking thread: a search may be due).
async fn feed_node(
    decision: StartDecision,
    items: &[UploadItem],
) -> (StartDecision, Vec<SessionStartEvent>) {
    let node = items.iter().find_map(|item| match item {
        UploadItem::NodeAdded(node) => Some((node.local_pose, node.points.clone())),
        _ => None,
    });
    let Some((local_pose, points)) = node else {
        return (decision, Vec::new());
    };
    let mut decision = decision;
    match tokio::task::spawn_blocking(move || {
        let events = decision.add_node(local_pose, points);
        (decision, events)
    })
    .await
    {
        Ok(done) => done,
        Err(e) => panic!("the session start's search panicked: {e}"),
    }
}

/// Feeds the robot's GLM matches among `items` (of the session's node `node`) to the session start.
fn feed_matches(
    decision: &mut StartDecision,
    cache: &Mutex<GlobalSubmapCache>,
    node: usize,
    items: &[UploadItem],
) -> Vec<SessionStartEvent> {
    let mut events = Vec::new();
    let Ok(cache) = cache.lock() else {
        return events;
    };
    for item in items {
        if let UploadItem::GlobalMatch {
            submap,
            submap_from_node,
            ..
        } = item
            && let Some(cached) = cache.submaps().get(submap)
        {
            events.extend(decision.add_match(node, cached.global_pose * submap_from_node, *submap));
        }
    }
    events
}

/// Where the robot's session start ([`StartDecision`], as [`stream_session`] runs it) places a session
/// whose nodes are known ahead of streaming (a benchmark's prepared session): the nodes among `items` are
/// fed in order, on a blocking thread, until it places the session, gives up, or has been fed
/// `max_search_nodes` nodes (what a streaming session holds back at most). `global_from_local` of the
/// placement; `None` when it did not place the session or had nothing to search (no cached submaps, no
/// node); an error when `session_start` is invalid.
pub async fn place_ahead<'a>(
    cache: &Mutex<GlobalSubmapCache>,
    relocalization: &RelocalizationOptions,
    session_start: &SessionStartOptions,
    items: impl IntoIterator<Item = &'a UploadItem>,
) -> Result<Option<Rigid2>, LifelongOptionsError> {
    let nodes: Vec<(Rigid2, Vec<Point2<f32>>)> = items
        .into_iter()
        .filter_map(|item| match item {
            UploadItem::NodeAdded(node) => Some((node.local_pose, node.points.clone())),
            _ => None,
        })
        .take(session_start.max_search_nodes)
        .collect();
    if nodes.is_empty() {
        return Ok(None);
    }
    let Some(search) = prepare_search(cache, relocalization).await else {
        return Ok(None);
    };
    let mut decision = StartDecision::new(session_start.clone(), Some(search))?;
    let placed = tokio::task::spawn_blocking(move || {
        for (local_pose, points) in nodes {
            for event in decision.add_node(local_pose, points) {
                match event {
                    SessionStartEvent::Placed(placement) => {
                        return Some(placement.global_from_local);
                    }
                    SessionStartEvent::GaveUp { .. } => return None,
                    _ => {}
                }
            }
        }
        None
    })
    .await;
    match placed {
        Ok(placed) => Ok(placed),
        Err(e) => panic!("the session start's search panicked: {e}"),
    }
}

/// What a session maps.
pub enum SessionInput {
    /// A recording, replayed at `SessionOptions::replay_speed`.
    Recording(Arc<Recording>),
    /// A live robot (`source::LiveRos2Source`), taken as it comes.
    Live(Box<dyn SensorStream + Send>),
}

/// [`stream_recording`] with an optional session-start relocalization (see [`SessionStart`]); also
/// returns the session's [`SessionTrace`].
pub async fn stream_session<U: MapUplink>(
    recording: Arc<Recording>,
    options: &SessionOptions,
    uploader: &mut Uploader<U>,
    start: Option<SessionStart<'_>>,
) -> Result<(SessionReport, SessionTrace), SessionError> {
    stream_session_from(SessionInput::Recording(recording), options, uploader, start).await
}

/// [`stream_session`] from a recording or a live robot: the same LLO, upload and GLM either way.
pub async fn stream_session_from<U: MapUplink>(
    input: SessionInput,
    options: &SessionOptions,
    uploader: &mut Uploader<U>,
    start: Option<SessionStart<'_>>,
) -> Result<(SessionReport, SessionTrace), SessionError> {
    let (sender, mut receiver) = mpsc::channel::<Vec<UploadItem>>(64);
    let llo_options = options.local.clone();
    let (speed, max_scans) = (options.replay_speed, options.max_scans);
    let llo = std::thread::Builder::new()
        .name("llo".into())
        .spawn(move || {
            let mut sink = |items| sender.blocking_send(items).is_ok();
            match input {
                SessionInput::Recording(recording) => {
                    run_llo(&recording, &llo_options, speed, max_scans, &mut sink)
                }
                SessionInput::Live(mut stream) => {
                    run_llo_stream(stream.as_mut(), &llo_options, None, max_scans, &mut sink)
                }
            }
        })
        .map_err(SessionError::LloSpawn)?;

    let mut session = SessionStream::new(options, start);
    let mut retry = tokio::time::interval(options.retry_interval);
    retry.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut backlog = false;
    loop {
        tokio::select! {
            items = receiver.recv() => {
                let Some(items) = items else { break };
                if !session.add(items, uploader.trajectory()).await {
                    continue; // held back while the start is searched for
                }
                if session.nodes_in_batch >= options.nodes_per_batch.max(1) {
                    uploader.enqueue(&session.batch)?;
                    session.report.batches += 1;
                    session.batch.clear();
                    session.nodes_in_batch = 0;
                    backlog = flush(uploader, &mut session.report).await?;
                }
            }
            _ = retry.tick(), if backlog => {
                backlog = flush(uploader, &mut session.report).await?;
            }
        }
    }
    session.report.llo = llo
        .join()
        .map_err(|_| SessionError::Llo("the LLO thread panicked".into()))?;
    session.end_start();
    let SessionStream {
        mut report,
        trace,
        batch,
        ..
    } = session;
    // The last data, then the session end in a batch of its own: the server publishes the data (the
    // submaps LLO finished at the end) at once, and ends the session — its heavy maintenance — after.
    if !batch.is_empty() {
        uploader.enqueue(&batch)?;
        report.batches += 1;
    }
    uploader.enqueue(&[UploadItem::SessionEnd])?;
    report.batches += 1;
    let deadline = Instant::now() + options.final_flush_timeout;
    while flush(uploader, &mut report).await? {
        if Instant::now() >= deadline {
            break;
        }
        tokio::time::sleep(options.retry_interval).await;
    }
    report.left_in_outbox =
        uploader.outbox().len().map_err(UplinkError::from)? + uploader.unstored();
    Ok((report, trace))
}

/// One flush of the outbox into `report`: whether a backlog remains (a transient failure, or batches
/// the full outbox disk could not take yet); an error when the server refused for good.
async fn flush<U: MapUplink>(
    uploader: &mut Uploader<U>,
    report: &mut SessionReport,
) -> Result<bool, UplinkError> {
    // Boxed: the gRPC call's future is large, and the session holds it across its loop's awaits.
    match Box::pin(uploader.flush()).await {
        Ok(stats) => {
            report.applied += stats.applied;
            report.map_version = stats.map_version;
            // Batches the full outbox disk could not take yet are a backlog too.
            Ok(uploader.unstored() > 0)
        }
        Err(e) if e.is_transient() => {
            report.failed_flushes += 1;
            Ok(true)
        }
        Err(e) => Err(e),
    }
}

/// A streaming session's state between LLO's nodes: the batch being filled, the nodes held back while
/// the start is searched for, the session start's decision and the robot's GLM.
struct SessionStream<'o, 'a> {
    options: &'o SessionOptions,
    start: Option<SessionStart<'a>>,
    report: SessionReport,
    trace: SessionTrace,
    batch: Vec<UploadItem>,
    nodes_in_batch: usize,
    /// Nodes held back until the start is decided (only with a `SessionStart`).
    held: Vec<Vec<UploadItem>>,
    started: bool,
    decision: Option<StartDecision>,
    prepared: bool,
    /// Every node's local pose, in node order.
    held_local: Vec<Option<Rigid2>>,
    /// GLM on the robot, once the start is relocalized.
    glm: Option<RobotGlm>,
}

impl<'o, 'a> SessionStream<'o, 'a> {
    fn new(options: &'o SessionOptions, start: Option<SessionStart<'a>>) -> Self {
        Self {
            options,
            started: start.is_none(),
            start,
            report: SessionReport::default(),
            trace: SessionTrace::default(),
            batch: Vec::new(),
            nodes_in_batch: 0,
            held: Vec::new(),
            decision: None,
            prepared: false,
            held_local: Vec::new(),
            glm: None,
        }
    }

    /// Records a session-start event in the trace.
    fn record(&mut self, event: &SessionStartEvent) {
        let held_local = &self.held_local;
        self.trace
            .start
            .record(event, &self.trace.node_times, &|node| {
                held_local.get(node).copied().flatten()
            });
    }

    /// Takes a node's items from LLO (`trajectory`: the session's, once the server opened it): streamed
    /// into the batch once the start is decided, held back before. Whether the batch may be sent now
    /// (false while the node is held back).
    async fn add(&mut self, items: Vec<UploadItem>, trajectory: Option<u32>) -> bool {
        for item in &items {
            if let UploadItem::NodeAdded(node) = item {
                self.trace.first_local_pose.get_or_insert(node.local_pose);
                self.trace.node_times.push(node.time);
            }
        }
        let node = self.trace.node_times.len().saturating_sub(1);
        if self.started {
            self.stream_node(items, node, trajectory).await;
            true
        } else {
            self.hold_node(items).await
        }
    }

    /// A node of a started session: matched by the robot's GLM, its matches judging a placement on
    /// probation, its estimate published, and into the batch.
    async fn stream_node(
        &mut self,
        mut items: Vec<UploadItem>,
        node: usize,
        trajectory: Option<u32>,
    ) {
        let estimate = match (self.glm.as_mut(), self.start.as_ref()) {
            (Some(glm), Some(start)) => glm.match_items(start.cache, trajectory, &mut items).await,
            _ => None,
        };
        if let (Some(d), Some(start)) = (self.decision.take(), self.start.as_ref()) {
            // On probation: the node judges the placement, and may be searched from (while unconfirmed).
            let (mut d, mut events) = feed_node(d, &items).await;
            events.extend(feed_matches(&mut d, start.cache, node, &items));
            for event in events {
                self.record(&event);
                if let SessionStartEvent::Revoked { .. } = event {
                    // The robot cannot take its prior back: it stops matching, and the server (which
                    // revokes it on the same matches) searches for it.
                    self.glm = None;
                }
            }
            if !(self.trace.start.revoked || d.is_committed()) {
                self.decision = Some(d);
            }
        }
        let local = node_local_pose(&items);
        self.held_local.push(local);
        let estimate = if self.trace.start.revoked {
            None
        } else {
            estimate.or_else(|| Some(self.trace.prior? * local?))
        };
        if let (Some(sink), Some(pose), Some(time)) = (
            &self.options.node_poses,
            estimate,
            self.trace.node_times.last(),
        ) {
            let _ = sink.try_send((*time, pose));
        }
        self.trace.node_estimates.push(estimate);
        self.nodes_in_batch += 1;
        self.batch.extend(items);
    }

    /// A node held back while the start is searched for: fed to the session start, and once it decides
    /// (placed, gave up, or nothing to search), the session starts streaming. Whether it started.
    async fn hold_node(&mut self, items: Vec<UploadItem>) -> bool {
        self.held_local.push(node_local_pose(&items));
        self.held.push(items);
        if !self.prepared {
            self.prepare_decision().await;
        }
        let mut decided = self.decision.is_none();
        if let (Some(d), Some(last)) = (self.decision.take(), self.held.last()) {
            let searches = d.searches();
            let began = Instant::now();
            let (d, events) = feed_node(d, last).await;
            if d.searches() > searches {
                self.trace.relocalization_attempted = true;
                self.trace.searches = d.searches();
                if searches == 0 {
                    self.trace.relocalization_ms = began.elapsed().as_secs_f64() * 1e3;
                }
            }
            for event in &events {
                self.record(event);
                match event {
                    SessionStartEvent::DockChecked { agreed, .. } => {
                        self.trace.dock = if *agreed {
                            DockOutcome::Placed
                        } else {
                            DockOutcome::NotPlaced
                        };
                    }
                    SessionStartEvent::Placed(placement) => {
                        self.trace.prior = Some(placement.global_from_local);
                        self.trace.fitted = placement.fitted_nodes();
                        self.trace.score = placement.score;
                        decided = true;
                    }
                    SessionStartEvent::GaveUp { .. } => decided = true,
                    _ => {}
                }
            }
            if !d.is_committed() && self.trace.prior.is_some() || !decided {
                self.decision = Some(d);
            }
        }
        if !decided {
            return false;
        }
        if let Some(start) = &self.start {
            self.glm = begin_glm(start, self.options, &mut self.held, &self.trace).await;
        }
        self.started = true;
        push_held_estimates(&mut self.trace, &self.held);
        self.batch
            .extend(start_prior(&self.trace, self.glm.is_some()));
        self.nodes_in_batch += self.held.len();
        self.batch.extend(self.held.drain(..).flatten());
        true
    }

    /// The session start, made at the first held node: the cache prepared for whole-map searches and the
    /// decision begun at the dock or without one (none when the cache holds no submaps).
    async fn prepare_decision(&mut self) {
        let Some(start) = self.start.as_ref() else {
            return;
        };
        self.prepared = true;
        let mut session_start = start.session_start.clone();
        // Nodes are held back while searching: not longer than `max_search_nodes`.
        if session_start.give_up_after_nodes == 0
            || session_start.give_up_after_nodes > session_start.max_search_nodes
        {
            session_start.give_up_after_nodes = session_start.max_search_nodes;
        }
        if let Some(search) = prepare_search(start.cache, &start.relocalization).await {
            self.decision = match start.dock {
                Some(dock) => StartDecision::from_dock(session_start, Some(search), dock),
                None => StartDecision::new(session_start, Some(search)),
            }
            .ok();
        }
    }

    /// What the end of LLO decides of the start: a session still held back streams without a prior (the
    /// server searches for it), and a dock placement still on probation that nothing disputed is kept.
    fn end_start(&mut self) {
        if !self.started {
            // Shorter than the hold-back, or still searching: the session streams without a prior and the
            // server searches for it.
            push_held_estimates(&mut self.trace, &self.held);
            self.batch
                .extend(start_prior(&self.trace, self.glm.is_some()));
            self.batch.extend(self.held.drain(..).flatten());
        }
        // A dock placement still on probation that nothing disputed is kept (the server commits it on
        // this word, after its own judging agrees).
        if let Some(mut d) = self.decision.take().filter(|_| self.trace.prior.is_some()) {
            for event in d.finish() {
                self.record(&event);
                if let SessionStartEvent::Committed { .. } = event {
                    self.trace.dock = DockOutcome::Kept;
                    self.batch.push(UploadItem::DockPlacementKept);
                }
            }
        }
        // After the short-session path above, which may start GLM too.
        self.trace.glm_on_robot = self.glm.is_some();
        self.trace.glm_matches = self.glm.as_ref().map_or(0, |g| g.matches);
    }
}

/// Keeps `cache` at the site's latest version until `stop` turns true: watches versions and, for each
/// one newer than the cache, fetches the delta since the cache's version. After a broken link it
/// reconnects every `retry_interval` and catches up by delta (not by re-reading the whole map).
pub async fn follow_site<U: MapUplink>(
    uplink: U,
    cache: Arc<Mutex<GlobalSubmapCache>>,
    stop: watch::Receiver<bool>,
    retry_interval: Duration,
) {
    follow_site_with(uplink, cache, stop, retry_interval, |_| {}).await;
}

/// [`follow_site`] that also calls `on_applied` with the cache's version after each applied delta (the
/// load benchmark times version arrival with it).
pub async fn follow_site_with<U: MapUplink>(
    mut uplink: U,
    cache: Arc<Mutex<GlobalSubmapCache>>,
    mut stop: watch::Receiver<bool>,
    retry_interval: Duration,
    mut on_applied: impl FnMut(u64) + Send,
) {
    let cached = |cache: &Arc<Mutex<GlobalSubmapCache>>| cache.lock().map_or(0, |c| c.version());
    while !*stop.borrow() {
        let Ok(mut versions) = uplink.watch_versions().await else {
            tokio::select! {
                () = tokio::time::sleep(retry_interval) => continue,
                _ = stop.changed() => return,
            }
        };
        loop {
            let next = tokio::select! {
                next = versions.next() => next,
                _ = stop.changed() => return,
            };
            let Some(Ok(version)) = next else { break };
            if version <= cached(&cache) {
                continue;
            }
            match uplink.delta_since(cached(&cache)).await {
                Ok(delta) => {
                    let applied = cache.lock().ok().map(|mut cache| {
                        // A delta from an older base is harmless; one from a newer base cannot happen.
                        let _ = cache.apply(delta);
                        cache.version()
                    });
                    if let Some(version) = applied {
                        on_applied(version);
                    }
                }
                Err(_) => break,
            }
        }
    }
}
