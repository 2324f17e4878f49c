//! Tests of the pose graph and optimizer together (the per-file pieces test themselves).

use std::fs::File;
use std::io::BufReader;

use approx::assert_relative_eq;
use nalgebra::Matrix3;

use super::*;
use crate::geometry::{Rigid2, Rigid2Ext as _, rigid2};
use crate::io::g2o::read_pose_graph;

fn node(index: u32) -> VariableId {
    VariableId::Node(NodeId {
        trajectory: 0,
        index,
    })
}

fn dataset(name: &str) -> PoseGraph {
    let path = test_support::datasets_dir().join("posegraphs").join(name);
    let file = File::open(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    read_pose_graph(BufReader::new(file)).unwrap().graph
}

fn constraint(from: u32, to: u32, z: Rigid2, loss: RobustLoss) -> Constraint {
    Constraint {
        kind: if to == from + 1 {
            ConstraintKind::Odometry
        } else {
            ConstraintKind::NodeToNode
        },
        from: node(from),
        to: node(to),
        from_from_to: z,
        information: Matrix3::from_diagonal(&nalgebra::Vector3::new(100.0, 100.0, 400.0)),
        loss,
    }
}

/// A square loop of `n` nodes with exact odometry and loop closures, initial poses perturbed.
fn square_world(n: u32, loss: RobustLoss) -> (PoseGraph, Vec<Rigid2>) {
    let truth: Vec<Rigid2> = (0..n)
        .map(|k| {
            let t = f64::from(k) / f64::from(n) * std::f64::consts::TAU;
            rigid2(
                5.0 * t.cos(),
                5.0 * t.sin(),
                t + std::f64::consts::FRAC_PI_2,
            )
        })
        .collect();
    let mut graph = PoseGraph::new();
    for (k, pose) in truth.iter().enumerate() {
        let wobble = (k as f64 * 1.7).sin();
        let initial = pose * rigid2(0.3 * wobble, -0.2 * wobble, 0.1 * wobble);
        graph
            .add_variable(node(k as u32), if k == 0 { *pose } else { initial })
            .unwrap();
    }
    for k in 0..n {
        let (i, j) = (k, (k + 1) % n);
        let (a, b) = (i.min(j), i.max(j));
        let z = truth[a as usize].inverse() * truth[b as usize];
        graph.add_constraint(constraint(a, b, z, loss)).unwrap();
    }
    for k in 0..n / 2 {
        let (a, b) = (k, k + n / 2);
        graph
            .add_constraint(constraint(
                a,
                b,
                truth[a as usize].inverse() * truth[b as usize],
                loss,
            ))
            .unwrap();
    }
    (graph, truth)
}

fn max_pose_error(graph: &PoseGraph, truth: &[Rigid2]) -> f64 {
    truth
        .iter()
        .enumerate()
        .map(|(k, t)| {
            let p = graph.pose(node(k as u32)).unwrap();
            (p.inverse() * t).translation.vector.norm() + (p.inverse() * t).theta().abs()
        })
        .fold(0.0, f64::max)
}

fn max_pose_error_except(graph: &PoseGraph, truth: &[Rigid2], skip: u32) -> f64 {
    truth
        .iter()
        .enumerate()
        .filter(|(k, _)| *k as u32 != skip)
        .map(|(k, t)| {
            let d = graph.pose(node(k as u32)).unwrap().inverse() * t;
            d.translation.vector.norm() + d.theta().abs()
        })
        .fold(0.0, f64::max)
}

fn optimizer() -> Optimizer {
    Optimizer::new(OptimizerOptions::default()).unwrap()
}

#[test]
fn recovers_ground_truth_of_ring_exactly() {
    let mut graph = dataset("ring_groundTruth.g2o");
    let before: Vec<_> = graph.variables().collect();
    let summary = optimizer().optimize(&mut graph);
    assert!(summary.termination.is_converged(), "{summary:?}");
    assert!(
        summary.initial_chi2 < 1e-6 && summary.final_chi2 <= summary.initial_chi2,
        "{summary:?}"
    );
    // The file prints 6 decimals (θ = 0.785398 for π/4): over the ring's ~100 m lever arm the optimum sits
    // ~10 µm from the printed poses.
    for ((_, a, _), (_, b, _)) in before.iter().zip(graph.variables()) {
        let d = a.inverse() * b;
        assert!(
            d.translation.vector.norm() < 1e-4 && d.theta().abs() < 1e-6,
            "{a:?} moved to {b:?}"
        );
    }
}

#[test]
fn reaches_best_known_chi2_on_ring() {
    let mut graph = dataset("ring.g2o");
    let summary = optimizer().optimize(&mut graph);
    assert!(summary.termination.is_converged(), "{summary:?}");
    assert!(
        summary.initial_chi2 > 1000.0,
        "ring starts far from the optimum: {summary:?}"
    );
    let best = 11.1631;
    assert!(
        (summary.final_chi2 - best).abs() <= 1e-4 * best,
        "{summary:?}"
    );
    assert_relative_eq!(graph.chi2(), summary.final_chi2, max_relative = 1e-12);
}

#[test]
fn converges_on_a_synthetic_loop() {
    let (mut graph, truth) = square_world(24, RobustLoss::Trivial);
    assert!(max_pose_error(&graph, &truth) > 0.1);
    let summary = optimizer().optimize(&mut graph);
    assert!(summary.termination.is_converged(), "{summary:?}");
    assert!(summary.final_chi2 < 1e-12, "{summary:?}");
    assert!(max_pose_error(&graph, &truth) < 1e-6);
}

#[test]
fn the_summary_says_what_a_step_cost() {
    // 24 poses, the first fixed (the default gauge): 23 move. L holds at least the pattern of H (each
    // free pose's 3×3 diagonal block, 6 nonzeros of it in one triangle, and a 3×3 block for each of the
    // 33 constraints between free poses) and at most a full square (supernodes store dense blocks).
    let (mut graph, _) = square_world(24, RobustLoss::Trivial);
    let summary = optimizer().optimize(&mut graph);
    assert_eq!(summary.free_variables, 23, "{summary:?}");
    let (n, pattern) = (3 * 23, 6 * 23 + 9 * 33);
    assert!(
        summary.factor_nonzeros >= pattern && summary.factor_nonzeros <= n * n,
        "{summary:?}"
    );
    // Nothing to move: nothing factorized, nothing counted.
    let mut single = PoseGraph::new();
    single.add_variable(node(0), Rigid2::identity()).unwrap();
    let summary = optimizer().optimize(&mut single);
    assert_eq!((summary.free_variables, summary.factor_nonzeros), (0, 0));
}

#[test]
fn robust_loss_down_weights_an_injected_outlier() {
    let run = |loss| {
        let (mut graph, truth) = square_world(24, loss);
        // A wrong loop closure: 3 m and 1 rad off.
        let z = truth[2].inverse() * truth[15] * rigid2(3.0, 0.0, 1.0);
        let outlier = graph.add_constraint(constraint(2, 15, z, loss)).unwrap();
        let summary = optimizer().optimize(&mut graph);
        assert!(summary.final_cost < summary.initial_cost, "{summary:?}");
        let c = graph.constraint(outlier).unwrap();
        let s = c.chi2(&graph.pose(c.from).unwrap(), &graph.pose(c.to).unwrap());
        (max_pose_error(&graph, &truth), c.loss.weight(s))
    };
    let (plain_error, _) = run(RobustLoss::Trivial);
    let (cauchy_error, cauchy_weight) = run(RobustLoss::Cauchy { scale: 1.0 });
    let (huber_error, huber_weight) = run(RobustLoss::Huber { delta: 1.0 });
    assert!(
        plain_error > 0.2,
        "the outlier must distort least squares: {plain_error}"
    );
    assert!(
        cauchy_error < 0.01 * plain_error,
        "{cauchy_error} vs {plain_error}"
    );
    assert!(
        huber_error < 0.5 * plain_error,
        "{huber_error} vs {plain_error}"
    );
    assert!(
        cauchy_weight < 1e-3 && huber_weight < 0.1,
        "{cauchy_weight} {huber_weight}"
    );
}

#[test]
fn fixed_variables_stay_put_and_smallest_id_is_the_default_gauge() {
    let (mut graph, _) = square_world(12, RobustLoss::Trivial);
    let pinned = graph.pose(node(5)).unwrap();
    let first = graph.pose(node(0)).unwrap();
    graph.set_fixed(node(5), true).unwrap();
    optimizer().optimize(&mut graph);
    assert_eq!(graph.pose(node(5)).unwrap(), pinned);
    assert_ne!(
        graph.pose(node(0)).unwrap(),
        first,
        "node 0 is free once another node is fixed"
    );

    let (mut graph, _) = square_world(12, RobustLoss::Trivial);
    let first = graph.pose(node(0)).unwrap();
    let other = graph.pose(node(3)).unwrap();
    optimizer().optimize(&mut graph);
    assert_eq!(graph.pose(node(0)).unwrap(), first);
    assert_ne!(graph.pose(node(3)).unwrap(), other);
    assert_eq!(
        graph.is_fixed(node(0)),
        Some(false),
        "the implicit gauge does not edit the graph"
    );
}

#[test]
fn remove_variable_keeps_the_graph_consistent() {
    let (mut graph, truth) = square_world(12, RobustLoss::Trivial);
    let touching = graph.constraints_of(node(4)).to_vec();
    assert_eq!(touching.len(), 3);
    let constraints_before = graph.num_constraints();
    let removed = graph.remove_variable(node(4)).unwrap();
    assert_eq!(
        removed.iter().map(|(id, _)| *id).collect::<Vec<_>>(),
        touching
    );
    assert_eq!(graph.num_constraints(), constraints_before - 3);
    assert!(!graph.contains_variable(node(4)));
    for (id, c) in graph.constraints() {
        assert!(c.from != node(4) && c.to != node(4));
        assert!(
            graph.constraints_of(c.from).contains(&id) && graph.constraints_of(c.to).contains(&id)
        );
    }
    for (id, _, _) in graph.variables() {
        for c in graph.constraints_of(id) {
            assert!(
                graph.constraint(*c).is_some(),
                "dangling constraint {c:?} on {id:?}"
            );
        }
    }
    assert!(graph.constraints_of(node(4)).is_empty());
    assert_eq!(
        graph.remove_variable(node(4)),
        Err(PoseGraphError::UnknownVariable(node(4)))
    );
    let summary = optimizer().optimize(&mut graph);
    assert!(
        summary.termination.is_converged() && summary.final_chi2 < 1e-10,
        "{summary:?}"
    );
    assert!(max_pose_error_except(&graph, &truth, 4) < 1e-6);
}

#[test]
fn edits_are_validated() {
    let mut graph = PoseGraph::new();
    graph.add_variable(node(0), Rigid2::identity()).unwrap();
    graph.add_variable(node(1), Rigid2::identity()).unwrap();
    assert_eq!(
        graph.add_variable(node(1), Rigid2::identity()),
        Err(PoseGraphError::DuplicateVariable(node(1)))
    );
    let good = constraint(0, 1, rigid2(1.0, 0.0, 0.0), RobustLoss::Trivial);
    assert_eq!(
        graph.add_constraint(Constraint {
            to: node(0),
            ..good.clone()
        }),
        Err(PoseGraphError::SelfLoop(node(0)))
    );
    assert_eq!(
        graph.add_constraint(Constraint {
            to: node(7),
            ..good.clone()
        }),
        Err(PoseGraphError::UnknownVariable(node(7)))
    );
    let mut asymmetric = good.clone();
    asymmetric.information[(0, 1)] = 1.0;
    assert_eq!(
        graph.add_constraint(asymmetric),
        Err(PoseGraphError::InvalidInformation)
    );
    let bad_loss = Constraint {
        loss: RobustLoss::Huber { delta: -1.0 },
        ..good.clone()
    };
    assert_eq!(
        graph.add_constraint(bad_loss),
        Err(PoseGraphError::InvalidLoss)
    );
    let id = graph.add_constraint(good.clone()).unwrap();
    let mut bad_information = good.information;
    bad_information[(2, 2)] = f64::NAN;
    assert_eq!(
        graph.set_information(id, bad_information),
        Err(PoseGraphError::NonFinite("information"))
    );
    let looser = good.information * 0.25;
    assert_eq!(graph.set_information(id, looser), Ok(()));
    assert_eq!(graph.constraint(id).map(|c| c.information), Some(looser));
    assert_eq!(graph.constraints_of(node(0)), [id], "same id, same place");
    graph.set_information(id, good.information).unwrap();
    assert_eq!(graph.remove_constraint(id), Ok(good));
    assert_eq!(
        graph.set_information(id, looser),
        Err(PoseGraphError::UnknownConstraint(id))
    );
    assert_eq!(
        graph.remove_constraint(id),
        Err(PoseGraphError::UnknownConstraint(id))
    );
    assert!(graph.constraints_of(node(0)).is_empty());
}

#[test]
fn symbolic_factorization_is_reused_while_the_structure_is_unchanged() {
    let (mut graph, _) = square_world(12, RobustLoss::Trivial);
    let mut optimizer = optimizer();
    optimizer.optimize(&mut graph);
    assert_eq!(optimizer.symbolic_factorizations(), 1);
    graph.set_pose(node(3), rigid2(1.0, 2.0, 0.3)).unwrap();
    let summary = optimizer.optimize(&mut graph);
    assert!(summary.final_chi2 < 1e-10, "{summary:?}");
    assert_eq!(optimizer.symbolic_factorizations(), 1);
    // A second constraint between already-joined variables keeps the pattern.
    graph
        .add_constraint(constraint(
            0,
            1,
            graph.pose(node(0)).unwrap().inverse() * graph.pose(node(1)).unwrap(),
            RobustLoss::Trivial,
        ))
        .unwrap();
    optimizer.optimize(&mut graph);
    assert_eq!(optimizer.symbolic_factorizations(), 1);
    graph
        .add_constraint(constraint(
            1,
            4,
            graph.pose(node(1)).unwrap().inverse() * graph.pose(node(4)).unwrap(),
            RobustLoss::Trivial,
        ))
        .unwrap();
    optimizer.optimize(&mut graph);
    assert_eq!(optimizer.symbolic_factorizations(), 2);
}

#[test]
fn options_are_validated() {
    assert_eq!(OptimizerOptions::default().validate(), Ok(()));
    let bad = OptimizerOptions {
        function_tolerance: -1.0,
        ..OptimizerOptions::default()
    };
    assert!(matches!(
        bad.validate(),
        Err(OptimizerOptionsError::Negative {
            field: "function_tolerance",
            ..
        })
    ));
    let bad = OptimizerOptions {
        initial_lambda: 0.0,
        ..OptimizerOptions::default()
    };
    assert_eq!(bad.validate(), Err(OptimizerOptionsError::Lambda));
    assert!(
        Optimizer::new(OptimizerOptions {
            min_diagonal: f64::NAN,
            ..OptimizerOptions::default()
        })
        .is_err()
    );
}

#[test]
fn degenerate_graphs_do_not_panic() {
    let mut empty = PoseGraph::new();
    let summary = optimizer().optimize(&mut empty);
    assert!(summary.termination.is_converged() && summary.iterations == 0);
    let mut lonely = PoseGraph::new();
    lonely.add_variable(node(0), rigid2(1.0, 2.0, 3.0)).unwrap();
    lonely.add_variable(node(9), rigid2(4.0, 5.0, 6.0)).unwrap();
    let summary = optimizer().optimize(&mut lonely);
    assert!(summary.termination.is_converged(), "{summary:?}");
    assert_eq!(lonely.pose(node(9)), Some(rigid2(4.0, 5.0, 6.0)));
}

#[test]
fn rotation_first_initialization_solves_exact_graphs_from_scratch() {
    let (mut graph, truth) = square_world(24, RobustLoss::Trivial);
    let ids: Vec<VariableId> = graph.variables().map(|(id, _, _)| id).skip(1).collect();
    for id in ids {
        graph.set_pose(id, Rigid2::identity()).unwrap();
    }
    let options = OptimizerOptions {
        rotation_first_initialization: true,
        ..OptimizerOptions::default()
    };
    let summary = Optimizer::new(options).unwrap().optimize(&mut graph);
    assert!(summary.termination.is_converged(), "{summary:?}");
    // Noise-free measurements: the two linear solves land on the optimum, leaving LM nothing to do.
    assert!(summary.iterations <= 2, "{summary:?}");
    assert!(max_pose_error(&graph, &truth) < 1e-6);
}

#[test]
fn rotation_first_initialization_is_ignored_when_worse_than_the_current_estimate() {
    let (mut graph, truth) = square_world(24, RobustLoss::Trivial);
    for (k, t) in truth.iter().enumerate() {
        graph.set_pose(node(k as u32), *t).unwrap();
    }
    let options = OptimizerOptions {
        rotation_first_initialization: true,
        ..OptimizerOptions::default()
    };
    let summary = Optimizer::new(options).unwrap().optimize(&mut graph);
    assert!(
        summary.initial_chi2 < 1e-20 && summary.final_chi2 < 1e-20,
        "{summary:?}"
    );
}

#[test]
fn reaches_best_known_chi2_on_csail_from_the_odometry_chain() {
    let graph = dataset("CSAIL.g2o");
    for rotation_first_initialization in [false, true] {
        let mut graph = graph.clone();
        let options = OptimizerOptions {
            rotation_first_initialization,
            ..OptimizerOptions::default()
        };
        let summary = Optimizer::new(options).unwrap().optimize(&mut graph);
        let best = 40.5551;
        assert!(summary.termination.is_converged(), "{summary:?}");
        assert!(
            (summary.final_chi2 - best).abs() <= 1e-4 * best,
            "{summary:?}"
        );
    }
}

#[test]
fn disconnected_components_without_an_anchor_still_converge() {
    // Two separate squares; only the first contains the implicit gauge (node 0).
    let (mut graph, _) = square_world(8, RobustLoss::Trivial);
    let offset = 100;
    let (other, _) = square_world(8, RobustLoss::Trivial);
    for (id, pose, _) in other.variables() {
        let VariableId::Node(n) = id else {
            unreachable!()
        };
        graph
            .add_variable(node(n.index + offset), rigid2(50.0, 0.0, 0.0) * pose)
            .unwrap();
    }
    for (_, c) in other.constraints() {
        let (VariableId::Node(a), VariableId::Node(b)) = (c.from, c.to) else {
            unreachable!()
        };
        graph
            .add_constraint(Constraint {
                from: node(a.index + offset),
                to: node(b.index + offset),
                ..c.clone()
            })
            .unwrap();
    }
    let summary = optimizer().optimize(&mut graph);
    assert!(summary.termination.is_converged(), "{summary:?}");
    assert!(summary.final_chi2 < 1e-10, "{summary:?}");
    for (_, pose, _) in graph.variables() {
        assert!(
            pose.translation.vector.norm() < 100.0,
            "the floating component must not drift: {pose:?}"
        );
    }
}

/// `square_world(40)` with DCS on every constraint and 30 false loop closures (metres and radians off,
/// between scattered pairs), returning the graph, the truth and how the false closures were made.
fn square_world_with_false_closures(false_loss: RobustLoss) -> (PoseGraph, Vec<Rigid2>) {
    let (mut graph, truth) = square_world(40, RobustLoss::Dcs { phi: 1.0 });
    for k in 0..30u32 {
        let a = (7 * k) % 40;
        let b = (a + 3 + (13 * k) % 34) % 40;
        let (a, b) = (a.min(b), a.max(b));
        assert!(b - a > 1, "{a} {b}");
        let z = rigid2(3.0 + f64::from(k % 5), -2.0, 1.0 + 0.1 * f64::from(k));
        graph
            .add_constraint(constraint(a, b, z, false_loss))
            .unwrap();
    }
    (graph, truth)
}

#[test]
fn dcs_ignores_false_closures_that_drag_least_squares() {
    let (mut robust, truth) = square_world_with_false_closures(RobustLoss::Dcs { phi: 1.0 });
    let summary = optimizer().optimize(&mut robust);
    assert!(summary.termination.is_converged(), "{summary:?}");
    assert!(max_pose_error(&robust, &truth) < 1e-6, "{summary:?}");
    assert_eq!(summary.pruned_constraints, 30, "{summary:?}");
    let (mut plain, _) = square_world_with_false_closures(RobustLoss::Trivial);
    optimizer().optimize(&mut plain);
    assert!(max_pose_error(&plain, &truth) > 0.5);
}

#[test]
fn pruning_moves_the_optimum_only_by_the_pruned_constraints_residual_pull() {
    // The same problem without pruning (every constraint in the linear system, the factor filled in by
    // the false closures) and with it (the pattern of the clean graph plus whatever survives).
    let unpruned_options = OptimizerOptions {
        prune_weight: 0.0,
        ..OptimizerOptions::default()
    };
    let (mut unpruned, truth) = square_world_with_false_closures(RobustLoss::Dcs { phi: 1.0 });
    let mut unpruned_optimizer = Optimizer::new(unpruned_options).unwrap();
    let full = unpruned_optimizer.optimize(&mut unpruned);
    assert_eq!(full.pruned_constraints, 0);
    let (mut pruned, _) = square_world_with_false_closures(RobustLoss::Dcs { phi: 1.0 });
    let mut pruned_optimizer = optimizer();
    let summary = pruned_optimizer.optimize(&mut pruned);
    assert_eq!(summary.pruned_constraints, 30, "{summary:?}");
    // Both reach the truth up to the pull of the false closures' residual weights (DCS never reaches
    // zero): measured 2.5e-5 m without pruning, 1e-10 m with it — pruning drops a pull of that size.
    assert!(max_pose_error(&unpruned, &truth) < 1e-4, "{full:?}");
    assert!(max_pose_error(&pruned, &truth) < 1e-4, "{summary:?}");
    for ((_, a, _), (_, b, _)) in unpruned.variables().zip(pruned.variables()) {
        let d = a.inverse() * b;
        assert!(d.translation.vector.norm() < 1e-4 && d.theta().abs() < 1e-4);
    }
    assert_eq!(summary.iterations, full.iterations, "{summary:?} {full:?}");
    assert_relative_eq!(summary.final_cost, full.final_cost, max_relative = 1e-8);
    // A pruned edge returns when its weight rises again: the same optimizer on a graph where the false
    // closures are made true (measurement at the truth) ends with every constraint active.
    let mut fixed = PoseGraph::new();
    for (id, pose, is_fixed) in pruned.variables() {
        fixed.add_variable(id, pose).unwrap();
        fixed.set_fixed(id, is_fixed).unwrap();
    }
    for (_, c) in pruned.constraints() {
        let mut c = c.clone();
        c.from_from_to = pruned.pose(c.from).unwrap().inverse() * pruned.pose(c.to).unwrap();
        fixed.add_constraint(c).unwrap();
    }
    let again = pruned_optimizer.optimize(&mut fixed);
    assert_eq!(again.pruned_constraints, 0, "{again:?}");
}

#[test]
fn with_constraints_keeps_the_variables_and_maps_or_drops_each_constraint() {
    let (mut graph, _) = square_world(12, RobustLoss::Dcs { phi: 1.0 });
    graph.set_fixed(node(0), true).unwrap();
    let loop_closures = graph
        .constraints()
        .filter(|(_, c)| c.kind == ConstraintKind::NodeToNode)
        .count();
    assert!(loop_closures > 0);
    let odometry_only = graph
        .with_constraints(|c| {
            (c.kind == ConstraintKind::Odometry).then(|| Constraint {
                loss: RobustLoss::Trivial,
                ..c.clone()
            })
        })
        .unwrap();
    assert_eq!(odometry_only.num_variables(), graph.num_variables());
    assert_eq!(
        odometry_only.num_constraints(),
        graph.num_constraints() - loop_closures
    );
    assert!(
        odometry_only
            .constraints()
            .all(|(_, c)| c.loss == RobustLoss::Trivial)
    );
    for (id, pose, fixed) in graph.variables() {
        assert_eq!(odometry_only.pose(id), Some(pose));
        assert_eq!(odometry_only.is_fixed(id), Some(fixed));
    }
    // A constraint the map makes invalid is an error, not a silently smaller graph.
    let broken = graph.with_constraints(|c| {
        Some(Constraint {
            information: Matrix3::from_element(f64::NAN),
            ..c.clone()
        })
    });
    assert!(broken.is_err());
}

/// Loop closures in these tests: every constraint between non-consecutive nodes (in `square_world`, the
/// closures across the square and the edge that closes the loop of odometry).
fn is_loop_closure(c: &Constraint) -> bool {
    match (c.from, c.to) {
        (VariableId::Node(a), VariableId::Node(b)) => a.index.abs_diff(b.index) != 1,
        _ => true,
    }
}

fn robust_optimizer() -> RobustOptimizer {
    RobustOptimizer::new(RobustOptimizerOptions::default()).unwrap()
}

/// `square_world(n)` with every measurement off by a small deterministic amount (≈ 0.1–0.5 σ), so that
/// the least-squares optimum has residuals everywhere.
fn noisy_square_world(n: u32) -> PoseGraph {
    let (graph, _) = square_world(n, RobustLoss::Trivial);
    let mut k = 0.0;
    graph
        .with_constraints(|c| {
            k += 1.0;
            let noise = rigid2(
                0.03 * f64::sin(k),
                0.02 * f64::cos(2.0 * k),
                0.01 * f64::sin(3.0 * k),
            );
            Some(Constraint {
                from_from_to: c.from_from_to * noise,
                ..c.clone()
            })
        })
        .unwrap()
}

#[test]
fn robust_optimizer_keeps_the_least_squares_optimum_when_every_closure_fits() {
    let mut robust = noisy_square_world(40);
    let mut plain = robust.clone();
    let summary = robust_optimizer().optimize(&mut robust, is_loop_closure);
    let least_squares = Optimizer::new(RobustOptimizerOptions::DEFAULT.optimizer)
        .unwrap()
        .optimize(&mut plain);
    assert_eq!(summary.track, RobustTrack::AllInliers, "{summary:?}");
    assert!(!summary.rejection_track_ran);
    assert_eq!((summary.candidates, summary.rejected), (21, 0));
    assert!(
        least_squares.final_chi2 > 0.1,
        "the optimum must have residuals"
    );
    assert_relative_eq!(
        summary.final_chi2,
        least_squares.final_chi2,
        max_relative = 1e-12
    );
    assert_eq!(summary.iterations, least_squares.iterations);
    for (id, pose, _) in plain.variables() {
        assert_relative_eq!(robust.pose(id).unwrap(), pose, epsilon = 1e-12);
    }
}

#[test]
fn robust_optimizer_rejects_false_closures_and_keeps_no_pull_from_them() {
    let (mut graph, truth) = square_world_with_false_closures(RobustLoss::Trivial);
    let graph_losses: Vec<RobustLoss> = graph.constraints().map(|(_, c)| c.loss).collect();
    let summary = robust_optimizer().optimize(&mut graph, is_loop_closure);
    assert_eq!(summary.track, RobustTrack::Rejection, "{summary:?}");
    assert_eq!(
        (summary.candidates, summary.rejected),
        (51, 30),
        "{summary:?}"
    );
    assert_eq!(summary.pruned_constraints, 30);
    // Exact measurements and no residual pull from the rejected closures: the truth, to round-off.
    assert!(max_pose_error(&graph, &truth) < 1e-9, "{summary:?}");
    // The caller's constraints keep their losses.
    let after: Vec<RobustLoss> = graph.constraints().map(|(_, c)| c.loss).collect();
    assert_eq!(after, graph_losses);
    // What is not a candidate is never rejected: with only odometry as candidates, the false closures
    // hold and drag the graph.
    let (mut dragged, _) = square_world_with_false_closures(RobustLoss::Trivial);
    let summary = robust_optimizer().optimize(&mut dragged, |c| !is_loop_closure(c));
    assert_eq!(summary.candidates, 39);
    assert!(max_pose_error(&dragged, &truth) > 0.5, "{summary:?}");
}

#[test]
fn robust_optimizer_reaches_the_truncated_least_squares_minimum_found_by_exhaustive_search() {
    // 8 nodes, 5 true closures (one of them 3σ off) and 2 false ones; F's global minimum is the best,
    // over every subset S of closures, of the least-squares optimum over the odometry and S plus the
    // threshold for each closure left out (min_x Σ min(s, c̄²) = min_S min_x [Σ_S s + c̄²·|S̄|]).
    let (clean, _) = square_world(8, RobustLoss::Trivial);
    let mut graph = clean
        .with_constraints(|c| {
            let off = c.from == node(1) && c.to == node(5);
            Some(Constraint {
                from_from_to: if off {
                    c.from_from_to * rigid2(0.3, 0.0, 0.0)
                } else {
                    c.from_from_to
                },
                ..c.clone()
            })
        })
        .unwrap();
    for (a, b) in [(0, 3), (2, 7)] {
        graph
            .add_constraint(constraint(
                a,
                b,
                rigid2(2.0, -1.5, 0.8),
                RobustLoss::Trivial,
            ))
            .unwrap();
    }
    let threshold = RobustOptimizerOptions::DEFAULT.inlier_chi2;
    let closures: Vec<Constraint> = graph
        .constraints()
        .map(|(_, c)| c.clone())
        .filter(is_loop_closure)
        .collect();
    assert_eq!(closures.len(), 7);
    let mut best = f64::INFINITY;
    for subset in 0u32..(1 << closures.len()) {
        let mut k = 0;
        let mut candidate = graph
            .with_constraints(|c| {
                if !is_loop_closure(c) {
                    return Some(c.clone());
                }
                k += 1;
                (subset & (1 << (k - 1)) != 0).then(|| c.clone())
            })
            .unwrap();
        // Least squares from the truth-like start of the clean graph's optimum.
        for (id, pose, _) in clean.variables() {
            candidate.set_pose(id, pose).unwrap();
        }
        let summary = optimizer().optimize(&mut candidate);
        let left_out = closures.len() - subset.count_ones() as usize;
        best = best.min(summary.final_chi2 + threshold * left_out as f64);
    }
    let summary = robust_optimizer().optimize(&mut graph, is_loop_closure);
    assert_relative_eq!(summary.final_cost, best, max_relative = 1e-6);
    // The 3σ-off closure fits (χ² = 0.3² · 100 = 9 before the graph bends towards it): an inlier.
    assert_eq!(summary.rejected, 2, "{summary:?}");
}

#[test]
fn robust_optimizer_options_are_validated() {
    let defaults = RobustOptimizerOptions::default();
    assert_eq!(defaults.validate(), Ok(()));
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let inlier = RobustOptimizerOptions {
            inlier_chi2: bad,
            ..defaults.clone()
        };
        assert!(matches!(
            RobustOptimizer::new(inlier),
            Err(RobustOptimizerOptionsError::InlierChi2(_))
        ));
        let phi = RobustOptimizerOptions {
            rejection_phi: bad,
            ..defaults.clone()
        };
        assert!(matches!(
            phi.validate(),
            Err(RobustOptimizerOptionsError::RejectionPhi(_))
        ));
    }
    let optimizer = RobustOptimizerOptions {
        optimizer: OptimizerOptions {
            prune_weight: 0.5,
            ..OptimizerOptions::DEFAULT
        },
        ..defaults
    };
    assert!(matches!(
        optimizer.validate(),
        Err(RobustOptimizerOptionsError::Optimizer(
            OptimizerOptionsError::PruneWeight(_)
        ))
    ));
}

/// A graph rebuilt from its parts (a checkpoint) equals the original, gaps in the constraint ids and the
/// next id included, and keeps numbering where the original would.
#[test]
fn a_graph_rebuilt_from_its_parts_equals_the_original_and_numbers_on_alike() {
    let (mut graph, truth) = square_world(12, RobustLoss::Trivial);
    graph.set_fixed(node(0), true).unwrap();
    graph.remove_constraint(ConstraintId(3)).unwrap();
    graph.remove_variable(node(7)).unwrap();
    let removed_last = graph.add_constraint(constraint(
        1,
        5,
        truth[1].inverse() * truth[5],
        RobustLoss::Huber { delta: 0.5 },
    ));
    graph.remove_constraint(removed_last.unwrap()).unwrap();

    let mut rebuilt = PoseGraph::from_parts(
        graph.variables(),
        graph.constraints().map(|(id, c)| (id, c.clone())),
        graph.next_constraint_id(),
    )
    .unwrap();
    assert_eq!(rebuilt, graph);
    for id in [node(2), node(6), node(8)] {
        assert_eq!(rebuilt.constraints_of(id), graph.constraints_of(id));
    }
    let z = truth[2].inverse() * truth[9];
    assert_eq!(
        rebuilt.add_constraint(constraint(2, 9, z, RobustLoss::Trivial)),
        graph.add_constraint(constraint(2, 9, z, RobustLoss::Trivial))
    );
    assert_eq!(rebuilt, graph);
}

#[test]
fn a_graph_from_parts_with_repeated_or_stale_ids_is_refused() {
    let (graph, _) = square_world(6, RobustLoss::Trivial);
    let constraints: Vec<(ConstraintId, Constraint)> =
        graph.constraints().map(|(id, c)| (id, c.clone())).collect();
    let repeated = constraints
        .iter()
        .cloned()
        .chain(constraints.first().cloned());
    assert!(matches!(
        PoseGraph::from_parts(graph.variables(), repeated, graph.next_constraint_id()),
        Err(PoseGraphError::ConstraintIdOutOfOrder(_))
    ));
    assert!(matches!(
        PoseGraph::from_parts(graph.variables(), constraints, ConstraintId(2)),
        Err(PoseGraphError::ConstraintIdOutOfOrder(ConstraintId(2)))
    ));
}

#[test]
fn the_largest_shift_is_over_the_variables_both_graphs_hold() {
    let mut a = PoseGraph::new();
    let mut b = PoseGraph::new();
    a.add_variable(node(0), rigid2(0.0, 0.0, 0.0)).unwrap();
    a.add_variable(node(1), rigid2(1.0, 0.0, 0.1)).unwrap();
    a.add_variable(node(2), rigid2(2.0, 0.0, 0.0)).unwrap();
    b.add_variable(node(0), rigid2(0.0, 0.2, 0.0)).unwrap();
    b.add_variable(node(1), rigid2(1.0, 0.1, -0.2)).unwrap();
    // Only in `b`: far off, and not compared.
    b.add_variable(node(3), rigid2(50.0, 0.0, 3.0)).unwrap();
    let (translation, rotation) = a.largest_shift(&b);
    assert_relative_eq!(translation, 0.2, epsilon = 1e-12);
    assert_relative_eq!(rotation, 0.3, epsilon = 1e-12);
    assert_eq!(a.largest_shift(&a), (0.0, 0.0));
}
