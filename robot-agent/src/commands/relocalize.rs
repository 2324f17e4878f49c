//! `evermap-agent relocalize`: how well and how fast a robot finds itself on a map with no prior.
//!
//! The map is built from the first 60 % of the recording (by time); scans sampled from the remaining 40 %
//! are matched against the whole map with branch and bound over every position and rotation, then
//! refined by least squares. Truth for each scan is its pose in a full `offline` run of the same
//! recording (both runs hold the first node fixed at the same pose, so they share a frame).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use clap::Args;
use mapping::geometry::{Rigid2, rigid2};
use mapping::geometry::{Rigid2Ext as _, normalize_angle};
use mapping::local_slam::adaptive_voxel_filter;
use mapping::scan_matching::Relocalizer;
use mapping::sensor::{SensorEvent, Timestamp};
use rand::SeedableRng as _;
use rand::seq::index::sample;
use rand_pcg::Pcg64;
use robot_agent::offline_slam::{render_map, run_offline};
use robot_agent::source::{self, Recording};
use serde_json::json;

use super::offline::load_config;

/// Arguments of `relocalize`.
#[derive(Args)]
pub struct RelocalizeArgs {
    /// The recording: a ROS1 bag or a CARMEN log.
    #[arg(long)]
    input: PathBuf,
    /// How many scans of the last 40 % to relocalize.
    #[arg(long, default_value_t = 100)]
    samples: usize,
    /// Seed of the scan sampling.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// A TOML file overriding the default SLAM configuration.
    #[arg(long)]
    config: Option<PathBuf>,
}

/// A relocalization counts as correct within this distance of the truth, metres.
const SUCCESS_TRANSLATION_M: f64 = 0.15;
/// … and this rotation, degrees.
const SUCCESS_ROTATION_DEG: f64 = 3.0;

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// Runs the command.
pub fn run(args: &RelocalizeArgs) -> anyhow::Result<()> {
    let config = load_config(args.config.as_deref())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let recording = source::read_recording(&args.input)?;
    let (Some(first), Some(last)) = (recording.events.first(), recording.events.last()) else {
        anyhow::bail!("{} has no sensor data", args.input.display());
    };
    let cut = first
        .time()
        .offset_by(0.6 * last.time().seconds_since(first.time()));

    eprintln!("mapping the whole recording for ground truth");
    let full = run_offline(&recording, &config, &mut |_| {})?;
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
    let map_run = run_offline(&head, &config, &mut |_| {})?;
    let map = render_map(&map_run, config.local.submaps.resolution);

    config
        .relocalization
        .validate()
        .context("invalid relocalization options")?;
    let build_start = Instant::now();
    let relocalizer = Relocalizer::new(&map, config.relocalization.clone());
    let precompute_ms = build_start.elapsed().as_secs_f64() * 1e3;

    // The map's frame is the head run's; the two runs agree on the first node but their maps differ by
    // decimetres in places as their loop closures differ. A scan is relocalized against the part of the
    // map around it, so its truth is the full run's pose expressed in the head run's frame through the
    // rigid transform that best aligns the common scans within `LOCAL_ALIGNMENT_RADIUS_M` of it.
    let full_poses: std::collections::BTreeMap<Timestamp, Rigid2> =
        full.scan_poses.iter().copied().collect();
    let common: Vec<(Rigid2, Rigid2)> = map_run
        .scan_poses
        .iter()
        .filter_map(|(t, h)| full_poses.get(t).map(|f| (*h, *f)))
        .collect();
    let truth: std::collections::BTreeMap<Timestamp, Rigid2> = full
        .scan_poses
        .iter()
        .filter(|(t, _)| *t >= cut)
        .map(|(t, p)| (*t, align_near(&common, p) * p))
        .collect();
    let candidates: Vec<_> = recording
        .events
        .iter()
        .filter_map(|e| match e {
            SensorEvent::Scan(s) if truth.contains_key(&s.time) => Some(s),
            _ => None,
        })
        .collect();
    anyhow::ensure!(
        !candidates.is_empty(),
        "no scans with a ground-truth pose after the 60 % cut"
    );
    let n = args.samples.min(candidates.len());
    let mut rng = Pcg64::seed_from_u64(args.seed);
    let mut picks = sample(&mut rng, candidates.len(), n).into_vec();
    picks.sort_unstable();

    let mut times_ms = Vec::with_capacity(n);
    let mut results = Vec::with_capacity(n);
    let mut successes = 0;
    for &k in &picks {
        let scan = candidates[k];
        let (range_data, _) = scan.to_range_data(&config.local.range_conversion);
        let range_data = range_data.transformed(&recording.base_from_laser);
        let start = Instant::now();
        let points =
            adaptive_voxel_filter(&range_data.returns, &config.local.adaptive_voxel_filter);
        let pose = relocalizer.relocalize(&points).map(|r| (r.pose, r.score));
        let ms = start.elapsed().as_secs_f64() * 1e3;
        times_ms.push(ms);
        let truth_pose = truth[&scan.time];
        // How far the scan is from where the map's run went: far means its area may not be mapped.
        let nearest_mapped_m = common
            .iter()
            .map(|(h, _)| (h.translation.vector - truth_pose.translation.vector).norm())
            .fold(f64::INFINITY, f64::min);
        let (ok, dt, dth, score) = match pose {
            Some((p, score)) => {
                let dt = (p.translation.vector - truth_pose.translation.vector).norm();
                let dth = normalize_angle(p.theta() - truth_pose.theta())
                    .abs()
                    .to_degrees();
                (
                    dt <= SUCCESS_TRANSLATION_M && dth <= SUCCESS_ROTATION_DEG,
                    Some(dt),
                    Some(dth),
                    Some(score),
                )
            }
            None => (false, None, None, None),
        };
        successes += usize::from(ok);
        results.push(
            json!({"time": scan.time.to_string(), "success": ok, "translation_error_m": dt,
                            "rotation_error_deg": dth, "score": score, "ms": ms,
                            "nearest_mapped_m": nearest_mapped_m}),
        );
    }
    let mut sorted = times_ms.clone();
    sorted.sort_by(f64::total_cmp);
    let report = json!({
        "input": args.input.display().to_string(),
        "samples": n,
        "success_rate": successes as f64 / n as f64,
        "median_ms": percentile(&sorted, 0.5),
        "p95_ms": percentile(&sorted, 0.95),
        "precompute_ms": precompute_ms,
        "map_cells": [map.limits().width, map.limits().height],
        "truth_alignment_radius_m": LOCAL_ALIGNMENT_RADIUS_M,
        "success_translation_m": SUCCESS_TRANSLATION_M,
        "success_rotation_deg": SUCCESS_ROTATION_DEG,
        "results": results,
    });
    let path = args.out.join("report.json");
    std::fs::write(&path, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", path.display()))?;
    println!(
        "{}",
        json!({"samples": n, "success_rate": report["success_rate"], "median_ms": report["median_ms"], "p95_ms": report["p95_ms"]})
    );
    Ok(())
}

/// Radius (metres) around a sampled scan within which the two runs' common scans define its truth frame.
const LOCAL_ALIGNMENT_RADIUS_M: f64 = 8.0;

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

/// The rigid transform `head_from_full` minimizing the squared distances between the positions of the
/// pairs `(head pose, full pose)` (2D Kabsch without scale); identity for no pairs.
fn align(pairs: &[(Rigid2, Rigid2)]) -> Rigid2 {
    if pairs.is_empty() {
        return Rigid2::identity();
    }
    let n = pairs.len() as f64;
    let mean_h = pairs
        .iter()
        .map(|p| p.0.translation.vector)
        .sum::<nalgebra::Vector2<f64>>()
        / n;
    let mean_f = pairs
        .iter()
        .map(|p| p.1.translation.vector)
        .sum::<nalgebra::Vector2<f64>>()
        / n;
    let (mut sin, mut cos) = (0.0, 0.0);
    for (h, f) in pairs {
        let (a, b) = (f.translation.vector - mean_f, h.translation.vector - mean_h);
        cos += a.dot(&b);
        sin += a.x * b.y - a.y * b.x;
    }
    let theta = sin.atan2(cos);
    let t = mean_h - nalgebra::Rotation2::new(theta) * mean_f;
    rigid2(t.x, t.y, theta)
}
