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
    println!("{}", execute(args)?);
    Ok(())
}

/// Reads, optimizes and (with `--out`) writes the graph; returns the JSON report.
fn execute(args: &OptimizeArgs) -> Result<serde_json::Value> {
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
    Ok(serde_json::json!({
        "file": args.input.display().to_string(),
        "nodes": graph.num_variables(),
        "edges": graph.num_constraints(),
        "initial_chi2": summary.initial_chi2,
        "final_chi2": summary.final_chi2,
        "iterations": summary.iterations,
        "time_ms": time_ms,
        "termination": summary.termination.to_string(),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    struct TempDir(PathBuf);

    impl TempDir {
        fn new(name: &str) -> Self {
            let dir = std::env::temp_dir().join(format!("evermap-{name}-{}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            Self(dir)
        }
    }

    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn args(input: PathBuf, out: Option<PathBuf>) -> OptimizeArgs {
        OptimizeArgs {
            input,
            out,
            no_rotation_init: false,
            max_iterations: None,
        }
    }

    #[test]
    fn optimizes_a_toro_file_and_writes_g2o() {
        let dir = TempDir::new("optimize-ok");
        let input = dir.0.join("square.graph");
        // A unit square with a slightly inconsistent loop, TORO format, poorly initialised.
        std::fs::write(
            &input,
            "VERTEX2 0 0 0 0
VERTEX2 1 0.8 0.3 1.2
VERTEX2 2 1.2 1.3 3.0
VERTEX2 3 -0.2 0.9 -1.2
             EDGE2 0 1 1 0 1.5707963 10 0 10 10 0 0
EDGE2 1 2 1 0 1.5707963 10 0 10 10 0 0
             EDGE2 2 3 1 0 1.5707963 10 0 10 10 0 0
EDGE2 3 0 1.05 0 1.5707963 10 0 10 10 0 0
",
        )
        .unwrap();
        let out = dir.0.join("out.g2o");
        let report = execute(&args(input, Some(out.clone()))).unwrap();
        assert_eq!(report["nodes"], 4);
        assert_eq!(report["edges"], 4);
        let (initial, final_) = (
            report["initial_chi2"].as_f64().unwrap(),
            report["final_chi2"].as_f64().unwrap(),
        );
        assert!(final_ < 0.1 && initial > 10.0, "{report}");
        assert!(
            report["termination"]
                .as_str()
                .unwrap()
                .starts_with("converged"),
            "{report}"
        );
        let written = std::fs::read_to_string(&out).unwrap();
        assert_eq!(
            written
                .lines()
                .filter(|l| l.starts_with("EDGE_SE2"))
                .count(),
            4
        );
        // Re-optimizing the written graph starts at the optimum.
        let again = execute(&args(out, None)).unwrap();
        assert!(
            (again["initial_chi2"].as_f64().unwrap() - final_).abs() < 1e-9,
            "{again}"
        );
    }

    #[test]
    fn malformed_and_missing_files_give_clear_errors() {
        let dir = TempDir::new("optimize-bad");
        let input = dir.0.join("bad.g2o");
        std::fs::write(
            &input,
            "VERTEX_SE2 0 0 0 0
EDGE_SE2 0 1 1 0
",
        )
        .unwrap();
        let message = format!("{:#}", execute(&args(input.clone(), None)).unwrap_err());
        assert!(
            message.contains(&input.display().to_string()) && message.contains("line 2"),
            "{message}"
        );
        let missing = dir.0.join("missing.g2o");
        let message = format!("{:#}", execute(&args(missing.clone(), None)).unwrap_err());
        assert!(
            message.contains("cannot open") && message.contains(&missing.display().to_string()),
            "{message}"
        );
    }
}
