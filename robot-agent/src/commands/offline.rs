//! `evermap-agent offline`: one recording in, trajectory + map + report out.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use robot_agent::offline_slam::{SlamConfig, render_map, run_offline};
use robot_agent::{map_image, process_stats, source};
use serde_json::json;

/// Arguments of `offline`.
#[derive(Args)]
pub struct OfflineArgs {
    /// The recording: a ROS1 bag or a CARMEN log (`.clf`, `.log`, `.log.gz`).
    #[arg(long)]
    input: PathBuf,
    /// Ground-truth relations (`t1 t2 x y z roll pitch yaw`) to score the trajectory with.
    #[arg(long)]
    relations: Option<PathBuf>,
    /// Output folder (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// A TOML file overriding the default SLAM configuration (see `SlamConfig`).
    #[arg(long)]
    config: Option<PathBuf>,
}

/// Reads a TOML SLAM configuration, or the defaults.
pub fn load_config(path: Option<&Path>) -> anyhow::Result<SlamConfig> {
    let Some(path) = path else {
        return Ok(SlamConfig::default());
    };
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read config {}", path.display()))?;
    toml::from_str(&text).with_context(|| format!("invalid config {}", path.display()))
}

/// Runs the command.
pub fn run(args: &OfflineArgs) -> anyhow::Result<()> {
    let config = load_config(args.config.as_deref())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let relations = match &args.relations {
        Some(path) => {
            let file = std::fs::File::open(path)
                .with_context(|| format!("cannot open {}", path.display()))?;
            Some(
                mapping::io::relations::read_relations(std::io::BufReader::new(file))
                    .with_context(|| format!("invalid relations file {}", path.display()))?,
            )
        }
        None => None,
    };

    let start = Instant::now();
    eprintln!("reading {}", args.input.display());
    let recording = source::read_recording(&args.input)?;
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
    let wall_time_s = start.elapsed().as_secs_f64();

    let tum_path = args.out.join("trajectory.tum");
    let tum = std::fs::File::create(&tum_path)
        .with_context(|| format!("cannot create {}", tum_path.display()))?;
    mapping::io::tum::write_tum(std::io::BufWriter::new(tum), &run.scan_poses)
        .with_context(|| format!("cannot write {}", tum_path.display()))?;

    let map = render_map(&run, config.local.submaps.resolution);
    let (w, h, pixels) = map_image::grid_to_gray(&map);
    map_image::write_gray_png(&args.out.join("map.png"), w, h, &pixels)?;
    map_image::write_nav2_map(&args.out, "map", &map)?;

    let relations_json = relations.as_ref().map(|r| {
        let error = mapping::metrics::relations_error(&run.scan_poses, r);
        serde_json::to_value(error).unwrap_or_default()
    });
    let scores = run.global.loop_closure_scores();
    let ams = if scores.is_empty() {
        0.0
    } else {
        scores.iter().map(|&s| f64::from(s)).sum::<f64>() / scores.len() as f64
    };
    let graph = run.global.graph();
    let report = json!({
        "input": args.input.display().to_string(),
        "scans": run.scans,
        "scans_dropped": run.scans_dropped,
        "data_duration_s": run.data_duration_s,
        "wall_time_s": wall_time_s,
        "realtime_factor": if wall_time_s > 0.0 { run.data_duration_s / wall_time_s } else { 0.0 },
        "nodes": run.global.nodes().len(),
        "submaps": run.global.submaps().len(),
        "constraints": graph.num_constraints(),
        "loop_closures": scores.len(),
        "loop_closure_searches": run.global.searches_queued(),
        "ams": ams,
        "optimizations": run.optimizations,
        "final_optimization": format!("{:?}", run.final_optimization),
        "range_stats": run.range_stats,
        "read_report": format!("{:?}", recording.report),
        "peak_rss_mb": process_stats::peak_rss_mb(),
        "relations": relations_json,
    });
    let report_path = args.out.join("report.json");
    std::fs::write(&report_path, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", report_path.display()))?;
    println!("{}", serde_json::to_string(&report)?);
    Ok(())
}
