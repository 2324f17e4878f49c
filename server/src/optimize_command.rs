//! `evermap-server optimize`: optimize a g2o/TORO pose graph file and report one JSON line.

use std::fs::File;
use std::io::{BufReader, BufWriter, Write as _};
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context as _, Result};
use mapping::io::g2o::{read_pose_graph, write_pose_graph};
use mapping::pose_graph::{Optimizer, OptimizerOptions};

/// Arguments of `evermap-server optimize`.
#[derive(clap::Args, Debug)]
pub struct OptimizeArgs {
    /// Pose graph to optimize, g2o (`VERTEX_SE2`/`EDGE_SE2`) or TORO (`VERTEX2`/`EDGE2`), detected by content.
    #[arg(long = "g2o", value_name = "FILE")]
    pub input: PathBuf,
    /// Write the optimized graph here, as g2o.
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// Start from the file's values only, without trying the rotation-first initial guess.
    #[arg(long)]
    pub no_rotation_init: bool,
    /// Override the maximum number of Levenberg–Marquardt steps.
    #[arg(long)]
    pub max_iterations: Option<usize>,
}

/// Runs the command: prints `{"file", "nodes", "edges", "initial_chi2", "final_chi2", "iterations", "time_ms",
/// "termination"}` on one line; `time_ms` covers the optimization only (not parsing or writing).
pub fn run(args: &OptimizeArgs) -> Result<()> {
    let file =
        File::open(&args.input).with_context(|| format!("cannot open {}", args.input.display()))?;
    let parsed = read_pose_graph(BufReader::new(file))
        .with_context(|| format!("cannot read pose graph {}", args.input.display()))?;
    let mut graph = parsed.graph;
    let defaults = OptimizerOptions::default();
    let options = OptimizerOptions {
        rotation_first_initialization: !args.no_rotation_init,
        max_iterations: args.max_iterations.unwrap_or(defaults.max_iterations),
        ..defaults
    };
    let mut optimizer = Optimizer::new(options).context("invalid optimizer options")?;
    let start = Instant::now();
    let summary = optimizer.optimize(&mut graph);
    let time_ms = start.elapsed().as_secs_f64() * 1e3;
    if let Some(out) = &args.out {
        let file = File::create(out).with_context(|| format!("cannot create {}", out.display()))?;
        let mut writer = BufWriter::new(file);
        write_pose_graph(&graph, &mut writer)
            .with_context(|| format!("cannot write {}", out.display()))?;
        writer
            .flush()
            .with_context(|| format!("cannot write {}", out.display()))?;
    }
    let report = serde_json::json!({
        "file": args.input.display().to_string(),
        "nodes": graph.num_variables(),
        "edges": graph.num_constraints(),
        "initial_chi2": summary.initial_chi2,
        "final_chi2": summary.final_chi2,
        "iterations": summary.iterations,
        "time_ms": time_ms,
        "termination": summary.termination.to_string(),
    });
    println!("{report}");
    Ok(())
}
