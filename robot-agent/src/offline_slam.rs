//! The SLAM pipeline: one sensor stream in (a recording, or a live ROS 2 robot), an optimized trajectory
//! and map out. One driver, [`run_slam`], for both: a file and a live robot are mapped by the same code.
//!
//! LLO runs on the calling thread; global SLAM (GLM searches and optimization) runs on a named worker
//! thread fed through a bounded channel, so both cores of a small robot computer are busy. A
//! [`SlamObserver`] (the live shell's ROS 2 publisher) hears each matched scan, each odometry reading and,
//! after each optimization, the global frame and (if asked for) the map rendered from the finished
//! submaps.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::mpsc;

use mapping::geometry::Rigid2;
use mapping::global_slam::{
    ConstraintBuilder, GlobalSlam, GlobalSlamError, GlobalSlamEvent, GlobalSlamOptions,
    LoopClosure, MatchDecided, SearchJob,
};
use mapping::grid::{MapLimits, ProbabilityGrid, RangeDataInserter, RangeDataInserterOptions};
use mapping::lifelong::{PlacedGrid, RelocalizationOptions, render_submaps_max};
use mapping::local_slam::{
    CorrelativeBranch, LloDriver, LloEvent, LloNode, LocalTrajectoryBuilderOptions,
};
use mapping::pose_graph::{NodeId, OptimizationSummary};
use mapping::sensor::{OdometryReading, RangeData, RangeStats, SensorEvent, Timestamp};
use serde::Deserialize;

use crate::config_file::{ConfigFileError, load_toml};
use crate::source::{Recording, RecordingStream, SensorStream};

/// Everything the agent's SLAM can be configured with; one TOML file, every field optional.
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SlamConfig {
    /// Local LiDAR odometry (LLO).
    pub local: LocalTrajectoryBuilderOptions,
    /// Global matching and pose graph (GLM + PGR).
    pub global: GlobalSlamOptions,
    /// Whole-map relocalization with no prior (`relocalize`; the lifelong session start's options).
    pub relocalization: RelocalizationOptions,
}

impl SlamConfig {
    /// The configuration in the TOML file at `path`, or the defaults without one. Its sections are
    /// validated where they are used ([`run_slam`]).
    pub fn load(path: Option<&Path>) -> Result<Self, ConfigFileError> {
        Ok(path.map(load_toml).transpose()?.unwrap_or_default())
    }
}

/// Errors of the offline pipeline.
#[derive(Debug, thiserror::Error)]
pub enum OfflineError {
    /// Global SLAM refused the configuration or a node.
    #[error("global SLAM: {0}")]
    Global(#[from] GlobalSlamError),
    /// The configuration is invalid.
    #[error("invalid local SLAM configuration: {0}")]
    LocalOptions(#[source] mapping::local_slam::LocalTrajectoryBuilderOptionsError),
    /// The recording has no laser scans.
    #[error("the recording has no laser scans")]
    NoScans,
    /// The global SLAM worker thread died.
    #[error("global SLAM worker failed: {0}")]
    Worker(String),
    /// The global SLAM worker thread could not be started.
    #[error("global SLAM worker failed: {0}")]
    Spawn(#[source] std::io::Error),
}

/// The pose of one scan: its LLO pose and the node it hangs off.
#[derive(Clone, Copy, Debug)]
struct ScanAnchor {
    time: Timestamp,
    local_pose: Rigid2,
    node: Option<NodeId>,
}

/// How LLO placed one scan, as it happened (before any optimization).
#[derive(Clone, Copy, Debug)]
pub struct LloScan {
    /// Scan time.
    pub time: Timestamp,
    /// `local_from_tracking` as LLO matched it.
    pub local_pose: Rigid2,
    /// The correlative search that placed it.
    pub branch: CorrelativeBranch,
    /// Whether it became a node (inserted into the submaps).
    pub inserted: bool,
    /// Whether it retracted a held recovered scan (`insert_recovered_scans` false).
    pub retracted: bool,
}

/// What an offline run produced.
pub struct SlamRun {
    /// The final global pose of every scan that LLO matched, in time order.
    pub scan_poses: Vec<(Timestamp, Rigid2)>,
    /// How LLO placed each of those scans, in the same order.
    pub llo_scans: Vec<LloScan>,
    /// Global SLAM state after the final optimization.
    pub global: GlobalSlam,
    /// Each node's full range data in its tracking frame (for rendering the map).
    pub node_range_data: BTreeMap<NodeId, RangeData>,
    /// How the scans' beams were classified.
    pub range_stats: RangeStats,
    /// Scans in the recording.
    pub scans: usize,
    /// Scans LLO could not match (e.g. too few points), skipped.
    pub scans_dropped: usize,
    /// Scans of a driver's backlog put back at the times they were taken (`SensorStream::scans_retimed`).
    pub scans_retimed: usize,
    /// The offset of the odometry's clock against the scanner's as LLO estimated it by the end, seconds
    /// (`mapping::sensor::OdometryClock`; positive: the odometry is stamped late; `None` if it could not
    /// tell). Reported, not applied.
    pub odometry_offset_s: Option<f64>,
    /// Data duration from the first to the last event, seconds.
    pub data_duration_s: f64,
    /// Summary of the final optimization.
    pub final_optimization: OptimizationSummary,
    /// Periodic optimizations run during the recording.
    pub optimizations: usize,
    /// Every GLM match that reached the acceptance rules, with the rule that decided it, in order.
    pub match_decisions: Vec<MatchDecided>,
}

enum WorkerMessage {
    Node(LloNode),
}

/// What the worker tells the LLO thread after an optimization.
struct WorkerUpdate {
    global_from_local: Rigid2,
    map: Option<ProbabilityGrid>,
    optimizations: usize,
}

/// Hears what SLAM does while it runs (all calls on the thread that called [`run_slam`]).
pub trait SlamObserver {
    /// An odometry reading was handed to LLO.
    fn odometry(&mut self, _reading: &OdometryReading) {}

    /// LLO matched a scan at `time`: `local_from_base` in LLO's frame, and the latest `map_from_local`
    /// global SLAM has given (identity before its first optimization).
    fn scan_matched(
        &mut self,
        _time: Timestamp,
        _local_from_base: &Rigid2,
        _map_from_local: &Rigid2,
    ) {
    }

    /// Global SLAM optimized (its `optimizations`-th time); `map` is the finished submaps rendered at
    /// their optimized poses when [`SlamObserver::map_resolution`] asked for it (`None` before the first
    /// submap is finished). Called once more at the end of the stream with the final map: every node's
    /// scan at its optimized pose.
    fn optimized(&mut self, _optimizations: usize, _map: Option<&ProbabilityGrid>) {}

    /// Cell size (metres) of the map [`SlamObserver::optimized`] receives; `None` (default): no map.
    fn map_resolution(&self) -> Option<f64> {
        None
    }
}

/// An observer that hears nothing.
struct NoObserver;

impl SlamObserver for NoObserver {}

/// Runs LLO + GLM + PGR over a recording, as trajectory 0 of a new map. `progress` is called with the
/// number of scans processed so far.
pub fn run_offline(
    recording: &Recording,
    config: &SlamConfig,
    progress: &mut dyn FnMut(usize),
) -> Result<SlamRun, OfflineError> {
    if !recording
        .events
        .iter()
        .any(|e| matches!(e, SensorEvent::Scan(_)))
    {
        return Err(OfflineError::NoScans);
    }
    run_slam(
        &mut RecordingStream::new(recording),
        config,
        progress,
        &mut NoObserver,
    )
}

/// Runs LLO + GLM + PGR over a sensor stream (a recording or a live robot), as trajectory 0 of a new
/// map, until the stream ends. `progress` is called with the number of scans processed so far.
pub fn run_slam(
    stream: &mut dyn SensorStream,
    config: &SlamConfig,
    progress: &mut dyn FnMut(usize),
    observer: &mut dyn SlamObserver,
) -> Result<SlamRun, OfflineError> {
    config
        .local
        .validate()
        .map_err(OfflineError::LocalOptions)?;
    let global = GlobalSlam::new(config.global.clone())?;
    let render_resolution = observer.map_resolution();

    let (sender, receiver) = mpsc::sync_channel::<WorkerMessage>(256);
    let (update_sender, updates) = mpsc::sync_channel::<WorkerUpdate>(4);
    std::thread::scope(|scope| {
        let worker = std::thread::Builder::new()
            .name("global-slam".into())
            .spawn_scoped(scope, move || {
                global_worker(global, &receiver, &update_sender, render_resolution)
            })
            .map_err(OfflineError::Spawn)?;

        let mut llo = LloDriver::new(config.local.clone());
        let mut anchors = Vec::new();
        let mut llo_scans = Vec::new();
        let mut node_range_data = BTreeMap::new();
        let mut range_stats = RangeStats::default();
        let mut scans_done = 0;
        let mut scans_dropped = 0;
        let mut last_node: Option<NodeId> = None;
        let mut next_node_index = 0u32;
        let mut first_time: Option<Timestamp> = None;
        let mut last_time: Option<Timestamp> = None;
        let mut map_from_local = Rigid2::identity();
        while let Some(event) = stream.next_event() {
            first_time.get_or_insert(event.time());
            last_time = Some(event.time());
            while let Ok(update) = updates.try_recv() {
                map_from_local = update.global_from_local;
                observer.optimized(update.optimizations, update.map.as_ref());
            }
            if let SensorEvent::Odometry(o) = &event {
                observer.odometry(o);
            }
            let (result, range_data) = match llo.add_event(&event, &stream.base_from_laser()) {
                LloEvent::ReadingAdded => continue,
                LloEvent::ScanDropped { stats } => {
                    scans_done += 1;
                    range_stats += stats;
                    scans_dropped += 1;
                    continue;
                }
                LloEvent::ScanMatched {
                    result,
                    range_data,
                    stats,
                } => {
                    scans_done += 1;
                    range_stats += stats;
                    (result, range_data)
                }
            };
            observer.scan_matched(result.time, &result.local_pose, &map_from_local);
            llo_scans.push(LloScan {
                time: result.time,
                local_pose: result.local_pose,
                branch: result.branch,
                inserted: result.insertion.is_some(),
                retracted: result.retracted,
            });
            if let Some(insertion) = result.insertion {
                let id = NodeId {
                    trajectory: 0,
                    index: next_node_index,
                };
                next_node_index += 1;
                last_node = Some(id);
                node_range_data.insert(id, range_data);
                let message = WorkerMessage::Node(insertion.into_llo_node());
                if sender.send(message).is_err() {
                    break; // the worker died; its join below reports why
                }
            }
            anchors.push(ScanAnchor {
                time: result.time,
                local_pose: result.local_pose,
                node: last_node,
            });
            if scans_done % 64 == 0 {
                progress(scans_done);
            }
        }
        progress(scans_done);
        drop(sender);
        // Keep hearing the worker while it finishes (it may wait on the update channel).
        let WorkerOutcome {
            global,
            optimizations,
            final_optimization,
            match_decisions,
        } = loop {
            while let Ok(update) = updates.try_recv() {
                observer.optimized(update.optimizations, update.map.as_ref());
            }
            if worker.is_finished() {
                break worker.join().map_err(|_| {
                    OfflineError::Worker("the global SLAM thread panicked".into())
                })??;
            }
            std::thread::sleep(std::time::Duration::from_millis(5));
        };
        if scans_done == 0 {
            return Err(OfflineError::NoScans);
        }
        // The final map, every node's scan at its optimized pose (as `render_map` draws it).
        if let Some(resolution) = render_resolution {
            let map = render_range_data(
                node_range_data
                    .iter()
                    .filter_map(|(id, data)| Some((global.node_pose(*id)?, data))),
                resolution,
            );
            observer.optimized(optimizations + 1, Some(&map));
        }
        let data_duration_s = match (first_time, last_time) {
            (Some(a), Some(b)) => b.seconds_since(a),
            _ => 0.0,
        };

        let scan_poses = anchors
            .iter()
            .map(|a| {
                let pose = match a
                    .node
                    .and_then(|n| Some((global.node_pose(n)?, global.nodes().get(&n)?)))
                {
                    Some((node_global, record)) => {
                        node_global * record.local_pose.inverse() * a.local_pose
                    }
                    None => global.global_from_local(0) * a.local_pose,
                };
                (stream.stamped(a.time), pose)
            })
            .collect();
        Ok(SlamRun {
            scan_poses,
            llo_scans,
            global,
            node_range_data,
            range_stats,
            scans: scans_done,
            scans_dropped,
            scans_retimed: stream.scans_retimed(),
            odometry_offset_s: llo.odometry_clock().offset_s(),
            data_duration_s,
            final_optimization,
            optimizations,
            match_decisions,
        })
    })
}

/// The finished submaps of `global` rendered at their optimized poses (`None` before the first one).
pub fn render_finished_submaps(global: &GlobalSlam, resolution: f64) -> Option<ProbabilityGrid> {
    render_submaps_max(
        global.submaps().iter().filter_map(|(id, record)| {
            let grid = record.grid.as_deref()?;
            let global_from_submap = global.submap_pose(*id)?;
            Some(PlacedGrid {
                global_from_grid: global_from_submap * record.local_pose.inverse(),
                grid,
            })
        }),
        resolution,
    )
}

/// Loop-closure searches worth splitting across threads; below this, one thread is cheaper.
const PARALLEL_SEARCH_MIN_JOBS: usize = 4;

/// Runs search jobs on this thread and one helper thread (the machine this targets has two cores, and LLO
/// sleeps while it waits on a full channel). Results keep the jobs' order, so runs are deterministic.
pub fn run_searches(builder: &ConstraintBuilder, jobs: &[SearchJob]) -> Vec<LoopClosure> {
    if jobs.len() < PARALLEL_SEARCH_MIN_JOBS {
        return jobs.iter().filter_map(|j| builder.run(j)).collect();
    }
    let (first, second) = jobs.split_at(jobs.len() / 2);
    std::thread::scope(|scope| {
        let helper = std::thread::Builder::new()
            .name("glm-search".into())
            .spawn_scoped(scope, || {
                second.iter().map(|j| builder.run(j)).collect::<Vec<_>>()
            });
        let mut results: Vec<Option<LoopClosure>> = first.iter().map(|j| builder.run(j)).collect();
        match helper.map(std::thread::ScopedJoinHandle::join) {
            Ok(Ok(rest)) => results.extend(rest),
            // The helper could not start, or a search panicked (a bug): do its half here.
            _ => results.extend(second.iter().map(|j| builder.run(j))),
        }
        results.into_iter().flatten().collect()
    })
}

/// What the global SLAM worker hands back when the recording ends.
struct WorkerOutcome {
    global: GlobalSlam,
    optimizations: usize,
    final_optimization: OptimizationSummary,
    match_decisions: Vec<MatchDecided>,
}

fn global_worker(
    mut global: GlobalSlam,
    receiver: &mpsc::Receiver<WorkerMessage>,
    updates: &mpsc::SyncSender<WorkerUpdate>,
    render_resolution: Option<f64>,
) -> Result<WorkerOutcome, GlobalSlamError> {
    let mut optimizations = 0;
    let mut match_decisions = Vec::new();
    for message in receiver {
        match message {
            WorkerMessage::Node(node) => {
                global.add_node(0, node)?;
                let jobs = global.take_search_jobs();
                let results = run_searches(global.constraint_builder(), &jobs);
                let mut optimized = 0;
                for event in global.add_search_results(results) {
                    match event {
                        GlobalSlamEvent::Optimized(_) => optimized += 1,
                        GlobalSlamEvent::MatchDecided(decided) => match_decisions.push(decided),
                        _ => {}
                    }
                }
                optimizations += optimized;
                if optimized > 0 {
                    // Never blocks (the LLO thread may be waiting on this worker): when the LLO thread
                    // is four updates behind, this one is skipped; the next supersedes it.
                    let _ = updates.try_send(WorkerUpdate {
                        global_from_local: global.global_from_local(0),
                        map: render_resolution.and_then(|r| render_finished_submaps(&global, r)),
                        optimizations,
                    });
                }
            }
        }
    }
    let summary = global.optimize();
    // The LLO thread keeps taking updates until this thread ends, so this send cannot block for good.
    // (The final map is drawn by the LLO thread from every node's scan.)
    let _ = updates.send(WorkerUpdate {
        global_from_local: global.global_from_local(0),
        map: None,
        optimizations: optimizations + 1,
    });
    Ok(WorkerOutcome {
        global,
        optimizations,
        final_optimization: summary,
        match_decisions,
    })
}

/// Renders the optimized map at `resolution` by re-inserting every node's range data at its optimized
/// global pose into one fresh grid (crisper than blending submaps).
pub fn render_map(run: &SlamRun, resolution: f64) -> ProbabilityGrid {
    render_range_data(
        run.node_range_data
            .iter()
            .filter_map(|(id, data)| Some((run.global.node_pose(*id)?, data))),
        resolution,
    )
}

/// Inserts range data (each in its tracking frame, with `world_from_tracking`) into one fresh grid of
/// cell size `resolution`, cropped to the known cells.
pub fn render_range_data<'a>(
    scans: impl IntoIterator<Item = (Rigid2, &'a RangeData)>,
    resolution: f64,
) -> ProbabilityGrid {
    let inserter = RangeDataInserter::new(RangeDataInserterOptions::default());
    let mut grid = ProbabilityGrid::new(MapLimits::new(
        resolution,
        nalgebra::Vector2::new(-5.0, -5.0),
        1,
        1,
    ));
    let mut first = true;
    for (pose, range_data) in scans {
        let data = range_data.transformed(&pose);
        if first {
            let half = 100;
            let origin =
                data.origin - nalgebra::Vector2::new(f64::from(half), f64::from(half)) * resolution;
            grid = ProbabilityGrid::new(MapLimits::new(resolution, origin, 2 * half, 2 * half));
            first = false;
        }
        inserter.insert(&data, &mut grid);
    }
    grid.cropped_to_known()
}
