//! Tests of sparsification against the dense marginal (the oracle), brute force over trees, the
//! `delete` baseline and re-optimization (the real-data benchmark is `benches/sparsification.rs`).

use nalgebra::{Matrix3, Vector3};
use rand::{Rng as _, SeedableRng as _};
use rand_pcg::Pcg64;

use super::*;
use crate::geometry::rigid2;
use crate::pose_graph::{NodeId, Optimizer, OptimizerOptions, SubmapId};

fn node(index: u32) -> VariableId {
    VariableId::Node(NodeId {
        trajectory: 0,
        index,
    })
}

fn submap(index: u32) -> VariableId {
    VariableId::Submap(SubmapId {
        trajectory: 0,
        index,
    })
}

fn random_information(rng: &mut Pcg64, scale: f64) -> Matrix3<f64> {
    let a = Matrix3::from_fn(|_, _| rng.random_range(-1.0..1.0));
    scale * (a * a.transpose() + Matrix3::from_diagonal(&Vector3::new(0.5, 0.5, 2.0)))
}

fn random_pose(rng: &mut Pcg64) -> Rigid2 {
    rigid2(
        rng.random_range(-5.0..5.0),
        rng.random_range(-5.0..5.0),
        rng.random_range(-3.0..3.0),
    )
}

/// Adds a constraint whose measurement is the current relative pose (zero residual) times `noise`.
fn link(
    graph: &mut PoseGraph,
    from: VariableId,
    to: VariableId,
    kind: ConstraintKind,
    information: Matrix3<f64>,
    noise: Rigid2,
    loss: RobustLoss,
) {
    let z = graph.pose(from).unwrap().inverse() * graph.pose(to).unwrap() * noise;
    graph
        .add_constraint(Constraint {
            kind,
            from,
            to,
            from_from_to: z,
            information,
            loss,
        })
        .unwrap();
}

fn exact_link(graph: &mut PoseGraph, rng: &mut Pcg64, from: VariableId, to: VariableId) {
    let information = random_information(rng, 10.0);
    link(
        graph,
        from,
        to,
        ConstraintKind::NodeToNode,
        information,
        Rigid2::identity(),
        RobustLoss::Trivial,
    );
}

fn options(edge_model: EdgeModel) -> SparsificationOptions {
    SparsificationOptions {
        edge_model,
        ..SparsificationOptions::DEFAULT
    }
}

/// Blanket poses `labels[0..5]`, eliminated nodes 10..=14, removed constraints forming the tree
/// `l0–l1, l1–l2, l1–l3, l3–l4` through eliminated poses: the blanket marginal is itself a tree.
fn tree_marginal_graph(labels: [u32; 5]) -> (PoseGraph, Vec<VariableId>) {
    let mut rng = Pcg64::seed_from_u64(11);
    let mut graph = PoseGraph::new();
    for id in labels.iter().chain(&[10, 11, 12, 13, 14]) {
        graph
            .add_variable(node(*id), random_pose(&mut rng))
            .unwrap();
    }
    let b = |k: usize| node(labels[k]);
    for (x, y) in [
        (b(0), node(10)),
        (node(10), b(1)),
        (b(1), node(11)),
        (node(11), b(2)),
        (node(12), b(1)),
        (node(12), node(13)),
        (node(13), b(3)),
        (b(3), node(14)),
        (b(4), node(14)),
    ] {
        exact_link(&mut graph, &mut rng, x, y);
    }
    (graph, (10..=14).map(node).collect())
}

// Chow & Liu 1968: a distribution that already factors over a tree is its own best tree (KL = 0).
#[test]
fn tree_shaped_marginal_is_reproduced_exactly() {
    for model in [EdgeModel::RelativeMarginal, EdgeModel::Conditional] {
        // Root (smallest id) 0 is a leaf of the tree.
        let (graph, eliminate) = tree_marginal_graph([0, 1, 2, 3, 4]);
        let result = sparsify(&graph, &eliminate, &options(model)).unwrap();
        assert_eq!(result.blanket, (0..5).map(node).collect::<Vec<_>>());
        assert_eq!(result.new_constraints.len(), 4);
        assert_eq!(result.removed_constraints.len(), 9);
        assert_eq!(result.diagnostics.marginal_rank, 12);
        assert!(
            result.diagnostics.kl_divergence < 1e-9,
            "{model:?}: {}",
            result.diagnostics.kl_divergence
        );
        let global =
            kl_divergence(&graph, &eliminate, &result.new_constraints, &options(model)).unwrap();
        assert!(global < 1e-9, "{model:?}: {global}");
        let mut edges: Vec<(VariableId, VariableId)> = result
            .new_constraints
            .iter()
            .map(|c| (c.from.min(c.to), c.from.max(c.to)))
            .collect();
        edges.sort();
        assert_eq!(
            edges,
            vec![
                (node(0), node(1)),
                (node(1), node(2)),
                (node(1), node(3)),
                (node(3), node(4))
            ]
        );
        // The deletion baseline loses everything.
        let delete_kld = kl_divergence(&graph, &eliminate, &[], &options(model)).unwrap();
        assert!(delete_kld.is_infinite());
    }
}

// The root-shifted conditional recipe conditions every edge on the root too: with the root (smallest
// id, here the hub l1 = 0) inside the tree, it is no longer exact; the relative-marginal tree is.
#[test]
fn conditional_model_depends_on_the_root_relative_marginal_does_not() {
    let (graph, eliminate) = tree_marginal_graph([1, 0, 2, 3, 4]);
    let exact = sparsify(&graph, &eliminate, &options(EdgeModel::RelativeMarginal)).unwrap();
    assert!(exact.diagnostics.kl_divergence < 1e-9);
    let conditional = sparsify(&graph, &eliminate, &options(EdgeModel::Conditional)).unwrap();
    assert!(
        conditional.diagnostics.kl_divergence > 1e-3,
        "{}",
        conditional.diagnostics.kl_divergence
    );
}

#[test]
fn two_pose_blanket_gives_the_dense_marginal_as_one_constraint() {
    let mut rng = Pcg64::seed_from_u64(3);
    let mut graph = PoseGraph::new();
    for id in [0, 1, 5, 6] {
        graph.add_variable(node(id), random_pose(&mut rng)).unwrap();
    }
    // Slightly inconsistent measurements: the marginal mean differs from the estimate.
    for (x, y, noise) in [
        (node(0), node(5), rigid2(0.02, -0.01, 0.01)),
        (node(5), node(1), rigid2(-0.01, 0.03, -0.02)),
        (node(5), node(6), rigid2(0.01, 0.0, 0.005)),
        (node(6), node(1), rigid2(0.0, -0.02, 0.01)),
    ] {
        let information = random_information(&mut rng, 20.0);
        link(
            &mut graph,
            x,
            y,
            ConstraintKind::NodeToNode,
            information,
            noise,
            RobustLoss::Trivial,
        );
    }
    let eliminate = [node(5), node(6)];
    for model in [EdgeModel::RelativeMarginal, EdgeModel::Conditional] {
        let result = sparsify(&graph, &eliminate, &options(model)).unwrap();
        assert_eq!(result.new_constraints.len(), 1);
        let c = &result.new_constraints[0];
        assert_eq!((c.from, c.to), (node(0), node(1)));
        assert_eq!(c.kind, ConstraintKind::NodeToNode);
        assert_eq!(c.loss, RobustLoss::Trivial);
        // Its information on δx₁ (x₀ held) is the gauge-fixed dense marginal.
        let marginal = marginalize(&graph, &eliminate, &options(model)).unwrap();
        let x0 = graph.pose(node(0)).unwrap();
        let x1 = graph.pose(node(1)).unwrap();
        let (_, _, j1) = linearize(&c.from_from_to, &x0, &x1);
        let on_x1 = j1.transpose() * c.information * j1;
        let dense = marginal.information.fixed_view::<3, 3>(3, 3).into_owned();
        assert!((on_x1 - dense).norm() < 1e-9 * dense.norm(), "{model:?}");
        assert!(result.diagnostics.kl_divergence < 1e-12);
        assert_eq!(result.diagnostics.marginal_rank, 3);
    }
    // Its measurement is the (nonlinear) optimum of the removed constraints, to first order.
    let result = sparsify(&graph, &eliminate, &SparsificationOptions::DEFAULT).unwrap();
    let mut alone = graph.clone();
    alone.set_fixed(node(0), true).unwrap();
    Optimizer::new(OptimizerOptions::default())
        .unwrap()
        .optimize(&mut alone);
    let optimum = alone.pose(node(0)).unwrap().inverse() * alone.pose(node(1)).unwrap();
    let z = result.new_constraints[0].from_from_to;
    let before = graph.pose(node(0)).unwrap().inverse() * graph.pose(node(1)).unwrap();
    let error = (z.inverse() * optimum).translation.vector.norm();
    let prior = (before.inverse() * optimum).translation.vector.norm();
    assert!(prior > 0.01, "the test needs a residual ({prior})");
    assert!(error < 0.05 * prior, "{error} vs {prior}");
}

/// Optimizes both graphs and checks that they end at the same poses (a summed constraint costs what the
/// two it replaced did, up to a constant).
fn assert_same_optimum(a: &mut PoseGraph, b: &mut PoseGraph) {
    let mut optimizer = Optimizer::new(OptimizerOptions::default()).unwrap();
    optimizer.optimize(a);
    optimizer.optimize(b);
    let (translation, rotation) = a.largest_shift(b);
    assert!(
        translation < 1e-9 && rotation < 1e-9,
        "{translation} m, {rotation} rad"
    );
}

#[test]
fn a_second_tree_edge_on_a_pair_is_summed_into_the_first() {
    // Two detours between nodes 0 and 1 (through 5 and through 6), trimmed one after the other: each
    // trim's tree is one edge 0 → 1; the second is summed into the first, and the graph optimizes to the
    // same poses as with both edges side by side.
    let mut rng = Pcg64::seed_from_u64(11);
    let mut graph = PoseGraph::new();
    for id in [0, 1, 5, 6] {
        graph.add_variable(node(id), random_pose(&mut rng)).unwrap();
    }
    graph.set_fixed(node(0), true).unwrap();
    for (x, y, noise) in [
        (node(0), node(5), rigid2(0.02, -0.01, 0.01)),
        (node(5), node(1), rigid2(-0.01, 0.03, -0.02)),
        (node(0), node(6), rigid2(-0.03, 0.02, 0.015)),
        (node(6), node(1), rigid2(0.01, -0.02, -0.01)),
    ] {
        let information = random_information(&mut rng, 20.0);
        link(
            &mut graph,
            x,
            y,
            ConstraintKind::NodeToNode,
            information,
            noise,
            RobustLoss::Trivial,
        );
    }
    let first = sparsify(&graph, &[node(5)], &SparsificationOptions::DEFAULT).unwrap();
    apply(&mut graph, &first, ParallelMerge::EveryPlain).unwrap();
    assert_eq!(graph.num_constraints(), 3);
    let second = sparsify(&graph, &[node(6)], &SparsificationOptions::DEFAULT).unwrap();
    assert_eq!(second.new_constraints.len(), 1);
    let mut side_by_side = graph.clone();
    side_by_side.remove_variable(node(6)).unwrap();
    side_by_side
        .add_constraint(second.new_constraints[0].clone())
        .unwrap();
    assert_eq!(side_by_side.num_constraints(), 2);
    let ids = apply(&mut graph, &second, ParallelMerge::EveryPlain).unwrap();
    assert_eq!(graph.num_constraints(), 1, "summed, not stacked");
    assert_eq!(graph.constraints_of(node(1)), ids.as_slice());
    assert_same_optimum(&mut graph, &mut side_by_side);
}

#[test]
fn a_tree_edge_beside_another_plain_constraint_is_summed_into_it() {
    // Nodes 0 and 1 tied by odometry and by a detour through 5; trimming 5 puts a tree edge 0 → 1 beside
    // the odometry.
    let mut rng = Pcg64::seed_from_u64(12);
    let mut graph = PoseGraph::new();
    for id in [0, 1, 5] {
        graph.add_variable(node(id), random_pose(&mut rng)).unwrap();
    }
    graph.set_fixed(node(0), true).unwrap();
    for (x, y, kind, noise) in [
        (
            node(0),
            node(1),
            ConstraintKind::Odometry,
            rigid2(0.02, 0.01, -0.01),
        ),
        (
            node(0),
            node(5),
            ConstraintKind::NodeToNode,
            rigid2(-0.01, 0.02, 0.01),
        ),
        (
            node(5),
            node(1),
            ConstraintKind::NodeToNode,
            rigid2(0.01, -0.03, 0.02),
        ),
    ] {
        let information = random_information(&mut rng, 20.0);
        link(
            &mut graph,
            x,
            y,
            kind,
            information,
            noise,
            RobustLoss::Trivial,
        );
    }
    let result = sparsify(&graph, &[node(5)], &SparsificationOptions::DEFAULT).unwrap();
    let mut beside = graph.clone();
    beside.remove_variable(node(5)).unwrap();
    for constraint in &result.new_constraints {
        beside.add_constraint(constraint.clone()).unwrap();
    }
    assert_eq!(beside.num_constraints(), 2);
    let mut summed = graph.clone();
    apply(&mut summed, &result, ParallelMerge::EveryPlain).unwrap();
    assert_eq!(summed.num_constraints(), 1);
    let (_, only) = summed.constraints().next().unwrap();
    assert_eq!(
        only.kind,
        ConstraintKind::Odometry,
        "the merged constraint keeps its kind"
    );
    assert_same_optimum(&mut summed, &mut beside);
}

#[test]
fn a_node_to_submap_constraint_its_owner_may_rewrite_takes_in_no_tree_edge() {
    // Submap 0 holds node 1 (LLO's node-to-submap constraint) and node 5, which odometry ties to node 1;
    // trimming 5 puts a tree edge 0 → 1 beside LLO's constraint.
    let mut rng = Pcg64::seed_from_u64(13);
    let mut graph = PoseGraph::new();
    graph
        .add_variable(submap(0), random_pose(&mut rng))
        .unwrap();
    for id in [1, 5] {
        graph.add_variable(node(id), random_pose(&mut rng)).unwrap();
    }
    graph.set_fixed(submap(0), true).unwrap();
    for (x, y, kind) in [
        (submap(0), node(1), ConstraintKind::NodeToSubmapIntra),
        (submap(0), node(5), ConstraintKind::NodeToSubmapIntra),
        (node(5), node(1), ConstraintKind::Odometry),
    ] {
        let information = random_information(&mut rng, 20.0);
        link(
            &mut graph,
            x,
            y,
            kind,
            information,
            rigid2(0.01, -0.02, 0.01),
            RobustLoss::Trivial,
        );
    }
    let result = sparsify(&graph, &[node(5)], &SparsificationOptions::DEFAULT).unwrap();
    let VariableId::Submap(held) = submap(0) else {
        unreachable!()
    };
    let mut beside = graph.clone();
    apply(
        &mut beside,
        &result,
        ParallelMerge::EveryPlainBut(&BTreeSet::from([held])),
    )
    .unwrap();
    assert_eq!(
        beside.num_constraints(),
        2,
        "LLO's constraint stays as it was"
    );
    let mut summed = graph.clone();
    apply(
        &mut summed,
        &result,
        ParallelMerge::EveryPlainBut(&BTreeSet::new()),
    )
    .unwrap();
    assert_eq!(summed.num_constraints(), 1);
    let (_, only) = summed.constraints().next().unwrap();
    assert_eq!(only.kind, ConstraintKind::NodeToSubmapIntra);
    assert_same_optimum(&mut summed, &mut beside);
}

#[test]
fn one_pose_blanket_and_disconnected_components() {
    let mut rng = Pcg64::seed_from_u64(5);
    let mut graph = PoseGraph::new();
    for id in 0..7 {
        graph.add_variable(node(id), random_pose(&mut rng)).unwrap();
    }
    for k in 0..6 {
        exact_link(&mut graph, &mut rng, node(k), node(k + 1));
    }
    // A leaf: one blanket pose, nothing to add.
    let leaf = sparsify(&graph, &[node(6)], &SparsificationOptions::DEFAULT).unwrap();
    assert_eq!(leaf.blanket, vec![node(5)]);
    assert!(leaf.new_constraints.is_empty());
    assert_eq!(leaf.removed_constraints.len(), 1);
    // Two separate eliminated poses: two components, one constraint each.
    let split = sparsify(&graph, &[node(1), node(4)], &SparsificationOptions::DEFAULT).unwrap();
    assert_eq!(split.diagnostics.components, 2);
    assert_eq!(split.diagnostics.marginal_dimension, 6);
    let mut pairs: Vec<_> = split
        .new_constraints
        .iter()
        .map(|c| (c.from, c.to))
        .collect();
    pairs.sort();
    assert_eq!(pairs, vec![(node(0), node(2)), (node(3), node(5))]);
    assert!(split.diagnostics.kl_divergence < 1e-12);
    // Chains are trees: exact globally too, while deleting disconnects the chain.
    let o = SparsificationOptions::DEFAULT;
    let kld = kl_divergence(&graph, &[node(1), node(4)], &split.new_constraints, &o).unwrap();
    assert!(kld < 1e-9, "{kld}");
    assert!(
        kl_divergence(&graph, &[node(1), node(4)], &[], &o)
            .unwrap()
            .is_infinite()
    );
    // Errors.
    assert_eq!(
        sparsify(&graph, &[], &o),
        Err(SparsificationError::NothingToEliminate)
    );
    assert_eq!(
        sparsify(&graph, &[node(99)], &o),
        Err(SparsificationError::UnknownVariable(node(99)))
    );
    let mut fixed = graph.clone();
    fixed.set_fixed(node(3), true).unwrap();
    assert_eq!(
        sparsify(&fixed, &[node(3)], &o),
        Err(SparsificationError::FixedVariable(node(3)))
    );
}

#[test]
fn rank_deficient_marginal_is_reported_and_stays_finite() {
    let mut rng = Pcg64::seed_from_u64(9);
    let mut graph = PoseGraph::new();
    for id in [0, 1, 2, 5] {
        graph.add_variable(node(id), random_pose(&mut rng)).unwrap();
    }
    exact_link(&mut graph, &mut rng, node(0), node(5));
    exact_link(&mut graph, &mut rng, node(5), node(1));
    // Node 2 is tied to the eliminated pose by a bearing-only-like constraint: rotation only.
    link(
        &mut graph,
        node(5),
        node(2),
        ConstraintKind::NodeToNode,
        Matrix3::from_diagonal(&Vector3::new(0.0, 0.0, 5.0)),
        Rigid2::identity(),
        RobustLoss::Trivial,
    );
    let result = sparsify(&graph, &[node(5)], &SparsificationOptions::DEFAULT).unwrap();
    assert_eq!(result.diagnostics.marginal_dimension, 6);
    assert_eq!(result.diagnostics.marginal_rank, 4);
    assert_eq!(result.new_constraints.len(), 2);
    for c in &result.new_constraints {
        assert!(c.information.iter().all(|v| v.is_finite()));
        assert!(c.information.symmetric_eigenvalues().min() > -1e-9 * c.information.norm());
    }
    // Node 2's relative position is unknown, so the star's marginal is a clique in θ only.
    assert!(result.diagnostics.kl_divergence.is_finite());
    let mut applied = graph.clone();
    apply(&mut applied, &result, ParallelMerge::EveryPlain).unwrap();
    assert_eq!(applied.num_constraints(), 2);
}

#[test]
fn robust_weights_shrink_the_marginal_of_an_outlier() {
    let mut rng = Pcg64::seed_from_u64(13);
    let mut graph = PoseGraph::new();
    for id in [0, 1, 5] {
        graph.add_variable(node(id), random_pose(&mut rng)).unwrap();
    }
    exact_link(&mut graph, &mut rng, node(0), node(5));
    // An outlier loop closure, 1 m off, under a Cauchy loss.
    link(
        &mut graph,
        node(5),
        node(1),
        ConstraintKind::NodeToNode,
        Matrix3::identity() * 100.0,
        rigid2(1.0, 0.0, 0.0),
        RobustLoss::Cauchy { scale: 1.0 },
    );
    let trace = |weighting| {
        let o = SparsificationOptions {
            robust_weighting: weighting,
            ..SparsificationOptions::DEFAULT
        };
        let result = sparsify(&graph, &[node(5)], &o).unwrap();
        result.new_constraints[0].information.trace()
    };
    let irls = trace(RobustWeighting::Irls);
    let ignored = trace(RobustWeighting::Ignore);
    assert!(irls < 0.05 * ignored, "{irls} vs {ignored}");
}

/// All spanning trees of the complete graph on 4 vertices (16, by Cayley).
fn spanning_trees_of_four() -> Vec<Vec<(usize, usize)>> {
    let pairs: Vec<(usize, usize)> = (0..4)
        .flat_map(|a| (a + 1..4).map(move |b| (a, b)))
        .collect();
    let mut trees = Vec::new();
    for mask in 0u32..64 {
        if mask.count_ones() != 3 {
            continue;
        }
        let edges: Vec<(usize, usize)> = (0..6)
            .filter(|k| mask & (1 << k) != 0)
            .map(|k| pairs[k])
            .collect();
        let mut uf = UnionFind::new(4);
        let acyclic = edges.iter().all(|&(a, b)| {
            let (ra, rb) = (uf.find(a), uf.find(b));
            uf.union(a, b);
            ra != rb
        });
        if acyclic {
            trees.push(edges);
        }
    }
    trees
}

// The relative-marginal tree minimises KL over every tree of relative-pose constraints (module docs,
// step 3): brute force over all 16 spanning trees of a 4-pose blanket, and over scaled informations.
#[test]
fn relative_marginal_tree_is_kl_minimal_over_all_trees() {
    let trees = spanning_trees_of_four();
    assert_eq!(trees.len(), 16);
    let o = SparsificationOptions::DEFAULT;
    for seed in 0..5 {
        let mut rng = Pcg64::seed_from_u64(100 + seed);
        let mut graph = PoseGraph::new();
        for id in [0, 1, 2, 3, 10, 11] {
            graph.add_variable(node(id), random_pose(&mut rng)).unwrap();
        }
        for (x, y) in [
            (node(0), node(10)),
            (node(10), node(1)),
            (node(10), node(2)),
            (node(11), node(2)),
            (node(11), node(3)),
            (node(10), node(11)),
            (node(0), node(11)),
        ] {
            exact_link(&mut graph, &mut rng, x, y);
        }
        let eliminate = [node(10), node(11)];
        let result = sparsify(&graph, &eliminate, &o).unwrap();
        let chosen = kl_divergence(&graph, &eliminate, &result.new_constraints, &o).unwrap();
        assert!((chosen - result.diagnostics.kl_divergence).abs() < 1e-9);
        assert!(chosen > 1e-3, "the marginal must not be a tree already");

        let marginal = marginalize(&graph, &eliminate, &o).unwrap();
        let members: Vec<usize> = (0..4).collect();
        let fixed = GaugeFixed::new(&marginal, &members, &o).unwrap();
        let points = marginal.linearization_point.clone();
        let tree_constraints = |edges: &[(usize, usize)], scale: f64| -> Vec<Constraint> {
            edges
                .iter()
                .map(|&(a, b)| {
                    let z = points[a].inverse() * points[b];
                    let cov = relative_covariance(&fixed, &points, &z, a, b);
                    Constraint {
                        kind: ConstraintKind::NodeToNode,
                        from: node(a as u32),
                        to: node(b as u32),
                        from_from_to: z,
                        information: spd_inverse(&cov) * scale,
                        loss: RobustLoss::Trivial,
                    }
                })
                .collect()
        };
        let mut best = f64::INFINITY;
        for edges in &trees {
            let kld = kl_divergence(&graph, &eliminate, &tree_constraints(edges, 1.0), &o).unwrap();
            best = best.min(kld);
            for scale in [0.8, 1.25] {
                let scaled =
                    kl_divergence(&graph, &eliminate, &tree_constraints(edges, scale), &o).unwrap();
                assert!(
                    scaled > kld,
                    "seed {seed}: scaling by {scale} must not help"
                );
            }
        }
        assert!(chosen <= best + 1e-9, "seed {seed}: {chosen} vs {best}");
        let conditional = sparsify(&graph, &eliminate, &options(EdgeModel::Conditional)).unwrap();
        let conditional_kld =
            kl_divergence(&graph, &eliminate, &conditional.new_constraints, &o).unwrap();
        assert!(conditional_kld >= chosen - 1e-9);
    }
}

/// Two laps around a circle of radius 8 m, 48 nodes a lap; a submap every 8 nodes of the first lap
/// (intra constraints to its nodes); odometry between consecutive nodes; every second node of the second
/// lap closes a loop (Huber loss) to the first-lap submap it passes. Measurements carry uniform noise;
/// the graph is optimized with node 0 fixed.
fn two_lap_world() -> PoseGraph {
    let mut rng = Pcg64::seed_from_u64(21);
    let per_lap = 48;
    let truth = |k: u32| {
        let t = f64::from(k) / f64::from(per_lap) * std::f64::consts::TAU;
        rigid2(
            8.0 * t.cos(),
            8.0 * t.sin(),
            t + std::f64::consts::FRAC_PI_2,
        )
    };
    let noise = |rng: &mut Pcg64, m: f64| {
        rigid2(
            rng.random_range(-m..m),
            rng.random_range(-m..m),
            rng.random_range(-m..m) / 4.0,
        )
    };
    let mut graph = PoseGraph::new();
    for k in 0..2 * per_lap {
        let n = noise(&mut rng, 0.3);
        graph.add_variable(node(k), truth(k) * n).unwrap();
    }
    for s in 0..per_lap / 8 {
        let n = noise(&mut rng, 0.3);
        graph.add_variable(submap(s), truth(8 * s) * n).unwrap();
    }
    let add = |graph: &mut PoseGraph,
               rng: &mut Pcg64,
               from: VariableId,
               from_truth: Rigid2,
               to: u32,
               kind: ConstraintKind,
               diagonal: Vector3<f64>,
               loss: RobustLoss| {
        let z = from_truth.inverse() * truth(to) * noise(rng, 0.05);
        graph
            .add_constraint(Constraint {
                kind,
                from,
                to: node(to),
                from_from_to: z,
                information: Matrix3::from_diagonal(&diagonal),
                loss,
            })
            .unwrap();
    };
    for k in 0..2 * per_lap - 1 {
        add(
            &mut graph,
            &mut rng,
            node(k),
            truth(k),
            k + 1,
            ConstraintKind::Odometry,
            Vector3::new(100.0, 100.0, 1000.0),
            RobustLoss::Trivial,
        );
    }
    for k in 0..per_lap {
        let s = k / 8;
        add(
            &mut graph,
            &mut rng,
            submap(s),
            truth(8 * s),
            k,
            ConstraintKind::NodeToSubmapIntra,
            Vector3::new(200.0, 200.0, 800.0),
            RobustLoss::Trivial,
        );
    }
    for k in (per_lap..2 * per_lap).step_by(2) {
        let s = (k - per_lap) / 8;
        add(
            &mut graph,
            &mut rng,
            submap(s),
            truth(8 * s),
            k,
            ConstraintKind::NodeToSubmapInter,
            Vector3::new(50.0, 50.0, 200.0),
            RobustLoss::Huber { delta: 3.0 },
        );
    }
    graph.set_fixed(node(0), true).unwrap();
    let summary = Optimizer::new(OptimizerOptions::default())
        .unwrap()
        .optimize(&mut graph);
    assert!(summary.termination.is_converged());
    graph
}

/// Submap 2 of the first lap and its nodes 16..24.
fn submap_two() -> Vec<VariableId> {
    std::iter::once(submap(2))
        .chain((16..24).map(node))
        .collect()
}

// Design notes §5: KLD(clt) ≪ KLD(delete) on a realistic small graph. Four second-lap loop closures
// to the eliminated submap make its marginal a star around a hidden hub, which no tree represents
// well: measured 0.41 nats (relative-marginal) vs 1.73 (delete). The root-shifted conditional recipe
// is over-confident here and does worse than deleting (2.21 nats).
#[test]
fn tree_is_far_closer_to_the_marginal_than_deletion() {
    let graph = two_lap_world();
    let eliminate = submap_two();
    let o = SparsificationOptions::DEFAULT;
    let result = sparsify(&graph, &eliminate, &o).unwrap();
    assert!(result.blanket.len() >= 5, "{:?}", result.blanket);
    assert_eq!(result.new_constraints.len(), result.blanket.len() - 1);
    let delete_kld = kl_divergence(&graph, &eliminate, &[], &o).unwrap();
    assert!(delete_kld.is_finite() && delete_kld > 1.0, "{delete_kld}");
    let clt = kl_divergence(&graph, &eliminate, &result.new_constraints, &o).unwrap();
    assert!(clt <= 0.3 * delete_kld, "{clt} vs delete {delete_kld}");
    let conditional = sparsify(&graph, &eliminate, &options(EdgeModel::Conditional)).unwrap();
    let conditional_kld =
        kl_divergence(&graph, &eliminate, &conditional.new_constraints, &o).unwrap();
    assert!(
        clt < conditional_kld,
        "{clt} vs conditional {conditional_kld}"
    );
}

// Design notes §5: after sparsification and re-optimization the remaining poses barely move, and far
// less than after deletion.
#[test]
fn reoptimized_sparsified_graph_stays_near_the_full_optimum() {
    let graph = two_lap_world();
    let eliminate = submap_two();
    let mut optimizer = Optimizer::new(OptimizerOptions::default()).unwrap();
    let sparsified_and_optimized = |tree_mean: TreeMean, optimizer: &mut Optimizer| {
        let options = SparsificationOptions {
            tree_mean,
            ..SparsificationOptions::DEFAULT
        };
        let mut sparsified = graph.clone();
        let result = sparsify(&graph, &eliminate, &options).unwrap();
        let added = apply(&mut sparsified, &result, ParallelMerge::EveryPlain).unwrap();
        assert_eq!(added.len(), result.new_constraints.len());
        assert!(
            eliminate
                .iter()
                .all(|&id| !sparsified.contains_variable(id))
        );
        optimizer.optimize(&mut sparsified);
        (
            graph.largest_shift(&sparsified),
            result.removed_constraints.len(),
        )
    };
    let (gradient, removed) = sparsified_and_optimized(TreeMean::MatchGradient, &mut optimizer);
    let (marginal_mean, _) = sparsified_and_optimized(TreeMean::MatchMarginalMean, &mut optimizer);
    let mut deleted = graph.clone();
    assert_eq!(delete(&mut deleted, &eliminate).unwrap().len(), removed);
    optimizer.optimize(&mut deleted);
    let del = graph.largest_shift(&deleted);
    // Measured: matching the gradient keeps the optimum stationary (0.12 mm / 7 µrad); the marginal's
    // own mean (the default, see `TreeMean`) moves poses by 1.2 cm / 1.4 mrad; deletion by 5.3 cm /
    // 4.3 mrad.
    assert!(gradient.0 < 1e-3 && gradient.1 < 1e-4, "{gradient:?}");
    assert!(
        marginal_mean.0 > 10.0 * gradient.0,
        "{marginal_mean:?} vs {gradient:?}"
    );
    for shift in [gradient, marginal_mean] {
        assert!(
            shift.0 < 0.3 * del.0 && shift.1 < 0.5 * del.1,
            "{shift:?} vs delete {del:?}"
        );
    }
}

#[test]
fn apply_checks_before_editing() {
    let graph = two_lap_world();
    let result = sparsify(&graph, &submap_two(), &SparsificationOptions::DEFAULT).unwrap();
    let mut edited = graph.clone();
    apply(&mut edited, &result, ParallelMerge::EveryPlain).unwrap();
    // Applying twice fails without touching the graph.
    let before = edited.num_constraints();
    assert!(matches!(
        apply(&mut edited, &result, ParallelMerge::EveryPlain),
        Err(SparsificationError::UnknownVariable(_))
    ));
    assert_eq!(edited.num_constraints(), before);
    // Kinds follow the endpoints; mixed edges run submap → node.
    for c in &result.new_constraints {
        match (c.from, c.to) {
            (VariableId::Node(_), VariableId::Node(_)) => {
                assert_eq!(c.kind, ConstraintKind::NodeToNode);
            }
            (VariableId::Submap(_), VariableId::Node(_)) => {
                assert_eq!(c.kind, ConstraintKind::NodeToSubmapInter);
            }
            (VariableId::Submap(_), VariableId::Submap(_)) => {
                assert_eq!(c.kind, ConstraintKind::SubmapToSubmap);
            }
            (VariableId::Node(_), VariableId::Submap(_)) => {
                panic!("mixed edge must start at the submap")
            }
        }
    }
}
