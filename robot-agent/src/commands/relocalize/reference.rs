//! The map a relocalization is placed on and the truth it is scored against (`--truth`, `--reference`).

use anyhow::Context as _;
use mapping::geometry::{Rigid2, Rigid2Ext as _};
use mapping::sensor::Timestamp;
use robot_agent::offline_slam::{render_map, render_range_data, run_offline};
use robot_agent::source::Recording;

/// What relocalizations are placed on and scored against.
pub(super) struct Reference {
    /// The map of the recording before the cut.
    pub(super) map: mapping::grid::ProbabilityGrid,
    /// Every scan after the cut: its true pose in the map's frame.
    pub(super) truth: std::collections::BTreeMap<Timestamp, Rigid2>,
    /// The scans drawn into the map, with their poses in the map's frame, in time order.
    pub(super) map_poses: Vec<(Timestamp, Rigid2)>,
    /// Every scan's pose in the full run (its own frame), in time order: its short-range relative motion
    /// bridges from a relation's stamp to a nearby sampled scan.
    pub(super) full_poses: Vec<(Timestamp, Rigid2)>,
}

/// A pose as `[x, y, θ]` (m, m, rad), for the reference file.
fn to_xyt(pose: &Rigid2) -> [f64; 3] {
    [pose.translation.x, pose.translation.y, pose.theta()]
}

fn from_xyt([x, y, theta]: [f64; 3]) -> Rigid2 {
    mapping::geometry::rigid2(x, y, theta)
}

/// [`Reference`] as stored by `--reference`.
#[derive(serde::Serialize, serde::Deserialize)]
struct StoredReference {
    limits: mapping::grid::MapLimits,
    cells: Vec<u16>,
    truth: Vec<(Timestamp, [f64; 3])>,
    map_poses: Vec<(Timestamp, [f64; 3])>,
    full_poses: Vec<(Timestamp, [f64; 3])>,
}

impl Reference {
    pub(super) fn write(&self, path: &std::path::Path) -> anyhow::Result<()> {
        let poses = |v: &[(Timestamp, Rigid2)]| v.iter().map(|(t, p)| (*t, to_xyt(p))).collect();
        let stored = StoredReference {
            limits: self.map.limits().clone(),
            cells: self.map.values().to_vec(),
            truth: self.truth.iter().map(|(t, p)| (*t, to_xyt(p))).collect(),
            map_poses: poses(&self.map_poses),
            full_poses: poses(&self.full_poses),
        };
        std::fs::write(path, serde_json::to_string(&stored)?)
            .with_context(|| format!("cannot write {}", path.display()))
    }

    pub(super) fn read(path: &std::path::Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let stored: StoredReference = serde_json::from_str(&text)
            .with_context(|| format!("invalid reference file {}", path.display()))?;
        let mut map = mapping::grid::ProbabilityGrid::new(stored.limits);
        anyhow::ensure!(
            map.values().len() == stored.cells.len(),
            "invalid reference file {}: the cells do not fill the map",
            path.display()
        );
        map.values_mut().copy_from_slice(&stored.cells);
        let poses = |v: Vec<(Timestamp, [f64; 3])>| -> Vec<(Timestamp, Rigid2)> {
            v.into_iter().map(|(t, p)| (t, from_xyt(p))).collect()
        };
        Ok(Self {
            map,
            truth: poses(stored.truth).into_iter().collect(),
            map_poses: poses(stored.map_poses),
            full_poses: poses(stored.full_poses),
        })
    }
}

/// `--truth own`: one run of the whole recording; the map is its nodes before `cut` re-inserted at their
/// optimized poses, and the truth of a later scan is that run's pose of it.
pub(super) fn prepare_own(
    recording: &Recording,
    config: &robot_agent::offline_slam::SlamConfig,
    cut: Timestamp,
) -> anyhow::Result<Reference> {
    eprintln!("mapping the whole recording");
    let full = run_offline(recording, config, &mut |_| {})?;
    let nodes = full.global.nodes();
    let map = render_range_data(
        full.node_range_data.iter().filter_map(|(id, data)| {
            (nodes.get(id)?.time < cut).then_some((full.global.node_pose(*id)?, data))
        }),
        config.local.submaps.resolution,
    );
    let (map_poses, after): (Vec<_>, Vec<_>) =
        full.scan_poses.iter().copied().partition(|(t, _)| *t < cut);
    Ok(Reference {
        map,
        truth: after.into_iter().collect(),
        map_poses,
        full_poses: full.scan_poses,
    })
}

/// `--truth aligned`: maps the whole recording and its part before `cut`, and expresses the first in the
/// second's frame.
pub(super) fn prepare_aligned(
    recording: &Recording,
    config: &robot_agent::offline_slam::SlamConfig,
    cut: Timestamp,
) -> anyhow::Result<Reference> {
    eprintln!("mapping the whole recording for ground truth");
    let full = run_offline(recording, config, &mut |_| {})?;
    eprintln!("mapping the first 60 %");
    let head = Recording {
        events: recording
            .events
            .iter()
            .filter(|e| e.time() < cut)
            .cloned()
            .collect(),
        base_from_laser: recording.base_from_laser,
        report: recording.report.clone(),
    };
    let map_run = run_offline(&head, config, &mut |_| {})?;
    let map = render_map(&map_run, config.local.submaps.resolution);

    // The map's frame is the head run's; the two runs agree on the first node but their maps differ by
    // decimetres in places as their loop closures differ. A scan is relocalized against the part of the
    // map around it, so its truth is the full run's pose expressed in the head run's frame through the
    // rigid transform that best aligns the common scans within `LOCAL_ALIGNMENT_RADIUS_M` of it.
    let full_by_time: std::collections::BTreeMap<Timestamp, Rigid2> =
        full.scan_poses.iter().copied().collect();
    let common: Vec<(Rigid2, Rigid2)> = map_run
        .scan_poses
        .iter()
        .filter_map(|(t, h)| full_by_time.get(t).map(|f| (*h, *f)))
        .collect();
    let truth: std::collections::BTreeMap<Timestamp, Rigid2> = full
        .scan_poses
        .iter()
        .filter(|(t, _)| *t >= cut)
        .map(|(t, p)| (*t, align_near(&common, p) * p))
        .collect();
    Ok(Reference {
        map,
        truth,
        map_poses: map_run.scan_poses,
        full_poses: full.scan_poses,
    })
}

/// Radius (metres) around a sampled scan within which the two runs' common scans define its truth frame.
pub(super) const LOCAL_ALIGNMENT_RADIUS_M: f64 = 8.0;

/// `head_from_full` aligning the pairs `(head pose, full pose)` of common scans within
/// [`LOCAL_ALIGNMENT_RADIUS_M`] of `near` (full-run frame), or all of them if fewer than 10 are that close.
fn align_near(common: &[(Rigid2, Rigid2)], near: &Rigid2) -> Rigid2 {
    let close: Vec<(Rigid2, Rigid2)> = common
        .iter()
        .copied()
        .filter(|(_, f)| {
            (f.translation.vector - near.translation.vector).norm() <= LOCAL_ALIGNMENT_RADIUS_M
        })
        .collect();
    if close.len() >= 10 {
        align(&close)
    } else {
        align(common)
    }
}

/// The rigid transform `head_from_full` best aligning the positions of the pairs `(head pose, full pose)`.
fn align(pairs: &[(Rigid2, Rigid2)]) -> Rigid2 {
    let positions: Vec<_> = pairs
        .iter()
        .map(|(h, f)| (f.translation.vector, h.translation.vector))
        .collect();
    mapping::metrics::rigid_alignment(&positions)
}
