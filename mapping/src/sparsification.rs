//! Chow–Liu sparsification of marginalized submaps: Algorithm 1 of Zhao et al., "A General Framework
//! for Lifelong Localization and Mapping in Changing Environment" (IROS 2021).
//!
//! When the trimmer removes a submap `m` and its nodes `X`, deleting every constraint that touches them
//! throws away what they told us about the poses around them (the Markov blanket `B`). Exact
//! marginalization keeps it but joins all of `B` in a dense clique, and cliques compound into a dense
//! graph over a long life. This module keeps the best *tree* over `B` instead:
//!
//! 1. **Dense marginal** ([`marginalize`]): linearise every constraint touching `E = {m} ∪ X` at the
//!    current estimate and take the Schur complement `Λ_B = Λ_BB − Λ_BE Λ_EE⁺ Λ_EB` (and `g_B` alike).
//! 2. **Gauge**: `Λ_B` only knows relative poses, so it is singular along global rigid motions. Holding
//!    one blanket pose `r` fixed (deleting its block) gives the marginal of the poses *relative to `r`*
//!    (a linear re-parametrisation of GLC's root shift); it is full rank unless the removed constraints
//!    leave some direction undetermined (see [`SparsificationOptions::marginal_eigenvalue_threshold`]).
//!    Its mean is one Gauss–Newton step `δ = −Λ⁻¹ g` from the estimate.
//! 3. **Tree and constraints** ([`EdgeModel`]). Let `z_ij = x_i⁻¹ ⊕ x_j` be a relative pose; to first
//!    order `δz_ij = J_i δx_i + J_j δx_j` with `J_j` a rotation (unit determinant). A tree of
//!    relative-pose constraints is, in the root-fixed coordinates, `q(x) = Π_(p,c) q(z_pc)` (the map
//!    from the poses to the tree's relative poses is triangular with unit-determinant blocks), so
//!    `KL(p‖q) = −H_p(x) + Σ_(p,c) CE(p(z_pc), q(z_pc))`. For a fixed tree it is minimal when every
//!    `q(z_pc)` is the *marginal* of `z_pc` under `p`, and then equals `Σ_(p,c) H(z_pc) − H_p(x)`:
//!    the best tree minimises `Σ ½ ln det Σ_rel(p, c)`, a maximum spanning tree on `−ln det Σ_rel`
//!    ([`EdgeModel::RelativeMarginal`], the default). This is the Chow–Liu argument with the relative
//!    pose in place of the child pose; the marginal of `z_pc` is also the conditional `p(x_c | x_p)`
//!    with the gauge held at `p`. The design notes' recipe ([`EdgeModel::Conditional`]: mutual
//!    information of root-relative poses, `Σ_c|p` mapped into the relative pose) conditions every edge
//!    on the root as well and is implemented for comparison.
//! 4. Every tree edge becomes a [`Constraint`] with measurement `μ_p⁻¹ μ_c` and a trivial loss. By
//!    default ([`TreeMean::MatchMarginalMean`]) `μ` is the marginal mean `x̂ − Λ_B⁻¹ g_B`;
//!    [`TreeMean::MatchGradient`] uses `μ = x̂ − Λ_tree⁻¹ g_B` instead, so that at the linearization
//!    point the tree pulls on `B` exactly as the removed constraints did (an optimized graph stays at
//!    its optimum to first order, but a tree much weaker than the clique puts `μ` far from `x̂`).
//!    Robust losses in the clique are linearised with their IRLS weight ([`RobustWeighting`]). Each
//!    constraint's kind follows its ends ([`ConstraintKind::NodeToNode`],
//!    [`ConstraintKind::SubmapToSubmap`], or [`ConstraintKind::NodeToSubmapInter`] oriented
//!    submap → node as loop closures are).
//!
//! A tree edge on a pair of variables that already carries a plain least-squares constraint is summed
//! into it ([`apply`], [`ParallelMerge`]): trees would otherwise stack parallel constraints beside the
//! node-to-submap constraints of the blanket and beside earlier trees' edges, trim after trim.
//!
//! Blankets split into connected components of the removed constraints are handled one component at a
//! time (each with its own root). A component with one blanket pose gets no constraint.
//!
//! [`kl_divergence`] measures any replacement (the tree, or nothing at all for [`delete`]) against the
//! exact marginal of the whole remaining graph.

mod chow_liu;
mod divergence;
mod linearization;
mod marginalization;
mod options;
mod symmetric_eigen;
#[cfg(test)]
mod tests;

use std::collections::BTreeSet;

use nalgebra::{DMatrix, DVector, Matrix3, Matrix3x6, Matrix6};
use thiserror::Error;

pub use divergence::kl_divergence;
pub use marginalization::{DenseMarginal, marginalize};
pub use options::{
    EdgeModel, RobustWeighting, SparsificationOptions, SparsificationOptionsError, TreeMean,
};
use symmetric_eigen::{scale_columns, symmetric_eigen};

use self::chow_liu::maximum_spanning_tree;
use self::divergence::gaussian_kl_divergence;
use self::linearization::{LinearFactor, linearize};
use self::marginalization::pseudo_inverse;
use crate::geometry::{Rigid2, Rigid2Ext as _};
use crate::pose_graph::{
    Constraint, ConstraintId, ConstraintKind, PoseGraph, PoseGraphError, RobustLoss, SubmapId,
    VariableId, merged,
};

/// Errors of sparsification, deletion and divergence computations.
#[derive(Debug, Error, Clone, PartialEq)]
pub enum SparsificationError {
    /// The options are unusable.
    #[error("invalid sparsification options: {0}")]
    InvalidOptions(#[from] SparsificationOptionsError),
    /// The set of variables to eliminate is empty.
    #[error("no variable to eliminate")]
    NothingToEliminate,
    /// A variable is not in the graph.
    #[error("unknown variable {0:?}")]
    UnknownVariable(VariableId),
    /// A constraint is not in the graph.
    #[error("unknown constraint {0:?}")]
    UnknownConstraint(ConstraintId),
    /// Fixed variables cannot be eliminated (they carry no distribution to marginalize).
    #[error("cannot eliminate fixed variable {0:?}")]
    FixedVariable(VariableId),
    /// A replacement constraint touches an eliminated variable.
    #[error("replacement constraint touches eliminated variable {0:?}")]
    TouchesEliminated(VariableId),
    /// The exact marginal of the remaining graph is not positive definite after fixing the gauge
    /// (some remaining pose is undetermined), so no divergence can be measured against it.
    #[error("the exact marginal of the remaining graph is singular")]
    SingularMarginal,
    /// Editing the graph failed.
    #[error(transparent)]
    Graph(#[from] PoseGraphError),
}

/// Diagnostics of one [`sparsify`] call.
#[derive(Clone, Debug, PartialEq)]
pub struct SparsificationDiagnostics {
    /// `KL(dense marginal ‖ tree)` over the blanket (nats), summed over components, both gauge-fixed
    /// at each component's root. 0 when nothing had to be approximated.
    pub kl_divergence: f64,
    /// Numerical rank of the gauge-fixed dense marginal (summed over components).
    pub marginal_rank: usize,
    /// Its dimension: `3 (|B| − number of components)`. `rank < dimension` means the removed
    /// constraints left some relative direction of the blanket undetermined.
    pub marginal_dimension: usize,
    /// Connected components of the removed constraints that reach the blanket.
    pub components: usize,
    /// Largest translation of a blanket pose from its estimate to the marginal mean (metres).
    pub max_mean_shift: f64,
}

/// What [`sparsify`] proposes; [`apply`] carries it out.
#[derive(Clone, Debug, PartialEq)]
pub struct SparsificationResult {
    /// The eliminated variables, sorted.
    pub eliminated: Vec<VariableId>,
    /// The constraints to remove: every one touching an eliminated variable, in id order.
    pub removed_constraints: Vec<ConstraintId>,
    /// The Markov blanket, sorted.
    pub blanket: Vec<VariableId>,
    /// The Chow–Liu tree constraints over the blanket (`|B| − components` of them).
    pub new_constraints: Vec<Constraint>,
    /// How good the approximation is.
    pub diagnostics: SparsificationDiagnostics,
}

/// Marginalizes `eliminate` out of `graph` and approximates the dense marginal over its blanket by its
/// Chow–Liu tree of relative-pose constraints (see the module docs). The graph is not modified.
pub fn sparsify(
    graph: &PoseGraph,
    eliminate: &[VariableId],
    options: &SparsificationOptions,
) -> Result<SparsificationResult, SparsificationError> {
    let marginal = marginalize(graph, eliminate, options)?;
    let mut new_constraints = Vec::new();
    let mut diagnostics = SparsificationDiagnostics {
        kl_divergence: 0.0,
        marginal_rank: 0,
        marginal_dimension: 0,
        components: marginal.components.len(),
        max_mean_shift: 0.0,
    };
    for members in &marginal.components {
        diagnostics.marginal_dimension += 3 * (members.len() - 1);
        if members.len() < 2 {
            continue;
        }
        let Some(fixed) = GaugeFixed::new(&marginal, members, options) else {
            continue;
        };
        diagnostics.marginal_rank += fixed.rank;
        let points: Vec<Rigid2> = members
            .iter()
            .map(|&b| marginal.linearization_point[b])
            .collect();
        let marginal_means = GaugeFixed::means(&points, &fixed.delta);
        for (mean, point) in marginal_means.iter().zip(&points) {
            let shift = (mean.translation.vector - point.translation.vector).norm();
            diagnostics.max_mean_shift = diagnostics.max_mean_shift.max(shift);
        }
        let ids: Vec<VariableId> = members.iter().map(|&b| marginal.blanket[b]).collect();
        let shape_means = match options.tree_mean {
            TreeMean::MatchMarginalMean => &marginal_means,
            TreeMean::MatchGradient => &points,
        };
        let mut edges = match options.edge_model {
            EdgeModel::RelativeMarginal => {
                relative_marginal_tree(&fixed, &ids, shape_means, &points)
            }
            EdgeModel::Conditional => conditional_tree(&fixed, &ids, shape_means, &points),
        };
        // The tree's own information, in the same root-fixed coordinates.
        let tree_information = tree_information(&edges, &points, fixed.dimension());
        let tree_delta = match options.tree_mean {
            TreeMean::MatchMarginalMean => fixed.delta.clone(),
            TreeMean::MatchGradient => -solve_symmetric(&tree_information, &fixed.gradient),
        };
        let means = GaugeFixed::means(&points, &tree_delta);
        for edge in &mut edges {
            // New measurement, same quadratic form at the linearization point: Ω's information on
            // δx_to is J_toᵀ Ω J_to, and J_to (a rotation) turns with the measurement's angle.
            let measurement = means[edge.from].inverse() * means[edge.to];
            let (_, _, j_old) = linearize(&edge.measurement, &points[edge.from], &points[edge.to]);
            let (_, _, j_new) = linearize(&measurement, &points[edge.from], &points[edge.to]);
            let turn = j_new * j_old.transpose();
            let information = turn * edge.information * turn.transpose();
            edge.information = 0.5 * (information + information.transpose());
            edge.measurement = measurement;
            new_constraints.push(Constraint {
                kind: kind_between(ids[edge.from], ids[edge.to]),
                from: ids[edge.from],
                to: ids[edge.to],
                from_from_to: edge.measurement,
                information: edge.information,
                loss: RobustLoss::Trivial,
            });
        }
        let mean_difference = &fixed.delta - &tree_delta;
        diagnostics.kl_divergence += gaussian_kl_divergence(
            &tree_information,
            &fixed.covariance,
            fixed.log_det_information,
        ) + 0.5
            * mean_difference.dot(&(&tree_information * &mean_difference));
    }
    Ok(SparsificationResult {
        eliminated: marginal.eliminated,
        removed_constraints: marginal.removed_constraints,
        blanket: marginal.blanket,
        new_constraints,
        diagnostics,
    })
}

/// Which constraints already in the graph take in a tree edge on their pair ([`apply`]). Summing two
/// plain least-squares constraints on one pair is exact (`pose_graph::constraint_merge`); robust ones
/// (loop closures) are never summed. The merged constraint keeps the existing one's kind.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ParallelMerge<'a> {
    /// Every plain least-squares constraint on the pair, whatever made it (a node-to-submap constraint
    /// LLO made, odometry, an earlier tree's edge).
    EveryPlain,
    /// Every plain constraint but the node-to-submap constraints LLO made on these submaps: those whose
    /// information the graph's owner may still rewrite (GLM's bends), which must stay as LLO made them.
    EveryPlainBut(&'a BTreeSet<SubmapId>),
}

impl ParallelMerge<'_> {
    /// Whether `existing` may take in a tree edge on its pair.
    fn takes_in(self, existing: &Constraint) -> bool {
        match self {
            Self::EveryPlain => true,
            Self::EveryPlainBut(rewritable) => {
                existing.kind != ConstraintKind::NodeToSubmapIntra
                    || ![existing.from, existing.to]
                        .iter()
                        .any(|end| matches!(end, VariableId::Submap(s) if rewritable.contains(s)))
            }
        }
    }
}

/// Carries out a [`SparsificationResult`] on the graph it was computed from: removes the eliminated
/// variables with every constraint touching them, and adds the tree constraints; a tree constraint on a
/// pair that already has a plain least-squares constraint `merge` allows is summed into it instead (the
/// merged constraint replaces it under a new id). Returns the ids of the tree's constraints, merged or
/// new. Everything is checked before the graph is touched, so on error it is unchanged.
pub fn apply(
    graph: &mut PoseGraph,
    result: &SparsificationResult,
    merge: ParallelMerge<'_>,
) -> Result<Vec<ConstraintId>, SparsificationError> {
    let eliminated: BTreeSet<VariableId> = result.eliminated.iter().copied().collect();
    for &id in &eliminated {
        if !graph.contains_variable(id) {
            return Err(SparsificationError::UnknownVariable(id));
        }
    }
    for &cid in &result.removed_constraints {
        if graph.constraint(cid).is_none() {
            return Err(SparsificationError::UnknownConstraint(cid));
        }
    }
    for c in &result.new_constraints {
        for end in [c.from, c.to] {
            if eliminated.contains(&end) {
                return Err(SparsificationError::TouchesEliminated(end));
            }
            if !graph.contains_variable(end) {
                return Err(SparsificationError::UnknownVariable(end));
            }
        }
    }
    for &id in &eliminated {
        graph.remove_variable(id)?;
    }
    let mut ids = Vec::with_capacity(result.new_constraints.len());
    for constraint in &result.new_constraints {
        // A plain constraint already on the pair absorbs this one: the sum of two Gaussians on a pair is
        // one Gaussian, so the graph does not grow a parallel constraint with every trim.
        let parallel = graph
            .constraints_of(constraint.from)
            .iter()
            .find_map(|&id| {
                let existing = graph.constraint(id)?;
                let same_pair = (existing.from == constraint.to && existing.to == constraint.from)
                    || (existing.from == constraint.from && existing.to == constraint.to);
                if !same_pair || !merge.takes_in(existing) {
                    return None;
                }
                merged(existing, constraint).map(|sum| (id, sum))
            });
        let added = match parallel {
            Some((id, sum)) => {
                // Re-added under a new id, so that the next optimization sees it as new.
                let added = graph.add_constraint(sum)?;
                graph.remove_constraint(id)?;
                added
            }
            None => graph.add_constraint(constraint.clone())?,
        };
        ids.push(added);
    }
    Ok(ids)
}

/// The baseline: removes the variables and every constraint touching them, replacing nothing. Returns
/// the removed constraints in id order. Unknown variables are reported before anything is removed.
pub fn delete(
    graph: &mut PoseGraph,
    eliminate: &[VariableId],
) -> Result<Vec<(ConstraintId, Constraint)>, SparsificationError> {
    let eliminated: BTreeSet<VariableId> = eliminate.iter().copied().collect();
    if let Some(&id) = eliminated.iter().find(|&&id| !graph.contains_variable(id)) {
        return Err(SparsificationError::UnknownVariable(id));
    }
    let mut removed = Vec::new();
    for id in eliminated {
        removed.extend(graph.remove_variable(id)?);
    }
    removed.sort_by_key(|(id, _)| *id);
    Ok(removed)
}

/// `Λ_tree` over the component's poses `1..m` (root held), linearised at `points`.
fn tree_information(edges: &[TreeEdge], points: &[Rigid2], dimension: usize) -> DMatrix<f64> {
    let mut information = DMatrix::zeros(dimension, dimension);
    for edge in edges {
        let (e, ja, jb) = linearize(&edge.measurement, &points[edge.from], &points[edge.to]);
        LinearFactor {
            a: edge.from,
            b: edge.to,
            e,
            ja,
            jb,
            omega: edge.information,
        }
        .accumulate(|k| k.checked_sub(1), &mut information, None);
    }
    information
}

/// `M⁻¹ v` for symmetric positive semi-definite `M` (Cholesky, else the pseudo-inverse).
fn solve_symmetric(m: &DMatrix<f64>, v: &DVector<f64>) -> DVector<f64> {
    match m.clone().cholesky() {
        Some(cholesky) => cholesky.solve(v),
        None => pseudo_inverse(m, 1e-12) * v,
    }
}

/// The constraint kind for a tree edge between `from` and `to`.
fn kind_between(from: VariableId, to: VariableId) -> ConstraintKind {
    match (from, to) {
        (VariableId::Node(_), VariableId::Node(_)) => ConstraintKind::NodeToNode,
        (VariableId::Submap(_), VariableId::Submap(_)) => ConstraintKind::SubmapToSubmap,
        _ => ConstraintKind::NodeToSubmapInter,
    }
}

/// Orients a tree edge: a mixed edge runs submap → node (as loop closures do), others parent → child.
fn orient(ids: &[VariableId], parent: usize, child: usize) -> (usize, usize) {
    match (ids[parent], ids[child]) {
        (VariableId::Node(_), VariableId::Submap(_)) => (child, parent),
        _ => (parent, child),
    }
}

/// Union–find over `0..n` (path halving, union by index).
pub(crate) struct UnionFind {
    parent: Vec<usize>,
}

impl UnionFind {
    pub(crate) fn new(n: usize) -> Self {
        Self {
            parent: (0..n).collect(),
        }
    }

    pub(crate) fn find(&mut self, mut v: usize) -> usize {
        while self.parent[v] != v {
            self.parent[v] = self.parent[self.parent[v]];
            v = self.parent[v];
        }
        v
    }

    pub(crate) fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            let (low, high) = (ra.min(rb), ra.max(rb));
            self.parent[high] = low;
        }
    }
}

/// One component's marginal with its root (local index 0, the smallest blanket id) held fixed.
struct GaugeFixed {
    /// `Σ` over local poses `1..m` (3(m−1) square), from the clamped eigenvalues.
    covariance: DMatrix<f64>,
    /// `ln det` of the clamped information.
    log_det_information: f64,
    /// Eigenvalues above the threshold.
    rank: usize,
    /// The marginal mean's offset from the linearization point, local poses `1..m`.
    delta: DVector<f64>,
    /// The marginal gradient `g` over local poses `1..m`.
    gradient: DVector<f64>,
}

impl GaugeFixed {
    /// `None` when the component's marginal carries no information at all.
    fn new(
        marginal: &DenseMarginal,
        members: &[usize],
        options: &SparsificationOptions,
    ) -> Option<Self> {
        let k = 3 * (members.len() - 1);
        let mut information = DMatrix::zeros(k, k);
        let mut gradient = DVector::zeros(k);
        for (r, &br) in members[1..].iter().enumerate() {
            for (c, &bc) in members[1..].iter().enumerate() {
                information
                    .view_mut((3 * r, 3 * c), (3, 3))
                    .copy_from(&marginal.information.view((3 * br, 3 * bc), (3, 3)));
            }
            gradient
                .rows_mut(3 * r, 3)
                .copy_from(&marginal.gradient.rows(3 * br, 3));
        }
        let eigen = symmetric_eigen(&information);
        let max = eigen.eigenvalues.max();
        if max.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
            return None;
        }
        let floor = options.marginal_eigenvalue_threshold * max;
        let rank = eigen.eigenvalues.iter().filter(|&&l| l > floor).count();
        let clamped = eigen.eigenvalues.map(|l| l.max(floor));
        let v = &eigen.eigenvectors;
        let covariance = scale_columns(v, &clamped.map(|l| 1.0 / l)) * v.transpose();
        let covariance = 0.5 * (&covariance + covariance.transpose());
        let pseudo = eigen
            .eigenvalues
            .map(|l| if l > floor { 1.0 / l } else { 0.0 });
        let delta = -(v * (v.transpose() * &gradient).component_mul(&pseudo));
        Some(Self {
            covariance,
            log_det_information: clamped.iter().map(|l| l.ln()).sum(),
            rank,
            delta,
            gradient,
        })
    }

    fn dimension(&self) -> usize {
        self.covariance.nrows()
    }

    /// `points` moved by `delta` (over local poses `1..m`; the root stays put).
    fn means(points: &[Rigid2], delta: &DVector<f64>) -> Vec<Rigid2> {
        points
            .iter()
            .enumerate()
            .map(|(t, point)| {
                if t == 0 {
                    *point
                } else {
                    Rigid2::from_xytheta(&(point.to_xytheta() + delta.fixed_rows::<3>(3 * (t - 1))))
                }
            })
            .collect()
    }

    /// `Σ_ab` for local poses; the root's rows and columns are zero.
    fn block(&self, a: usize, b: usize) -> Matrix3<f64> {
        if a == 0 || b == 0 {
            return Matrix3::zeros();
        }
        self.covariance
            .fixed_view::<3, 3>(3 * (a - 1), 3 * (b - 1))
            .into_owned()
    }

    /// The 6×6 joint covariance of local poses `a`, `b`.
    fn joint(&self, a: usize, b: usize) -> Matrix6<f64> {
        let mut m = Matrix6::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&self.block(a, a));
        m.fixed_view_mut::<3, 3>(0, 3).copy_from(&self.block(a, b));
        m.fixed_view_mut::<3, 3>(3, 0).copy_from(&self.block(b, a));
        m.fixed_view_mut::<3, 3>(3, 3).copy_from(&self.block(b, b));
        m
    }
}

/// A tree edge as a constraint between local poses.
struct TreeEdge {
    from: usize,
    to: usize,
    measurement: Rigid2,
    information: Matrix3<f64>,
}

/// The covariance of the relative pose `from⁻¹ ⊕ to` (error coordinates of the constraint
/// `from → to` with measurement `measurement`, linearised at `points`).
fn relative_covariance(
    fixed: &GaugeFixed,
    points: &[Rigid2],
    measurement: &Rigid2,
    from: usize,
    to: usize,
) -> Matrix3<f64> {
    let (_, ja, jb) = linearize(measurement, &points[from], &points[to]);
    let mut j = Matrix3x6::zeros();
    j.fixed_view_mut::<3, 3>(0, 0).copy_from(&ja);
    j.fixed_view_mut::<3, 3>(0, 3).copy_from(&jb);
    let s = j * fixed.joint(from, to) * j.transpose();
    0.5 * (s + s.transpose())
}

/// Inverse of a symmetric positive semi-definite 3×3 matrix, eigenvalues floored at `1e-15 × λ_max`
/// (symmetric, finite, positive semi-definite result; zero for a zero matrix).
fn spd_inverse(m: &Matrix3<f64>) -> Matrix3<f64> {
    let eigen = (0.5 * (m + m.transpose())).symmetric_eigen();
    let max = eigen.eigenvalues.max();
    if max.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return Matrix3::zeros();
    }
    let floor = 1e-15 * max;
    let inv = eigen.eigenvalues.map(|l| 1.0 / l.max(floor));
    let r = eigen.eigenvectors * Matrix3::from_diagonal(&inv) * eigen.eigenvectors.transpose();
    0.5 * (r + r.transpose())
}

/// `ln det` of a symmetric positive semi-definite 3×3 matrix (`−∞` if singular).
fn log_det3(m: &Matrix3<f64>) -> f64 {
    let d = m.determinant();
    if d > 0.0 { d.ln() } else { f64::NEG_INFINITY }
}

fn relative_marginal_tree(
    fixed: &GaugeFixed,
    ids: &[VariableId],
    means: &[Rigid2],
    points: &[Rigid2],
) -> Vec<TreeEdge> {
    let measurement = |a: usize, b: usize| means[a].inverse() * means[b];
    let tree = maximum_spanning_tree(ids.len(), 0, |a, b| {
        -log_det3(&relative_covariance(
            fixed,
            points,
            &measurement(a, b),
            a,
            b,
        ))
    });
    tree.into_iter()
        .map(|(parent, child)| {
            let (from, to) = orient(ids, parent, child);
            let z = measurement(from, to);
            TreeEdge {
                from,
                to,
                measurement: z,
                information: spd_inverse(&relative_covariance(fixed, points, &z, from, to)),
            }
        })
        .collect()
}

fn conditional_tree(
    fixed: &GaugeFixed,
    ids: &[VariableId],
    means: &[Rigid2],
    points: &[Rigid2],
) -> Vec<TreeEdge> {
    let m = ids.len();
    // The tree's own root c₀: the pose best determined relative to r (smallest ln det Σ_cc).
    let c0 = (1..m)
        .min_by(|&a, &b| log_det3(&fixed.block(a, a)).total_cmp(&log_det3(&fixed.block(b, b))))
        .unwrap_or(1);
    // Chow–Liu over poses 1..m (vertex v is local pose v + 1) on mutual information.
    let mutual_information = |a: usize, b: usize| {
        let joint = fixed.joint(a, b).determinant();
        0.5 * (log_det3(&fixed.block(a, a)) + log_det3(&fixed.block(b, b))
            - if joint > 0.0 {
                joint.ln()
            } else {
                f64::NEG_INFINITY
            })
    };
    let tree = maximum_spanning_tree(m - 1, c0 - 1, |a, b| mutual_information(a + 1, b + 1));
    let mut edges = Vec::with_capacity(m - 1);
    // (parent, child, covariance of the child given the parent, in world-additive coordinates).
    let mut conditionals = vec![(0, c0, fixed.block(c0, c0))];
    for (p, c) in tree {
        let (p, c) = (p + 1, c + 1);
        let gain = fixed.block(c, p) * spd_inverse(&fixed.block(p, p));
        let conditional = fixed.block(c, c) - gain * fixed.block(p, c);
        conditionals.push((p, c, 0.5 * (conditional + conditional.transpose())));
    }
    for (p, c, conditional) in conditionals {
        let z = means[p].inverse() * means[c];
        // The constraint p → c whose information on δx_c (p held) is Σ_c|p⁻¹: Ω = J_c Σ_c|p⁻¹ J_cᵀ
        // (J_c is a rotation).
        let (_, jp, jc) = linearize(&z, &points[p], &points[c]);
        let omega = jc * spd_inverse(&conditional) * jc.transpose();
        let (from, to) = orient(ids, p, c);
        if (from, to) == (p, c) {
            edges.push(TreeEdge {
                from,
                to,
                measurement: z,
                information: 0.5 * (omega + omega.transpose()),
            });
        } else {
            // The same quadratic form as a constraint c → p: its information on δx_p is Jpᵀ Ω Jp.
            let on_p = jp.transpose() * omega * jp;
            let z_reverse = means[c].inverse() * means[p];
            let (_, _, jp_reverse) = linearize(&z_reverse, &points[c], &points[p]);
            let reversed = jp_reverse * on_p * jp_reverse.transpose();
            edges.push(TreeEdge {
                from,
                to,
                measurement: z_reverse,
                information: 0.5 * (reversed + reversed.transpose()),
            });
        }
    }
    edges
}
