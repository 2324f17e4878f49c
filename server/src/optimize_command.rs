//! `evermap-server optimize`: optimize a g2o/TORO pose graph file and report one JSON line.

use std::fs::File;
use std::io::{BufReader, BufWriter, Write as _};
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context as _, Result};
use mapping::geometry::rigid2;
use mapping::io::g2o::{read_pose_graph, write_pose_graph};
use mapping::pose_graph::{
    Constraint, ConstraintKind, NodeId, OptimizationSummary, Optimizer, OptimizerOptions,
    PoseGraph, RobustLoss, VariableId,
};
use nalgebra::Matrix3;
use rand::{Rng as _, SeedableRng as _};
use rand_pcg::Pcg64;

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
    /// Treat every loop closure (an edge between vertices whose ids are not consecutive; consecutive ones
    /// are odometry and stay plain least squares) with dynamic covariance scaling, so that false ones
    /// are rejected. Not the default: at Φ = 1 it leaves ring (a bad start) and CSAIL, input_INTEL and
    /// M3500a (true closures above Φ at the optimum) away from their least-squares optimum, and no Φ or
    /// Φ schedule measured keeps those while rejecting 1000 random false closures (BENCHMARKS.md).
    #[arg(long)]
    pub robust: bool,
    /// Φ of that dynamic covariance scaling (unitless, on the squared Mahalanobis norm).
    #[arg(long, default_value_t = DEFAULT_LOOP_CLOSURE_PHI)]
    pub loop_closure_phi: f64,
    /// With `--robust`, stages before the last: optimize with the loop closures' DCS at each Φ in turn (each
    /// stage to convergence, from the previous one's result), then at `--loop-closure-phi`.
    #[arg(long, value_delimiter = ',')]
    pub phi_stages: Vec<f64>,
    /// With `--robust`: choose between the file's values and the rotation-first guess by their cost
    /// under DCS at this Φ (0: under the first stage's loss, as the optimizer does).
    #[arg(long, default_value_t = 0.0)]
    pub guess_phi: f64,
    /// With `--robust`: after the DCS stages, drop the loop closures whose χ² exceeds this (unitless,
    /// squared Mahalanobis norm) and optimize the rest as plain least squares, so that rejected closures
    /// keep no residual pull (DCS's weight never reaches 0) and the true ones DCS down-weighted (s above Φ)
    /// count fully again. 0: off.
    #[arg(long, default_value_t = DEFAULT_TRUNCATE_CHI2)]
    pub truncate_chi2: f64,
    /// Constraints whose robust weight falls below this are left out of the linear system until it
    /// rises above ten times this (`OptimizerOptions::prune_weight`; 0 keeps every constraint).
    #[arg(long, default_value_t = OptimizerOptions::DEFAULT.prune_weight)]
    pub prune_weight: f64,
    /// Benchmark: add this many false loop closures between random vertex pairs (random relative pose,
    /// the file's first loop closure's information), optimize the clean and the corrupted graph, and report
    /// how far the corrupted optimum lies from the clean one.
    #[arg(long, default_value_t = 0)]
    pub add_outliers: usize,
    /// Benchmark: add this many groups of 10 false loop closures, each linking 10 consecutive vertices to
    /// 10 others with one common wrong relative pose.
    #[arg(long, default_value_t = 0)]
    pub outlier_groups: usize,
    /// Seed of the false loop closures.
    #[arg(long, default_value_t = 1)]
    pub outlier_seed: u64,
}

/// Default Φ of the loop closures' dynamic covariance scaling (Agarwal et al. use 1).
pub const DEFAULT_LOOP_CLOSURE_PHI: f64 = 1.0;

/// Default χ² above which `--robust` drops a loop closure after DCS (5σ; the benchmark graphs' true
/// closures stay below it at their optimum — CSAIL and M3500a keep their best χ² — while false ones sit
/// in the thousands).
pub const DEFAULT_TRUNCATE_CHI2: f64 = 25.0;

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
    let loss = if args.robust {
        let loss = RobustLoss::Dcs {
            phi: args.loop_closure_phi,
        };
        anyhow::ensure!(
            loss.is_valid(),
            "--loop-closure-phi must be a positive number"
        );
        loss
    } else {
        RobustLoss::Trivial
    };
    let mut graph = with_loop_closure_loss(&parsed.graph, loss)?;
    let defaults = OptimizerOptions::default();
    let options = OptimizerOptions {
        rotation_first_initialization: !args.no_rotation_init,
        max_iterations: args.max_iterations.unwrap_or(defaults.max_iterations),
        prune_weight: args.prune_weight,
        ..defaults
    };
    let stages: Vec<RobustLoss> = match loss {
        RobustLoss::Dcs { phi } => args
            .phi_stages
            .iter()
            .chain(std::iter::once(&phi))
            .map(|&phi| RobustLoss::Dcs { phi })
            .collect(),
        _ => vec![loss],
    };
    anyhow::ensure!(
        stages.iter().all(RobustLoss::is_valid),
        "--phi-stages must be positive numbers"
    );
    anyhow::ensure!(
        [args.guess_phi, args.truncate_chi2]
            .iter()
            .all(|v| v.is_finite() && *v >= 0.0),
        "--guess-phi and --truncate-chi2 must be finite and non-negative"
    );
    let mut optimizer = Optimizer::new(options.clone()).context("invalid optimizer options")?;
    let benchmark = if args.add_outliers > 0 || args.outlier_groups > 0 {
        // The clean optimum first, on a copy; the file's graph is then corrupted and optimized below.
        let mut clean = graph.clone();
        let start = Instant::now();
        let mut clean_optimizer =
            Optimizer::new(options.clone()).context("invalid optimizer options")?;
        optimize_in_stages(&mut clean_optimizer, &mut clean, &stages, args)?;
        let clean_time_ms = start.elapsed().as_secs_f64() * 1e3;
        let added = add_false_loop_closures(
            &mut graph,
            args.add_outliers,
            args.outlier_groups,
            args.outlier_seed,
            loss,
        )?;
        Some((clean, clean_time_ms, added))
    } else {
        None
    };
    let start = Instant::now();
    let summary = optimize_in_stages(&mut optimizer, &mut graph, &stages, args)?;
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
    let mut report = serde_json::json!({
        "file": args.input.display().to_string(),
        "nodes": graph.num_variables(),
        "edges": graph.num_constraints(),
        "loop_closure_loss": format!("{loss:?}"),
        "initial_chi2": summary.initial_chi2,
        "final_chi2": summary.final_chi2,
        "iterations": summary.iterations,
        "pruned_constraints": summary.pruned_constraints,
        "time_ms": time_ms,
        "termination": summary.termination.to_string(),
    });
    if let Some((clean, clean_time_ms, added)) = benchmark {
        let (outliers_rejected, inliers_rejected) = rejected(&graph, &added);
        report["clean_time_ms"] = serde_json::json!(clean_time_ms);
        report["clean_chi2"] = serde_json::json!(clean.chi2());
        report["outliers_added"] = serde_json::json!(added.len());
        report["outliers_rejected"] = serde_json::json!(outliers_rejected);
        report["inliers_rejected"] = serde_json::json!(inliers_rejected);
        report["rms_vs_clean_m"] = serde_json::json!(rms_position_difference(&clean, &graph));
        report["time_vs_clean"] = serde_json::json!(time_ms / clean_time_ms.max(1e-9));
    }
    Ok(report)
}

/// Optimizes `graph` once per loop-closure loss in `stages` (each from the previous stage's result; the
/// rotation-first guess only in the first), leaving the last stage's losses on the graph. The summary
/// is the last stage's, with the first stage's initial χ²/cost and the iterations of all stages.
fn optimize_in_stages(
    optimizer: &mut Optimizer,
    graph: &mut PoseGraph,
    stages: &[RobustLoss],
    args: &OptimizeArgs,
) -> Result<OptimizationSummary> {
    let mut total: Option<OptimizationSummary> = None;
    let mut later: Option<Optimizer> = None;
    let later_options = OptimizerOptions {
        rotation_first_initialization: false,
        ..optimizer.options().clone()
    };
    let mut skip_guess = false;
    if args.robust && args.guess_phi > 0.0 && optimizer.options().rotation_first_initialization {
        *graph = with_loop_closure_loss(
            graph,
            RobustLoss::Dcs {
                phi: args.guess_phi,
            },
        )?;
        let mut chooser = Optimizer::new(OptimizerOptions {
            max_iterations: 0,
            ..optimizer.options().clone()
        })?;
        chooser.optimize(graph);
        skip_guess = true;
    }
    for (k, &loss) in stages.iter().enumerate() {
        if stages.len() > 1 {
            *graph = with_loop_closure_loss(graph, loss)?;
        }
        let summary = if k == 0 && !skip_guess {
            optimizer.optimize(graph)
        } else {
            let later = match later.as_mut() {
                Some(o) => o,
                None => later.insert(
                    Optimizer::new(later_options.clone()).context("invalid optimizer options")?,
                ),
            };
            later.optimize(graph)
        };
        total = Some(match total {
            None => summary,
            Some(t) => OptimizationSummary {
                initial_chi2: t.initial_chi2,
                initial_cost: t.initial_cost,
                iterations: t.iterations + summary.iterations,
                accepted_steps: t.accepted_steps + summary.accepted_steps,
                ..summary
            },
        });
    }
    if args.robust && args.truncate_chi2 > 0.0 {
        let mut inliers = graph.with_constraints(|c| {
            let keep = !is_loop_closure(c)
                || match (graph.pose(c.from), graph.pose(c.to)) {
                    (Some(a), Some(b)) => c.chi2(&a, &b) <= args.truncate_chi2,
                    _ => false,
                };
            keep.then(|| Constraint {
                loss: RobustLoss::Trivial,
                ..c.clone()
            })
        })?;
        let summary = Optimizer::new(later_options)?.optimize(&mut inliers);
        for (id, pose, _) in inliers.variables() {
            graph.set_pose(id, pose)?;
        }
        if let Some(t) = total.as_mut() {
            t.iterations += summary.iterations;
            t.accepted_steps += summary.accepted_steps;
            t.final_chi2 = graph.chi2();
            t.final_cost = graph.cost();
        }
    }
    total.context("no optimization stage")
}

/// Whether an edge of a g2o/TORO graph is a loop closure: its vertex ids are not consecutive.
fn is_loop_closure(constraint: &Constraint) -> bool {
    match (constraint.from, constraint.to) {
        (VariableId::Node(a), VariableId::Node(b)) => a.index.abs_diff(b.index) != 1,
        _ => true,
    }
}

/// A copy of `graph` whose loop closures (see [`is_loop_closure`]) carry `loss`; odometry edges stay plain
/// least squares.
fn with_loop_closure_loss(graph: &PoseGraph, loss: RobustLoss) -> Result<PoseGraph> {
    Ok(graph.with_constraints(|c| {
        Some(Constraint {
            loss: if is_loop_closure(c) {
                loss
            } else {
                RobustLoss::Trivial
            },
            ..c.clone()
        })
    })?)
}

/// Adds `random` false loop closures between random vertex pairs and `groups` groups of 10 (10
/// consecutive vertices linked to 10 others by one common wrong relative pose): translations uniform
/// within ±10 m, rotations uniform; information copied from the graph's first loop closure. Returns the
/// added constraints.
fn add_false_loop_closures(
    graph: &mut PoseGraph,
    random: usize,
    groups: usize,
    seed: u64,
    loss: RobustLoss,
) -> Result<Vec<Constraint>> {
    let nodes: Vec<u32> = graph
        .variables()
        .filter_map(|(id, _, _)| match id {
            VariableId::Node(n) => Some(n.index),
            VariableId::Submap(_) => None,
        })
        .collect();
    let max = nodes
        .iter()
        .copied()
        .max()
        .context("the graph has no vertices")?;
    anyhow::ensure!(max >= 20, "too few vertices for false loop closures");
    let information = graph
        .constraints()
        .map(|(_, c)| c)
        .find(|c| is_loop_closure(c))
        .map_or_else(Matrix3::identity, |c| c.information);
    let mut rng = Pcg64::seed_from_u64(seed);
    let node = |index: u32| {
        VariableId::Node(NodeId {
            trajectory: 0,
            index,
        })
    };
    let random_pose = |rng: &mut Pcg64| {
        rigid2(
            rng.random_range(-10.0..10.0),
            rng.random_range(-10.0..10.0),
            rng.random_range(-std::f64::consts::PI..std::f64::consts::PI),
        )
    };
    let mut pairs = Vec::new();
    for _ in 0..random {
        let (i, j) = loop {
            let (i, j) = (rng.random_range(0..=max), rng.random_range(0..=max));
            if i.abs_diff(j) > 1 {
                break (i, j);
            }
        };
        pairs.push((i, j, random_pose(&mut rng)));
    }
    for _ in 0..groups {
        let (i, j) = loop {
            let (i, j) = (
                rng.random_range(0..=max - 10),
                rng.random_range(0..=max - 10),
            );
            if i.abs_diff(j) > 10 {
                break (i, j);
            }
        };
        let pose = random_pose(&mut rng);
        pairs.extend((0..10).map(|k| (i + k, j + k, pose)));
    }
    let mut added = Vec::with_capacity(pairs.len());
    for (i, j, pose) in pairs {
        let constraint = Constraint {
            kind: ConstraintKind::NodeToNode,
            from: node(i),
            to: node(j),
            from_from_to: pose,
            information,
            loss,
        };
        graph.add_constraint(constraint.clone())?;
        added.push(constraint);
    }
    Ok(added)
}

/// How many of `added` (false closures) and of the other loop closures end with an IRLS weight below 0.5.
fn rejected(graph: &PoseGraph, added: &[Constraint]) -> (usize, usize) {
    let weight = |c: &Constraint| -> Option<f64> {
        let (a, b) = (graph.pose(c.from)?, graph.pose(c.to)?);
        Some(c.loss.weight(c.chi2(&a, &b)))
    };
    let outliers = added
        .iter()
        .filter(|c| weight(c).is_some_and(|w| w < 0.5))
        .count();
    let all_rejected = graph
        .constraints()
        .map(|(_, c)| c)
        .filter(|c| is_loop_closure(c) && weight(c).is_some_and(|w| w < 0.5))
        .count();
    (outliers, all_rejected.saturating_sub(outliers))
}

/// RMS (m) of the difference of vertex positions between two graphs over the same vertices.
fn rms_position_difference(a: &PoseGraph, b: &PoseGraph) -> f64 {
    let mut sum = 0.0;
    let mut count = 0usize;
    for (id, pose, _) in a.variables() {
        if let Some(other) = b.pose(id) {
            sum += (pose.translation.vector - other.translation.vector).norm_squared();
            count += 1;
        }
    }
    if count == 0 {
        0.0
    } else {
        (sum / count as f64).sqrt()
    }
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
            loop_closure_phi: DEFAULT_LOOP_CLOSURE_PHI,
            robust: false,
            prune_weight: OptimizerOptions::DEFAULT.prune_weight,
            phi_stages: Vec::new(),
            guess_phi: 0.0,
            truncate_chi2: DEFAULT_TRUNCATE_CHI2,
            add_outliers: 0,
            outlier_groups: 0,
            outlier_seed: 1,
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
    fn robust_loop_closures_ignore_a_hundred_false_ones() {
        // `../shared/datasets` beside the repository root, found by walking up from this crate.
        let manifest = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
        let input = manifest
            .ancestors()
            .map(|dir| dir.join("shared/datasets/posegraphs/intel_sesync1728.g2o"))
            .find(|path| path.is_file())
            .expect("../shared/datasets beside the repository");
        let report = execute(&OptimizeArgs {
            robust: true,
            add_outliers: 90,
            outlier_groups: 1,
            outlier_seed: 7,
            ..args(input.clone(), None)
        })
        .unwrap();
        // DCS alone: 0.0034 m (the false closures' residual pull); truncating them afterwards leaves the
        // clean optimum over the true closures.
        let rms = report["rms_vs_clean_m"].as_f64().unwrap();
        assert!(rms < 1e-3, "{report}");
        assert_eq!(report["outliers_rejected"], 100, "{report}");
        assert_eq!(report["inliers_rejected"], 0, "{report}");
        // Plain least squares is dragged away by the same closures.
        let plain = execute(&OptimizeArgs {
            add_outliers: 90,
            outlier_groups: 1,
            outlier_seed: 7,
            ..args(input, None)
        })
        .unwrap();
        assert!(plain["rms_vs_clean_m"].as_f64().unwrap() > 1.0, "{plain}");
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
