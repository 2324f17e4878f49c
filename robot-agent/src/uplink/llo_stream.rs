//! Local LiDAR odometry over a recording, emitting upload items: one group per node (the node, then the
//! submaps its insertion finished), optionally paced at the recording's speed.

use std::time::{Duration, Instant};

use mapping::local_slam::{
    LloDriver, LloEvent, LocalTrajectoryBuilder, LocalTrajectoryBuilderOptions,
};
use mapping::sensor::{SensorEvent, Timestamp};
use proto::{NodeAdded, UploadItem};

use crate::source::{Recording, RecordingStream, SensorStream};

/// What [`run_llo`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LloStats {
    /// Scans read.
    pub scans: usize,
    /// Scans LLO could not match.
    pub scans_dropped: usize,
    /// Nodes emitted.
    pub nodes: usize,
    /// Submaps finished.
    pub submaps_finished: usize,
    /// Whether the sink asked to stop early.
    pub stopped: bool,
}

/// Runs LLO over the first `max_scans` scans of `recording` (all if `None`), calling `sink` with each
/// node's items; `sink` returns `false` to stop. With `replay_speed > 0`, events are paced at that
/// multiple of real time (1: as recorded); 0 runs as fast as possible. Blocks: run it on its own thread.
pub fn run_llo(
    recording: &Recording,
    options: &LocalTrajectoryBuilderOptions,
    replay_speed: f64,
    max_scans: Option<usize>,
    sink: &mut dyn FnMut(Vec<UploadItem>) -> bool,
) -> LloStats {
    let first_time = recording.events.first().map(SensorEvent::time);
    run_llo_stream(
        &mut RecordingStream::new(recording),
        options,
        first_time
            .filter(|_| replay_speed > 0.0)
            .map(|t| (t, replay_speed)),
        max_scans,
        sink,
    )
}

/// [`run_llo`] over any [`SensorStream`] (a live robot: `pace` `None`, events are taken as they come);
/// with `pace` `Some((t0, speed))`, the event stamped `t` is taken `(t - t0) / speed` after the start.
pub fn run_llo_stream(
    stream: &mut dyn SensorStream,
    options: &LocalTrajectoryBuilderOptions,
    pace: Option<(Timestamp, f64)>,
    max_scans: Option<usize>,
    sink: &mut dyn FnMut(Vec<UploadItem>) -> bool,
) -> LloStats {
    let mut llo = LloDriver::new(options.clone());
    let mut stats = LloStats::default();
    let mut held: Option<Vec<UploadItem>> = None;
    let started = Instant::now();
    while let Some(event) = stream.next_event() {
        if let Some((t0, speed)) = pace {
            let due = event.time().seconds_since(t0) / speed;
            if let Ok(due) = Duration::try_from_secs_f64(due)
                && let Some(wait) = due.checked_sub(started.elapsed())
            {
                std::thread::sleep(wait);
            }
        }
        if matches!(event, SensorEvent::Scan(_)) {
            if max_scans.is_some_and(|m| stats.scans >= m) {
                break;
            }
            stats.scans += 1;
        }
        let result = match llo.add_event(&event, &stream.base_from_laser()) {
            LloEvent::ReadingAdded => continue,
            LloEvent::ScanDropped { .. } => {
                stats.scans_dropped += 1;
                continue;
            }
            LloEvent::ScanMatched { result, .. } => result,
        };
        let Some(insertion) = result.insertion else {
            continue;
        };
        stats.nodes += 1;
        let mut items = vec![UploadItem::NodeAdded(NodeAdded {
            time: result.time,
            local_pose: result.local_pose,
            points: insertion.node.filtered_points,
            insertion_submaps: insertion
                .insertion_submaps
                .iter()
                .map(|s| (s.index as u32, s.local_pose))
                .collect(),
            recovered: insertion.node.recovered,
        })];
        for (index, submap) in insertion.finished_submaps {
            stats.submaps_finished += 1;
            items.push(UploadItem::SubmapFinished {
                index: index as u32,
                grid: submap.grid,
            });
        }
        // Each node is handed over one node late, so that the session's last node can carry the
        // submaps still active when the recording ends.
        if let Some(previous) = held.replace(items)
            && !sink(previous)
        {
            stats.stopped = true;
            return stats;
        }
    }
    if let Some(mut last) = held {
        finish_active_submaps(llo.builder(), &mut last, &mut stats);
        if !sink(last) {
            stats.stopped = true;
        }
    }
    stats
}

/// Appends to the session's last node (`items`) a `SubmapFinished` for every submap still active that the
/// node was inserted into and that is not finished yet: the end of the session finishes them, so later
/// sessions and other robots can match against the whole trip.
fn finish_active_submaps(
    llo: &LocalTrajectoryBuilder,
    items: &mut Vec<UploadItem>,
    stats: &mut LloStats,
) {
    let Some(UploadItem::NodeAdded(node)) = items.first() else {
        return;
    };
    let inserted: Vec<u32> = node.insertion_submaps.iter().map(|(i, _)| *i).collect();
    let already: Vec<u32> = items
        .iter()
        .filter_map(|item| match item {
            UploadItem::SubmapFinished { index, .. } => Some(*index),
            _ => None,
        })
        .collect();
    for (index, submap) in llo.active_submaps().submaps() {
        let index = *index as u32;
        if inserted.contains(&index) && !already.contains(&index) {
            stats.submaps_finished += 1;
            items.push(UploadItem::SubmapFinished {
                index,
                grid: submap.grid.cropped_to_known(),
            });
        }
    }
}
