//! One recording run as several time sessions through the lifelong map (`evermap-agent sessions`; the
//! simulated store's sessions go through the same driver in `evermap-demo lifelong`).
//!
//! The recording is cut into `split` equal spans of time. Each span is a session: LLO starts afresh (its
//! own local frame, no knowledge of the others), and the session starts on the map with no prior: a
//! [`SessionStart`] decides where (its first few nodes merged and searched over the map of the earlier
//! sessions, retries while unplaced, probation until GLM matches along the route agree with the
//! placement); this shell only feeds it nodes and matches and acts on its events. Its nodes localize by
//! GLM against the older sessions' submaps while its own submaps join the map, and at its end stale
//! submaps are trimmed per the policy (by a session whose placement was committed).
//!
//! As in `offline_slam`, LLO runs on the calling thread and the map (relocalization, GLM searches on two
//! threads, optimization, trimming) on a named worker thread fed through a bounded channel.

use std::collections::BTreeMap;
use std::sync::mpsc;
use std::time::Instant;

use mapping::geometry::{Rigid2, Rigid2Ext as _};
use mapping::grid::ProbabilityGrid;
use mapping::lifelong::{
    GraphCounts, LifelongError, LifelongEvent, LifelongMap, LifelongOptions, RelocalizationOutcome,
    SessionStart, SessionStartEvent, StartSearch, render_submaps_max,
};
use mapping::local_slam::{
    LloDriver, LloEvent, LloNode, LocalTrajectoryBuilder, LocalTrajectoryBuilderOptions,
};
use mapping::metrics::{MatchScorer, ScoringOptions, SessionTrack, StartRecord};
use mapping::pose_graph::NodeId;
use mapping::sensor::{RangeData, SensorEvent, Timestamp};
use serde::{Deserialize, Serialize};

use crate::map_probes::{MapProbe, MapProbes};
use crate::offline_slam::run_searches;
use crate::process_stats::thread_cpu_ms;
use crate::source::Recording;

/// Configuration of a multi-session run; one TOML file, every field optional.
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SessionsConfig {
    /// Local LiDAR odometry (LLO), restarted for every session.
    pub local: LocalTrajectoryBuilderOptions,
    /// The lifelong map (global SLAM, the session start — `[lifelong.relocalization]` and
    /// `[lifelong.session_start]` —, trimming, policy).
    pub lifelong: LifelongOptions,
    /// What the scores count, and the window AMS searches each node's match in.
    pub scoring: ScoringOptions,
}

impl SessionsConfig {
    /// The configuration in the TOML file at `path`, or the defaults without one; `policy` overrides the
    /// file's trimming policy.
    pub fn load(
        path: Option<&std::path::Path>,
        policy: Option<mapping::lifelong::TrimPolicy>,
    ) -> Result<Self, SessionsError> {
        let mut config = match path {
            Some(path) => {
                let text =
                    std::fs::read_to_string(path).map_err(|source| SessionsError::ConfigFile {
                        path: path.display().to_string(),
                        source: Box::new(source),
                    })?;
                toml::from_str(&text).map_err(|source| SessionsError::ConfigFile {
                    path: path.display().to_string(),
                    source: Box::new(source),
                })?
            }
            None => Self::default(),
        };
        if let Some(policy) = policy {
            config.lifelong.policy = policy;
        }
        Ok(config)
    }
}

/// Errors of a multi-session run.
#[derive(Debug, thiserror::Error)]
pub enum SessionsError {
    /// The lifelong map refused the configuration, a session or a node.
    #[error("lifelong map: {0}")]
    Map(#[from] LifelongError),
    /// The configuration is invalid.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// The configuration file could not be read or parsed.
    #[error("configuration {path}: {source}")]
    ConfigFile {
        /// The file.
        path: String,
        /// Why.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A section of the configuration refused its options.
    #[error("invalid configuration: {0}")]
    Options(#[source] Box<dyn std::error::Error + Send + Sync>),
    /// The recording has no laser scans.
    #[error("the recording has no laser scans")]
    NoScans,
    /// The worker thread died.
    #[error("lifelong map worker failed: {0}")]
    Worker(String),
    /// The worker thread could not be started.
    #[error("lifelong map worker failed: {0}")]
    Spawn(#[source] std::io::Error),
}

/// One optimization's figures in a [`SessionSummary`].
#[derive(Clone, Debug, Serialize)]
pub struct OptimizationFigures {
    /// Levenberg-Marquardt steps tried.
    pub iterations: usize,
    /// Steps accepted.
    pub accepted_steps: usize,
    /// χ² before and after (robust losses ignored).
    pub chi2: [f64; 2],
    /// Why it stopped.
    pub termination: String,
    /// Poses it moved.
    pub free_variables: usize,
    /// Values stored for its Cholesky factor, fill-in included: with `free_variables`, what each step
    /// costs.
    pub factor_nonzeros: usize,
}

impl SessionSummary {
    /// Levenberg-Marquardt steps tried at the session's end (each one numeric factorization), over every
    /// optimization `finish_ms` covers.
    pub fn finish_iterations(&self) -> usize {
        self.finish_optimizations.iter().map(|o| o.iterations).sum()
    }

    /// The largest Cholesky factor (values stored) of the session end's optimizations; 0 if none
    /// factorized.
    pub fn finish_factor_nonzeros(&self) -> usize {
        self.finish_optimizations
            .iter()
            .map(|o| o.factor_nonzeros)
            .max()
            .unwrap_or(0)
    }
}

/// The check of a robot's dock at a session's start ([`SessionStartEvent::DockChecked`]).
#[derive(Clone, Debug, Serialize)]
pub struct DockCheckFigures {
    /// Whether the evidence agreed with the dock (the session was placed there, on probation).
    pub agreed: bool,
    /// How well the first nodes' cloud fit the map at the dock (mean probability).
    pub fit: Option<f32>,
    /// The dock's weakest paired test against the whole map's other candidates (positive: the dock fits
    /// better).
    pub weakest_z: Option<f64>,
}

/// One whole-map search of a session start in a [`SessionSummary`].
#[derive(Clone, Debug, Serialize)]
pub struct SearchFigures {
    /// The node it was made at (index in the session).
    pub node: usize,
    /// `placed`, `ambiguous`, `not_found` or `revoked_again` (it found a revoked placement).
    pub outcome: &'static str,
    /// Its paired test of the best against the weakest rival (`None` for the first search, which ranks
    /// by score margin).
    pub weakest_z: Option<f64>,
    /// How well its cloud fit the map at its best candidate (mean probability on the unfiltered map, the
    /// score the fit floor `min_unfiltered_score` judges; `None` without a candidate, or where the
    /// first search refused its best as ambiguous by score margin before judging the fit).
    pub fit: Option<f32>,
    /// How far its best candidate (the placement, for `placed`) put the session's latest node from the
    /// truth, metres (filled in by the scoring shell; `None` without a candidate or truth).
    pub best_error_m: Option<f64>,
}

/// What happened in one session.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SessionSummary {
    /// Session id (0, 1, …).
    pub session: u32,
    /// First data time of the session's span.
    pub start_time: Timestamp,
    /// Scans in the span.
    pub scans: usize,
    /// Nodes the session added.
    pub nodes_added: usize,
    /// Whether the first whole-map search (after the hold-back) placed the session (always false for
    /// session 0).
    pub relocalized: bool,
    /// Whole-map searches after the first (retries while the session was unplaced).
    pub relocalization_retries: usize,
    /// The node index at which a retry placed the session (tentatively), if one did.
    pub placed_by_retry_at_node: Option<usize>,
    /// The node index at which the session's placement was committed (probation passed), if it was.
    pub committed_at_node: Option<usize>,
    /// Placements revoked during the session (probation failed: `disagreement` or `timeout`), in order.
    pub revoked: Vec<String>,
    /// Whether the session ended with its placement still on probation (then dropped, like an unplaced
    /// session).
    pub ended_on_probation: bool,
    /// The time of that node: the session was not localized before it.
    pub placed_at_time: Option<Timestamp>,
    /// Its branch-and-bound score.
    pub relocalization_score: Option<f32>,
    /// Why session-start relocalization was refused: `ambiguous` (a clearly different pose scored within
    /// the margin), `not_found` (nothing reached the minimum score); `None` when it placed the session.
    pub relocalization_refused: Option<String>,
    /// When refused as ambiguous, the best and the runner-up scores.
    pub relocalization_ambiguity: Option<[f32; 2]>,
    /// When refused as ambiguous, the runner-up pose in the best pose's frame `[x, y, θ]` (m, m, rad).
    pub relocalization_runner_up_from_best: Option<[f64; 3]>,
    /// Wall time of the first whole-map search, milliseconds.
    pub relocalization_ms: f64,
    /// Wall time of every whole-map search of the session, milliseconds.
    pub relocalization_ms_total: f64,
    /// Distance (m) between the relocalized pose of the session's first node and its final estimate
    /// (how far off relocalization was, judged by the finished map).
    pub relocalization_offset_m: Option<f64>,
    /// Whether the session ended placed in the map with its placement committed.
    pub placed: bool,
    /// GLM constraints accepted during the session between its nodes and older sessions' submaps.
    pub cross_session_closures: usize,
    /// GLM constraints accepted during the session in all.
    pub closures: usize,
    /// Stale submaps trimmed when the session ended.
    pub trimmed: usize,
    /// The session's own submaps dropped when it ended, since it does not update the map (never placed;
    /// `frozen`).
    pub dropped: usize,
    /// Nodes removed with them.
    pub nodes_trimmed: usize,
    /// Chow–Liu tree constraints added in their place.
    pub tree_edges: usize,
    /// Mean KL divergence (nats) of the trims that measured one (`clt`: over each blanket).
    pub trim_kld_mean: Option<f64>,
    /// Mean score of the closures accepted during the session, within it and against older sessions.
    pub ams: f64,
    /// Mean score of the accepted matches of the session's nodes against older sessions' submaps (the
    /// paper's AMS: how well the session matches the map it localizes in); `None` when there was none.
    pub cross_session_ams: Option<f64>,
    /// Graph size after the session ended.
    pub counts: GraphCounts,
    /// Wall time of pose graph refinement at the session's end (`finish_session`: the final
    /// optimization, trimming, sparsification, as the server runs it), milliseconds.
    pub finish_ms: f64,
    /// CPU time of that refinement on the thread that ran it, milliseconds (what it costs, however
    /// loaded the machine is; `None` where the platform does not report it).
    pub finish_cpu_ms: Option<f64>,
    /// Each optimization `finish_ms` covers, in order (the session's final one, then one after its trims
    /// once `optimize_every_n_sparsifications` have accumulated): where the steps went.
    pub finish_optimizations: Vec<OptimizationFigures>,
    /// Every whole-map search of the session start, in order: what it answered and how decisively.
    pub searches: Vec<SearchFigures>,
    /// Where the session started from the robot's dock ([`SessionInput::from_dock`]): the check of it.
    pub dock_check: Option<DockCheckFigures>,
    /// Time of the session's first node (the one relocalization places).
    pub first_node_time: Option<Timestamp>,
    /// Global pose `[x, y, θ]` (m, m, rad) relocalization gave the session's first node.
    pub relocalized_first_pose: Option<[f64; 3]>,
    /// Peak resident memory of the process when the session ended, MB (Linux only).
    pub peak_rss_mb: Option<f64>,
    /// Resident memory of the process when the session ended, MB (Linux only): unlike the peak, it
    /// falls when memory is given back, so a trend over sessions shows in it.
    pub rss_mb: Option<f64>,
}

/// One session's sensor data.
pub struct SessionInput {
    /// Time-ordered scans, odometry and IMU readings.
    pub events: Vec<SensorEvent>,
    /// The LiDAR's extrinsic.
    pub base_from_laser: Rigid2,
    /// The robot starts from its dock: it believes it is where its last session ended (the last pose it
    /// had there, when that session was placed) and checks that first ([`SessionStart::from_dock`]).
    pub from_dock: bool,
}

/// What one session lived, recorded as it happened: the robot's estimate at the time of each scan, the
/// placement it committed to, each node's match score against the map as it was then, and the
/// trajectory smoothed at the session's end. [`Self::track`] hands it to
/// [`mapping::metrics::score_session`].
#[derive(Clone, Debug, Default)]
pub struct SessionRecord {
    /// Session id.
    pub session: u32,
    /// Time of the session's first event.
    pub start_time: Timestamp,
    /// `map_from_base` of each matched scan as the robot estimated it at that scan: its node's global
    /// pose right after the map took the node in (its matches and any placement included), composed with
    /// LLO's motion since. Only scans while the session was placed (on probation — the robot navigates
    /// with a tentative placement too — or committed) have one (session 0: every scan).
    pub online: Vec<(Timestamp, Rigid2)>,
    /// `map_from_base` of each matched scan when the session ended (after its final optimization).
    pub smoothed: Vec<(Timestamp, Rigid2)>,
    /// What its session start decided: the placements the robot acted on, the one it committed to and
    /// each whole-map search's best (empty for session 0, which defines the map).
    pub start: StartRecord,
    /// Per node, in order, its branch-and-bound score ([`MatchScorer`], within the scoring's match window
    /// of the robot's estimate) against the map of the finished sessions rendered when the session
    /// started; 0 while the session was not placed.
    /// Empty for session 0 (no map before it).
    pub match_scores: Vec<f64>,
}

impl SessionRecord {
    /// The record as [`mapping::metrics::score_session`] takes it, with the session's truth.
    pub fn track<'a>(&'a self, truth: &'a [(Timestamp, Rigid2)]) -> SessionTrack<'a> {
        SessionTrack {
            truth,
            start_time: self.start_time,
            online: &self.online,
            smoothed: &self.smoothed,
            placements: &self.start.placements,
            committed: self.start.committed,
            match_scores: &self.match_scores,
            search_bests: &self.start.search_bests,
        }
    }
}

/// Handed to the caller of [`run_session_inputs`] when a session has ended (on the map's worker thread).
pub struct SessionEnd<'a> {
    /// What happened.
    pub summary: &'a SessionSummary,
    /// What it lived.
    pub record: &'a SessionRecord,
    /// The map right after the session ended (trimmed).
    pub map: &'a LifelongMap,
}

/// What a multi-session run produced.
pub struct SessionsRun {
    /// The final global pose of every scan LLO matched, in time order: from the final map where its node
    /// is still there, else from the last estimate before its node was trimmed.
    pub scan_poses: Vec<(Timestamp, Rigid2)>,
    /// Start time of each session's span (session `k` runs from `boundaries[k]` to `boundaries[k + 1]`).
    pub boundaries: Vec<Timestamp>,
    /// Per session.
    pub sessions: Vec<SessionSummary>,
    /// The map after the last session.
    pub map: LifelongMap,
    /// Each node's range data in its tracking frame, and its last known global pose (for rendering).
    pub node_range_data: BTreeMap<NodeId, (Rigid2, RangeData)>,
    /// Data duration, seconds: the sum of each session's first-to-last event span.
    pub data_duration_s: f64,
    /// What each session that had data lived, in session order.
    pub records: Vec<SessionRecord>,
    /// The answer to each of the run's [`MapProbe`]s, in their order.
    pub probe_poses: Vec<Option<Rigid2>>,
}

enum Message {
    Start {
        session: u32,
        /// The session's first event.
        start_time: Timestamp,
        /// See [`SessionInput::from_dock`].
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

/// A matched scan: its time, LLO's pose and the node it follows.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ScanAnchor {
    pub(crate) time: Timestamp,
    pub(crate) local_pose: Rigid2,
    pub(crate) node: Option<NodeId>,
}

/// Where `run_sessions` cuts `recording` into `split` sessions: the start time of each (session `k` runs
/// from `boundaries[k]` to `boundaries[k + 1]`).
pub fn session_boundaries(
    recording: &Recording,
    split: usize,
) -> Result<Vec<Timestamp>, SessionsError> {
    if split == 0 {
        return Err(SessionsError::Config("split must be at least 1".into()));
    }
    let (Some(first), Some(last)) = (recording.events.first(), recording.events.last()) else {
        return Err(SessionsError::NoScans);
    };
    let data_duration_s = last.time().seconds_since(first.time());
    Ok((0..split)
        .map(|k| {
            first
                .time()
                .offset_by(data_duration_s * k as f64 / split as f64)
        })
        .collect())
}

/// Runs `recording` as `split` time sessions (see the module docs), answering `probes` on the way.
/// `progress` gets the number of scans processed so far.
pub fn run_sessions(
    recording: &Recording,
    split: usize,
    from_dock: bool,
    config: &SessionsConfig,
    probes: &[MapProbe],
    progress: &mut dyn FnMut(usize),
) -> Result<SessionsRun, SessionsError> {
    let boundaries = session_boundaries(recording, split)?;
    let data_duration_s = match (recording.events.first(), recording.events.last()) {
        (Some(first), Some(last)) => last.time().seconds_since(first.time()),
        _ => 0.0,
    };
    let session_of = |t: Timestamp| boundaries.partition_point(|b| *b <= t).saturating_sub(1);
    let mut inputs: Vec<SessionInput> = (0..split)
        .map(|_| SessionInput {
            events: Vec::new(),
            base_from_laser: recording.base_from_laser,
            from_dock,
        })
        .collect();
    for event in &recording.events {
        inputs[session_of(event.time())].events.push(event.clone());
    }
    let mut run = run_session_inputs(inputs.into_iter(), config, probes, progress, &mut |_| {})?;
    // Spans without data still count as sessions of the split.
    run.boundaries = boundaries;
    run.data_duration_s = data_duration_s;
    Ok(run)
}

/// Runs each of `inputs` as one session, in order, through the lifelong map (see the module docs).
/// Sessions are pulled from the iterator one at a time, so a simulator can generate them lazily.
/// `probes` are answered on the way (see [`MapProbe`]); `progress` gets the number of scans processed so
/// far; `on_session_end` is called on the map's worker thread as each session ends (a long run can report
/// what it measured so far).
pub fn run_session_inputs(
    inputs: impl Iterator<Item = SessionInput>,
    config: &SessionsConfig,
    probes: &[MapProbe],
    progress: &mut dyn FnMut(usize),
    on_session_end: &mut (dyn FnMut(&SessionEnd<'_>) + Send),
) -> Result<SessionsRun, SessionsError> {
    config
        .local
        .validate()
        .map_err(|e| SessionsError::Options(e.into()))?;
    config
        .scoring
        .validate()
        .map_err(|e| SessionsError::Options(e.into()))?;
    let map = LifelongMap::new(config.lifelong.clone())?;

    let (sender, receiver) = mpsc::sync_channel::<Message>(256);
    std::thread::scope(|scope| {
        let worker = std::thread::Builder::new()
            .name("lifelong-map".into())
            .spawn_scoped(scope, move || {
                worker(
                    map,
                    config,
                    MapProbes::new(probes),
                    &receiver,
                    on_session_end,
                )
            })
            .map_err(SessionsError::Spawn)?;

        let mut anchors: Vec<(u32, ScanAnchor)> = Vec::new();
        let mut session_anchors: Vec<ScanAnchor> = Vec::new();
        let mut node_data: BTreeMap<NodeId, (Rigid2, RangeData)> = BTreeMap::new();
        let mut scans_per_session: Vec<usize> = Vec::new();
        let mut boundaries: Vec<Timestamp> = Vec::new();
        let mut data_duration_s = 0.0;
        let mut scans_done = 0;
        let send = |m: Message| sender.send(m).is_ok();
        for (session, input) in inputs.enumerate() {
            let session = u32::try_from(session)
                .map_err(|_| SessionsError::Config("too many sessions".into()))?;
            let (Some(first), Some(last)) = (input.events.first(), input.events.last()) else {
                // An empty session still exists (its id is used) but adds nothing.
                scans_per_session.push(0);
                boundaries.push(boundaries.last().copied().unwrap_or_default());
                continue;
            };
            boundaries.push(first.time());
            data_duration_s += last.time().seconds_since(first.time());
            let mut scans = 0usize;
            let mut llo = LloDriver::new(config.local.clone());
            let mut next_index = 0u32;
            let mut last_node: Option<NodeId> = None;
            let mut alive = send(Message::Start {
                session,
                start_time: first.time(),
                from_dock: input.from_dock,
            });
            for event in mapping::sensor::collate_for_llo(&input.events) {
                if matches!(event, SensorEvent::Scan(_)) {
                    scans_done += 1;
                    scans += 1;
                }
                let LloEvent::ScanMatched {
                    result, range_data, ..
                } = llo.add_event(event, &input.base_from_laser)
                else {
                    continue;
                };
                if let Some(insertion) = result.insertion {
                    let id = NodeId {
                        trajectory: session,
                        index: next_index,
                    };
                    next_index += 1;
                    last_node = Some(id);
                    node_data.insert(id, (result.local_pose, range_data));
                    let message = Message::Node {
                        session,
                        node: insertion.into_llo_node(),
                    };
                    alive = alive && send(message);
                    if !alive {
                        break;
                    }
                }
                let anchor = ScanAnchor {
                    time: result.time,
                    local_pose: result.local_pose,
                    node: last_node,
                };
                anchors.push((session, anchor));
                session_anchors.push(anchor);
                if scans_done % 64 == 0 {
                    progress(scans_done);
                }
            }
            scans_per_session.push(scans);
            alive = alive
                && send(Message::Finish {
                    session,
                    active_submaps: active_grids(llo.builder()),
                    scans: std::mem::take(&mut session_anchors),
                });
            if !alive {
                // The worker stopped; its error is reported by `join` below.
                break;
            }
        }
        progress(scans_done);
        drop(sender);
        let output = worker
            .join()
            .map_err(|_| SessionsError::Worker("the lifelong map thread panicked".into()))??;
        let WorkerOutput {
            map,
            mut sessions,
            retired,
            records,
            probe_poses,
        } = output;

        // Last known global pose of every node: the final map, else its pose when it was trimmed.
        let mut node_pose: BTreeMap<NodeId, Rigid2> = retired;
        for (id, _, pose) in map.node_poses() {
            node_pose.insert(id, pose);
        }
        let scan_pose = |poses: &BTreeMap<NodeId, Rigid2>, a: &ScanAnchor| {
            let node = a.node?;
            let global = poses.get(&node)?;
            let (local, _) = node_data.get(&node)?;
            Some((a.time, global * local.inverse() * a.local_pose))
        };
        let scan_poses = anchors
            .iter()
            .filter_map(|(_, a)| scan_pose(&node_pose, a))
            .collect();
        for summary in &mut sessions {
            let k = summary.session as usize;
            summary.start_time = boundaries[k];
            summary.scans = scans_per_session[k];
        }
        let node_range_data = node_data
            .into_iter()
            .filter_map(|(id, (_, data))| Some((id, (*node_pose.get(&id)?, data))))
            .collect();
        Ok(SessionsRun {
            scan_poses,
            boundaries,
            sessions,
            map,
            node_range_data,
            data_duration_s,
            records,
            probe_poses,
        })
    })
}

/// The grids of LLO's submaps still active (to finish them when the session ends).
fn active_grids(llo: &LocalTrajectoryBuilder) -> Vec<(usize, ProbabilityGrid)> {
    llo.active_submaps()
        .submaps()
        .iter()
        .map(|(index, submap)| (*index, submap.grid.cropped_to_known()))
        .collect()
}

struct WorkerOutput {
    map: LifelongMap,
    sessions: Vec<SessionSummary>,
    /// Every node's pose when the last session that saw it in the map ended.
    retired: BTreeMap<NodeId, Rigid2>,
    records: Vec<SessionRecord>,
    probe_poses: Vec<Option<Rigid2>>,
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

fn worker(
    mut map: LifelongMap,
    config: &SessionsConfig,
    mut probes: MapProbes,
    receiver: &mpsc::Receiver<Message>,
    on_session_end: &mut (dyn FnMut(&SessionEnd<'_>) + Send),
) -> Result<WorkerOutput, SessionsError> {
    let relocalization = &config.lifelong.relocalization;
    let mut sessions: Vec<SessionSummary> = Vec::new();
    let mut retired: BTreeMap<NodeId, Rigid2> = BTreeMap::new();
    let mut records: Vec<SessionRecord> = Vec::new();
    // The current session's: node local poses, node poses as the robot had them when each was added,
    // and the map of the finished sessions as it was at its start (for the match scores).
    let mut node_local: BTreeMap<NodeId, Rigid2> = BTreeMap::new();
    let mut online_nodes: BTreeMap<NodeId, Rigid2> = BTreeMap::new();
    let mut map_at_start: Option<MatchScorer> = None;
    let mut priors: BTreeMap<u32, (Rigid2, Rigid2)> = BTreeMap::new();
    let mut scores: Vec<f32> = Vec::new();
    // The current session's start (none for session 0, which defines the map) and its nodes' times.
    let mut start: Option<SessionStart> = None;
    let mut node_times: Vec<Timestamp> = Vec::new();
    // Acts on session `$session`'s start decisions `$decisions` with this worker's books
    // (`$first_search`: they come from its first whole-map search); see `act_on_start`.
    macro_rules! act_on_start {
        ($session:expr, $first_search:expr, $decisions:expr) => {
            act_on_start(
                &mut map,
                $session,
                $first_search,
                $decisions,
                &node_times,
                &node_local,
                sessions.last_mut(),
                records.last_mut(),
                &mut priors,
            )?
        };
    }
    for message in receiver {
        match message {
            Message::Start {
                session,
                start_time,
                from_dock,
            } => {
                scores.clear();
                node_local.clear();
                // Where the robot was at the end of its last session, as it had it then: its dock.
                let dock = online_nodes.values().next_back().copied();
                online_nodes.clear();
                node_times.clear();
                map_at_start = None;
                start = None;
                if session > 0 {
                    // AMS scores every scan against everything the map holds (each cell at the
                    // highest value any submap gives it: the definition every earlier figure used);
                    // the session start searches the map as `map_cells` renders it.
                    map_at_start =
                        render_submaps_max(map.placed_submaps(), relocalization.resolution)
                            .map(|grid| MatchScorer::new(&grid, config.scoring.match_window));
                    let rendered = map.relocalization_map(relocalization);
                    let search = rendered
                        .as_ref()
                        .map(|grid| StartSearch::new(grid, relocalization));
                    let options = config.lifelong.session_start.clone();
                    start = Some(
                        match dock.filter(|_| from_dock) {
                            Some(dock) => SessionStart::from_dock(options, search, dock),
                            None => SessionStart::new(options, search),
                        }
                        .map_err(|e| SessionsError::Options(e.into()))?,
                    );
                }
                // Every later session starts unplaced; its `SessionStart` places it.
                map.start_session(session, None)?;
                sessions.push(SessionSummary {
                    session,
                    ..SessionSummary::default()
                });
                records.push(SessionRecord {
                    session,
                    start_time,
                    ..SessionRecord::default()
                });
            }
            Message::Node { session, node } => {
                let (time, local_pose) = (node.time, node.local_pose);
                // The scans before this node were estimated from the map as it stands now.
                probes.answer_before(time, |id| map.global().node_pose(id));
                let scored_points = (session > 0).then(|| node.points.clone());
                let start_points = start.as_ref().map(|_| node.points.clone());
                let (id, events) = map.add_node(session, node)?;
                node_local.insert(id, local_pose);
                node_times.push(time);
                let mut decisions = Vec::new();
                let mut first_search = false;
                if let (Some(start), Some(points)) = (start.as_mut(), start_points) {
                    let began = Instant::now();
                    let searches = start.searches();
                    decisions = start.add_node(local_pose, points);
                    if let Some(summary) = sessions.last_mut() {
                        summary.first_node_time = node_times.first().copied();
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
                act_on_start!(session, first_search, &decisions);
                let jobs = map.take_search_jobs();
                let results = run_searches(map.constraint_builder(), &jobs);
                let mut events_after = map.add_search_results(results);
                events_after.extend(events);
                // The matches of this session's nodes against the existing map judge its placement.
                if let Some(start) = start.as_mut() {
                    let mut decisions = Vec::new();
                    for event in &events_after {
                        if let LifelongEvent::LoopClosureAdded(closure) = event
                            && closure.node.trajectory == session
                            && closure.submap.trajectory != session
                            && let Some(submap_pose) = map.global().submap_pose(closure.submap)
                        {
                            decisions.extend(start.add_match(
                                closure.node.index as usize,
                                submap_pose * closure.submap_from_node,
                                closure.submap,
                            ));
                        }
                    }
                    act_on_start!(session, false, &decisions);
                }
                if let Some(summary) = sessions.last_mut() {
                    summary.nodes_added += 1;
                    count_closures(summary, &events_after, &mut scores);
                }
                // What the robot has now, at this scan: placed (on probation or committed) or not, and
                // where.
                let online = map
                    .global()
                    .node_pose(id)
                    .filter(|_| map.is_placed(session));
                if let Some(pose) = online {
                    online_nodes.insert(id, pose);
                }
                if let (Some(points), Some(record)) = (scored_points, records.last_mut()) {
                    let score = match (online, &map_at_start) {
                        (Some(pose), Some(scorer)) => scorer.score(&points, &pose),
                        _ => 0.0,
                    };
                    record.match_scores.push(score);
                }
            }
            Message::Finish {
                session,
                active_submaps,
                scans,
            } => {
                if let Some(last) = scans.last() {
                    probes
                        .answer_before(Timestamp(last.time.0 + 1), |id| map.global().node_pose(id));
                }
                map.finish_submaps(session, active_submaps)?;
                let jobs = map.take_search_jobs();
                let results = run_searches(map.constraint_builder(), &jobs);
                let events = map.add_search_results(results);
                // Every node's pose before pose graph refinement: what a node `finish_session` removes
                // (trimmed, or its session dropped) keeps; the rest are updated after it.
                let mut at_session_end = BTreeMap::new();
                let mut note_poses = |map: &LifelongMap| {
                    for (id, _, pose) in map.node_poses() {
                        retired.insert(id, pose);
                        if id.trajectory == session {
                            at_session_end.insert(id, pose);
                        }
                    }
                };
                note_poses(&map);
                // What the session's end decides of its start (a dock placement never disputed).
                if let Some(start) = start.as_mut() {
                    let decisions = start.finish();
                    act_on_start!(session, false, &decisions);
                }
                let on_probation = map.is_on_probation(session);
                let start_ms = Instant::now();
                let start_cpu_ms = thread_cpu_ms();
                let events_finish = map.finish_session(session)?;
                let finish_ms = start_ms.elapsed().as_secs_f64() * 1e3;
                let finish_cpu_ms = thread_cpu_ms()
                    .zip(start_cpu_ms)
                    .map(|(end, start)| end - start);
                note_poses(&map);
                let placed = map.is_placed(session) && !on_probation;
                let counts = map.counts();
                let first_node = NodeId {
                    trajectory: session,
                    index: 0,
                };
                let offset = priors.get(&session).and_then(|(prior, first_local)| {
                    let last = retired.get(&first_node)?;
                    Some(
                        ((prior * first_local).translation.vector - last.translation.vector).norm(),
                    )
                });
                if let Some(summary) = sessions.last_mut() {
                    count_closures(summary, &events, &mut scores);
                    let mut klds = Vec::new();
                    for event in &events_finish {
                        if let LifelongEvent::SubmapTrimmed {
                            dropped,
                            nodes_removed,
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
                            summary.nodes_trimmed += nodes_removed;
                            summary.tree_edges += tree_edges;
                            klds.extend(*kld);
                        }
                    }
                    summary.trim_kld_mean =
                        (!klds.is_empty()).then(|| klds.iter().sum::<f64>() / klds.len() as f64);
                    summary.placed = placed;
                    summary.ended_on_probation = on_probation;
                    summary.counts = counts;
                    summary.finish_ms = finish_ms;
                    summary.finish_cpu_ms = finish_cpu_ms;
                    summary.finish_optimizations = events_finish
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
                        .collect();
                    summary.relocalization_offset_m = offset;
                    summary.peak_rss_mb = crate::process_stats::peak_rss_mb();
                    summary.rss_mb = crate::process_stats::current_rss_mb();
                }
                probes.add_ended_session(&scans, &node_local);
                if let (Some(summary), Some(record)) = (sessions.last(), records.last_mut()) {
                    record.online = poses_of_scans(&scans, &node_local, &online_nodes);
                    record.smoothed = poses_of_scans(&scans, &node_local, &at_session_end);
                    on_session_end(&SessionEnd {
                        summary,
                        record,
                        map: &map,
                    });
                }
            }
        }
    }
    // Nodes still in the map report their final pose; `retired` keeps the rest.
    Ok(WorkerOutput {
        map,
        sessions,
        retired,
        records,
        probe_poses: probes.into_answers(),
    })
}

/// Acts on the session start's `decisions` for `session` (`first_search`: they come from its first
/// whole-map search): places it in the map on probation, commits or revokes its placement, and notes
/// what happened in its summary and record.
#[allow(clippy::too_many_arguments)]
fn act_on_start(
    map: &mut LifelongMap,
    session: u32,
    first_search: bool,
    decisions: &[SessionStartEvent],
    node_times: &[Timestamp],
    node_local: &BTreeMap<NodeId, Rigid2>,
    mut summary: Option<&mut SessionSummary>,
    mut record: Option<&mut SessionRecord>,
    priors: &mut BTreeMap<u32, (Rigid2, Rigid2)>,
) -> Result<(), SessionsError> {
    let local = |node: usize| {
        node_local.get(&NodeId {
            trajectory: session,
            index: u32::try_from(node).ok()?,
        })
    };
    let mut from_dock = false;
    for decision in decisions {
        map.apply_start_decision(session, decision)?;
        if let Some(record) = record.as_deref_mut() {
            record
                .start
                .record(decision, node_times, &|node| local(node).copied());
        }
        match decision {
            SessionStartEvent::DockChecked {
                agreed,
                fit,
                weakest_z,
                ..
            } => {
                from_dock = *agreed;
                if let Some(summary) = summary.as_deref_mut() {
                    summary.dock_check = Some(DockCheckFigures {
                        agreed: *agreed,
                        fit: *fit,
                        weakest_z: *weakest_z,
                    });
                }
            }
            SessionStartEvent::Refused {
                node,
                outcome,
                weakest_z,
                fit,
                ..
            } => {
                if let Some(summary) = summary.as_deref_mut() {
                    summary.searches.push(SearchFigures {
                        node: *node,
                        outcome: match outcome {
                            RelocalizationOutcome::Ambiguous { .. } => "ambiguous",
                            RelocalizationOutcome::NotFound => "not_found",
                            RelocalizationOutcome::Found(_) => "revoked_again",
                        },
                        weakest_z: *weakest_z,
                        fit: *fit,
                        best_error_m: None,
                    });
                    // The first search's refusal, for the report.
                    if first_search {
                        match *outcome {
                            RelocalizationOutcome::Ambiguous {
                                score,
                                runner_up_score,
                                runner_up_from_best,
                            } => {
                                summary.relocalization_refused = Some("ambiguous".into());
                                summary.relocalization_ambiguity = Some([score, runner_up_score]);
                                summary.relocalization_runner_up_from_best =
                                    Some(runner_up_from_best);
                            }
                            RelocalizationOutcome::NotFound => {
                                summary.relocalization_refused = Some("not_found".into());
                            }
                            RelocalizationOutcome::Found(_) => {
                                summary.relocalization_refused = Some("revoked_before".into());
                            }
                        }
                    }
                }
            }
            SessionStartEvent::Placed(placement) => {
                if let Some(summary) = summary.as_deref_mut() {
                    summary.searches.push(SearchFigures {
                        node: placement.node,
                        outcome: "placed",
                        weakest_z: placement.weakest_z,
                        fit: placement.fit,
                        best_error_m: None,
                    });
                    if first_search {
                        summary.relocalized = true;
                    } else if from_dock {
                        summary.placed_at_time = node_times.get(placement.node).copied();
                    } else {
                        summary.placed_by_retry_at_node = Some(placement.node);
                        summary.placed_at_time = node_times.get(placement.node).copied();
                    }
                    summary.relocalization_score = placement.score;
                    if let Some(first_local) = local(0) {
                        let pose = placement.global_from_local * first_local;
                        priors.insert(session, (placement.global_from_local, *first_local));
                        summary.relocalized_first_pose = Some([
                            pose.translation.vector.x,
                            pose.translation.vector.y,
                            pose.theta(),
                        ]);
                    }
                }
            }
            SessionStartEvent::Committed { node, .. } => {
                if let Some(summary) = summary.as_deref_mut() {
                    summary.committed_at_node = Some(*node);
                }
            }
            SessionStartEvent::Revoked { reason, .. } => {
                priors.remove(&session);
                if let Some(summary) = summary.as_deref_mut() {
                    summary.revoked.push(reason.as_str().into());
                }
            }
            SessionStartEvent::GaveUp { .. } => {}
        }
    }
    Ok(())
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
