//! Submaps bent along a confirmed correction's drift path.
//!
//! The graph holds each submap rigid, yet LLO built it while drifting. When matches far from their
//! estimates are confirmed by agreement (a correction), the drift they correct accumulated along the path
//! the trajectory drove since it was last known to be right (`drift_path`): the submaps LLO built there
//! are the ones likely bent. Their nodes are then held to them more loosely the farther along the submap
//! they are (`GlobalSlamOptions::bent_submap_translation_sigma_per_m` and `…_rotation_…`), so the
//! optimization spreads the correction along the path instead of breaking it at a submap's edge. With
//! `bend_drift_rate_multiple` > 0 each bend loosens them by the drift rate its own correction measured
//! ([`BendGrowth`], stored with the bend), up to those rates.
//!
//! Growth everywhere (`intra_submap_translation_sigma_per_m`) loosens every submap for a drift that most
//! never had; here the loosening is granted by evidence and lasts as long as the evidence does: while at
//! least one match of a correction that bent a submap is in the graph. Once all of them are retracted (by
//! the optimized graph or by the correction's probation) or forgotten, the submap is held as before.
//! What is bent is rebuilt from the bends and the closures' states, so a checkpoint stores only the bends.

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::Matrix3;

use super::{Acceptance, ClosureState, GlobalSlam, closure_refs, information};
use crate::global_slam::{GlobalSlamOptions, LoopClosure};
use crate::metrics::median;
use crate::pose_graph::{ConstraintId, ConstraintKind, NodeId, SubmapId, VariableId};

/// The submaps a confirmed correction bent, and the matches that grant it.
#[derive(Clone, Debug, PartialEq)]
pub struct SubmapBend {
    /// The correction's matches, by node and submap.
    pub closures: Vec<(NodeId, SubmapId)>,
    /// The submaps of the corrected trajectory LLO built along the drift path, the matched ones excluded.
    pub submaps: Vec<SubmapId>,
    /// The growth this bend grants (translation σ in m per m of path, rotation σ in rad per m; see
    /// [`GlobalSlamOptions::bend_drift_rate_multiple`]).
    pub growth: BendGrowth,
}

/// How fast a bent submap's node-to-submap σ grows with the path from its first node.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BendGrowth {
    /// Translation σ growth (m per m of path).
    pub translation_per_m: f64,
    /// Rotation σ growth (rad per m of path).
    pub rotation_per_m: f64,
}

impl BendGrowth {
    fn max(self, other: Self) -> Self {
        Self {
            translation_per_m: self.translation_per_m.max(other.translation_per_m),
            rotation_per_m: self.rotation_per_m.max(other.rotation_per_m),
        }
    }
}

/// The information of a node's pose in a submap it was inserted `span_m` (m of path) after the submap's
/// first node: the standard deviations grow with the span, faster in a bent submap.
pub(super) fn intra_submap_information(
    options: &GlobalSlamOptions,
    bend: Option<BendGrowth>,
    span_m: f64,
) -> Matrix3<f64> {
    let (per_m_translation, per_m_rotation) = match bend {
        Some(growth) => (growth.translation_per_m, growth.rotation_per_m),
        None => (
            options.intra_submap_translation_sigma_per_m,
            options.intra_submap_rotation_sigma_per_m,
        ),
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

/// The growth at the options' fixed rates (`bent_submap_*_sigma_per_m`): every bend's with
/// `bend_drift_rate_multiple` 0, the cap of each otherwise.
pub(super) fn fixed_growth(options: &GlobalSlamOptions) -> BendGrowth {
    BendGrowth {
        translation_per_m: options.bent_submap_translation_sigma_per_m,
        rotation_per_m: options.bent_submap_rotation_sigma_per_m,
    }
}

impl GlobalSlam {
    /// The submaps whose node-to-submap constraints GLM may still rewrite (a bend changes their
    /// information), so whoever edits the graph must leave those constraints as LLO made them: none with
    /// bends off; with bends on, every submap of a trajectory not settled but `settling` (about to be: it
    /// gets no node, so no bend, any more; GLM grants none to a settled trajectory) and every submap a
    /// recorded bend in [`Self::submap_bends`] names (retracting its matches unbends it).
    pub fn intra_submap_rewritable(&self, settling: u32) -> BTreeSet<SubmapId> {
        if !self.bends_enabled() {
            return BTreeSet::new();
        }
        let named: BTreeSet<SubmapId> = self
            .submap_bends
            .iter()
            .flat_map(|bend| bend.submaps.iter().copied())
            .collect();
        self.submaps
            .keys()
            .filter(|sid| {
                let over = sid.trajectory == settling || self.settled.contains(&sid.trajectory);
                !over || named.contains(sid)
            })
            .copied()
            .collect()
    }

    fn bends_enabled(&self) -> bool {
        self.options.bent_submap_translation_sigma_per_m > 0.0
            || self.options.bent_submap_rotation_sigma_per_m > 0.0
    }

    /// Records the bend a group of matches confirmed by agreement grants: the submaps of the corrected
    /// trajectory with a node on the group's drift path (from the newest match's node back by
    /// `drift_path`), except the matched ones and those up to the newest matched submap of the same
    /// trajectory (the map the correction was made against). Takes effect at [`Self::sync_bends`], once
    /// the matches are in the graph.
    ///
    /// Only the group's matches against the corrected trajectory's own submaps are evidence of a bend: two
    /// visits of one trajectory that disagree measure the drift LLO accumulated between them. A match
    /// against another trajectory's submap measures where this trajectory sits in that one's frame as
    /// well, which is not LLO's drift (a session being placed on the site's map); it grants nothing.
    /// Neither does a correction of a settled trajectory: its route is over, and the node-to-submap
    /// constraints of its submaps no bend names are final (a lifelong map sums trees' edges into them).
    pub(super) fn bend_along_drift<'a>(
        &mut self,
        group: impl Iterator<Item = &'a (LoopClosure, Acceptance)>,
    ) {
        if !self.bends_enabled() {
            return;
        }
        let group: Vec<&(LoopClosure, Acceptance)> = group
            .filter(|(c, _)| c.submap.trajectory == c.node.trajectory)
            .collect();
        let Some((newest, _)) = group.iter().max_by_key(|(c, _)| c.node) else {
            return;
        };
        let trajectory = newest.node.trajectory;
        if self.settled.contains(&trajectory) {
            return;
        }
        let (Some(record), Some(submap)) = (
            self.nodes.get(&newest.node),
            self.submaps.get(&newest.submap),
        ) else {
            return;
        };
        let to_path = record.path_m;
        let drift_path = self.drift_path(newest.node, record, newest.submap, submap);
        let from_path = to_path - drift_path;
        let growth = self.bend_growth(group.iter().map(|(_, a)| a), drift_path);
        let matched: BTreeSet<SubmapId> = group.iter().map(|(c, _)| c.submap).collect();
        let old_submaps_to = group
            .iter()
            .filter(|(c, _)| c.submap.trajectory == trajectory)
            .map(|(c, _)| c.submap.index)
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
                closures: group.iter().map(|(c, _)| (c.node, c.submap)).collect(),
                submaps,
                growth,
            });
        }
    }

    /// The growth a correction grants: the options' `bent_submap_*_sigma_per_m`, or with
    /// `bend_drift_rate_multiple` m > 0 the drift rate the correction measured (the median innovation of its
    /// matches over the drift path, at least 1 m; the median, so that one wrong match among agreeing ones
    /// does not set it) times m, capped by them.
    fn bend_growth<'a>(
        &self,
        acceptances: impl Iterator<Item = &'a Acceptance>,
        drift_path_m: f64,
    ) -> BendGrowth {
        let cap = fixed_growth(&self.options);
        let multiple = self.options.bend_drift_rate_multiple;
        if multiple <= 0.0 {
            return cap;
        }
        let (translations, rotations): (Vec<f64>, Vec<f64>) = acceptances
            .map(|a| (a.innovation_translation_m, a.innovation_rotation_rad))
            .unzip();
        let rate = |innovations: Vec<f64>, cap: f64| {
            (multiple * median(&innovations) / drift_path_m.max(1.0)).min(cap)
        };
        BendGrowth {
            translation_per_m: rate(translations, cap.translation_per_m),
            rotation_per_m: rate(rotations, cap.rotation_per_m),
        }
    }

    /// The submaps a bend holds loosely now, with the fastest growth a bend grants them: those of bends
    /// with at least one match in the graph.
    pub(super) fn bent_by_evidence(&self) -> BTreeMap<SubmapId, BendGrowth> {
        let mut bent = BTreeMap::new();
        if self.submap_bends.is_empty() {
            return bent;
        }
        let in_graph: BTreeSet<(NodeId, SubmapId)> = self
            .accepted_loop_closures
            .iter()
            .zip(&self.closure_states)
            .filter(|(_, state)| matches!(state, ClosureState::InGraph(_)))
            .map(|(c, _)| (c.node, c.submap))
            .collect();
        for bend in self
            .submap_bends
            .iter()
            .filter(|b| b.closures.iter().any(|c| in_graph.contains(c)))
        {
            for sid in bend
                .submaps
                .iter()
                .filter(|sid| self.submaps.contains_key(sid))
            {
                bent.entry(*sid)
                    .and_modify(|g: &mut BendGrowth| *g = g.max(bend.growth))
                    .or_insert(bend.growth);
            }
        }
        bent
    }

    /// Loosens the node-to-submap constraints of the submaps a bend now holds and tightens again those of
    /// submaps no bend holds any longer (their matches retracted or forgotten). Call after anything that
    /// adds, retracts or forgets closures.
    pub(super) fn sync_bends(&mut self) {
        let wanted = self.bent_by_evidence();
        if wanted == self.bent_submaps {
            return;
        }
        let changed: Vec<(SubmapId, Option<BendGrowth>)> = wanted
            .keys()
            .chain(self.bent_submaps.keys())
            .collect::<BTreeSet<_>>()
            .into_iter()
            .filter(|sid| wanted.get(sid) != self.bent_submaps.get(sid))
            .map(|sid| (*sid, wanted.get(sid).copied()))
            .collect();
        for (sid, bend) in changed {
            self.set_intra_submap_information(sid, bend);
        }
        self.bent_submaps = wanted;
    }

    /// Rewrites the information of every node-to-submap constraint LLO gave `sid`, bent or not.
    fn set_intra_submap_information(&mut self, sid: SubmapId, bend: Option<BendGrowth>) {
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
            let information = intra_submap_information(&self.options, bend, span_m);
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
        self.bent_submaps.retain(|sid, _| submaps.contains_key(sid));
    }

    /// The bends confirmed corrections granted (see [`SubmapBend`]).
    pub fn submap_bends(&self) -> &[SubmapBend] {
        &self.submap_bends
    }

    /// The submaps a bend holds loosely now, and how loosely.
    pub fn bent_submaps(&self) -> &BTreeMap<SubmapId, BendGrowth> {
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
        bent_run_settled(retraction_chi2, probation_nodes, false)
    }

    /// [`bent_run`], with trajectory 0 `settled` before the matches come.
    fn bent_run_settled(retraction_chi2: f64, probation_nodes: usize, settled: bool) -> GlobalSlam {
        let mut global = straight_run(171);
        global.options.bent_submap_translation_sigma_per_m = 0.1;
        global.options.bent_submap_rotation_sigma_per_m = 0.01;
        global.options.loop_closure_retraction_chi2 = retraction_chi2;
        global.options.correction_probation_nodes = probation_nodes;
        global.set_trajectory_settled(0, settled);
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
        assert_eq!(
            global.bent_submaps().keys().copied().collect::<Vec<_>>(),
            [submap(1)]
        );
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
    fn a_settled_trajectory_is_granted_no_bend() {
        let global = bent_run_settled(0.0, 20, true);
        assert!(global.submap_bends().is_empty());
        assert!((intra_sigma_x(&global, 160) - 0.5).abs() < 1e-9);
    }

    #[test]
    fn only_a_running_trajectorys_submaps_and_bent_ones_may_be_rewritten() {
        let all: BTreeSet<SubmapId> = straight_run(171).submaps().keys().copied().collect();
        assert_eq!(all, BTreeSet::from([submap(0), submap(1)]));
        // Bends off: GLM rewrites nothing.
        let mut unbent = straight_run(171);
        unbent.options.bent_submap_translation_sigma_per_m = 0.0;
        unbent.options.bent_submap_rotation_sigma_per_m = 0.0;
        assert!(unbent.intra_submap_rewritable(1).is_empty());
        // Running: every submap; settling or settled: only the submap the bend names.
        let mut global = bent_run(0.0, 20);
        assert_eq!(global.intra_submap_rewritable(1), all);
        let bent = BTreeSet::from([submap(1)]);
        assert_eq!(global.intra_submap_rewritable(0), bent);
        global.set_trajectory_settled(0, true);
        assert_eq!(global.intra_submap_rewritable(1), bent);
        // Settled with no bend: none.
        let settled = bent_run_settled(0.0, 20, true);
        assert!(settled.intra_submap_rewritable(1).is_empty());
    }

    /// [`straight_run`] to node 170 with bends capped at 0.1 m/m and 0.01 rad/m growing at `multiple`
    /// times the drift rate of the correction nodes 160 and 170 confirm (0.6 m from their estimates).
    fn rate_bent_run(multiple: f64) -> GlobalSlam {
        let mut global = straight_run(171);
        global.options.bent_submap_translation_sigma_per_m = 0.1;
        global.options.bent_submap_rotation_sigma_per_m = 0.01;
        global.options.bend_drift_rate_multiple = multiple;
        global.options.loop_closure_retraction_chi2 = 0.0;
        global.add_search_results([wide_closure(160, drift())]);
        global.add_search_results([wide_closure(170, drift() * rigid2(0.02, 0.01, 0.002))]);
        global
    }

    #[test]
    fn a_bend_at_its_corrections_drift_rate_grows_by_what_the_correction_measured() {
        // The correction moves node 160 by 0.6 m (and hardly turns it): the bend grows at m · 0.6 m over the
        // drift path, below the cap, and the node is held by that growth.
        let global = rate_bent_run(2.0);
        let growth = global.submap_bends()[0].growth;
        assert!(
            growth.translation_per_m > 0.0 && growth.translation_per_m < 0.1,
            "{growth:?}"
        );
        assert!(growth.rotation_per_m < 0.01, "{growth:?}");
        assert_eq!(global.bent_submaps().get(&submap(1)), Some(&growth));
        let expected = 0.5f64.hypot(growth.translation_per_m * 29.8);
        assert!((intra_sigma_x(&global, 160) - expected).abs() < 1e-9);
        // Twice the multiple, twice the growth (nothing capped here).
        let twice = rate_bent_run(4.0).submap_bends()[0].growth;
        assert!((twice.translation_per_m - 2.0 * growth.translation_per_m).abs() < 1e-12);
    }

    #[test]
    fn a_correction_against_another_trajectory_bends_nothing() {
        // Trajectory 1 placed beside the map, then two of its nodes 2 m apart confirm a correction 0.6 m
        // from their estimates against trajectory 0's submap 0: where trajectory 1 sits in the map, not a
        // drift of its own submaps.
        use super::super::tests::{drive_second_trajectory, placed_second_trajectory};
        let mut global = placed_second_trajectory();
        global.options.bent_submap_translation_sigma_per_m = 0.1;
        global.options.bent_submap_rotation_sigma_per_m = 0.01;
        global.options.loop_closure_retraction_chi2 = 0.0;
        drive_second_trajectory(&mut global, 250..300);
        let across = |node: u32, error: Rigid2| LoopClosure {
            node: NodeId {
                trajectory: 1,
                index: node,
            },
            submap_from_node: rigid2(-48.0 + 0.2 * f64::from(node), 0.0, 0.0) * error,
            ..wide_closure(node, error)
        };
        global.add_search_results([across(280, drift())]);
        global.add_search_results([across(290, drift() * rigid2(0.02, 0.01, 0.002))]);
        let confirmed = global
            .accepted_loop_closures
            .iter()
            .zip(&global.closure_states)
            .filter(|(c, state)| {
                c.node.trajectory == 1 && matches!(state, ClosureState::InGraph(_))
            })
            .count();
        assert_eq!(confirmed, 2);
        assert!(global.submap_bends().is_empty() && global.bent_submaps().is_empty());
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
    fn a_bend_from_a_checkpoint_without_its_growth_grows_at_the_fixed_rates() {
        let global = bent_run(0.0, 20);
        let mut older = global.to_state();
        older.submap_bends[0].growth = BendGrowth::default();
        let mut restored = GlobalSlam::from_state(global.options.clone(), older).expect("restored");
        assert_eq!(
            restored.submap_bends()[0].growth,
            BendGrowth {
                translation_per_m: 0.1,
                rotation_per_m: 0.01
            }
        );
        // Nodes inserted after the restore are held as loosely as before it.
        super::super::tests::drive_on(&mut restored, 171..181);
        let expected = 0.5f64.hypot(0.1 * 33.8);
        assert!((intra_sigma_x(&restored, 180) - expected).abs() < 1e-9);
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
