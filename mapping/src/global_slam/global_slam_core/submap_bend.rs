//! Submaps bent along a confirmed correction's drift path.
//!
//! The graph holds each submap rigid, yet LLO built it while drifting. When matches far from their
//! estimates are confirmed by agreement (a correction), the drift they correct accumulated along the path
//! the trajectory drove since it was last known to be right (`drift_path`): the submaps LLO built there
//! are the ones likely bent. Their nodes are then held to them more loosely the farther along the submap
//! they are (`GlobalSlamOptions::bent_submap_translation_sigma_per_m` and `…_rotation_…`), so the
//! optimization spreads the correction along the path instead of breaking it at a submap's edge.
//!
//! Growth everywhere (`intra_submap_translation_sigma_per_m`) loosens every submap for a drift that most
//! never had; here the loosening is granted by evidence and lasts as long as the evidence does: while at
//! least one match of a correction that bent a submap is in the graph. Once all of them are retracted (by
//! the optimized graph or by the correction's probation) or forgotten, the submap is held as before.
//! What is bent is rebuilt from the bends and the closures' states, so a checkpoint stores only the bends.

use std::collections::BTreeSet;

use nalgebra::Matrix3;

use super::{ClosureState, GlobalSlam, closure_refs, information};
use crate::global_slam::{GlobalSlamOptions, LoopClosure};
use crate::pose_graph::{ConstraintId, ConstraintKind, NodeId, SubmapId, VariableId};

/// The submaps a confirmed correction bent, and the matches that grant it.
#[derive(Clone, Debug, PartialEq)]
pub struct SubmapBend {
    /// The correction's matches, by node and submap.
    pub closures: Vec<(NodeId, SubmapId)>,
    /// The submaps of the corrected trajectory LLO built along the drift path, the matched ones excluded.
    pub submaps: Vec<SubmapId>,
}

/// The information of a node's pose in a submap it was inserted `span_m` (m of path) after the submap's
/// first node: the standard deviations grow with the span, faster in a bent submap.
pub(super) fn intra_submap_information(
    options: &GlobalSlamOptions,
    bent: bool,
    span_m: f64,
) -> Matrix3<f64> {
    let (per_m_translation, per_m_rotation) = if bent {
        (
            options.bent_submap_translation_sigma_per_m,
            options.bent_submap_rotation_sigma_per_m,
        )
    } else {
        (
            options.intra_submap_translation_sigma_per_m,
            options.intra_submap_rotation_sigma_per_m,
        )
    };
    information(
        options
            .intra_submap_translation_sigma
            .hypot(per_m_translation * span_m),
        options
            .intra_submap_rotation_sigma
            .hypot(per_m_rotation * span_m),
    )
}

impl GlobalSlam {
    fn bends_enabled(&self) -> bool {
        self.options.bent_submap_translation_sigma_per_m > 0.0
            || self.options.bent_submap_rotation_sigma_per_m > 0.0
    }

    /// Records the bend a group of matches confirmed by agreement grants: the submaps of the corrected
    /// trajectory with a node on the group's drift path (from the newest match's node back by
    /// `drift_path`), except the matched ones and those up to the newest matched submap of the same
    /// trajectory (the map the correction was made against). Takes effect at [`Self::sync_bends`], once
    /// the matches are in the graph.
    pub(super) fn bend_along_drift<'a>(&mut self, group: impl Iterator<Item = &'a LoopClosure>) {
        if !self.bends_enabled() {
            return;
        }
        let group: Vec<&LoopClosure> = group.collect();
        let Some(newest) = group.iter().max_by_key(|c| c.node) else {
            return;
        };
        let trajectory = newest.node.trajectory;
        let (Some(record), Some(submap)) = (
            self.nodes.get(&newest.node),
            self.submaps.get(&newest.submap),
        ) else {
            return;
        };
        let to_path = record.path_m;
        let from_path = to_path - self.drift_path(newest.node, record, newest.submap, submap);
        let matched: BTreeSet<SubmapId> = group.iter().map(|c| c.submap).collect();
        let old_submaps_to = group
            .iter()
            .filter(|c| c.submap.trajectory == trajectory)
            .map(|c| c.submap.index)
            .max();
        let submaps: Vec<SubmapId> = self
            .submaps
            .iter()
            .filter(|(sid, s)| {
                sid.trajectory == trajectory
                    && !matched.contains(sid)
                    && old_submaps_to.is_none_or(|old| sid.index > old)
                    && s.nodes.iter().any(|n| {
                        self.nodes
                            .get(n)
                            .is_some_and(|r| (from_path..=to_path).contains(&r.path_m))
                    })
            })
            .map(|(sid, _)| *sid)
            .collect();
        if !submaps.is_empty() {
            self.submap_bends.push(SubmapBend {
                closures: group.iter().map(|c| (c.node, c.submap)).collect(),
                submaps,
            });
        }
    }

    /// The submaps a bend holds loosely now: those of bends with at least one match in the graph.
    pub(super) fn bent_by_evidence(&self) -> BTreeSet<SubmapId> {
        if self.submap_bends.is_empty() {
            return BTreeSet::new();
        }
        let in_graph: BTreeSet<(NodeId, SubmapId)> = self
            .accepted_loop_closures
            .iter()
            .zip(&self.closure_states)
            .filter(|(_, state)| matches!(state, ClosureState::InGraph(_)))
            .map(|(c, _)| (c.node, c.submap))
            .collect();
        self.submap_bends
            .iter()
            .filter(|b| b.closures.iter().any(|c| in_graph.contains(c)))
            .flat_map(|b| b.submaps.iter().copied())
            .filter(|sid| self.submaps.contains_key(sid))
            .collect()
    }

    /// Loosens the node-to-submap constraints of the submaps a bend now holds and tightens again those of
    /// submaps no bend holds any longer (their matches retracted or forgotten). Call after anything that
    /// adds, retracts or forgets closures.
    pub(super) fn sync_bends(&mut self) {
        let wanted = self.bent_by_evidence();
        if wanted == self.bent_submaps {
            return;
        }
        let flipped: Vec<(SubmapId, bool)> = wanted
            .symmetric_difference(&self.bent_submaps)
            .map(|sid| (*sid, wanted.contains(sid)))
            .collect();
        for (sid, bent) in flipped {
            self.set_intra_submap_information(sid, bent);
        }
        self.bent_submaps = wanted;
    }

    /// Rewrites the information of every node-to-submap constraint LLO gave `sid`, bent or not.
    fn set_intra_submap_information(&mut self, sid: SubmapId, bent: bool) {
        let Some(first_path) = self.submaps.get(&sid).and_then(|s| {
            s.nodes
                .first()
                .and_then(|n| self.nodes.get(n))
                .map(|r| r.path_m)
        }) else {
            return;
        };
        let ids: Vec<ConstraintId> = self
            .graph
            .constraints_of(VariableId::Submap(sid))
            .iter()
            .copied()
            .filter(|id| {
                self.graph
                    .constraint(*id)
                    .is_some_and(|c| c.kind == ConstraintKind::NodeToSubmapIntra)
            })
            .collect();
        for id in ids {
            let Some(VariableId::Node(node)) = self.graph.constraint(id).map(|c| c.to) else {
                continue;
            };
            let span_m = self
                .nodes
                .get(&node)
                .map_or(0.0, |r| (r.path_m - first_path).abs());
            let information = intra_submap_information(&self.options, bent, span_m);
            if self.graph.set_information(id, information).is_ok() {
                self.changed
                    .extend([VariableId::Submap(sid), VariableId::Node(node)]);
            }
        }
    }

    /// Drops what forgotten closures and submaps leave of the bends (a bend with no match left grants
    /// nothing).
    pub(super) fn forget_bends(&mut self) {
        let known = closure_refs(&self.accepted_loop_closures);
        let submaps = &self.submaps;
        self.submap_bends.retain_mut(|b| {
            b.closures.retain(|c| known.contains(c));
            b.submaps.retain(|sid| submaps.contains_key(sid));
            !b.closures.is_empty() && !b.submaps.is_empty()
        });
        self.bent_submaps.retain(|sid| submaps.contains_key(sid));
    }

    /// The bends confirmed corrections granted (see [`SubmapBend`]).
    pub fn submap_bends(&self) -> &[SubmapBend] {
        &self.submap_bends
    }

    /// The submaps a bend holds loosely now.
    pub fn bent_submaps(&self) -> &BTreeSet<SubmapId> {
        &self.bent_submaps
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::{intra_information_x, straight_run, wide_closure};
    use super::*;
    use crate::geometry::{Rigid2, rigid2};

    fn submap(index: u32) -> SubmapId {
        SubmapId {
            trajectory: 0,
            index,
        }
    }

    /// The translation σ (m, x) of node `index`'s constraint to submap 1 of [`straight_run`].
    fn intra_sigma_x(global: &GlobalSlam, index: u32) -> f64 {
        intra_information_x(global, index).sqrt().recip()
    }

    fn drift() -> Rigid2 {
        rigid2(0.48, 0.36, 0.0)
    }

    /// [`straight_run`] to node 170 with bends on (0.1 m/m, 0.01 rad/m), nodes 160 and 170 confirming a
    /// correction 0.6 m from the estimates against submap 0 (see `correction_probation`'s tests);
    /// `retraction_chi2` for the optimization the confirmation triggers.
    fn bent_run(retraction_chi2: f64, probation_nodes: usize) -> GlobalSlam {
        let mut global = straight_run(171);
        global.options.bent_submap_translation_sigma_per_m = 0.1;
        global.options.bent_submap_rotation_sigma_per_m = 0.01;
        global.options.loop_closure_retraction_chi2 = retraction_chi2;
        global.options.correction_probation_nodes = probation_nodes;
        global.add_search_results([wide_closure(140, rigid2(0.05, -0.03, 0.004))]);
        global.add_search_results([wide_closure(160, drift())]);
        global.add_search_results([wide_closure(170, drift() * rigid2(0.02, 0.01, 0.002))]);
        global
    }

    #[test]
    fn a_confirmed_correction_bends_the_submaps_along_its_drift_path() {
        let mut global = bent_run(0.0, 20);
        // Submap 1 (nodes 11..) lies on the drift path; submap 0, the matched one, stays rigid.
        assert_eq!(global.submap_bends().len(), 1);
        assert_eq!(global.submap_bends()[0].submaps, [submap(1)]);
        assert_eq!(global.bent_submaps(), &BTreeSet::from([submap(1)]));
        // Node 160 is 29.8 m of path along submap 1: σ = √(0.5² + (0.1·29.8)²).
        let expected = 0.5f64.hypot(0.1 * 29.8);
        assert!((intra_sigma_x(&global, 160) - expected).abs() < 1e-9);
        assert!((intra_sigma_x(&global, 11) - 0.5).abs() < 1e-9);
        // Later nodes in a bent submap are held as loosely.
        super::super::tests::drive_on(&mut global, 171..181);
        let expected = 0.5f64.hypot(0.1 * 33.8);
        assert!((intra_sigma_x(&global, 180) - expected).abs() < 1e-9);
    }

    #[test]
    fn without_the_option_nothing_bends() {
        let mut global = straight_run(171);
        global.options.loop_closure_retraction_chi2 = 0.0;
        global.options.bent_submap_translation_sigma_per_m = 0.0;
        global.options.bent_submap_rotation_sigma_per_m = 0.0;
        global.add_search_results([wide_closure(160, drift())]);
        global.add_search_results([wide_closure(170, drift() * rigid2(0.02, 0.01, 0.002))]);
        assert!(global.submap_bends().is_empty() && global.bent_submaps().is_empty());
        assert!((intra_sigma_x(&global, 160) - 0.5).abs() < 1e-9);
    }

    #[test]
    fn a_bend_ends_when_its_correction_is_retracted() {
        // No probation and a retraction so strict that the optimized graph refuses the correction at once:
        // its matches are out, so the submap is held as before (the bend is remembered, granting nothing).
        let global = bent_run(1e-9, 0);
        assert_eq!(global.submap_bends().len(), 1);
        assert!(global.bent_submaps().is_empty());
        assert!((intra_sigma_x(&global, 160) - 0.5).abs() < 1e-9);
        // Refused by the probation: two later nodes match where the trajectory was before the correction.
        let mut global = bent_run(0.0, 20);
        super::super::tests::drive_on(&mut global, 171..180);
        assert!(!global.bent_submaps().is_empty());
        global.add_search_results([wide_closure(175, Rigid2::identity())]);
        global.add_search_results([wide_closure(178, rigid2(0.01, 0.0, 0.0))]);
        assert!(global.bent_submaps().is_empty());
        assert!((intra_sigma_x(&global, 170) - 0.5).abs() < 1e-9);
        assert!((intra_sigma_x(&global, 179) - 0.5).abs() < 1e-9);
    }

    #[test]
    fn what_is_bent_is_rebuilt_from_a_state_and_forgotten_with_its_matches() {
        let global = bent_run(0.0, 20);
        let restored =
            GlobalSlam::from_state(global.options.clone(), global.to_state()).expect("restored");
        assert_eq!(restored.bent_submaps(), global.bent_submaps());
        assert_eq!(restored.to_state(), global.to_state());
        // Forgetting the matched submap forgets the matches, and with them the bend.
        let mut global = global;
        global
            .graph_mut()
            .remove_variable(VariableId::Submap(submap(0)))
            .expect("removed");
        global.forget(&[submap(0)], &[]);
        assert!(global.submap_bends().is_empty() && global.bent_submaps().is_empty());
        assert!((intra_sigma_x(&global, 160) - 0.5).abs() < 1e-9);
    }
}
