//! `evermap-agent lifelong`: the paper's month-in-a-supermarket experiment on the simulated changing store.
//!
//! Session 0 maps the store; sessions 1..N are cleaning runs on later days (goods, pallets, displays and
//! doors changed, people and carts about) that start with no prior, relocalize, localize by GLM and feed
//! the lifelong map, which trims stale submaps per the policy. Sessions are generated one at a time, so
//! memory holds one session's sensor data. Every figure is measured against the simulator's ground truth
//! in one fixed frame: `world_from_map` is the rigid alignment of session 0's trajectory to its truth, so
//! a later session is only "correctly localized" where it is correct in the map the fleet shares.

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use mapping::geometry::{Rigid2, Rigid2Ext as _, normalize_angle};
use mapping::lifelong::{
    MAP_CHANGE_TOLERANCE_M, TrimPolicy, map_change_rate, render_submaps_newest,
};
use mapping::metrics::{
    MRCL_ROTATION_DEG, MRCL_TRANSLATION_M, TrajectoryAccuracy, rigid_alignment, trajectory_accuracy,
};
use mapping::sensor::Timestamp;
use mapping::simulation::{SessionOptions, Store, StoreOptions};
use robot_agent::lifelong_run::{SessionInput, SessionSummary, SessionsConfig, run_session_inputs};
use robot_agent::line_chart::{LineChart, Series};
use robot_agent::{map_image, process_stats};
use serde::Serialize;
use serde_json::json;

use super::simulate::World;

/// Arguments of `lifelong`.
#[derive(Args)]
pub struct LifelongArgs {
    /// Which world.
    #[arg(long, value_enum, default_value_t = World::Store)]
    world: World,
    /// Number of sessions after the mapping session 0 (the paper: 25).
    #[arg(long, default_value_t = 25)]
    sessions: u32,
    /// Seed of the store layout, its change schedule and the routes.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Trimming policy (clt, delete, keep, frozen); overrides the configuration's (default clt).
    #[arg(long)]
    policy: Option<TrimPolicy>,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// A TOML file overriding the default configuration (see `SessionsConfig`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Length cap of sessions 1..N, seconds (default: the simulator's, 300 s).
    #[arg(long)]
    session_duration_s: Option<f64>,
    /// Length cap of the mapping session 0, seconds (default: the whole sweep of every aisle, ~45 min).
    #[arg(long)]
    mapping_duration_s: Option<f64>,
}

/// What one session scored.
#[derive(Debug, Serialize)]
struct SessionScore {
    session: u32,
    /// Whether session-start relocalization (no prior) put the first node within the MRCL tolerance of
    /// the truth (the paper's correct initialization). Session 0 defines the map: always true.
    initialized: bool,
    /// Relocalization error of the first node, metres, when relocalization found a pose.
    initialization_error_m: Option<f64>,
    mrcl: f64,
    /// Mean score of the session's accepted GLM matches against older sessions' submaps (`null` when none
    /// was; session 0: its matches within itself).
    ams: Option<f64>,
    ate_rms_m: f64,
    max_error_m: f64,
    distance_m: f64,
    nodes: usize,
    submaps: usize,
    constraints: usize,
    trimmed_total: usize,
    /// Submaps of sessions that did not update the map (never placed; `frozen`), dropped so far.
    dropped_total: usize,
    pgr_ms: f64,
    peak_rss_mb: Option<f64>,
    scans: usize,
    closures: usize,
    cross_session_closures: usize,
    trimmed: usize,
    /// The session's own submaps dropped at its end (it did not update the map).
    dropped: usize,
    tree_edges: usize,
    trim_kld_mean: Option<f64>,
    /// Branch-and-bound score of the session-start relocalization, when it found a pose.
    relocalization_score: Option<f32>,
    /// Relocalization retries while the session was unplaced.
    relocalization_retries: usize,
    /// The node count at which a retry placed the session (`null`: placed at its start, or never).
    placed_by_retry_at_node: Option<usize>,
    /// Whether the session was placed in the map at all (by its start or a retry).
    placed: bool,
}

fn load_config(args: &LifelongArgs) -> anyhow::Result<SessionsConfig> {
    let mut config = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("cannot read config {}", path.display()))?;
            toml::from_str(&text).with_context(|| format!("invalid config {}", path.display()))?
        }
        None => SessionsConfig::default(),
    };
    if let Some(policy) = args.policy {
        config.lifelong.policy = policy;
    }
    Ok(config)
}

/// Truth of one generated session, kept for scoring.
struct SessionTruth {
    poses: Vec<(Timestamp, Rigid2)>,
}

/// Runs the command.
pub fn run(args: &LifelongArgs) -> anyhow::Result<()> {
    let World::Store = args.world;
    let config = load_config(args)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let mut options = SessionOptions::default();
    if let Some(t) = args.session_duration_s {
        options.max_duration_s = t;
    }
    if let Some(t) = args.mapping_duration_s {
        options.mapping_max_duration_s = t;
    }
    options.validate()?;
    let start = Instant::now();
    let store = Store::generate(&StoreOptions::default(), args.seed)?;

    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} {msg} [{bar:30}] {pos}/{len} scans ({per_sec})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let truths: RefCell<Vec<SessionTruth>> = RefCell::new(Vec::new());
    let failure: RefCell<Option<anyhow::Error>> = RefCell::new(None);
    let inputs = (0..=args.sessions).map_while(|k| {
        bar.set_message(format!("simulating session {k}/{}", args.sessions));
        match store.session(k, &options) {
            Ok(session) => {
                bar.inc_length(session.ground_truth.len() as u64);
                let message = format!(
                    "session {k}/{} ({:.0} s, {:.0} m)",
                    args.sessions, session.duration_s, session.distance_m
                );
                if bar.is_hidden() {
                    // No terminal (CI, a log file): one line per session instead of a bar.
                    eprintln!("[{:>6.0} s] {message}", start.elapsed().as_secs_f64());
                }
                bar.set_message(message);
                truths.borrow_mut().push(SessionTruth {
                    poses: session.ground_truth,
                });
                Some(SessionInput {
                    events: session.events,
                    base_from_laser: session.base_from_laser,
                })
            }
            Err(e) => {
                *failure.borrow_mut() = Some(e.into());
                None
            }
        }
    });
    let run = run_session_inputs(inputs, &config, &mut |done| {
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    if let Some(e) = failure.into_inner() {
        return Err(e.context("the simulator failed"));
    }
    let truths = truths.into_inner();
    let wall_time_s = start.elapsed().as_secs_f64();

    // The fixed frame: session 0's end-of-session trajectory aligned to its truth.
    let world_from_map = align(
        run.session_scan_poses
            .first()
            .map_or(&[][..], Vec::as_slice),
        &truths[0].poses,
    );
    let summaries: BTreeMap<u32, &SessionSummary> =
        run.sessions.iter().map(|s| (s.session, s)).collect();
    let mut scores = Vec::new();
    let mut later: Vec<TrajectoryAccuracy> = Vec::new();
    for (k, truth) in truths.iter().enumerate() {
        let session = k as u32;
        let summary = summaries.get(&session);
        // A session placed late was not localized before: its scans until then count as lost (the
        // end-of-session estimate would place them after the fact).
        let placed_at = summary.and_then(|s| s.placed_at_time);
        let estimate: Vec<(Timestamp, Rigid2)> = run
            .session_scan_poses
            .get(k)
            .map_or(&[][..], Vec::as_slice)
            .iter()
            .filter(|(t, _)| placed_at.is_none_or(|p| *t >= p))
            .copied()
            .collect();
        let accuracy = trajectory_accuracy(&estimate, &truth.poses, &world_from_map);
        let initialization_error = summary.and_then(|s| {
            let [x, y, theta] = s.relocalized_first_pose?;
            let time = s.first_node_time?;
            let truth_pose = truth.poses.iter().find(|(t, _)| *t == time)?.1;
            let found = world_from_map * mapping::geometry::rigid2(x, y, theta);
            Some((
                (found.translation.vector - truth_pose.translation.vector).norm(),
                normalize_angle(found.theta() - truth_pose.theta())
                    .abs()
                    .to_degrees(),
            ))
        });
        let initialized = session == 0
            || initialization_error
                .is_some_and(|(m, deg)| m <= MRCL_TRANSLATION_M && deg <= MRCL_ROTATION_DEG);
        if session > 0 {
            later.push(accuracy);
        }
        let counts = summary.map(|s| s.counts).unwrap_or_default();
        scores.push(SessionScore {
            session,
            initialized,
            initialization_error_m: initialization_error.map(|(m, _)| m),
            mrcl: accuracy.mrcl,
            ams: if session == 0 {
                summary.filter(|s| s.closures > 0).map(|s| s.ams)
            } else {
                summary.and_then(|s| s.cross_session_ams)
            },
            ate_rms_m: accuracy.ate_rms_m,
            max_error_m: accuracy.max_error_m,
            distance_m: accuracy.distance_m,
            nodes: counts.nodes,
            submaps: counts.submaps,
            constraints: counts.constraints,
            trimmed_total: counts.trimmed_total,
            dropped_total: counts.dropped_total,
            pgr_ms: summary.map_or(0.0, |s| s.finish_ms),
            peak_rss_mb: summary.and_then(|s| s.peak_rss_mb),
            scans: summary.map_or(0, |s| s.scans),
            closures: summary.map_or(0, |s| s.closures),
            cross_session_closures: summary.map_or(0, |s| s.cross_session_closures),
            trimmed: summary.map_or(0, |s| s.trimmed),
            dropped: summary.map_or(0, |s| s.dropped),
            tree_edges: summary.map_or(0, |s| s.tree_edges),
            trim_kld_mean: summary.and_then(|s| s.trim_kld_mean),
            relocalization_score: summary.and_then(|s| s.relocalization_score),
            relocalization_retries: summary.map_or(0, |s| s.relocalization_retries),
            placed_by_retry_at_node: summary.and_then(|s| s.placed_by_retry_at_node),
            placed: session == 0 || summary.is_some_and(|s| s.placed),
        });
    }

    // MCR: session 0's map against the map as its newest submaps describe the site now (both rendered
    // newest-wins, so that an unchanged site compares equal).
    let resolution = config.local.submaps.resolution;
    let before = render_submaps_newest(
        run.map
            .placed_submaps_by_id()
            .filter(|(id, _)| id.trajectory == 0)
            .map(|(_, g)| g),
        resolution,
    );
    let after = render_submaps_newest(run.map.placed_submaps_by_id().map(|(_, g)| g), resolution);
    let mut mcr = None;
    if let (Some(before), Some(after)) = (&before, &after) {
        let change = map_change_rate(before, after, MAP_CHANGE_TOLERANCE_M);
        let (w, h, pixels) = map_image::map_change_to_rgb(&change);
        map_image::write_rgb_png(&args.out.join("map_change.png"), w, h, &pixels)?;
        let (w, h, pixels) = map_image::grid_to_gray(after);
        map_image::write_gray_png(&args.out.join("map.png"), w, h, &pixels)?;
        mcr = Some(json!({
            "rate": change.rate, "unchanged": change.unchanged, "removed": change.removed,
            "added": change.added,
        }));
    }
    let truth_resolution = 0.1;
    let world_change_rate = store
        .occupancy(0, truth_resolution)
        .change_rate(&store.occupancy(args.sessions, truth_resolution));

    let localized: Vec<&SessionScore> = scores.iter().filter(|s| s.session > 0).collect();
    let n = localized.len().max(1) as f64;
    let distance: f64 = later.iter().map(|a| a.distance_m).sum();
    let good: f64 = later.iter().map(|a| a.mrcl * a.distance_m).sum();
    let matched: usize = later.iter().map(|a| a.matched).sum();
    let squared: f64 = later
        .iter()
        .map(|a| a.ate_rms_m * a.ate_rms_m * a.matched as f64)
        .sum();
    let ams: Vec<f64> = localized.iter().filter_map(|s| s.ams).collect();
    let summary = json!({
        "sessions": localized.len(),
        "cri": localized.iter().filter(|s| s.initialized).count() as f64 / n,
        // Sessions placed in the map at all, and of those placed after their start (an ambiguous start
        // told apart further on, or a retry): CRI counts neither as initialized.
        "placed": localized.iter().filter(|s| s.placed).count(),
        "placed_late": localized.iter().filter(|s| s.placed_by_retry_at_node.is_some()).count(),
        "mrcl": if distance > 0.0 { good / distance } else { 0.0 },
        "ams_mean": if ams.is_empty() { None } else { Some(ams.iter().sum::<f64>() / ams.len() as f64) },
        "ams_min": ams.iter().copied().reduce(f64::min),
        "mcr": mcr.as_ref().map(|m| m["rate"].clone()),
        "ate_rms_m": if matched > 0 { (squared / matched as f64).sqrt() } else { 0.0 },
        "world_change_rate": world_change_rate,
        "final": run.map.counts(),
        "wall_time_s": wall_time_s,
        "data_duration_s": run.data_duration_s,
        "peak_rss_mb": process_stats::peak_rss_mb(),
    });
    write_charts(&args.out, &scores)?;
    write_trajectories(
        &args.out.join("trajectories.csv"),
        &run.session_scan_poses,
        &truths,
        &world_from_map,
    )?;
    let report = json!({
        "world": "store",
        "seed": args.seed,
        "policy": config.lifelong.policy.name(),
        "session_options": options,
        "mcr_detail": mcr,
        "summary": summary,
        "sessions": scores,
        "session_details": run.sessions,
    });
    let report_path = args.out.join("report.json");
    std::fs::write(&report_path, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", report_path.display()))?;
    for s in &scores {
        eprintln!(
            "session {:>2}: init {:<5} mrcl {:.3} ams {} ate {:.3} m | nodes {} submaps {} constraints {} | pgr {:.0} ms",
            s.session,
            s.initialized,
            s.mrcl,
            s.ams.map_or("-".to_string(), |a| format!("{a:.3}")),
            s.ate_rms_m,
            s.nodes,
            s.submaps,
            s.constraints,
            s.pgr_ms
        );
    }
    println!(
        "{}",
        json!({"policy": config.lifelong.policy.name(), "summary": report["summary"]})
    );
    Ok(())
}

/// `world_from_map` aligning `estimate` to `truth` at equal stamps (identity when none match).
fn align(estimate: &[(Timestamp, Rigid2)], truth: &[(Timestamp, Rigid2)]) -> Rigid2 {
    let truth: BTreeMap<Timestamp, Rigid2> = truth.iter().copied().collect();
    let pairs: Vec<_> = estimate
        .iter()
        .filter_map(|(t, pose)| {
            let world = truth.get(t)?;
            Some((pose.translation.vector, world.translation.vector))
        })
        .collect();
    rigid_alignment(&pairs)
}

/// Writes every scan's estimated pose (in the truth's frame, through `world_from_map`) beside its truth:
/// `session,time_s,x,y,theta,true_x,true_y,true_theta,error_m` (m, rad), for plotting where a session lost
/// its way.
fn write_trajectories(
    path: &Path,
    estimates: &[Vec<(Timestamp, Rigid2)>],
    truths: &[SessionTruth],
    world_from_map: &Rigid2,
) -> anyhow::Result<()> {
    use std::fmt::Write as _;
    let mut csv = String::from("session,time_s,x,y,theta,true_x,true_y,true_theta,error_m\n");
    for (session, (estimate, truth)) in estimates.iter().zip(truths).enumerate() {
        let truth: BTreeMap<Timestamp, Rigid2> = truth.poses.iter().copied().collect();
        for (time, map_from_base) in estimate {
            let Some(world) = truth.get(time) else {
                continue;
            };
            let e = world_from_map * map_from_base;
            let error = (e.translation.vector - world.translation.vector).norm();
            let _ = writeln!(
                csv,
                "{session},{:.3},{:.4},{:.4},{:.5},{:.4},{:.4},{:.5},{error:.4}",
                time.as_secs_f64(),
                e.translation.x,
                e.translation.y,
                e.theta(),
                world.translation.x,
                world.translation.y,
                world.theta(),
            );
        }
    }
    std::fs::write(path, csv).with_context(|| format!("cannot write {}", path.display()))
}

fn write_charts(out: &Path, scores: &[SessionScore]) -> anyhow::Result<()> {
    let series = |name: &str, color: [u8; 3], f: &dyn Fn(&SessionScore) -> Option<f64>| Series {
        name: name.to_string(),
        color,
        points: scores
            .iter()
            .filter_map(|s| Some((f64::from(s.session), f(s)?)))
            .collect(),
    };
    let graph = LineChart {
        title: "graph size after each session".into(),
        x_label: "session".into(),
        y_label: "count".into(),
        series: vec![
            series("nodes", [30, 90, 200], &|s| Some(s.nodes as f64)),
            series("submaps x10", [0, 150, 0], &|s| {
                Some(10.0 * s.submaps as f64)
            }),
            series("constraints", [200, 40, 40], &|s| {
                Some(s.constraints as f64)
            }),
        ],
        y_min: Some(0.0),
    };
    let (w, h, pixels) = graph.render(720, 420);
    map_image::write_rgb_png(&out.join("graph_size.png"), w, h, &pixels)?;
    let ams = LineChart {
        title: "matching score and localization per session".into(),
        x_label: "session".into(),
        y_label: "score / rate".into(),
        series: vec![
            series("AMS", [30, 90, 200], &|s| s.ams),
            series("MRCL", [0, 150, 0], &|s| Some(s.mrcl)),
        ],
        y_min: Some(0.0),
    };
    let (w, h, pixels) = ams.render(720, 420);
    map_image::write_rgb_png(&out.join("ams.png"), w, h, &pixels)?;
    Ok(())
}
