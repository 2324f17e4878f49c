//! Sparse Levenberg–Marquardt over a [`PoseGraph`], with robust losses by iteratively reweighted least squares.
//!
//! Objective: `F(x) = Σ_c ρ_c(e_cᵀ Ω_c e_c)` over all constraints (see [`super::constraint`] for `e`), with
//! each variable parametrised additively as `(x, y, θ)` in the world frame. Each iteration linearises
//! `e_c(x + h) ≈ e_c + J_c h` and solves the damped normal equations
//!
//! ```text
//! (H + λ D) h = −g,    H = Σ w_c J_cᵀ Ω_c J_c,    g = Σ w_c J_cᵀ Ω_c e_c,    w_c = ρ_c'(e_cᵀ Ω_c e_c)
//! ```
//!
//! with Marquardt's scaling `D = diag(H)` (clamped), by sparse Cholesky (see `linear_system.rs`). The step
//! is accepted when the gain ratio `ϱ = (F(x) − F(x + h)) / (−gᵀh + λ hᵀDh)` is positive; `λ` follows
//! Nielsen's rule (`λ ← λ·max(1/3, 1 − (2ϱ − 1)³)` on success, `λ ← λ·ν, ν ← 2ν` on failure). Only
//! improving steps are taken, so the graph always ends at the best estimate seen.
//!
//! Gauge: fixed variables stay put; if no variable is fixed the smallest id is held instead.
//! The trade-off: exact sparse Cholesky per step is robust on ill-conditioned graphs (unlike
//! conjugate gradients), at the price of fill-in on very large, densely looped graphs.

use nalgebra::{Matrix3, Vector3};

use super::constraint::{Constraint, PreparedMeasurement, RobustLoss};
use super::graph::PoseGraph;
use super::ids::VariableId;
use super::linear_system::{BlockPattern, LinearSystemError, NO_BLOCK, SparseCholesky};
use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle};

mod optimization_summary;
mod optimizer_options;
mod rotation_first_guess;
pub use optimization_summary::{
    ConvergenceCriterion, FailureReason, OptimizationSummary, Termination,
};
pub use optimizer_options::{OptimizerOptions, OptimizerOptionsError};
use rotation_first_guess::take_rotation_first_guess;

/// One constraint in dense form.
#[derive(Clone, Copy, Debug)]
struct Edge {
    from: u32,
    to: u32,
    measurement: PreparedMeasurement,
    /// Blocks of `H` this edge writes to, or [`NO_BLOCK`] for fixed endpoints (set by `assign_blocks`).
    from_block: u32,
    to_block: u32,
    /// Off-diagonal block at (min, max) of the free indices, or [`NO_BLOCK`] if an endpoint is fixed.
    cross_block: u32,
    /// Whether the edge is in the linear system (see [`OptimizerOptions::prune_weight`]); an inactive
    /// edge has [`NO_BLOCK`] everywhere, so assembly skips it.
    active: bool,
}

/// Sparse Levenberg–Marquardt pose-graph optimizer. Keeps its symbolic factorization and work buffers
/// between calls, and reuses the factorization while the graph's block sparsity pattern is unchanged.
#[derive(Debug)]
pub struct Optimizer {
    options: OptimizerOptions,
    solver: Option<SparseCholesky>,
    symbolic_factorizations: usize,
    // Work buffers, reused across iterations and calls.
    hessian: Vec<f64>,
    damped: Vec<f64>,
    gradient: Vec<f64>,
    step: Vec<f64>,
    damping_diagonal: Vec<f64>,
}

impl Optimizer {
    /// An optimizer with these options (validated).
    pub fn new(options: OptimizerOptions) -> Result<Self, OptimizerOptionsError> {
        options.validate()?;
        Ok(Self {
            options,
            solver: None,
            symbolic_factorizations: 0,
            hessian: Vec::new(),
            damped: Vec::new(),
            gradient: Vec::new(),
            step: Vec::new(),
            damping_diagonal: Vec::new(),
        })
    }

    /// The options.
    pub fn options(&self) -> &OptimizerOptions {
        &self.options
    }

    /// How many symbolic factorizations this optimizer has computed (to observe reuse).
    pub fn symbolic_factorizations(&self) -> usize {
        self.symbolic_factorizations
    }

    /// Only the rotation-first initialization of [`OptimizerOptions::rotation_first_initialization`],
    /// whatever that option says: computes the guess and writes it into `graph` if its χ² is lower than
    /// the graph's. Returns whether it did. The guess's symbolic factorization (all constraints) stays
    /// cached, so an [`Optimizer::optimize`] that follows on the same structure reuses it.
    pub fn initialize_rotation_first(&mut self, graph: &mut PoseGraph) -> bool {
        let mut problem = Problem::new(graph, |c| c.loss);
        if problem.num_free == 0 || problem.edges.is_empty() {
            return false;
        }
        let mut factorization = Factorization {
            solver: &mut self.solver,
            count: &mut self.symbolic_factorizations,
        };
        let mut work = Work {
            hessian: &mut self.hessian,
            damped: &mut self.damped,
            gradient: &mut self.gradient,
            step: &mut self.step,
            damping_diagonal: &mut self.damping_diagonal,
        };
        let taken = matches!(
            take_rotation_first_guess(&mut problem, &mut factorization, &mut work),
            Ok(Some(_))
        );
        if taken {
            problem.write_back(graph);
        }
        taken
    }

    /// Minimises the graph's cost, writing the best estimate found back into `graph`.
    pub fn optimize(&mut self, graph: &mut PoseGraph) -> OptimizationSummary {
        self.optimize_with_losses(graph, |c| c.loss)
    }

    /// [`Optimizer::optimize`] with `loss_of(constraint)` in place of each constraint's own loss (for
    /// this call only: the graph's constraints are left as they are, only the poses are written). Each
    /// returned loss must be valid ([`RobustLoss::is_valid`]).
    pub fn optimize_with_losses(
        &mut self,
        graph: &mut PoseGraph,
        loss_of: impl Fn(&Constraint) -> RobustLoss,
    ) -> OptimizationSummary {
        let mut problem = Problem::new(graph, loss_of);
        let (initial_cost, initial_chi2) = problem.cost_and_chi2(&problem.poses);
        let mut summary = OptimizationSummary {
            initial_chi2,
            final_chi2: initial_chi2,
            initial_cost,
            final_cost: initial_cost,
            iterations: 0,
            accepted_steps: 0,
            pruned_constraints: 0,
            termination: Termination::Converged(ConvergenceCriterion::GradientTolerance),
            free_variables: problem.num_free,
            factor_nonzeros: 0,
        };
        if !initial_cost.is_finite() {
            summary.termination = Termination::Failed(FailureReason::NonFiniteCost);
            return summary;
        }
        if problem.num_free == 0 || problem.edges.is_empty() {
            return summary;
        }
        let mut factorization = Factorization {
            solver: &mut self.solver,
            count: &mut self.symbolic_factorizations,
        };
        let mut work = Work {
            hessian: &mut self.hessian,
            damped: &mut self.damped,
            gradient: &mut self.gradient,
            step: &mut self.step,
            damping_diagonal: &mut self.damping_diagonal,
        };
        let mut start_cost = initial_cost;
        if self.options.rotation_first_initialization {
            match take_rotation_first_guess(&mut problem, &mut factorization, &mut work) {
                Err(()) => {
                    summary.termination = Termination::Failed(FailureReason::SymbolicFactorization);
                    return summary;
                }
                Ok(Some(cost)) => start_cost = cost,
                Ok(None) => {}
            }
        }
        // Then only the constraints whose weight at the start is not negligible.
        let changed = problem.update_active(self.options.prune_weight);
        if (changed || !self.options.rotation_first_initialization)
            && factorization.prepare(&mut problem).is_none()
        {
            summary.termination = Termination::Failed(FailureReason::SymbolicFactorization);
            return summary;
        }
        let (termination, progress) = levenberg_marquardt(
            &self.options,
            &mut problem,
            &mut factorization,
            &mut work,
            start_cost,
        );
        summary.termination = termination;
        summary.pruned_constraints = problem.edges.iter().filter(|e| !e.active).count();
        summary.final_cost = progress.cost;
        summary.final_chi2 = progress.chi2;
        summary.iterations = progress.iterations;
        summary.accepted_steps = progress.accepted;
        summary.factor_nonzeros = factorization
            .solver
            .as_ref()
            .map_or(0, SparseCholesky::factor_nonzeros);
        problem.write_back(graph);
        summary
    }
}

/// The optimizer's symbolic factorization slot: rebuilt when the active edges' block pattern changes.
struct Factorization<'a> {
    solver: &'a mut Option<SparseCholesky>,
    count: &'a mut usize,
}

impl Factorization<'_> {
    /// A solver for the block pattern of the problem's active edges (reused when unchanged), with the
    /// edges' blocks assigned; `None` if the symbolic factorization fails.
    fn prepare(&mut self, problem: &mut Problem) -> Option<&mut SparseCholesky> {
        let pattern = problem.block_pattern();
        if self.solver.as_ref().is_none_or(|s| *s.pattern() != pattern) {
            *self.solver = None;
            *self.solver = Some(SparseCholesky::new(pattern).ok()?);
            *self.count += 1;
        }
        let solver = self.solver.as_mut()?;
        problem.assign_blocks(solver.pattern());
        Some(solver)
    }

    fn solver(&mut self) -> &mut SparseCholesky {
        self.solver
            .as_mut()
            .expect("prepared before the Levenberg–Marquardt loop")
    }
}

struct Work<'a> {
    hessian: &'a mut Vec<f64>,
    damped: &'a mut Vec<f64>,
    gradient: &'a mut Vec<f64>,
    step: &'a mut Vec<f64>,
    damping_diagonal: &'a mut Vec<f64>,
}

/// The graph in dense, index-addressed form.
struct Problem {
    ids: Vec<VariableId>,
    poses: Vec<Vector3<f64>>,
    /// Dense variable → index among the free variables, or `u32::MAX` for fixed ones.
    free_index: Vec<u32>,
    num_free: usize,
    edges: Vec<Edge>,
}

impl Problem {
    fn new(graph: &PoseGraph, loss_of: impl Fn(&Constraint) -> RobustLoss) -> Self {
        let mut ids = Vec::with_capacity(graph.num_variables());
        let mut poses = Vec::with_capacity(graph.num_variables());
        let mut fixed = Vec::with_capacity(graph.num_variables());
        for (id, pose, is_fixed) in graph.variables() {
            ids.push(id);
            poses.push(pose.to_xytheta());
            fixed.push(is_fixed);
        }
        if !fixed.iter().any(|&f| f)
            && let Some(first) = fixed.first_mut()
        {
            *first = true;
        }
        let mut num_free = 0;
        let free_index = fixed
            .iter()
            .map(|&f| {
                if f {
                    u32::MAX
                } else {
                    num_free += 1;
                    (num_free - 1) as u32
                }
            })
            .collect();
        let index = |id: &VariableId| ids.binary_search(id).ok().map(|k| k as u32);
        let free_index: Vec<u32> = free_index;
        let edges = graph
            .constraints()
            .filter_map(|(_, c)| {
                let (from, to) = (index(&c.from)?, index(&c.to)?);
                if free_index[from as usize] == u32::MAX && free_index[to as usize] == u32::MAX {
                    // Between two fixed variables: a constant of the cost, left out so that the
                    // convergence tests compare the decrease with the cost that can change.
                    return None;
                }
                Some(Edge {
                    from,
                    to,
                    measurement: PreparedMeasurement {
                        loss: loss_of(c),
                        ..PreparedMeasurement::new(c)
                    },
                    from_block: NO_BLOCK,
                    to_block: NO_BLOCK,
                    cross_block: NO_BLOCK,
                    active: true,
                })
            })
            .collect::<Vec<_>>();
        Self {
            ids,
            poses,
            free_index,
            num_free,
            edges,
        }
    }

    /// The sparsity pattern of `H`: one block per free variable, plus one per pair of free variables
    /// joined by an active edge.
    fn block_pattern(&self) -> BlockPattern {
        let free = &self.free_index;
        BlockPattern::new(
            self.num_free,
            self.edges.iter().filter(|e| e.active).filter_map(|e| {
                let (a, b) = (free[e.from as usize], free[e.to as usize]);
                (a != u32::MAX && b != u32::MAX).then_some((a, b))
            }),
        )
    }

    /// Re-decides which edges are in the linear system at the current poses: an active edge leaves when
    /// its robust weight falls below `prune_weight`, an inactive one returns when its weight exceeds
    /// ten times that (the gap keeps an edge near the threshold from toggling every step). Returns
    /// whether the active set changed. `prune_weight = 0` keeps (or makes) every edge active.
    fn update_active(&mut self, prune_weight: f64) -> bool {
        let mut changed = false;
        for e in &mut self.edges {
            let m = &e.measurement;
            let active = if prune_weight <= 0.0 {
                true
            } else {
                let r = m.error(&self.poses[e.from as usize], &self.poses[e.to as usize]);
                let w = m.loss.weight(r.dot(&(m.information * r)));
                if e.active {
                    w >= prune_weight
                } else {
                    w > 10.0 * prune_weight
                }
            };
            changed |= active != e.active;
            e.active = active;
        }
        changed
    }

    fn assign_blocks(&mut self, pattern: &BlockPattern) {
        for e in &mut self.edges {
            if !e.active {
                e.from_block = NO_BLOCK;
                e.to_block = NO_BLOCK;
                e.cross_block = NO_BLOCK;
                continue;
            }
            let a = self.free_index[e.from as usize];
            let b = self.free_index[e.to as usize];
            e.from_block = if a == u32::MAX {
                NO_BLOCK
            } else {
                pattern.block(a, a)
            };
            e.to_block = if b == u32::MAX {
                NO_BLOCK
            } else {
                pattern.block(b, b)
            };
            e.cross_block = if a == u32::MAX || b == u32::MAX {
                NO_BLOCK
            } else {
                pattern.block(a.min(b), a.max(b))
            };
        }
    }

    fn cost_and_chi2(&self, poses: &[Vector3<f64>]) -> (f64, f64) {
        let mut cost = 0.0;
        let mut chi2 = 0.0;
        for e in &self.edges {
            let m = &e.measurement;
            let r = m.error(&poses[e.from as usize], &poses[e.to as usize]);
            let s = r.dot(&(m.information * r));
            chi2 += s;
            cost += m.loss.rho(s);
        }
        (cost, chi2)
    }

    /// Fills the upper triangle of `H` and the gradient `g` at the current poses.
    fn linearize(&self, pattern: &BlockPattern, hessian: &mut [f64], gradient: &mut [f64]) {
        hessian.fill(0.0);
        gradient.fill(0.0);
        for e in &self.edges {
            let m = &e.measurement;
            let (r, ji, jj) = m.linearize(&self.poses[e.from as usize], &self.poses[e.to as usize]);
            let omega_r = m.information * r;
            let w = m.loss.weight(r.dot(&omega_r));
            let omega: Matrix3<f64> = m.information * w;
            let omega_r = omega_r * w;
            let omega_ji = omega * ji;
            let omega_jj = omega * jj;
            if e.from_block != NO_BLOCK {
                let f = 3 * self.free_index[e.from as usize] as usize;
                pattern.add_diagonal(hessian, e.from_block, &(ji.transpose() * omega_ji));
                let gi = ji.transpose() * omega_r;
                gradient[f] += gi.x;
                gradient[f + 1] += gi.y;
                gradient[f + 2] += gi.z;
            }
            if e.to_block != NO_BLOCK {
                let t = 3 * self.free_index[e.to as usize] as usize;
                pattern.add_diagonal(hessian, e.to_block, &(jj.transpose() * omega_jj));
                let gj = jj.transpose() * omega_r;
                gradient[t] += gj.x;
                gradient[t + 1] += gj.y;
                gradient[t + 2] += gj.z;
            }
            if e.cross_block != NO_BLOCK {
                if self.free_index[e.from as usize] < self.free_index[e.to as usize] {
                    pattern.add_off_diagonal(hessian, e.cross_block, &(ji.transpose() * omega_jj));
                } else {
                    pattern.add_off_diagonal(hessian, e.cross_block, &(jj.transpose() * omega_ji));
                }
            }
        }
    }

    /// `out = poses ⊞ step` for the free variables (see [`retract`]).
    fn apply_step(&self, step: &[f64], out: &mut [Vector3<f64>]) {
        for ((pose, &free), out) in self.poses.iter().zip(&self.free_index).zip(out.iter_mut()) {
            *out = if free == u32::MAX {
                *pose
            } else {
                let f = 3 * free as usize;
                retract(pose, step[f], step[f + 1], step[f + 2])
            };
        }
    }

    fn free_norm(&self) -> f64 {
        self.poses
            .iter()
            .zip(&self.free_index)
            .filter(|(_, f)| **f != u32::MAX)
            .map(|(p, _)| p.norm_squared())
            .sum::<f64>()
            .sqrt()
    }

    fn write_back(&self, graph: &mut PoseGraph) {
        for ((id, pose), &free) in self.ids.iter().zip(&self.poses).zip(&self.free_index) {
            if free != u32::MAX {
                // Cannot fail: the id came from this graph and accepted poses are finite.
                let _ = graph.set_pose(*id, Rigid2::from_xytheta(pose));
            }
        }
    }
}

/// Moves `pose` by the world-frame increment `(dx, dy, dθ)` along the SE(2) exponential:
/// `t ← t + V(dθ)·(dx, dy)`, `θ ← θ + dθ`, with `V` the left Jacobian of SO(2) (see `geometry::se2`).
///
/// To first order this is the additive update the Jacobians are written for, so the linear system is
/// unchanged; to second order it moves the pose along the arc of the rigid rotation that the increment
/// describes. A Gauss–Newton step that turns a branch of the graph by `dθ` gives every pose downstream
/// the increment `dθ·S·(t − c)` around the pivot `c`, and this retraction turns them exactly about `c`,
/// where the plain additive update would push them off along tangents (by `|t − c|·dθ²/2`). On M3500
/// from odometry that is the difference between 27 and 6 iterations.
fn retract(pose: &Vector3<f64>, dx: f64, dy: f64, dtheta: f64) -> Vector3<f64> {
    let (a, b) = if dtheta.abs() < 1e-6 {
        (1.0 - dtheta * dtheta / 6.0, dtheta / 2.0)
    } else {
        let (s, c) = dtheta.sin_cos();
        (s / dtheta, (1.0 - c) / dtheta)
    };
    Vector3::new(
        pose.x + a * dx - b * dy,
        pose.y + b * dx + a * dy,
        normalize_angle(pose.z + dtheta),
    )
}

/// Where the Levenberg–Marquardt loop stands: the cost and χ² at the current poses, the iterations
/// made and the steps accepted.
struct LmProgress {
    cost: f64,
    chi2: f64,
    iterations: usize,
    accepted: usize,
}

/// What one damped step did.
enum StepOutcome {
    /// Taken: the cost fell by `rho` times the model's prediction.
    Accepted { rho: f64 },
    /// Not taken (no decrease, or the damped system had no finite solution): damp harder.
    Rejected,
    /// The loop is done: the step or the decrease is below its tolerance.
    Converged(ConvergenceCriterion),
}

/// The Levenberg–Marquardt loop: relinearize after each accepted step, damp harder after each rejected
/// one, until a tolerance, the iteration limit or the damping limit ends it.
fn levenberg_marquardt(
    options: &OptimizerOptions,
    problem: &mut Problem,
    factorization: &mut Factorization<'_>,
    work: &mut Work<'_>,
    initial_cost: f64,
) -> (Termination, LmProgress) {
    let n = factorization.solver().pattern().dim();
    work.gradient.resize(n, 0.0);
    work.step.resize(n, 0.0);
    work.damping_diagonal.resize(n, 0.0);
    let mut candidate = problem.poses.clone();

    let mut progress = LmProgress {
        cost: initial_cost,
        chi2: problem.cost_and_chi2(&problem.poses).1,
        iterations: 0,
        accepted: 0,
    };
    let mut lambda = options.initial_lambda;
    let mut nu = 2.0;
    let mut relinearize = true;
    loop {
        if relinearize {
            if let Some(termination) = linearize(options, problem, factorization, work) {
                return (termination, progress);
            }
            relinearize = false;
        }
        if progress.iterations >= options.max_iterations {
            return (Termination::MaxIterations, progress);
        }
        if lambda > options.max_lambda {
            return (
                Termination::Failed(FailureReason::DampingExhausted),
                progress,
            );
        }
        progress.iterations += 1;
        match damped_step(
            options,
            problem,
            factorization,
            work,
            &mut candidate,
            lambda,
            &mut progress,
        ) {
            StepOutcome::Converged(criterion) => {
                return (Termination::Converged(criterion), progress);
            }
            StepOutcome::Accepted { rho } => {
                lambda *= (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0);
                nu = 2.0;
                relinearize = true;
            }
            StepOutcome::Rejected => {
                lambda *= nu;
                nu *= 2.0;
            }
        }
    }
}

/// Linearizes the problem at its poses into `work` (a new sparsity pattern when the active constraints
/// changed) and sets the damping diagonal. `Some` ends the loop: the pattern could not be factorized, or
/// the gradient is already within tolerance.
fn linearize(
    options: &OptimizerOptions,
    problem: &mut Problem,
    factorization: &mut Factorization<'_>,
    work: &mut Work<'_>,
) -> Option<Termination> {
    // The active set follows the poses; a changed set means a new pattern (and ordering).
    if problem.update_active(options.prune_weight) && factorization.prepare(problem).is_none() {
        return Some(Termination::Failed(FailureReason::SymbolicFactorization));
    }
    let nnz = factorization.solver().pattern().nnz();
    work.hessian.resize(nnz, 0.0);
    work.damped.resize(nnz, 0.0);
    let solver = factorization.solver();
    problem.linearize(solver.pattern(), work.hessian, work.gradient);
    if work
        .gradient
        .iter()
        .all(|g| g.abs() <= options.gradient_tolerance)
    {
        return Some(Termination::Converged(
            ConvergenceCriterion::GradientTolerance,
        ));
    }
    for (d, &offset) in work
        .damping_diagonal
        .iter_mut()
        .zip(solver.pattern().diagonal_offsets())
    {
        *d = work.hessian[offset].clamp(options.min_diagonal, options.max_diagonal);
    }
    None
}

/// Solves the system damped by `lambda`, tries the step on `candidate` and, if the cost falls, takes it
/// (the poses, cost and χ² in `progress`).
fn damped_step(
    options: &OptimizerOptions,
    problem: &mut Problem,
    factorization: &mut Factorization<'_>,
    work: &mut Work<'_>,
    candidate: &mut Vec<Vector3<f64>>,
    lambda: f64,
    progress: &mut LmProgress,
) -> StepOutcome {
    let solver = factorization.solver();
    work.damped.copy_from_slice(work.hessian);
    for (&offset, &d) in solver
        .pattern()
        .diagonal_offsets()
        .iter()
        .zip(work.damping_diagonal.iter())
    {
        work.damped[offset] += lambda * d;
    }
    for (s, g) in work.step.iter_mut().zip(work.gradient.iter()) {
        *s = -g;
    }
    let step_ok = match solver.solve(work.damped, work.step) {
        Ok(()) => work.step.iter().all(|s| s.is_finite()),
        Err(LinearSystemError::NotPositiveDefinite(_) | LinearSystemError::Symbolic(_)) => false,
    };
    if !step_ok {
        return StepOutcome::Rejected;
    }
    let step_norm = work.step.iter().map(|s| s * s).sum::<f64>().sqrt();
    let x_norm = problem.free_norm();
    if step_norm <= options.parameter_tolerance * (x_norm + options.parameter_tolerance) {
        return StepOutcome::Converged(ConvergenceCriterion::ParameterTolerance);
    }
    problem.apply_step(work.step, candidate);
    let (new_cost, new_chi2) = problem.cost_and_chi2(candidate);
    // Predicted decrease of the (weighted) quadratic model: −gᵀh + λ hᵀDh.
    let predicted: f64 = work
        .step
        .iter()
        .zip(work.gradient.iter())
        .zip(work.damping_diagonal.iter())
        .map(|((h, g), d)| -g * h + lambda * d * h * h)
        .sum();
    let cost = progress.cost;
    let actual = cost - new_cost;
    if new_cost.is_finite() && actual > 0.0 && predicted > 0.0 {
        std::mem::swap(&mut problem.poses, candidate);
        progress.accepted += 1;
        progress.cost = new_cost;
        progress.chi2 = new_chi2;
        if actual <= options.function_tolerance * cost {
            return StepOutcome::Converged(ConvergenceCriterion::FunctionTolerance);
        }
        return StepOutcome::Accepted {
            rho: actual / predicted,
        };
    }
    // Neither the model nor the cost can decrease by more than the tolerance: round-off level.
    if predicted <= options.function_tolerance * cost
        && actual.abs() <= options.function_tolerance * cost
    {
        return StepOutcome::Converged(ConvergenceCriterion::FunctionTolerance);
    }
    StepOutcome::Rejected
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;
    use crate::pose_graph::{Constraint, ConstraintKind, NodeId, RobustLoss};

    /// A small graph with mixed losses, full information matrices and one fixed variable.
    fn graph() -> PoseGraph {
        let node = |index| {
            VariableId::Node(NodeId {
                trajectory: 0,
                index,
            })
        };
        let mut graph = PoseGraph::new();
        for k in 0..5u32 {
            let t = f64::from(k);
            graph
                .add_variable(node(k), rigid2(t, 0.3 * t * t, 0.7 * t - 1.0))
                .unwrap();
        }
        graph.set_fixed(node(2), true).unwrap();
        let information = Matrix3::new(30.0, 2.0, 1.0, 2.0, 20.0, -1.5, 1.0, -1.5, 50.0);
        let losses = [
            RobustLoss::Trivial,
            RobustLoss::Huber { delta: 0.5 },
            RobustLoss::Cauchy { scale: 1.0 },
        ];
        let edges = [(0, 1), (1, 2), (2, 3), (3, 4), (0, 3), (4, 1), (2, 0)];
        for (k, &(a, b)) in edges.iter().enumerate() {
            graph
                .add_constraint(Constraint {
                    kind: ConstraintKind::NodeToNode,
                    from: node(a),
                    to: node(b),
                    from_from_to: rigid2(0.9, -0.2 + 0.1 * k as f64, 0.5),
                    information,
                    loss: losses[k % 3],
                })
                .unwrap();
        }
        graph
    }

    #[test]
    fn assembled_gradient_matches_finite_differences_of_the_cost() {
        let graph = graph();
        let mut problem = Problem::new(&graph, |c| c.loss);
        assert_eq!(
            problem.num_free, 4,
            "node 2 is fixed, so no implicit gauge is added"
        );
        let pattern = problem.block_pattern();
        problem.assign_blocks(&pattern);
        let mut hessian = vec![0.0; pattern.nnz()];
        let mut gradient = vec![0.0; pattern.dim()];
        problem.linearize(&pattern, &mut hessian, &mut gradient);
        let h = 1e-6;
        let mut checked = 0;
        for (v, &f) in problem.free_index.iter().enumerate() {
            if f == u32::MAX {
                continue;
            }
            for k in 0..3 {
                let mut plus = problem.poses.clone();
                let mut minus = problem.poses.clone();
                plus[v][k] += h;
                minus[v][k] -= h;
                let numeric =
                    (problem.cost_and_chi2(&plus).0 - problem.cost_and_chi2(&minus).0) / (2.0 * h);
                // F = Σ ρ(eᵀΩe), so ∂F/∂x = 2 Σ ρ' JᵀΩe = 2g.
                let analytic = 2.0 * gradient[3 * f as usize + k];
                assert!(
                    (numeric - analytic).abs() <= 1e-5 * (1.0 + numeric.abs()),
                    "{v} {k}: {numeric} vs {analytic}"
                );
                checked += 1;
            }
        }
        assert_eq!(checked, 12);
        assert!(
            gradient.iter().any(|g| g.abs() > 1.0),
            "the test point must not be a stationary point"
        );
        // Diagonal of H: positive.
        assert!(pattern.diagonal_offsets().iter().all(|&d| hessian[d] > 0.0));
    }

    #[test]
    fn retraction_turns_a_branch_rigidly_about_its_pivot() {
        // Increment dθ·S·(t − c) with c the pivot: the pose must end exactly on the circle around c.
        let pivot = nalgebra::Vector2::new(1.0, 2.0);
        let pose = Vector3::new(4.0, 6.0, 0.3);
        let dtheta = 0.4;
        let arm = nalgebra::Vector2::new(pose.x - pivot.x, pose.y - pivot.y);
        let moved = retract(&pose, -dtheta * arm.y, dtheta * arm.x, dtheta);
        let expected = pivot + nalgebra::Rotation2::new(dtheta) * arm;
        assert!(
            (moved.x - expected.x).abs() < 1e-12 && (moved.y - expected.y).abs() < 1e-12,
            "{moved:?}"
        );
        assert!((moved.z - 0.7).abs() < 1e-12);
        // Small angles use the series and agree with the additive update to first order.
        let tiny = retract(&pose, 0.1, -0.2, 1e-9);
        assert!((tiny.x - 4.1).abs() < 1e-9 && (tiny.y - 5.8).abs() < 1e-9);
    }
}
