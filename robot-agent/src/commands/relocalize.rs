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
use mapping::geometry::{Rigid2Ext as _, normalize_angle};
use mapping::local_slam::adaptive_voxel_filter;
use mapping::scan_matching::{FastCorrelativeScanMatcher, LeastSquaresScanMatcher};
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

    let global_options = &config.global.constraint_builder;
    let build_start = Instant::now();
    let mut full_options = global_options.fast_correlative.clone();
    full_options.angular_search_window = std::f64::consts::PI;
    let matcher = FastCorrelativeScanMatcher::new(&map, full_options);
    let precompute_ms = build_start.elapsed().as_secs_f64() * 1e3;
    let refiner = LeastSquaresScanMatcher::new(global_options.least_squares.clone());

    let truth: std::collections::BTreeMap<Timestamp, mapping::geometry::Rigid2> = full
        .scan_poses
        .iter()
        .copied()
        .filter(|(t, _)| *t >= cut)
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
        let found = matcher.match_full(&points, global_options.global_localization_min_score);
        let pose = found.map(|m| {
            let (refined, _) =
                refiner.match_pose(&m.pose.translation.vector, &m.pose, &points, &map);
            (refined, m.score)
        });
        let ms = start.elapsed().as_secs_f64() * 1e3;
        times_ms.push(ms);
        let truth_pose = truth[&scan.time];
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
                            "rotation_error_deg": dth, "score": score, "ms": ms}),
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
