//! The offline SLAM pipeline: one recording in, an optimized trajectory and map out.
//!
//! LLO runs on the calling thread; global SLAM (GLM searches and optimization) runs on a named worker
//! thread fed through a bounded channel, so both cores of a small robot computer are busy.

use std::collections::BTreeMap;
use std::sync::mpsc;

use mapping::geometry::Rigid2;
use mapping::global_slam::{
    ConstraintBuilder, GlobalSlam, GlobalSlamError, GlobalSlamEvent, GlobalSlamOptions,
    LoopClosure, SearchJob,
};
use mapping::grid::{MapLimits, ProbabilityGrid, RangeDataInserter, RangeDataInserterOptions};
use mapping::lifelong::RelocalizationOptions;
use mapping::local_slam::{LocalTrajectoryBuilder, LocalTrajectoryBuilderOptions};
use mapping::pose_graph::{NodeId, OptimizationSummary};
use mapping::sensor::{RangeData, RangeStats, SensorEvent, Timestamp};
use nalgebra::Point2;
use serde::Deserialize;

use crate::source::Recording;

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

/// Errors of the offline pipeline.
#[derive(Debug, thiserror::Error)]
pub enum OfflineError {
    /// Global SLAM refused the configuration or a node.
    #[error("global SLAM: {0}")]
    Global(#[from] GlobalSlamError),
    /// The configuration is invalid.
    #[error("invalid local SLAM configuration: {0}")]
    LocalOptions(String),
    /// The recording has no laser scans.
    #[error("the recording has no laser scans")]
    NoScans,
    /// The global SLAM worker thread could not be started or died.
    #[error("global SLAM worker failed: {0}")]
    Worker(String),
}

/// The pose of one scan: its LLO pose and the node it hangs off.
#[derive(Clone, Copy, Debug)]
struct ScanAnchor {
    time: Timestamp,
    local_pose: Rigid2,
    node: Option<NodeId>,
}

/// What an offline run produced.
pub struct SlamRun {
    /// The final global pose of every scan that LLO matched, in time order.
    pub scan_poses: Vec<(Timestamp, Rigid2)>,
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
    /// Data duration from the first to the last event, seconds.
    pub data_duration_s: f64,
    /// Summary of the final optimization.
    pub final_optimization: OptimizationSummary,
    /// Periodic optimizations run during the recording.
    pub optimizations: usize,
}

enum WorkerMessage {
    Node {
        time: Timestamp,
        local_pose: Rigid2,
        points: Vec<Point2<f32>>,
        insertion_submaps: Vec<(usize, Rigid2)>,
        finished_submaps: Vec<(usize, ProbabilityGrid)>,
    },
}

/// Runs LLO + GLM + PGR over a recording, as trajectory 0 of a new map. `progress` is called with the
/// number of scans processed so far.
pub fn run_offline(
    recording: &Recording,
    config: &SlamConfig,
    progress: &mut dyn FnMut(usize),
) -> Result<SlamRun, OfflineError> {
    config
        .local
        .validate()
        .map_err(|e| OfflineError::LocalOptions(e.to_string()))?;
    let global = GlobalSlam::new(config.global.clone())?;
    let scans = recording
        .events
        .iter()
        .filter(|e| matches!(e, SensorEvent::Scan(_)))
        .count();
    if scans == 0 {
        return Err(OfflineError::NoScans);
    }
    let data_duration_s = match (recording.events.first(), recording.events.last()) {
        (Some(a), Some(b)) => b.time().seconds_since(a.time()),
        _ => 0.0,
    };

    let (sender, receiver) = mpsc::sync_channel::<WorkerMessage>(256);
    std::thread::scope(|scope| {
        let worker = std::thread::Builder::new()
            .name("global-slam".into())
            .spawn_scoped(scope, move || global_worker(global, &receiver))
            .map_err(|e| OfflineError::Worker(e.to_string()))?;

        let mut llo = LocalTrajectoryBuilder::new(config.local.clone());
        let mut anchors = Vec::with_capacity(scans);
        let mut node_range_data = BTreeMap::new();
        let mut range_stats = RangeStats::default();
        let mut scans_done = 0;
        let mut scans_dropped = 0;
        let mut last_node: Option<NodeId> = None;
        let mut next_node_index = 0u32;
        for event in mapping::sensor::collate_for_llo(&recording.events) {
            match event {
                SensorEvent::Odometry(o) => llo.add_odometry(o),
                SensorEvent::Imu(i) => llo.add_imu(i),
                SensorEvent::Scan(scan) => {
                    scans_done += 1;
                    let (range_data, stats) = scan.to_range_data(&config.local.range_conversion);
                    range_stats += stats;
                    let range_data = range_data.transformed(&recording.base_from_laser);
                    let Some(result) = llo.add_range_data(scan.time, &range_data) else {
                        scans_dropped += 1;
                        continue;
                    };
                    if let Some(insertion) = result.insertion {
                        let id = NodeId {
                            trajectory: 0,
                            index: next_node_index,
                        };
                        next_node_index += 1;
                        last_node = Some(id);
                        node_range_data.insert(id, range_data);
                        let message = WorkerMessage::Node {
                            time: result.time,
                            local_pose: result.local_pose,
                            points: insertion.node.filtered_points,
                            insertion_submaps: insertion
                                .insertion_submaps
                                .iter()
                                .map(|s| (s.index, s.local_pose))
                                .collect(),
                            finished_submaps: insertion
                                .finished_submaps
                                .into_iter()
                                .map(|(index, submap)| (index, submap.grid))
                                .collect(),
                        };
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
            }
        }
        progress(scans_done);
        drop(sender);
        let (global, optimizations, final_optimization) = worker
            .join()
            .map_err(|_| OfflineError::Worker("the global SLAM thread panicked".into()))??;

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
                (a.time, pose)
            })
            .collect();
        Ok(SlamRun {
            scan_poses,
            global,
            node_range_data,
            range_stats,
            scans,
            scans_dropped,
            data_duration_s,
            final_optimization,
            optimizations,
        })
    })
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

fn global_worker(
    mut global: GlobalSlam,
    receiver: &mpsc::Receiver<WorkerMessage>,
) -> Result<(GlobalSlam, usize, OptimizationSummary), GlobalSlamError> {
    let mut optimizations = 0;
    for message in receiver {
        match message {
            WorkerMessage::Node {
                time,
                local_pose,
                points,
                insertion_submaps,
                finished_submaps,
            } => {
                global.add_node(
                    0,
                    time,
                    local_pose,
                    points,
                    &insertion_submaps,
                    finished_submaps,
                )?;
                let jobs = global.take_search_jobs();
                let results = run_searches(global.constraint_builder(), &jobs);
                let events = global.add_search_results(results);
                optimizations += events
                    .iter()
                    .filter(|e| matches!(e, GlobalSlamEvent::Optimized(_)))
                    .count();
            }
        }
    }
    let summary = global.optimize();
    Ok((global, optimizations, summary))
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
