//! The part of a settled pose graph an optimization moves.
//!
//! A lifelong map's finished sessions were optimized when they ended and nothing new touches most of
//! them; re-solving all of them every time a running session adds a few hundred nodes costs as much as
//! the whole graph (tens of thousands of variables) for changes that stay local. Like the local bundle
//! adjustment of keyframe SLAM systems, an optimization then moves only what is new and its
//! neighbourhood — the running trajectories' variables, the endpoints of constraints added since the last
//! optimization (a session's matches into old submaps, a Chow–Liu tree's edges), and every variable
//! within `hops` constraints of them — and holds the rest where the last optimization left it. The
//! variables on the region's border stay fixed, and the constraints between them and the region anchor
//! it: the region cannot drift as a whole.

use std::collections::BTreeSet;

use crate::pose_graph::{PoseGraph, VariableId};

/// `seeds` (those the graph holds) and every variable within `hops` constraints of one of them.
pub fn optimization_region(
    graph: &PoseGraph,
    seeds: impl IntoIterator<Item = VariableId>,
    hops: usize,
) -> BTreeSet<VariableId> {
    let mut region: BTreeSet<VariableId> = seeds
        .into_iter()
        .filter(|id| graph.contains_variable(*id))
        .collect();
    let mut frontier: Vec<VariableId> = region.iter().copied().collect();
    for _ in 0..hops {
        let mut next = Vec::new();
        for id in frontier {
            for constraint in graph.constraints_of(id) {
                let Some(c) = graph.constraint(*constraint) else {
                    continue;
                };
                let other = if c.from == id { c.to } else { c.from };
                if region.insert(other) {
                    next.push(other);
                }
            }
        }
        if next.is_empty() {
            break;
        }
        frontier = next;
    }
    region
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;
    use crate::pose_graph::{Constraint, ConstraintKind, NodeId, RobustLoss};
    use nalgebra::Matrix3;

    fn node(index: u32) -> VariableId {
        VariableId::Node(NodeId {
            trajectory: 0,
            index,
        })
    }

    /// A chain 0 - 1 - ... - (n-1) of odometry constraints.
    fn chain(n: u32) -> PoseGraph {
        let mut graph = PoseGraph::new();
        for i in 0..n {
            graph
                .add_variable(node(i), rigid2(f64::from(i), 0.0, 0.0))
                .unwrap();
        }
        for i in 1..n {
            graph
                .add_constraint(Constraint {
                    kind: ConstraintKind::Odometry,
                    from: node(i - 1),
                    to: node(i),
                    from_from_to: rigid2(1.0, 0.0, 0.0),
                    information: Matrix3::identity(),
                    loss: RobustLoss::Trivial,
                })
                .unwrap();
        }
        graph
    }

    /// Breadth-first distance by brute force: all-pairs relaxation over the constraint list.
    fn brute_force(graph: &PoseGraph, seeds: &[VariableId], hops: usize) -> BTreeSet<VariableId> {
        let mut region: BTreeSet<VariableId> = seeds.iter().copied().collect();
        for _ in 0..hops {
            let mut grown = region.clone();
            for (_, c) in graph.constraints() {
                if region.contains(&c.from) {
                    grown.insert(c.to);
                }
                if region.contains(&c.to) {
                    grown.insert(c.from);
                }
            }
            region = grown;
        }
        region
    }

    #[test]
    fn the_region_is_the_seeds_and_their_neighbourhood() {
        let mut graph = chain(20);
        // A loop closure 2 - 15.
        graph
            .add_constraint(Constraint {
                kind: ConstraintKind::NodeToSubmapInter,
                from: node(2),
                to: node(15),
                from_from_to: rigid2(13.0, 0.0, 0.0),
                information: Matrix3::identity(),
                loss: RobustLoss::Trivial,
            })
            .unwrap();
        for (seeds, hops) in [
            (vec![node(5)], 0),
            (vec![node(5)], 2),
            (vec![node(3)], 1),
            (vec![node(0), node(19)], 3),
            (vec![node(2)], 1),
        ] {
            assert_eq!(
                optimization_region(&graph, seeds.iter().copied(), hops),
                brute_force(&graph, &seeds, hops),
                "seeds {seeds:?}, {hops} hops"
            );
        }
        let region = optimization_region(&graph, [node(2)], 1);
        assert!(region.contains(&node(15)), "the closure is one hop");
        assert_eq!(region.len(), 4);
    }

    #[test]
    fn unknown_seeds_are_left_out() {
        let graph = chain(3);
        assert!(optimization_region(&graph, [node(7)], 2).is_empty());
    }
}
