//! What GLM does with a search's matches: outvoted by the node's other matches, gated by the drift LLO
//! can explain, held until another match agrees, and added to the graph as robust constraints.

use std::collections::BTreeSet;

use super::{
    Acceptance, ClosureState, GlobalSlam, GlobalSlamEvent, MatchDecided, MatchDecision, information,
};
use crate::geometry::Rigid2;
use crate::global_slam::LoopClosure;
use crate::global_slam::constraint_builder::weak_axis;
use crate::pose_graph::{Constraint, ConstraintKind, NodeId, RobustLoss, SubmapId, VariableId};

/// The cycle of two matches (see [`GlobalSlam::match_cycle`]).
struct MatchCycle {
    /// The cycle's translation (m) in the first match's node frame.
    translation: nalgebra::Vector2<f64>,
    /// The cycle's rotation (rad).
    rotation: f64,
    /// The path (m) driven between the two nodes.
    path_m: f64,
}

/// `agreeing` pending matches and the `closure` that confirmed them, all marked confirmed by agreement.
fn confirmed(
    agreeing: Vec<(LoopClosure, Acceptance)>,
    closure: LoopClosure,
    acceptance: Acceptance,
) -> impl Iterator<Item = (LoopClosure, Acceptance)> {
    agreeing
        .into_iter()
        .chain([(closure, acceptance)])
        .map(|(c, a)| {
            (
                c,
                Acceptance {
                    confirmed_by_agreement: true,
                    ..a
                },
            )
        })
}

impl GlobalSlam {
    /// Whether a match moves its node farther from its estimate than drift can explain: more than
    /// `max_innovation_translation` plus `linear_window_growth` per metre of drift path, or more than
    /// `max_innovation_rotation` plus `angular_window_growth` per metre (see [`Self::drift_path`]).
    /// Trajectories not yet placed, and matches of unknown nodes or submaps, are never gated.
    fn beyond_drift(&self, closure: &LoopClosure, acceptance: &Acceptance) -> bool {
        if self.unanchored.contains(&closure.node.trajectory) {
            return false;
        }
        let (Some(record), Some(submap)) = (
            self.nodes.get(&closure.node),
            self.submaps.get(&closure.submap),
        ) else {
            return false;
        };
        let cb = &self.options.constraint_builder;
        let drift_path = self.drift_path(closure.node, record, closure.submap, submap);
        let (doubt_rad, doubt_m) =
            self.recovery_doubt(closure.node, record, closure.submap, submap);
        acceptance.innovation_translation_m
            > cb.max_innovation_translation + cb.linear_window_growth * drift_path + doubt_m
            || acceptance.innovation_rotation_rad
                > cb.max_innovation_rotation + cb.angular_window_growth * drift_path + doubt_rad
    }

    /// A confirmed group (the `agreeing` pending matches and the `closure` that confirmed them), marked
    /// confirmed by agreement, its correction put on probation and the submaps along its drift bent.
    fn confirm_group(
        &mut self,
        agreeing: Vec<(LoopClosure, Acceptance)>,
        closure: LoopClosure,
        acceptance: Acceptance,
    ) -> Vec<(LoopClosure, Acceptance)> {
        let group: Vec<(LoopClosure, Acceptance)> =
            confirmed(agreeing, closure, acceptance).collect();
        self.start_probation(group.iter().map(|(c, _)| c));
        self.bend_along_drift(group.iter());
        group
    }

    /// Adds accepted loop closures as robust node-to-submap constraints, then optimizes if
    /// `optimize_every_n_nodes` nodes arrived since the last optimization.
    pub fn add_search_results(
        &mut self,
        results: impl IntoIterator<Item = LoopClosure>,
    ) -> Vec<GlobalSlamEvent> {
        let mut events = Vec::new();
        let cb = &self.options.constraint_builder;
        let loop_closure_information = information(
            cb.loop_closure_translation_sigma,
            cb.loop_closure_rotation_sigma,
        );
        let loss = RobustLoss::Huber {
            delta: cb.huber_scale,
        };
        let results: Vec<LoopClosure> = results.into_iter().collect();
        let outvoted = self.outvoted(&results);
        let mut accepted: Vec<(LoopClosure, Acceptance)> = Vec::new();
        let mut confirmed_any = false;
        let mut decided =
            |closure: &LoopClosure, acceptance: Acceptance, innovation: Rigid2, decision| {
                events.push(GlobalSlamEvent::MatchDecided(MatchDecided {
                    closure: closure.clone(),
                    acceptance,
                    innovation,
                    decision,
                }));
            };
        for (closure, outvoted) in results.into_iter().zip(outvoted) {
            self.judge_corrections_by_match(&closure);
            let innovation = self.innovation(&closure);
            let acceptance = Acceptance::of_innovation(innovation.as_ref());
            let innovation = innovation.unwrap_or_else(Rigid2::identity);
            if outvoted {
                self.closures_outvoted += 1;
                decided(&closure, acceptance, innovation, MatchDecision::Outvoted);
                continue;
            }
            if !self.nodes.contains_key(&closure.node)
                || !self.submaps.contains_key(&closure.submap)
            {
                continue;
            }
            if closure.node.trajectory != closure.submap.trajectory
                && self.unanchored.contains(&closure.submap.trajectory)
            {
                continue; // never queued: an unplaced submap says nothing about placed nodes yet
            }
            if self.beyond_drift(&closure, &acceptance) {
                if self.fitted_by_placement(closure.node, closure.submap) {
                    // Its placement vouches for the LLO it would repair: no chorus confirms it.
                    decided(
                        &closure,
                        acceptance,
                        innovation,
                        MatchDecision::RefusedByPlacement,
                    );
                    self.closures_beyond_drift += 1;
                    continue;
                }
                // A sudden LLO slip also moves a node farther than drift explains: its repair waits for
                // several nodes' matches against more than one submap to agree on it.
                let mut agreeing = self.take_agreeing(&closure, true);
                let nodes: BTreeSet<NodeId> = agreeing
                    .iter()
                    .map(|(c, _)| c.node)
                    .chain([closure.node])
                    .collect();
                let submaps: BTreeSet<SubmapId> = agreeing
                    .iter()
                    .map(|(c, _)| c.submap)
                    .chain([closure.submap])
                    .collect();
                let needed = self.options.constraint_builder.beyond_drift_confirmations;
                if needed == 0 || nodes.len() < needed || submaps.len() < 2 {
                    decided(
                        &closure,
                        acceptance,
                        innovation,
                        MatchDecision::HeldBeyondDrift,
                    );
                    self.pending_beyond_drift.append(&mut agreeing);
                    self.pending_beyond_drift.push((closure, acceptance));
                    self.closures_beyond_drift += 1;
                    continue;
                }
                decided(
                    &closure,
                    acceptance,
                    innovation,
                    MatchDecision::ConfirmedBeyondDrift,
                );
                confirmed_any = true;
                self.closures_beyond_drift -= agreeing.len();
                accepted.extend(self.confirm_group(agreeing, closure, acceptance));
                continue;
            }
            if self.needs_confirmation(&closure, &acceptance) {
                let agreeing = self.take_agreeing(&closure, false);
                if agreeing.is_empty() {
                    decided(
                        &closure,
                        acceptance,
                        innovation,
                        MatchDecision::HeldUnconfirmed,
                    );
                    self.pending_unconfirmed.push((closure, acceptance));
                    continue;
                }
                decided(&closure, acceptance, innovation, MatchDecision::Confirmed);
                confirmed_any = true;
                accepted.extend(self.confirm_group(agreeing, closure, acceptance));
                continue;
            }
            decided(&closure, acceptance, innovation, MatchDecision::Accepted);
            accepted.push((closure, acceptance));
        }
        for (closure, acceptance) in accepted {
            if self.unanchored.contains(&closure.node.trajectory)
                && closure.node.trajectory != closure.submap.trajectory
            {
                self.anchor(&closure);
            }
            let added = self.graph.add_constraint(Constraint {
                kind: ConstraintKind::NodeToSubmapInter,
                from: VariableId::Submap(closure.submap),
                to: VariableId::Node(closure.node),
                from_from_to: closure.submap_from_node,
                information: closure.information.unwrap_or(loop_closure_information),
                loss,
            });
            let Ok(constraint_id) = added else {
                continue; // a non-finite match; nothing to learn from it
            };
            self.closure_states
                .push(ClosureState::InGraph(constraint_id));
            self.note_loop(&closure);
            self.accepted_loop_closures.push(closure.clone());
            self.acceptances.push(acceptance);
            self.loop_closures_accepted += 1;
            events.push(GlobalSlamEvent::LoopClosureAdded(closure));
        }
        // The confirmed groups' matches are in the graph now, and probation may have retracted others.
        self.sync_bends();
        let n = self.options.optimize_every_n_nodes;
        if confirmed_any || (n > 0 && self.nodes_since_optimization >= n) {
            // Confirmed matches far from the estimates close a loop that moves much of the trajectory:
            // optimize at once, so that the next nodes are searched near where they really are.
            events.push(GlobalSlamEvent::Optimized(self.optimize()));
        }
        events
    }

    /// Records that `closure` was accepted: if it closes a loop (another trajectory's submap, or one at
    /// least `min_loop_length` back along the path), drift and the search windows grow from its node again.
    fn note_loop(&mut self, closure: &LoopClosure) {
        let Some(node) = self.nodes.get(&closure.node) else {
            return;
        };
        let closes_loop = closure.submap.trajectory != closure.node.trajectory
            || self
                .submaps
                .get(&closure.submap)
                .and_then(|s| s.nodes.first())
                .and_then(|first| self.nodes.get(first))
                .is_some_and(|first| {
                    node.path_m - first.path_m >= self.options.constraint_builder.min_loop_length
                });
        if closes_loop {
            let last = self
                .last_loop_path
                .entry(closure.node.trajectory)
                .or_insert(0.0);
            *last = last.max(node.path_m);
        }
    }

    /// Matches of one node against several submaps must agree on where the node is (within
    /// `agreement_translation` and `agreement_rotation`, through the submaps' current poses). A match with
    /// a rival (another match of its node farther from it than `rival_translation` or `rival_rotation`)
    /// is outvoted when another match of its node has more matches agreeing with it, or when none agrees
    /// with it: two places that fit one scan about equally well cannot both be right, and which one is
    /// wrong is not known.
    fn outvoted(&self, results: &[LoopClosure]) -> Vec<bool> {
        let cb = &self.options.constraint_builder;
        let implied: Vec<Option<Rigid2>> = results
            .iter()
            .map(|c| self.submap_pose(c.submap).map(|s| s * c.submap_from_node))
            .collect();
        let agree = |a: &Rigid2, b: &Rigid2| {
            let d = a.inverse() * b;
            d.translation.vector.norm() <= cb.agreement_translation
                && d.rotation.angle().abs() <= cb.agreement_rotation
        };
        let rivals = |a: &Rigid2, b: &Rigid2| {
            let d = a.inverse() * b;
            d.translation.vector.norm() > cb.rival_translation
                || d.rotation.angle().abs() > cb.rival_rotation
        };
        // Per match: (whether a match of the same node is its rival, matches of the same node agreeing
        // with it, itself included).
        let support: Vec<(bool, usize)> = (0..results.len())
            .map(|i| {
                let Some(pi) = implied[i] else {
                    return (false, 1);
                };
                let mut rivalled = false;
                let mut agreeing = 1;
                for (j, pj) in implied.iter().enumerate() {
                    if j == i || results[j].node != results[i].node {
                        continue;
                    }
                    let Some(pj) = pj else { continue };
                    if agree(&pi, pj) {
                        agreeing += 1;
                    } else if rivals(&pi, pj) {
                        rivalled = true;
                    }
                }
                (rivalled, agreeing)
            })
            .collect();
        (0..results.len())
            .map(|i| {
                let (rivalled, agreeing) = support[i];
                if !rivalled {
                    return false;
                }
                let best = (0..results.len())
                    .filter(|&j| results[j].node == results[i].node)
                    .map(|j| support[j].1)
                    .max()
                    .unwrap_or(agreeing);
                agreeing == 1 || agreeing < best
            })
            .collect()
    }

    /// The match's pose of its node relative to the node's current estimate, in the estimate's frame
    /// (`None` for unknown nodes or submaps).
    fn innovation(&self, closure: &LoopClosure) -> Option<Rigid2> {
        let submap = self.submap_pose(closure.submap)?;
        let node = self.node_pose(closure.node)?;
        Some((submap.inverse() * node).inverse() * closure.submap_from_node)
    }

    /// Whether a match would move its node farther from its current estimate (in the submap's frame) than
    /// `max_unconfirmed_translation` or `max_unconfirmed_rotation`: then it is used only once another
    /// match agrees with it (see [`Self::agree`]). A wrong match (a look-alike place, a corridor's other
    /// end) is almost always far from the estimate; a right one far from it closes a loop after drift,
    /// where a second match soon follows. The match that places an unanchored trajectory is exempt.
    fn needs_confirmation(&self, closure: &LoopClosure, acceptance: &Acceptance) -> bool {
        if self.unanchored.contains(&closure.node.trajectory) {
            return false;
        }
        let cb = &self.options.constraint_builder;
        acceptance.innovation_translation_m > cb.max_unconfirmed_translation
            || acceptance.innovation_rotation_rad > cb.max_unconfirmed_rotation
    }

    /// Removes from the pending unconfirmed matches those that agree with `closure` (see [`Self::agree`]) and
    /// returns them; forgets pending matches too far behind along their trajectory to ever agree.
    fn take_agreeing(
        &mut self,
        closure: &LoopClosure,
        beyond_drift: bool,
    ) -> Vec<(LoopClosure, Acceptance)> {
        let horizon = self.options.constraint_builder.agreement_path_length;
        let newest_path = |trajectory: u32, this: &Self| {
            this.last_node
                .get(&trajectory)
                .and_then(|n| this.nodes.get(n))
                .map_or(0.0, |r| r.path_m)
        };
        let pending = std::mem::take(if beyond_drift {
            &mut self.pending_beyond_drift
        } else {
            &mut self.pending_unconfirmed
        });
        let mut kept = Vec::new();
        let mut agreeing = Vec::new();
        for (p, acceptance) in pending {
            let Some(record) = self.nodes.get(&p.node) else {
                continue;
            };
            if newest_path(p.node.trajectory, self) - record.path_m > horizon
                || !self.submaps.contains_key(&p.submap)
            {
                continue;
            }
            if self.agree(&p, closure) {
                agreeing.push((p, acceptance));
            } else {
                kept.push((p, acceptance));
            }
        }
        if beyond_drift {
            self.pending_beyond_drift = kept;
        } else {
            self.pending_unconfirmed = kept;
        }
        agreeing
    }

    /// The cycle two matches of different nodes of one trajectory close: the relative pose of their nodes
    /// through the two submaps against the one along the trajectory, its translation in `a`'s node frame.
    fn match_cycle(&self, a: &LoopClosure, b: &LoopClosure) -> Option<MatchCycle> {
        if a.node == b.node || a.node.trajectory != b.node.trajectory {
            return None;
        }
        let path_m = (self.nodes.get(&a.node)?.path_m - self.nodes.get(&b.node)?.path_m).abs();
        let through_submaps = (self.submap_pose(a.submap)? * a.submap_from_node).inverse()
            * (self.submap_pose(b.submap)? * b.submap_from_node);
        let along_trajectory = self.node_pose(a.node)?.inverse() * self.node_pose(b.node)?;
        let cycle = along_trajectory.inverse() * through_submaps;
        Some(MatchCycle {
            translation: along_trajectory.rotation * cycle.translation.vector,
            rotation: cycle.rotation.angle(),
            path_m,
        })
    }

    /// Whether two matches of different nodes of one trajectory close a consistent cycle: the relative
    /// pose of their nodes through the two submaps equals the one along the trajectory, within
    /// `agreement_translation` (plus 2 % of the path between them) and `agreement_rotation`.
    pub(super) fn agree(&self, a: &LoopClosure, b: &LoopClosure) -> bool {
        let cb = &self.options.constraint_builder;
        self.match_cycle(a, b).is_some_and(|c| {
            c.path_m <= cb.agreement_path_length
                && c.translation.norm() <= cb.agreement_translation + 0.02 * c.path_m
                && c.rotation.abs() <= cb.agreement_rotation
        })
    }

    /// Whether `a` and `b` disagree only along `a`'s weakly pinned translation direction (a corridor's
    /// axis, see `ConstraintBuilderOptions::degenerate_ratio`): across it and in rotation their cycle is
    /// within the tolerances of [`Self::agree`]. A corridor match cannot testify to a position along its
    /// corridor, so it neither confirms nor disputes one there.
    pub(super) fn disagree_only_along_weak_axis(&self, a: &LoopClosure, b: &LoopClosure) -> bool {
        let cb = &self.options.constraint_builder;
        let Some((_, across)) = a
            .information
            .and_then(|information| weak_axis(&information, cb.degenerate_ratio))
        else {
            return false;
        };
        self.match_cycle(a, b).is_some_and(|c| {
            across.dot(&c.translation).abs() <= cb.agreement_translation + 0.02 * c.path_m
                && c.rotation.abs() <= cb.agreement_rotation
        })
    }
}
