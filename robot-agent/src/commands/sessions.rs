//! `evermap-agent sessions`: one recording run as several time sessions through the lifelong map,
//! scored over the relations whose two stamps fall in different sessions, and over all.
//!
//! - `relations_cross_session`: the final map's trajectory (smoothed after the fact).
//! - `relations_all` and `relations_cross_session` score the map the fleet is left with: a relation
//!   between a session dropped at its end (never placed, or its placement never committed: its scans float
//!   in a frame nothing ties to the site) and another session says nothing of that map, and is counted
//!   apart (`relations_across_dropped_sessions`): a refusal, not an error.
//! - `relations_cross_session_at_the_time`: each such relation as the robot lived it, its later scan's
//!   estimate at that scan against the earlier scan's pose in the map as the map stood at that moment
//!   (the map the robot was placed on; see `mapping::metrics::judge_placements`). Scans before a session
//!   was placed have no estimate and leave their relations unmatched.
//! - Per session: every placement the robot acted on, judged right or wrong by the median of those
//!   relations while it held (0.5 m or 5°, `scoring.wrong_placement`), when the session was placed and
//!   committed, why each refused search refused, and the AMS over every node against the map as it was
//!   at the session's start (`mapping::metrics`, as `lifelong` scores them; there is no pose truth here,
//!   so no MRCL).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context as _;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use mapping::geometry::Rigid2;
use mapping::io::relations::{Relation, read_relations};
use mapping::lifelong::TrimPolicy;
use mapping::metrics::{
    RelationError, Verdict, average_match_score, judge_placements, relation_error_stats,
    relations_error,
};
use mapping::sensor::Timestamp;
use robot_agent::lifelong_run::{SessionsConfig, run_sessions, session_boundaries};
use robot_agent::map_probes::{
    cross_session_probes, relation_errors_at_the_time, relations_in_the_map,
};
use robot_agent::offline_slam::render_range_data;
use robot_agent::{map_image, process_stats, source};
use serde_json::json;

use super::perturb_args::PerturbArgs;

/// Arguments of `sessions`.
#[derive(Args)]
pub struct SessionsArgs {
    /// The recording: a ROS1 bag, a ROS 2 recording (rosbag2 folder, `metadata.yaml`, `.mcap` or `.db3`)
    /// or a CARMEN log.
    #[arg(long)]
    input: PathBuf,
    /// Into how many equal time spans (sessions) to cut the recording.
    #[arg(long, default_value_t = 3)]
    split: usize,
    /// Ground-truth relations (`t1 t2 x y z roll pitch yaw`) to score the trajectory with.
    #[arg(long)]
    relations: Option<PathBuf>,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// A TOML file overriding the default configuration (see `SessionsConfig`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Trimming policy (clt, delete, keep, frozen); overrides the configuration's.
    #[arg(long)]
    policy: Option<TrimPolicy>,
    /// Each later session first checks the last pose the robot had in the previous one (where the
    /// recording was cut, it has not moved: a dock start); without it, every later session searches.
    #[arg(long)]
    dock_starts: bool,
    /// The robustness suite's perturbations of the recording.
    #[command(flatten)]
    perturb: PerturbArgs,
}

/// Runs the command.
pub fn run(args: &SessionsArgs) -> anyhow::Result<()> {
    let config = SessionsConfig::load(args.config.as_deref(), args.policy)?;
    let perturbation_asked = args.perturb.perturbation()?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let relations: Option<Vec<Relation>> = match &args.relations {
        Some(path) => {
            let file = std::fs::File::open(path)
                .with_context(|| format!("cannot open {}", path.display()))?;
            Some(
                read_relations(std::io::BufReader::new(file))
                    .with_context(|| format!("invalid relations file {}", path.display()))?,
            )
        }
        None => None,
    };

    let start = Instant::now();
    eprintln!("reading {}", args.input.display());
    let (recording, perturbation, perturbed) = args.perturb.apply(
        perturbation_asked.as_ref(),
        source::read_recording(&args.input)?,
    );
    // The relations are made at the times scans were taken; the run goes by their stamps, which a
    // perturbation may have moved (`burst`, `scanburst`): each relation is asked at its scans' stamps, and
    // the trajectory written at the times they were taken, as `offline` does.
    let relations = relations.map(|relations| perturbed.relations_at_stamps(relations));
    let bar = ProgressBar::new(recording.report.scans as u64);
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:40}] {pos}/{len} scans ({per_sec}, eta {eta})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    // Relations tying a scan of one session to a scan of another: each asks where the map held the
    // earlier scan when the robot estimated the later one.
    let boundaries = session_boundaries(&recording, args.split)?;
    let session_of = |t: Timestamp| boundaries.partition_point(|b| *b <= t);
    let (cross, probes) =
        cross_session_probes(relations.as_deref().unwrap_or_default(), &boundaries);
    let run = run_sessions(
        &recording,
        args.split,
        args.dock_starts,
        &config,
        &probes,
        &mut |done| {
            bar.set_position(done as u64);
        },
    )?;
    bar.finish_and_clear();
    let wall_time_s = start.elapsed().as_secs_f64();

    let tum_path = args.out.join("trajectory.tum");
    let tum = std::fs::File::create(&tum_path)
        .with_context(|| format!("cannot create {}", tum_path.display()))?;
    let captured: Vec<(Timestamp, Rigid2)> = run
        .scan_poses
        .iter()
        .map(|(t, pose)| (perturbed.capture_time(*t), *pose))
        .collect();
    mapping::io::tum::write_tum(std::io::BufWriter::new(tum), &captured)
        .with_context(|| format!("cannot write {}", tum_path.display()))?;
    let map = render_range_data(
        run.node_range_data
            .values()
            .map(|(pose, data)| (*pose, data)),
        config.local.submaps.resolution,
    );
    let (w, h, pixels) = map_image::grid_to_gray(&map);
    map_image::write_gray_png(&args.out.join("map.png"), w, h, &pixels)?;

    let mut online: Vec<(Timestamp, Rigid2)> = run
        .records
        .iter()
        .flat_map(|r| r.online.iter().copied())
        .collect();
    online.sort_by_key(|(t, _)| *t);
    let at_the_time = relation_errors_at_the_time(&cross, &probes, &run.probe_poses, &online);
    // The first session, and each later one that ended placed and committed, are in the final map.
    let in_map: Vec<bool> = (0..args.split)
        .map(|k| {
            run.sessions
                .iter()
                .any(|s| s.session as usize == k && s.placed)
        })
        .collect();
    let (relations_scored, across_dropped) = relations_in_the_map(
        relations.as_deref().unwrap_or_default(),
        &boundaries,
        &in_map,
    );
    let (cross_scored, _) = relations_in_the_map(&cross, &boundaries, &in_map);
    let (all, cross_smoothed, cross_online) = match &relations {
        Some(_) => (
            Some(relations_error(&run.scan_poses, &relations_scored)),
            Some(relations_error(&run.scan_poses, &cross_scored)),
            Some(relation_error_stats(
                &at_the_time,
                cross.len() - at_the_time.len(),
            )),
        ),
        None => (None, None, None),
    };
    // Placements placed right / wrong / unjudged, and held right / wrong / unjudged.
    let mut verdict_counts = [[0usize; 3]; 2];
    let index = |v: Verdict| match v {
        Verdict::Right => 0,
        Verdict::Wrong => 1,
        Verdict::Unjudged => 2,
    };
    let scores: Vec<_> = run
        .records
        .iter()
        .map(|r| {
            let summary = run.sessions.iter().find(|s| s.session == r.session);
            let verdicts = relations.as_ref().map(|_| {
                let errors: Vec<RelationError> = at_the_time
                    .iter()
                    .filter(|e| session_of(e.t1.max(e.t2)) == r.session as usize + 1)
                    .copied()
                    .collect();
                judge_placements(&r.start.placements, &errors, config.scoring.wrong_placement)
            });
            for v in verdicts.iter().flatten() {
                verdict_counts[0][index(v.placed.verdict)] += 1;
                verdict_counts[1][index(v.held.verdict)] += 1;
            }
            let refusals: Vec<&str> = summary
                .map(|s| {
                    s.searches
                        .iter()
                        .map(|f| f.outcome)
                        .filter(|o| *o != "placed")
                        .collect()
                })
                .unwrap_or_default();
            json!({
                "session": r.session,
                "ams": average_match_score(&r.match_scores),
                "scored_nodes": r.match_scores.len(),
                "placed_after_s": r.start.placements.first().map(|p| p.decided_at.seconds_since(r.start_time)),
                "committed_after_s": r.start.committed.map(|p| p.decided_at.seconds_since(r.start_time)),
                "placements": verdicts,
                "refused_searches": refusals,
                "scans_localized_at_the_time": r.online.len(),
            })
        })
        .collect();
    let placement_counts = json!({
        "placed": {"right": verdict_counts[0][0], "wrong": verdict_counts[0][1], "unjudged": verdict_counts[0][2]},
        "held": {"right": verdict_counts[1][0], "wrong": verdict_counts[1][1], "unjudged": verdict_counts[1][2]},
    });
    let counts = run.map.counts();
    let report = json!({
        "input": args.input.display().to_string(),
        "split": args.split,
        "perturbation": perturbation,
        "policy": config.lifelong.policy.name(),
        "data_duration_s": run.data_duration_s,
        "wall_time_s": wall_time_s,
        "realtime_factor": if wall_time_s > 0.0 { run.data_duration_s / wall_time_s } else { 0.0 },
        "relations_all": all,
        "relations_cross_session": cross_smoothed,
        "relations_cross_session_at_the_time": cross_online,
        "relations_across_dropped_sessions": across_dropped,
        "session_scores": scores,
        "placements": placement_counts,
        "scan_poses": run.scan_poses.len(),
        "scans_retimed": run.scans_retimed,
        "final": counts,
        "sessions": run.sessions,
        "peak_rss_mb": process_stats::peak_rss_mb(),
    });
    let report_path = args.out.join("report.json");
    std::fs::write(&report_path, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", report_path.display()))?;
    println!(
        "{}",
        json!({"relations_all": report["relations_all"], "relations_cross_session": report["relations_cross_session"],
               "relations_across_dropped_sessions": across_dropped,
               "relations_cross_session_at_the_time": report["relations_cross_session_at_the_time"],
               "placements": placement_counts,
               "wall_time_s": wall_time_s, "final": counts})
    );
    Ok(())
}
