//! One recording run as several time sessions through the lifelong map (`evermap-agent sessions`; the
//! simulated store's sessions go through the same driver in `evermap-demo lifelong`).
//!
//! The recording is cut into `split` equal spans of time. Each span is a session: LLO starts afresh (its
//! own local frame, no knowledge of the others), and the session starts on the map with no prior: a
//! [`SessionStart`] decides where (its first few nodes merged and searched over the map of the earlier
//! sessions, retries while unplaced, probation until GLM matches along the route agree with the
//! placement); this shell only feeds it nodes and matches and acts on its events. Its nodes localize by
//! GLM against the older sessions' submaps while its own submaps join the map, and at its end stale
//! submaps are trimmed per the policy (by a session whose placement was committed). The pose the robot
//! has at each node (`SessionRecord::online`, what "at the time" scores) fuses its best matches
//! against the older sessions' map between optimizations, as the fleet's robots do
//! ([`mapping::lifelong::LiveAnchor`]).
//!
//! As in `offline_slam`, LLO runs on the calling thread and the map (relocalization, GLM searches on two
//! threads, optimization, trimming) on a named worker thread fed through a bounded channel.
//!
//! [`SessionStart`]: mapping::lifelong::SessionStart

use std::collections::BTreeMap;
use std::sync::mpsc;

use mapping::geometry::Rigid2;
use mapping::grid::ProbabilityGrid;
use mapping::lifelong::LifelongMap;
use mapping::local_slam::LocalTrajectoryBuilder;
use mapping::pose_graph::NodeId;
use mapping::sensor::{RangeData, ScanBacklog, ScanStamps, SensorEvent, Timestamp};

use crate::map_probes::{MapProbe, MapProbes};
use crate::source::Recording;

mod act_on_start;
mod carried_nodes;
mod map_worker;
mod session_feed;
mod session_record;
mod session_summary;
mod sessions_config;
mod sessions_error;

use map_worker::{Message, worker};
use session_feed::SessionFeed;
pub use session_record::SessionRecord;
pub use session_summary::{
    DockCheckFigures, OptimizationFigures, ProbationStepFigures, SearchFigures, SessionSummary,
};
pub use sessions_config::SessionsConfig;
pub use sessions_error::SessionsError;

/// One session's sensor data.
pub struct SessionInput {
    /// Scans, odometry and IMU readings in stamp order (or as `mapping::sensor::ScanBacklog` hands them
    /// on); each session's are collated for LLO (`mapping::sensor::collate_for_llo`).
    pub events: Vec<SensorEvent>,
    /// The LiDAR's extrinsic.
    pub base_from_laser: Rigid2,
    /// The robot starts from its dock: it believes it is where its last session ended (the last pose it
    /// had there, when that session was placed) and checks that first ([`SessionStart::from_dock`]).
    ///
    /// [`SessionStart::from_dock`]: mapping::lifelong::SessionStart::from_dock
    pub from_dock: bool,
}

/// Handed to the caller of [`run_session_inputs`] when a session has ended (on the map's worker thread).
pub struct SessionEnd<'a> {
    /// What happened.
    pub summary: &'a SessionSummary,
    /// What it lived.
    pub record: &'a SessionRecord,
    /// The map right after the session ended (trimmed).
    pub map: &'a LifelongMap,
    /// The robot's last pose of the session as it had it then (its dock for the next session), if the
    /// session was placed; what a resumed run needs besides the map ([`RunResume::dock`]).
    pub dock: Option<Rigid2>,
}

/// Where a run picks up from an earlier one (`evermap-demo lifelong --resume`): the map as it stood after
/// the earlier run's last ended session, restored from its checkpoint (`proto::SiteCheckpoint`), and the
/// robot's dock then. Fed the same later sessions, the resumed run does what the uninterrupted one did.
pub struct RunResume {
    /// The map after session `first_session - 1`.
    pub map: LifelongMap,
    /// The id of the first session the run feeds.
    pub first_session: u32,
    /// [`SessionEnd::dock`] of session `first_session - 1`.
    pub dock: Option<Rigid2>,
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
    /// Scans of a driver's backlog the run put back at the times they were taken
    /// (`mapping::sensor::ScanBacklog`). [`run_sessions`] hands `scan_poses` and each record's `online`
    /// back at the scans' stamps, as the references are.
    pub scans_retimed: usize,
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
///
/// The recording goes through the stages every shell's LLO input goes through: a driver's backlog of
/// scans put back at the times they were taken (`mapping::sensor::ScanBacklog`, as `offline`'s
/// `RecordingStream`), then each session's events collated for LLO. `probes` and the outputs are at the
/// scans' stamps, as the recording's references are.
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
    let (events, retimed) = ScanBacklog::retime(&recording.events);
    let stamps = ScanStamps::new(&retimed);
    for event in events {
        inputs[session_of(event.time())].events.push(event);
    }
    // The run knows a re-timed scan by the time it was taken.
    let probes: Vec<MapProbe> = probes
        .iter()
        .map(|p| MapProbe {
            earlier: stamps.taken(p.earlier),
            later: stamps.taken(p.later),
        })
        .collect();
    let mut run = run_session_inputs(inputs.into_iter(), config, &probes, progress, &mut |_| {})?;
    // Spans without data still count as sessions of the split.
    run.boundaries = boundaries;
    run.data_duration_s = data_duration_s;
    run.scans_retimed = stamps.len();
    for (time, _) in &mut run.scan_poses {
        *time = stamps.stamped(*time);
    }
    for record in &mut run.records {
        for (time, _) in &mut record.online {
            *time = stamps.stamped(*time);
        }
    }
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
    run_from(None, inputs, config, probes, progress, on_session_end)
}

/// [`run_session_inputs`] picking up where an earlier run left off (see [`RunResume`]): `inputs` are
/// sessions `resume.first_session`, `resume.first_session + 1`, ... The run's outputs cover those
/// sessions only.
pub fn resume_session_inputs(
    resume: RunResume,
    inputs: impl Iterator<Item = SessionInput>,
    config: &SessionsConfig,
    progress: &mut dyn FnMut(usize),
    on_session_end: &mut (dyn FnMut(&SessionEnd<'_>) + Send),
) -> Result<SessionsRun, SessionsError> {
    run_from(Some(resume), inputs, config, &[], progress, on_session_end)
}

fn run_from(
    resume: Option<RunResume>,
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
    let (map, first_session, dock) = match resume {
        Some(r) => (r.map, r.first_session, r.dock),
        None => (LifelongMap::new(config.lifelong.clone())?, 0, None),
    };

    let (sender, receiver) = mpsc::sync_channel::<Message>(256);
    std::thread::scope(|scope| {
        let worker = std::thread::Builder::new()
            .name("lifelong-map".into())
            .spawn_scoped(scope, move || {
                worker(
                    map,
                    dock,
                    config,
                    MapProbes::new(probes),
                    &receiver,
                    on_session_end,
                )
            })
            .map_err(SessionsError::Spawn)?;

        let mut feed = SessionFeed::starting_at(first_session);
        let send = |m: Message| sender.send(m).is_ok();
        for (session, input) in inputs.enumerate() {
            let session = u32::try_from(session)
                .ok()
                .and_then(|k| k.checked_add(first_session))
                .ok_or_else(|| SessionsError::Config("too many sessions".into()))?;
            if !feed.feed(session, &input, config, &send, progress) {
                // The worker stopped; its error is reported by `join` below.
                break;
            }
        }
        progress(feed.scans_done);
        drop(sender);
        let output = worker
            .join()
            .map_err(|_| SessionsError::Worker("the lifelong map thread panicked".into()))??;
        Ok(feed.into_run(output))
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
