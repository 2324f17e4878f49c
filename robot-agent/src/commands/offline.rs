//! `evermap-agent offline`: one recording in, trajectory + map + report out; or, with `--ros2`, a live
//! ROS 2 robot over zenoh (rmw_zenoh's keys, no ROS install) mapped as it drives, its map and pose
//! published back to ROS 2, until no scan has come for `--until-idle-s` seconds: the same outputs.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use mapping::geometry::{Rigid2, Rigid2Ext as _};
use mapping::global_slam::{GlobalSlam, LoopClosureCheck, loop_closure_precision};
use mapping::io::relations::Relation;
use mapping::metrics::{JudgedMatch, judge_matches, match_counts};
use mapping::sensor::Timestamp;
use robot_agent::line_chart::{LineChart, Series};
use robot_agent::offline_slam::{SlamConfig, SlamRun, render_map, run_offline, run_slam};
use robot_agent::perturbation::PerturbationReport;
use robot_agent::ros2_publisher::{Ros2Publisher, Ros2SlamPublisher};
use robot_agent::{map_image, process_stats, source};
use serde_json::json;

use super::perturb_args::PerturbArgs;

/// Arguments of `offline`.
#[derive(Args)]
pub struct OfflineArgs {
    /// The recording: a ROS1 bag, a ROS 2 recording (rosbag2 folder, its `metadata.yaml`, or one `.mcap`
    /// or `.db3` file) or a CARMEN log (`.clf`, `.log`, `.log.gz`).
    #[arg(long, required_unless_present = "ros2", conflicts_with = "ros2")]
    input: Option<PathBuf>,
    /// Map a live ROS 2 robot over zenoh (rmw_zenoh) instead of a recording.
    #[arg(long, requires = "until_idle_s")]
    ros2: bool,
    /// With `--ros2`: zenoh endpoint to connect to (repeatable). Default `tcp/127.0.0.1:7447`, the rmw_zenoh
    /// router's.
    #[arg(long, requires = "ros2")]
    zenoh_connect: Vec<String>,
    /// With `--ros2`: zenoh endpoint to listen on (repeatable). Default none.
    #[arg(long, requires = "ros2")]
    zenoh_listen: Vec<String>,
    /// With `--ros2`: the ROS domain id. Default 0.
    #[arg(long, requires = "ros2")]
    domain_id: Option<u32>,
    /// With `--ros2`: the laser scan topic. Default `/scan`.
    #[arg(long, requires = "ros2")]
    scan_topic: Option<String>,
    /// With `--ros2`: the odometry topic. Default `/odom`.
    #[arg(long, requires = "ros2")]
    odom_topic: Option<String>,
    /// With `--ros2`: stop after this many seconds without a scan.
    #[arg(long, requires = "ros2")]
    until_idle_s: Option<f64>,
    /// With `--ros2`: give up if no scan comes within this many seconds.
    #[arg(long, requires = "ros2", default_value_t = 60.0)]
    start_timeout_s: f64,
    /// With `--ros2`: do not publish the map and pose back to ROS 2.
    #[arg(long, requires = "ros2")]
    no_publish: bool,
    /// Ground-truth relations (`t1 t2 x y z roll pitch yaw`) to score the trajectory with.
    #[arg(long)]
    relations: Option<PathBuf>,
    /// A reference trajectory (TUM: the truth, or the final trajectory of the same recording's clean run)
    /// to judge each GLM match against: `glm_matches.csv` and `report.json`'s `glm_matches` then say,
    /// per acceptance rule, how many of the matches it decided were right (within 0.5 m and 3°).
    #[arg(long)]
    reference_trajectory: Option<PathBuf>,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// A TOML file overriding the default SLAM configuration (see `SlamConfig`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// The robustness suite's perturbations of the recording.
    #[command(flatten)]
    perturb: PerturbArgs,
}

/// Runs the command.
pub fn run(args: &OfflineArgs) -> anyhow::Result<()> {
    let config = SlamConfig::load(args.config.as_deref())?;
    let perturbation_asked = args.perturb.perturbation()?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let relations = args
        .relations
        .as_deref()
        .map(|path| {
            read_with(
                path,
                "relations file",
                mapping::io::relations::read_relations,
            )
        })
        .transpose()?;
    let reference = args
        .reference_trajectory
        .as_deref()
        .map(|path| read_with(path, "TUM trajectory", mapping::io::tum::read_tum))
        .transpose()?;

    let start = Instant::now();
    let mut perturbation = serde_json::Value::Null;
    // Where the perturbation restamped scans (`burst`), the run is written and scored at the times they
    // were taken.
    let mut capture_times = PerturbationReport::default();
    let (mut run, input, read_report, read_time_s, live) = if args.ros2 {
        anyhow::ensure!(
            perturbation_asked.is_none(),
            "--perturb works on recordings, not on a live robot"
        );
        let (run, live) = map_live(args, &config)?;
        (
            run,
            "ros2 (live)".to_owned(),
            String::new(),
            0.0,
            Some(live),
        )
    } else {
        let input = args
            .input
            .as_ref()
            .context("give --input (a recording) or --ros2 (a live robot)")?;
        eprintln!("reading {}", input.display());
        let (recording, done, perturbed) = args
            .perturb
            .apply(perturbation_asked.as_ref(), source::read_recording(input)?);
        perturbation = done;
        capture_times = perturbed;
        let read_time_s = start.elapsed().as_secs_f64();
        let scans = recording.report.scans;
        let bar = ProgressBar::new(scans as u64);
        bar.set_style(
            ProgressStyle::with_template(
                "{elapsed_precise} [{bar:40}] {pos}/{len} scans ({per_sec}, eta {eta})",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        let run = run_offline(&recording, &config, &mut |done| {
            bar.set_position(done as u64);
        })?;
        bar.finish_and_clear();
        (
            run,
            input.display().to_string(),
            format!("{:?}", recording.report),
            read_time_s,
            None,
        )
    };
    let wall_time_s = start.elapsed().as_secs_f64();
    for (time, _) in &mut run.scan_poses {
        *time = capture_times.capture_time(*time);
    }

    let tum_path = args.out.join("trajectory.tum");
    let tum = std::fs::File::create(&tum_path)
        .with_context(|| format!("cannot create {}", tum_path.display()))?;
    mapping::io::tum::write_tum(std::io::BufWriter::new(tum), &run.scan_poses)
        .with_context(|| format!("cannot write {}", tum_path.display()))?;

    write_llo_scans(&args.out.join("llo_scans.csv"), &run)?;
    let map = render_map(&run, config.local.submaps.resolution);
    let (w, h, pixels) = map_image::grid_to_gray(&map);
    map_image::write_gray_png(&args.out.join("map.png"), w, h, &pixels)?;
    map_image::write_nav2_map(&args.out, "map", &map)?;

    let relations_json = match &relations {
        Some(r) => {
            let start_time = run.scan_poses.first().map(|(t, _)| *t);
            write_relation_errors(&args.out, &run.scan_poses, r, start_time)?;
            let error = mapping::metrics::relations_error(&run.scan_poses, r);
            Some(serde_json::to_value(error)?)
        }
        None => None,
    };
    // The same relations scored only where the engine had a scan at both stamps (no interpolated
    // poses): equal to `relations` on a recording's own scans, and the fair score of a run with scans
    // dropped (`--perturb slow`).
    let relations_at_scans_json = match &relations {
        Some(r) => Some(serde_json::to_value(
            mapping::metrics::relations_error_at_scans(&run.scan_poses, r),
        )?),
        None => None,
    };
    let closures = run.global.accepted_loop_closures();
    let ams = if closures.is_empty() {
        0.0
    } else {
        closures.iter().map(|c| f64::from(c.score)).sum::<f64>() / closures.len() as f64
    };
    let checks = run.global.loop_closure_checks();
    write_loop_closures(&args.out.join("loop_closures.csv"), &run.global, &checks)?;
    let judged = judge_matches(&run.global, &run.match_decisions, reference.as_deref());
    write_glm_matches(&args.out.join("glm_matches.csv"), &run.global, &judged)?;
    let precision = loop_closure_precision(&checks);
    let graph = run.global.graph();
    let report = json!({
        "input": input,
        "scans": run.scans,
        "scans_dropped": run.scans_dropped,
        "scans_retimed": run.scans_retimed,
        "odometry_offset_s": run.odometry_offset_s,
        "llo_scans_by_branch": llo_branch_counts(&run),
        "data_duration_s": run.data_duration_s,
        "wall_time_s": wall_time_s,
        "read_time_s": read_time_s,
        "realtime_factor": if wall_time_s > 0.0 { run.data_duration_s / wall_time_s } else { 0.0 },
        "nodes": run.global.nodes().len(),
        "submaps": run.global.submaps().len(),
        "constraints": graph.num_constraints(),
        "loop_closures": closures.len(),
        "loop_closure_precision": precision.precision,
        "loop_closures_held": precision.held,
        "loop_closures_checked": precision.checked,
        "loop_closures_retracted": precision.retracted,
        "loop_closure_precision_as_matched": precision.precision_as_matched,
        "loop_closure_searches": run.global.searches_queued(),
        "loop_closures_beyond_drift": run.global.closures_beyond_drift(),
        "loop_closures_outvoted": run.global.closures_outvoted(),
        "glm_matches": match_counts(&judged),
        "glm_matches_reference": args.reference_trajectory.as_ref().map(|p| p.display().to_string()),
        "ams": ams,
        "optimizations": run.optimizations,
        "final_optimization": format!("{:?}", run.final_optimization),
        "range_stats": run.range_stats,
        "read_report": read_report,
        "live": live,
        "peak_rss_mb": process_stats::peak_rss_mb(),
        "relations": relations_json,
        "relations_at_scans": relations_at_scans_json,
        "perturbation": perturbation,
    });
    let report_path = args.out.join("report.json");
    std::fs::write(&report_path, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", report_path.display()))?;
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}

/// Opens `path` and parses it with `parse`; errors name the file and what it should have been.
fn read_with<T, E: std::error::Error + Send + Sync + 'static>(
    path: &Path,
    what: &str,
    parse: impl FnOnce(std::io::BufReader<std::fs::File>) -> Result<T, E>,
) -> anyhow::Result<T> {
    let file =
        std::fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
    parse(std::io::BufReader::new(file))
        .with_context(|| format!("invalid {what} {}", path.display()))
}

/// `--ros2`: maps the live robot until it has been idle `--until-idle-s` seconds, publishing the map and
/// pose back; returns the run and what the live source and the publisher counted (for `report.json`).
fn map_live(
    args: &OfflineArgs,
    config: &robot_agent::offline_slam::SlamConfig,
) -> anyhow::Result<(robot_agent::offline_slam::SlamRun, serde_json::Value)> {
    let mut options = source::Ros2LiveOptions::default();
    if !args.zenoh_connect.is_empty() || !args.zenoh_listen.is_empty() {
        options.zenoh.connect.clone_from(&args.zenoh_connect);
        options.zenoh.listen.clone_from(&args.zenoh_listen);
    }
    if let Some(d) = args.domain_id {
        options.domain_id = d;
    }
    if let Some(t) = &args.scan_topic {
        options.scan_topic.clone_from(t);
    }
    if let Some(t) = &args.odom_topic {
        options.odom_topic.clone_from(t);
    }
    let end = source::StreamEnd {
        until_idle_s: args.until_idle_s.unwrap_or(0.0),
        start_timeout_s: args.start_timeout_s,
    };
    let mut live = source::LiveRos2Source::open(&options, end)?;
    let publisher = if args.no_publish {
        None
    } else {
        Some(Ros2SlamPublisher::new(Ros2Publisher::open(
            live.session(),
            options.domain_id,
            &options.publish,
        )?))
    };
    eprintln!(
        "listening to {} and {} in ROS domain {} (stops {} s after the last scan)",
        options.scan_topic, options.odom_topic, options.domain_id, end.until_idle_s
    );
    let bar = ProgressBar::new_spinner();
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} {pos} scans ({per_sec})")
            .unwrap_or_else(|_| ProgressStyle::default_spinner()),
    );
    let mut progress = |done: usize| bar.set_position(done as u64);
    let (run, published) = match publisher {
        Some(mut observer) => {
            let run = run_slam(&mut live, config, &mut progress, &mut observer);
            (run, Some(observer.publisher_mut().stats()))
        }
        None => (
            run_slam(&mut live, config, &mut progress, &mut NoopObserver),
            None,
        ),
    };
    bar.finish_and_clear();
    let stats = live.stats();
    eprintln!(
        "live: received {}, decoded {}, dropped {}",
        stats.received(),
        stats.decoded(),
        stats.dropped()
    );
    anyhow::ensure!(
        stats.scans_out > 0,
        "no scan arrived on {} within {} s (received {} messages in all): is the robot publishing, and are \
         --zenoh-connect / --zenoh-listen, --domain-id and --scan-topic right?",
        options.scan_topic,
        args.start_timeout_s,
        stats.received()
    );
    let run = run?;
    Ok((
        run,
        json!({
            "received": stats.received(),
            "decoded": stats.decoded(),
            "dropped": stats.dropped(),
            "stats": stats,
            "published": published,
        }),
    ))
}

/// Publishes nothing (`--no-publish`).
struct NoopObserver;

impl robot_agent::offline_slam::SlamObserver for NoopObserver {}

/// Writes `llo_scans.csv`: how LLO placed each scan as it happened, `t_s` from the first scan, the
/// correlative search that placed it, whether it became a node, its local pose (m, m, degrees) and whether
/// it retracted a held recovered scan.
fn write_llo_scans(path: &Path, run: &SlamRun) -> anyhow::Result<()> {
    let mut csv = String::from("t_s,branch,inserted,x_m,y_m,theta_deg,retracted\n");
    let start = run.llo_scans.first().map(|s| s.time);
    for scan in &run.llo_scans {
        let t = start.map_or(0.0, |start| scan.time.seconds_since(start));
        let p = &scan.local_pose;
        let _ = writeln!(
            csv,
            "{t:.3},{:?},{},{:.4},{:.4},{:.3},{}",
            scan.branch,
            u8::from(scan.inserted),
            p.x(),
            p.y(),
            p.theta().to_degrees(),
            u8::from(scan.retracted)
        );
    }
    std::fs::write(path, csv).with_context(|| format!("cannot write {}", path.display()))
}

/// How many scans each correlative search placed (`llo_scans_by_branch` in `report.json`).
fn llo_branch_counts(run: &SlamRun) -> BTreeMap<String, usize> {
    let mut counts = BTreeMap::new();
    for scan in &run.llo_scans {
        *counts.entry(format!("{:?}", scan.branch)).or_default() += 1;
    }
    counts
}

/// Writes `relations.csv` (every relation's error, by time) and `relations_error.png` (translational error
/// against the time of the relation's first stamp: where the trajectory tears).
fn write_relation_errors(
    out: &Path,
    poses: &[(Timestamp, Rigid2)],
    relations: &[Relation],
    start: Option<Timestamp>,
) -> anyhow::Result<()> {
    let mut errors = mapping::metrics::relation_errors(poses, relations);
    errors.sort_by_key(|e| e.t1);
    let since_start = |t: Timestamp| start.map_or(0.0, |s| t.seconds_since(s));
    let mut csv = String::from("t1_s,t2_s,trans_error_m,rot_error_deg\n");
    for e in &errors {
        writeln!(
            csv,
            "{:.3},{:.3},{:.4},{:.3}",
            since_start(e.t1),
            since_start(e.t2),
            e.trans_m,
            e.rot_deg
        )?;
    }
    let path = out.join("relations.csv");
    std::fs::write(&path, csv).with_context(|| format!("cannot write {}", path.display()))?;
    let chart = LineChart {
        title: "relations error against time (spikes: where the trajectory tears)".into(),
        x_label: "time of the relation's first scan (s)".into(),
        y_label: "translation error (m)".into(),
        series: vec![
            Series {
                name: "translation (m)".into(),
                color: [200, 40, 40],
                points: errors
                    .iter()
                    .map(|e| (since_start(e.t1), e.trans_m))
                    .collect(),
            },
            Series {
                name: "rotation (deg / 10)".into(),
                color: [30, 90, 200],
                points: errors
                    .iter()
                    .map(|e| (since_start(e.t1), e.rot_deg / 10.0))
                    .collect(),
            },
        ],
        y_min: Some(0.0),
    };
    let (w, h, pixels) = chart.render(1000, 420);
    map_image::write_rgb_png(&out.join("relations_error.png"), w, h, &pixels)?;
    Ok(())
}

/// Writes `loop_closures.csv`: every accepted loop closure with its node's time, its score, the runner-up
/// score at a clearly different pose and its residual after the final optimization.
fn write_loop_closures(
    path: &Path,
    global: &GlobalSlam,
    checks: &[LoopClosureCheck],
) -> anyhow::Result<()> {
    let start = global.nodes().values().next().map(|n| n.time);
    let mut csv = String::from(
        "node_time_s,node,submap_trajectory,submap,score,runner_up_score,innovation_m,innovation_deg,confirmed,residual_m,residual_deg,holds,retracted\n",
    );
    for c in checks {
        let time = global
            .nodes()
            .get(&c.closure.node)
            .zip(start)
            .map_or(f64::NAN, |(n, s)| n.time.seconds_since(s));
        writeln!(
            csv,
            "{:.3},{},{},{},{:.4},{},{:.4},{:.3},{},{:.4},{:.3},{},{}",
            time,
            c.closure.node.index,
            c.closure.submap.trajectory,
            c.closure.submap.index,
            c.closure.score,
            c.closure
                .runner_up_score
                .map_or(String::new(), |r| format!("{r:.4}")),
            c.acceptance.innovation_translation_m,
            c.acceptance.innovation_rotation_rad.to_degrees(),
            u8::from(c.acceptance.confirmed_by_agreement),
            c.residual_translation_m,
            c.residual_rotation_rad.to_degrees(),
            u8::from(c.holds()),
            u8::from(c.retracted),
        )?;
    }
    std::fs::write(path, csv).with_context(|| format!("cannot write {}", path.display()))
}

/// Writes `glm_matches.csv`: every GLM match that reached the acceptance rules, in order, with the rule
/// that decided it, where it ended, its anchor (the submap's node nearest it) and, with a reference
/// trajectory, its error against it and whether that makes it right.
/// How well a match pins its weakest translation direction against its strongest (eigenvalues of its
/// information's translation block; 1 = a room, near 0 = a corridor) and how far along that weakest
/// direction it moves its node (m). No information: (1, 0).
fn weak_axis(information: Option<&nalgebra::Matrix3<f64>>, innovation: &Rigid2) -> (f64, f64) {
    let Some(information) = information else {
        return (1.0, 0.0);
    };
    let eigen = information
        .fixed_view::<2, 2>(0, 0)
        .into_owned()
        .symmetric_eigen();
    let (weak, strong) = if eigen.eigenvalues[0] <= eigen.eigenvalues[1] {
        (0, 1)
    } else {
        (1, 0)
    };
    if eigen.eigenvalues[strong].is_nan() || eigen.eigenvalues[strong] <= 0.0 {
        return (1.0, 0.0);
    }
    let along = eigen
        .eigenvectors
        .column(weak)
        .dot(&innovation.translation.vector)
        .abs();
    (eigen.eigenvalues[weak] / eigen.eigenvalues[strong], along)
}

fn write_glm_matches(
    path: &Path,
    global: &GlobalSlam,
    judged: &[JudgedMatch],
) -> anyhow::Result<()> {
    let start = global.nodes().values().next().map(|n| n.time);
    let since_start = |t: Timestamp| start.map_or(f64::NAN, |s| t.seconds_since(s));
    let mut csv = String::from(
        "node_time_s,node,submap_trajectory,submap,anchor_time_s,decision,fate,score,innovation_m,innovation_deg,pinned_ratio,innovation_along_weak_m,error_m,error_deg,right\n",
    );
    for j in judged {
        let c = &j.decided.closure;
        let (error_m, error_deg, right) = match j.error {
            Some((m, deg)) => (
                format!("{m:.4}"),
                format!("{deg:.3}"),
                u8::from(j.right() == Some(true)).to_string(),
            ),
            None => (String::new(), String::new(), String::new()),
        };
        let (pinned_ratio, along_weak) = weak_axis(c.information.as_ref(), &j.decided.innovation);
        writeln!(
            csv,
            "{:.3},{},{},{},{:.3},{},{},{:.4},{:.4},{:.3},{:.4},{:.4},{},{},{}",
            since_start(j.node_time),
            c.node.index,
            c.submap.trajectory,
            c.submap.index,
            since_start(j.anchor_time),
            j.decided.decision.name(),
            j.fate.name(),
            c.score,
            j.decided.acceptance.innovation_translation_m,
            j.decided.acceptance.innovation_rotation_rad.to_degrees(),
            pinned_ratio,
            along_weak,
            error_m,
            error_deg,
            right,
        )?;
    }
    std::fs::write(path, csv).with_context(|| format!("cannot write {}", path.display()))
}
