//! Optimizing the graph: the whole of it or the region around what changed once trajectories are
//! settled, and the loop closures the optimized graph refuses taken out (and put back once it fits them).

use super::{ClosureState, GlobalSlam};
use crate::global_slam::optimization_region;
use crate::pose_graph::{OptimizationSummary, Optimizer, VariableId};

impl GlobalSlam {
    /// Optimizes the graph now (once trajectories are settled, the region `settled_region_hops` draws around
    /// what changed) and updates each trajectory's `global_from_local`.
    pub fn optimize(&mut self) -> OptimizationSummary {
        let held = self.hold_settled();
        let mut summary = self.optimizer.optimize(&mut self.graph);
        self.release(held);
        if self.retract_refused_loop_closures() > 0 {
            // Without the refused closures' pull (and the bends they granted).
            self.sync_bends();
            let held = self.hold_settled();
            summary = self.optimizer.optimize(&mut self.graph);
            self.release(held);
        }
        self.optimized();
        self.nodes_since_optimization = 0;
        self.update_global_from_local();
        summary
    }

    /// Marks a trajectory settled (or not): once any is, optimizations move only the unsettled
    /// trajectories' variables, the endpoints of constraints added or changed since the last
    /// optimization, and what lies within `settled_region_hops` constraints of them, when that is set (see
    /// [`optimization_region`]); the rest holds still. A lifelong map settles a session when it ends.
    /// Settling a trajectory also ends the probation of its corrections, kept ones included (see
    /// [`CorrectionProbation`](super::CorrectionProbation)): its route is over, and from then on
    /// retraction judges their matches as any, against what later trajectories add.
    pub fn set_trajectory_settled(&mut self, trajectory: u32, settled: bool) {
        if settled {
            self.settled.insert(trajectory);
            self.probations
                .retain(|p| p.newest.node.trajectory != trajectory);
        } else {
            self.settled.remove(&trajectory);
        }
    }

    /// Notes that these variables' constraints changed other than by an addition (the caller deleted
    /// some through [`Self::graph_mut`]): the next optimization moves them even if they are settled.
    pub fn mark_changed(&mut self, ids: impl IntoIterator<Item = VariableId>) {
        self.changed.extend(ids);
    }

    /// Fixes, for one optimization, every free variable outside the optimization region (nothing when no
    /// trajectory is settled or `settled_region_hops` is 0); returns them for [`Self::release`].
    fn hold_settled(&mut self) -> Vec<VariableId> {
        let hops = self.options.settled_region_hops;
        if hops == 0 || self.settled.is_empty() {
            return Vec::new();
        }
        let seeds: Vec<VariableId> = self
            .graph
            .variables()
            .map(|(id, _, _)| id)
            .filter(|id| !self.settled.contains(&id.trajectory()))
            .chain(
                self.graph
                    .constraints_since(self.new_constraints_from)
                    .flat_map(|(_, c)| [c.from, c.to]),
            )
            .chain(self.changed.iter().copied())
            .collect();
        let region = optimization_region(&self.graph, seeds, hops);
        let held: Vec<VariableId> = self
            .graph
            .variables()
            .filter(|(id, _, fixed)| !fixed && !region.contains(id))
            .map(|(id, _, _)| id)
            .collect();
        for &id in &held {
            // Cannot fail: the id came from the graph.
            let _ = self.graph.set_fixed(id, true);
        }
        held
    }

    /// Frees what [`Self::hold_settled`] fixed.
    fn release(&mut self, held: Vec<VariableId>) {
        for id in held {
            let _ = self.graph.set_fixed(id, false);
        }
    }

    /// Everything added or changed so far is now optimized.
    fn optimized(&mut self) {
        self.new_constraints_from = self.graph.next_constraint_id();
        self.changed.clear();
    }

    /// Takes out of the graph every accepted loop closure that the optimized graph refuses — its χ² (with
    /// its own information) exceeds `loop_closure_retraction_chi2` at the current poses — and puts back
    /// every retracted one the graph now fits within it. A closure the graph has just been optimized with
    /// and still violates by that much disagrees with the odometry chain and the other closures together
    /// (a look-alike place, or several matches that agreed on the wrong one); as later closures reshape
    /// the graph, it is judged again. Returns how many changed sides.
    fn retract_refused_loop_closures(&mut self) -> usize {
        let max_chi2 = self.options.loop_closure_retraction_chi2;
        if max_chi2 <= 0.0 {
            return 0;
        }
        let mut changed = 0;
        let on_probation = self.closures_on_probation();
        for (closure, state) in self
            .accepted_loop_closures
            .iter()
            .zip(&mut self.closure_states)
        {
            if on_probation.contains(&(closure.node, closure.submap)) {
                continue;
            }
            let constraint = match state {
                ClosureState::InGraph(id) => {
                    let Some(c) = self.graph.constraint(*id) else {
                        *state = ClosureState::Gone; // its node or submap was trimmed
                        continue;
                    };
                    c.clone()
                }
                ClosureState::Retracted(c) => c.clone(),
                ClosureState::Gone => continue,
            };
            let (Some(from), Some(to)) = (
                self.graph.pose(constraint.from),
                self.graph.pose(constraint.to),
            ) else {
                *state = ClosureState::Gone;
                continue;
            };
            let fits = constraint.chi2(&from, &to) <= max_chi2;
            match state {
                ClosureState::InGraph(id) if !fits && self.graph.remove_constraint(*id).is_ok() => {
                    self.changed.extend([constraint.from, constraint.to]);
                    *state = ClosureState::Retracted(constraint);
                    changed += 1;
                }
                ClosureState::Retracted(_) if fits => {
                    if let Ok(id) = self.graph.add_constraint(constraint) {
                        *state = ClosureState::InGraph(id);
                        changed += 1;
                    }
                }
                _ => {}
            }
        }
        changed
    }

    /// Loop closures out of the graph now because the optimized graph refuses them (see
    /// `GlobalSlamOptions::loop_closure_retraction_chi2`).
    pub fn closures_retracted(&self) -> usize {
        self.closure_states
            .iter()
            .filter(|s| matches!(s, ClosureState::Retracted(_)))
            .count()
    }

    /// Re-derives each trajectory's `global_from_local` from its last node's optimized pose.
    fn update_global_from_local(&mut self) {
        for (&trajectory, last) in &self.last_node {
            if let (Some(global), Some(record)) = (
                self.graph.pose(VariableId::Node(*last)),
                self.nodes.get(last),
            ) {
                self.global_from_local
                    .insert(trajectory, global * record.local_pose.inverse());
            }
        }
    }

    /// Optimizes with at most `max_iterations` Levenberg–Marquardt steps (the same options otherwise), as
    /// after a batch of sparsifications; does not reset the periodic-optimization counter.
    pub fn optimize_capped(&mut self, max_iterations: usize) -> OptimizationSummary {
        let stale = self
            .capped_optimizer
            .as_ref()
            .is_none_or(|o| o.options().max_iterations != max_iterations);
        if stale {
            let options = crate::pose_graph::OptimizerOptions {
                max_iterations,
                ..self.options.optimizer.clone()
            };
            // The options were validated at construction and max_iterations is not checked.
            self.capped_optimizer = Optimizer::new(options).ok();
        }
        let held = self.hold_settled();
        let summary = match self.capped_optimizer.as_mut() {
            Some(optimizer) => optimizer.optimize(&mut self.graph),
            None => self.optimizer.optimize(&mut self.graph),
        };
        self.release(held);
        self.optimized();
        self.update_global_from_local();
        summary
    }

    /// Holds every variable of a trajectory fixed (or frees it) in later optimizations.
    pub fn set_trajectory_fixed(&mut self, trajectory: u32, fixed: bool) {
        let ids: Vec<VariableId> = self
            .graph
            .variables()
            .filter(|(id, _, _)| id.trajectory() == trajectory)
            .map(|(id, _, _)| id)
            .collect();
        for id in ids {
            // Cannot fail: the id came from the graph.
            let _ = self.graph.set_fixed(id, fixed);
        }
    }
}
