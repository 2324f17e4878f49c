//! A correction on probation: the nodes that come after a confirmed correction judge it by their own
//! matches, before retraction may (see `GlobalSlamOptions::correction_probation_nodes`).
//!
//! A group of matches confirmed by agreement moves its trajectory far from where LLO had it. Whether
//! the graph takes it is not a fair judge at first: an optimization started far from it stops with the
//! trajectory only part of the way there (Huber losses, a function tolerance), and retraction would then
//! take out a right correction (a long drift repaired) as readily as a wrong one (a look-alike place).
//! The route after it is a fair judge: where the correction is right, the next nodes' matches against the
//! map it was made against agree with it (they close a consistent cycle through the correction's newest
//! match, `GlobalSlam::agree`); where it is wrong, they do not. So the group stays in the graph, whatever
//! retraction says, while the trajectory's next nodes judge it: enough agreeing matches keep it for as
//! long as the trajectory runs; as many disagreeing ones with none agreeing retract it at once; no verdict
//! within the nodes allowed ends the probation, and retraction judges it as any closure. When the
//! trajectory is settled (a lifelong session ended), its kept corrections are handed back to retraction
//! too: later sessions reshape the graph around them, and a correction that no longer fits then must be
//! free to leave (kept for good, two slightly wrong ones tore Intel cut into five sessions by 0.2 m).

use std::collections::BTreeSet;

use super::{ClosureState, GlobalSlam, closure_refs};
use crate::global_slam::LoopClosure;
use crate::pose_graph::{NodeId, SubmapId};

/// A confirmed correction being judged by the nodes after it, or kept by them while its trajectory runs.
#[derive(Clone, Debug, PartialEq)]
pub struct CorrectionProbation {
    /// The group's matches, by node and submap.
    pub closures: Vec<(NodeId, SubmapId)>,
    /// The group's newest match (by node): a later match agrees with the correction when it closes a
    /// consistent cycle with it.
    pub newest: LoopClosure,
    /// Nodes of the trajectory up to this index were added before the correction and do not judge it.
    pub after_node: u32,
    /// Submaps of the trajectory up to this index are the map the correction was made against; later ones
    /// follow LLO and say nothing about it.
    pub old_submaps_to: u32,
    /// Later nodes with a match that agrees with the correction.
    pub agreeing: BTreeSet<NodeId>,
    /// Later nodes with a match that disagrees with it.
    pub disagreeing: BTreeSet<NodeId>,
    /// Later nodes added so far (count).
    pub nodes_judging: usize,
    /// Kept: never retracted while its trajectory runs (else still on probation).
    pub kept: bool,
}

impl CorrectionProbation {
    fn trajectory(&self) -> u32 {
        self.newest.node.trajectory
    }
}

impl GlobalSlam {
    /// Puts a group of matches confirmed by agreement on probation (when the options ask for it).
    pub(super) fn start_probation<'a>(&mut self, group: impl Iterator<Item = &'a LoopClosure>) {
        if self.options.correction_probation_nodes == 0 {
            return;
        }
        let group: Vec<&LoopClosure> = group.collect();
        let Some(newest) = group.iter().max_by_key(|c| c.node) else {
            return;
        };
        let trajectory = newest.node.trajectory;
        let Some(last) = self.last_node.get(&trajectory) else {
            return;
        };
        let old_submaps_to = group
            .iter()
            .filter(|c| c.submap.trajectory == trajectory)
            .map(|c| c.submap.index)
            .max()
            .unwrap_or(0);
        self.probations.push(CorrectionProbation {
            closures: group.iter().map(|c| (c.node, c.submap)).collect(),
            newest: (*newest).clone(),
            after_node: last.index,
            old_submaps_to,
            agreeing: BTreeSet::new(),
            disagreeing: BTreeSet::new(),
            nodes_judging: 0,
            kept: false,
        });
    }

    /// Counts a match of a later node for or against the corrections on probation on its trajectory, and
    /// keeps or retracts those it decides.
    pub(super) fn judge_corrections_by_match(&mut self, closure: &LoopClosure) {
        let needed = self.options.correction_probation_matches;
        let horizon = self.options.constraint_builder.agreement_path_length;
        let mut refused: BTreeSet<(NodeId, SubmapId)> = BTreeSet::new();
        let mut probations = std::mem::take(&mut self.probations);
        probations.retain_mut(|p| {
            let trajectory = p.trajectory();
            let judges = !p.kept
                && closure.node.trajectory == trajectory
                && closure.node.index > p.after_node
                && (closure.submap.trajectory != trajectory
                    || closure.submap.index <= p.old_submaps_to);
            let within_reach = match (
                self.nodes.get(&closure.node),
                self.nodes.get(&p.newest.node),
            ) {
                (Some(a), Some(b)) => (a.path_m - b.path_m).abs() <= horizon,
                _ => false,
            };
            if !judges || !within_reach {
                return true;
            }
            if self.agree(closure, &p.newest) {
                p.agreeing.insert(closure.node);
            } else if !self.disagree_only_along_weak_axis(closure, &p.newest) {
                p.disagreeing.insert(closure.node);
            }
            if p.agreeing.len() >= needed {
                p.kept = true;
            } else if p.disagreeing.len() >= needed && p.agreeing.is_empty() {
                refused.extend(p.closures.iter().copied());
                return false;
            }
            true
        });
        self.probations = probations;
        self.retract_at_once(&refused);
    }

    /// Counts a new node towards the corrections on probation on its trajectory: those it takes past
    /// `correction_probation_nodes` undecided end (retraction judges their matches as any).
    pub(super) fn judge_corrections_by_node(&mut self, node: NodeId) {
        let allowed = self.options.correction_probation_nodes;
        self.probations.retain_mut(|p| {
            if p.kept || p.trajectory() != node.trajectory || node.index <= p.after_node {
                return true;
            }
            p.nodes_judging += 1;
            p.nodes_judging < allowed
        });
    }

    /// Takes these closures out of the graph now, as retraction would (put back once the graph fits them).
    fn retract_at_once(&mut self, refused: &BTreeSet<(NodeId, SubmapId)>) {
        if refused.is_empty() {
            return;
        }
        for (closure, state) in self
            .accepted_loop_closures
            .iter()
            .zip(&mut self.closure_states)
        {
            let ClosureState::InGraph(id) = *state else {
                continue;
            };
            if !refused.contains(&(closure.node, closure.submap)) {
                continue;
            }
            if let Some(constraint) = self.graph.constraint(id).cloned()
                && self.graph.remove_constraint(id).is_ok()
            {
                self.changed.extend([constraint.from, constraint.to]);
                *state = ClosureState::Retracted(constraint);
            }
        }
    }

    /// The matches retraction leaves alone: those of corrections on probation or kept.
    pub(super) fn closures_on_probation(&self) -> BTreeSet<(NodeId, SubmapId)> {
        self.probations
            .iter()
            .flat_map(|p| p.closures.iter().copied())
            .collect()
    }

    /// Drops what forgotten nodes and submaps leave of the corrections: a probation whose newest match's
    /// node is gone can no longer be judged (its matches are judged as any), and forgotten matches need
    /// no exemption.
    pub(super) fn forget_probations(&mut self) {
        let known = closure_refs(&self.accepted_loop_closures);
        self.probations.retain_mut(|p| {
            p.closures.retain(|c| known.contains(c));
            !p.closures.is_empty() && (p.kept || self.nodes.contains_key(&p.newest.node))
        });
    }

    /// The corrections on probation or kept (see [`CorrectionProbation`]).
    pub fn correction_probations(&self) -> &[CorrectionProbation] {
        &self.probations
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{drive_on, straight_run, wide_closure};
    use super::*;
    use crate::geometry::{Rigid2, rigid2};
    use nalgebra::Vector2;

    /// A run whose nodes 160 and 170 confirm a correction 0.6 m from the estimates (see
    /// `a_match_far_from_the_estimate_waits_for_another_that_agrees_with_it`), with retraction so strict
    /// that it refuses any closure the graph does not fit exactly.
    fn confirmed_correction(probation_nodes: usize) -> GlobalSlam {
        let mut global = straight_run(171);
        global.options.loop_closure_retraction_chi2 = 1e-9;
        global.options.correction_probation_nodes = probation_nodes;
        global.add_search_results([wide_closure(140, rigid2(0.05, -0.03, 0.004))]);
        global.add_search_results([wide_closure(160, drift())]);
        global.add_search_results([wide_closure(170, drift() * rigid2(0.02, 0.01, 0.002))]);
        global
    }

    fn drift() -> crate::geometry::Rigid2 {
        rigid2(0.48, 0.36, 0.0)
    }

    /// The nodes of the group's closures that are in the graph now.
    fn in_graph(global: &GlobalSlam) -> Vec<u32> {
        global
            .accepted_loop_closures
            .iter()
            .zip(&global.closure_states)
            .filter(|(c, s)| matches!(s, ClosureState::InGraph(_)) && c.node.index >= 160)
            .map(|(c, _)| c.node.index)
            .collect()
    }

    #[test]
    fn a_confirmed_correction_stays_in_the_graph_while_the_nodes_after_it_judge_it() {
        // Without probation, the strict retraction takes the correction out at once.
        let global = confirmed_correction(0);
        assert!(in_graph(&global).is_empty());
        assert!(global.correction_probations().is_empty());
        // On probation, it stays in through the optimization its confirmation triggers.
        let mut global = confirmed_correction(20);
        assert_eq!(in_graph(&global), [160, 170]);
        let probation = &global.correction_probations()[0];
        assert_eq!((probation.after_node, probation.kept), (170, false));
        // Undecided over 20 later nodes, the probation ends and retraction judges it as any closure.
        drive_on(&mut global, 171..190);
        assert_eq!(global.correction_probations().len(), 1);
        drive_on(&mut global, 190..191);
        assert!(global.correction_probations().is_empty());
        global.optimize();
        assert!(in_graph(&global).is_empty());
    }

    #[test]
    fn later_matches_that_agree_keep_a_correction_while_its_trajectory_runs() {
        let mut global = confirmed_correction(20);
        drive_on(&mut global, 171..180);
        global.add_search_results([wide_closure(175, drift() * rigid2(0.01, 0.0, 0.001))]);
        assert!(!global.correction_probations()[0].kept, "one is not enough");
        global.add_search_results([wide_closure(178, drift())]);
        assert!(global.correction_probations()[0].kept);
        // Kept: no number of later nodes or optimizations takes it out.
        drive_on(&mut global, 180..230);
        global.optimize();
        assert_eq!(&in_graph(&global)[..2], [160, 170]);
    }

    #[test]
    fn a_kept_correction_is_judged_as_any_once_its_trajectory_is_settled() {
        let mut global = confirmed_correction(20);
        drive_on(&mut global, 171..180);
        global.add_search_results([wide_closure(175, drift())]);
        global.add_search_results([wide_closure(178, drift())]);
        assert!(global.correction_probations()[0].kept);
        global.set_trajectory_settled(0, true);
        assert!(global.correction_probations().is_empty());
        global.optimize();
        assert!(in_graph(&global).is_empty(), "{:?}", in_graph(&global));
    }

    #[test]
    fn later_matches_that_disagree_retract_a_correction_at_once() {
        let mut global = confirmed_correction(20);
        drive_on(&mut global, 171..180);
        // Two later nodes match where the trajectory was before the correction.
        global.options.loop_closure_retraction_chi2 = 0.0;
        global.add_search_results([wide_closure(175, rigid2(0.0, 0.0, 0.0))]);
        global.add_search_results([wide_closure(178, rigid2(0.01, 0.0, 0.0))]);
        assert!(global.correction_probations().is_empty());
        assert!(
            !in_graph(&global).contains(&160) && !in_graph(&global).contains(&170),
            "{:?}",
            in_graph(&global)
        );
        let retracted: Vec<u32> = global
            .loop_closure_checks()
            .iter()
            .filter(|c| c.retracted && c.closure.node.index >= 160)
            .map(|c| c.closure.node.index)
            .collect();
        assert_eq!(retracted, [160, 170]);
    }

    /// A match of node `node` seen through a corridor: pinned across the direction `along` (unit vector in
    /// the node's frame) 1000 times more than along it.
    fn corridor_closure(node: u32, error: Rigid2, along: Vector2<f64>) -> LoopClosure {
        let across = Vector2::new(-along.y, along.x);
        let translation = along * along.transpose() * 0.1 + across * across.transpose() * 100.0;
        let mut information = nalgebra::Matrix3::zeros();
        information
            .fixed_view_mut::<2, 2>(0, 0)
            .copy_from(&translation);
        information[(2, 2)] = 1000.0;
        LoopClosure {
            information: Some(information),
            ..wide_closure(node, error)
        }
    }

    /// [`confirmed_correction`] judged by two later matches seen through a corridor along `along` that
    /// agree with the correction across x but not along it (0.5 m short).
    fn judged_by_corridor_matches(along: Vector2<f64>) -> GlobalSlam {
        let short = |node| corridor_closure(node, rigid2(0.0, 0.37, 0.002), along);
        let mut global = confirmed_correction(20);
        drive_on(&mut global, 171..180);
        global.options.loop_closure_retraction_chi2 = 0.0;
        global.add_search_results([short(175)]);
        global.add_search_results([short(178)]);
        global
    }

    #[test]
    fn a_corridor_match_does_not_testify_along_its_corridor() {
        // Seen through a corridor along x, they cannot tell where along it the trajectory is.
        let global = judged_by_corridor_matches(Vector2::x());
        let probation = &global.correction_probations()[0];
        assert!(probation.disagreeing.is_empty(), "{probation:?}");
        assert_eq!(&in_graph(&global)[..2], [160, 170]);
        // Seen through a corridor along y, the same offset is across it: they retract the correction.
        let global = judged_by_corridor_matches(Vector2::y());
        assert!(global.correction_probations().is_empty());
        assert!(!in_graph(&global).contains(&160), "{:?}", in_graph(&global));
    }

    #[test]
    fn only_later_nodes_matched_against_the_old_map_judge() {
        let mut global = confirmed_correction(20);
        drive_on(&mut global, 171..180);
        // A node of the group's time, and a later node against the trajectory's own newer submap 1: no
        // evidence either way.
        global.add_search_results([wide_closure(169, rigid2(0.0, 0.0, 0.0))]);
        let newer_submap = LoopClosure {
            submap: SubmapId {
                trajectory: 0,
                index: 1,
            },
            submap_from_node: rigid2(0.2 * 176.0 - 2.2, 0.0, 0.0),
            ..wide_closure(176, rigid2(0.0, 0.0, 0.0))
        };
        global.add_search_results([newer_submap]);
        let probation = &global.correction_probations()[0];
        assert!(probation.agreeing.is_empty() && probation.disagreeing.is_empty());
    }
}
