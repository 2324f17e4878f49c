//! Chow–Liu sparsification against deletion on real pose graphs: on the first 600 nodes of Intel and
//! M3500 (`../shared/datasets/posegraphs`), optimized, runs of consecutive nodes (a "submap" and its
//! nodes) are eliminated one at a time from the optimum, and all of them in sequence. Prints, per run:
//! blanket size, marginal rank, the blanket-local KLD of the tree (what Chow–Liu minimises) for both
//! edge models, the whole-graph KLD for both models and for deletion, and the largest pose shift after
//! re-optimizing against the full optimum. Not a test (BENCHMARKS.md, "Chow-Liu sparsification vs
//! deletion"): run it with
//!
//!     cargo bench --workspace --bench sparsification
//!
//! (a plain `main`, `harness = false`).

use std::collections::BTreeSet;
use std::fs::File;
use std::io::BufReader;

use mapping::io::g2o::read_pose_graph;
use mapping::pose_graph::{
    Constraint, ConstraintId, NodeId, Optimizer, OptimizerOptions, PoseGraph, VariableId,
};
use mapping::sparsification::{
    EdgeModel, ParallelMerge, SparsificationOptions, SparsificationResult, apply, delete,
    kl_divergence, sparsify,
};

type BoxError = Box<dyn std::error::Error>;

fn node(index: u32) -> VariableId {
    VariableId::Node(NodeId {
        trajectory: 0,
        index,
    })
}

fn options(edge_model: EdgeModel) -> SparsificationOptions {
    SparsificationOptions {
        edge_model,
        ..SparsificationOptions::DEFAULT
    }
}

fn dataset(name: &str) -> Result<PoseGraph, BoxError> {
    let path = test_support::datasets_dir().join("posegraphs").join(name);
    let file = File::open(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(read_pose_graph(BufReader::new(file))?.graph)
}

/// The subgraph induced by nodes `0..n`, node 0 fixed, optimized.
fn optimized_prefix(graph: &PoseGraph, n: u32) -> Result<PoseGraph, BoxError> {
    let keep = |id: VariableId| matches!(id, VariableId::Node(NodeId { index, .. }) if index < n);
    let mut sub = PoseGraph::new();
    for (id, pose, _) in graph.variables().filter(|(id, _, _)| keep(*id)) {
        sub.add_variable(id, pose)?;
    }
    for (_, c) in graph
        .constraints()
        .filter(|(_, c)| keep(c.from) && keep(c.to))
    {
        sub.add_constraint(c.clone())?;
    }
    sub.set_fixed(node(0), true)?;
    let mut optimizer = Optimizer::new(OptimizerOptions {
        rotation_first_initialization: true,
        ..OptimizerOptions::DEFAULT
    })?;
    let summary = optimizer.optimize(&mut sub);
    if !summary.termination.is_converged() {
        return Err(format!("the prefix did not converge: {summary:?}").into());
    }
    Ok(sub)
}

fn main() -> Result<(), BoxError> {
    let ratio = |a: f64, b: f64| {
        if b.is_finite() {
            format!("{:5.3}", a / b)
        } else {
            "  n/a".to_owned()
        }
    };
    for (name, prefix) in [("intel_sesync1728.g2o", 600u32), ("M3500.g2o", 600)] {
        let full = dataset(name)?;
        let graph = optimized_prefix(&full, prefix)?;
        println!(
            "{name}: first {prefix} nodes, {} constraints, chi2 {:.3}",
            graph.num_constraints(),
            graph.chi2()
        );
        for run_length in [10u32, 15, 20] {
            println!(
                "run length {run_length}\nrun        |B| rank/dim  local(rel) local(cond) | KLD(rel) KLD(cond) KLD(delete) rel/del | shift rel (m, rad)  shift cond        shift delete     | ms"
            );
            let starts: Vec<u32> = (1..=6).map(|k| k * prefix / 7).collect();
            let o = SparsificationOptions::DEFAULT;
            let mut sequential = graph.clone();
            let mut all_eliminated = Vec::new();
            let mut ratios = Vec::new();
            for &start in &starts {
                let eliminate: Vec<VariableId> = (start..start + run_length).map(node).collect();
                let timer = std::time::Instant::now();
                let rel = sparsify(&graph, &eliminate, &o)?;
                let ms = timer.elapsed().as_secs_f64() * 1e3;
                let cond = sparsify(&graph, &eliminate, &options(EdgeModel::Conditional))?;
                let kld_rel = kl_divergence(&graph, &eliminate, &rel.new_constraints, &o)?;
                let kld_cond = kl_divergence(&graph, &eliminate, &cond.new_constraints, &o)?;
                let kld_delete = kl_divergence(&graph, &eliminate, &[], &o)?;
                if kld_delete.is_finite() {
                    ratios.push(kld_rel / kld_delete);
                }
                let shift =
                    |result: Option<&SparsificationResult>| -> Result<(f64, f64), BoxError> {
                        let mut g = graph.clone();
                        match result {
                            Some(r) => {
                                apply(&mut g, r, ParallelMerge::EveryPlain)?;
                            }
                            None => {
                                delete(&mut g, &eliminate)?;
                            }
                        }
                        Optimizer::new(OptimizerOptions::default())?.optimize(&mut g);
                        Ok(graph.largest_shift(&g))
                    };
                let (s_rel, s_cond, s_del) =
                    (shift(Some(&rel))?, shift(Some(&cond))?, shift(None)?);
                println!(
                    "{start:4}..{:<4} {:3} {:3}/{:<3}  {:9.4}  {:9.4}  | {kld_rel:8.4} {kld_cond:8.4} {kld_delete:11.3}   {} | ({:.1e}, {:.1e})  ({:.1e}, {:.1e})  ({:.1e}, {:.1e}) | {ms:.1}",
                    start + run_length,
                    rel.blanket.len(),
                    rel.diagnostics.marginal_rank,
                    rel.diagnostics.marginal_dimension,
                    rel.diagnostics.kl_divergence,
                    cond.diagnostics.kl_divergence,
                    ratio(kld_rel, kld_delete),
                    s_rel.0,
                    s_rel.1,
                    s_cond.0,
                    s_cond.1,
                    s_del.0,
                    s_del.1,
                );
                let seq = sparsify(&sequential, &eliminate, &o)?;
                apply(&mut sequential, &seq, ParallelMerge::EveryPlain)?;
                all_eliminated.extend(eliminate);
            }
            ratios.sort_by(f64::total_cmp);
            println!(
                "KLD(rel)/KLD(delete) over runs with finite KLD(delete): {:?}",
                ratios
                    .iter()
                    .map(|r| (r * 1000.0).round() / 1000.0)
                    .collect::<Vec<_>>()
            );
            // All runs eliminated one after the other: the trees (some re-sparsified) against the
            // exact marginal of all of them.
            let original: BTreeSet<ConstraintId> = graph.constraints().map(|(id, _)| id).collect();
            let added: Vec<Constraint> = sequential
                .constraints()
                .filter(|(id, _)| !original.contains(id))
                .map(|(_, c)| c.clone())
                .collect();
            let kld_seq = kl_divergence(&graph, &all_eliminated, &added, &o)?;
            let kld_del = kl_divergence(&graph, &all_eliminated, &[], &o)?;
            let mut deleted = graph.clone();
            delete(&mut deleted, &all_eliminated)?;
            let mut optimizer = Optimizer::new(OptimizerOptions::default())?;
            optimizer.optimize(&mut sequential);
            optimizer.optimize(&mut deleted);
            let (s_seq, s_del) = (
                graph.largest_shift(&sequential),
                graph.largest_shift(&deleted),
            );
            println!(
                "all {} runs in sequence: KLD(rel) {kld_seq:.4}  KLD(delete) {kld_del:.3}  shift rel ({:.1e}, {:.1e})  shift delete ({:.1e}, {:.1e})",
                starts.len(),
                s_seq.0,
                s_seq.1,
                s_del.0,
                s_del.1
            );
        }
    }
    Ok(())
}
