//! Exact (dense) marginalization of a set of variables onto their Markov blanket.
//!
//! Every constraint touching an eliminated variable is linearised at the current estimate (additive
//! `(x, y, θ)` per pose, the optimizer's parametrisation, see `linearization.rs`), giving the local cost
//! `½ δᵀ Λ δ + gᵀ δ` over `[E; B]`. Eliminating `E` exactly (the Schur complement) leaves
//!
//! ```text
//! Λ_B = Λ_BB − Λ_BE Λ_EE⁺ Λ_EB,      g_B = g_B − Λ_BE Λ_EE⁺ g_E
//! ```
//!
//! `Λ_EE⁺` is the eigen-decomposition pseudo-inverse (see
//! [`SparsificationOptions::elimination_eigenvalue_threshold`]). The work is done per connected
//! component of the removed constraints (a component of `E ∪ B`), so `Λ_B` is exactly block-diagonal
//! over components and each component carries its own gauge freedom (3 dimensions: `Λ_B` is invariant
//! under a global rigid motion of the component's blanket).

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{DMatrix, DVector};

use super::linearization::{LinearFactor, linearize};
use super::options::{RobustWeighting, SparsificationOptions};
use super::{SparsificationError, UnionFind};
use crate::geometry::Rigid2;
use crate::pose_graph::{Constraint, ConstraintId, PoseGraph, VariableId};

/// The exact Gaussian marginal, over the Markov blanket, of the constraints touching a set of
/// eliminated variables, linearised at the graph's current estimate.
///
/// The marginal cost is `½ δᵀ Λ δ + gᵀ δ + const` in the blanket perturbations `δ` (additive world-frame
/// `(x, y, θ)` per pose, blocks in [`DenseMarginal::blanket`] order).
#[derive(Clone, Debug)]
pub struct DenseMarginal {
    /// The eliminated variables, sorted and deduplicated.
    pub eliminated: Vec<VariableId>,
    /// The Markov blanket: variables that share a constraint with an eliminated one, sorted.
    pub blanket: Vec<VariableId>,
    /// The blanket's poses at linearization (`world_from_variable`).
    pub linearization_point: Vec<Rigid2>,
    /// Every constraint touching an eliminated variable, in id order.
    pub removed_constraints: Vec<ConstraintId>,
    /// `Λ_B` (3|B| × 3|B|); units 1/m², 1/(m·rad), 1/rad². Rank-deficient by at least 3 per component.
    pub information: DMatrix<f64>,
    /// `g_B` (3|B|), the gradient of the marginal cost at the linearization point; units 1/m, 1/rad.
    pub gradient: DVector<f64>,
    /// Indices into [`DenseMarginal::blanket`], grouped by connected component of the removed
    /// constraints; each group sorted, groups ordered by their first index.
    pub components: Vec<Vec<usize>>,
}

/// A constraint linearised at the graph's estimate, its robust weight applied per `weighting`.
pub(crate) fn linear_factor(
    graph: &PoseGraph,
    constraint: &Constraint,
    weighting: RobustWeighting,
    a: usize,
    b: usize,
) -> Result<LinearFactor, SparsificationError> {
    let from = graph
        .pose(constraint.from)
        .ok_or(SparsificationError::UnknownVariable(constraint.from))?;
    let to = graph
        .pose(constraint.to)
        .ok_or(SparsificationError::UnknownVariable(constraint.to))?;
    let (e, ja, jb) = linearize(&constraint.from_from_to, &from, &to);
    let weight = match weighting {
        RobustWeighting::Irls => constraint.loss.weight(e.dot(&(constraint.information * e))),
        RobustWeighting::Ignore => 1.0,
    };
    Ok(LinearFactor {
        a,
        b,
        e,
        ja,
        jb,
        omega: constraint.information * weight,
    })
}

/// `M⁺` of a symmetric matrix: eigenvalues at or below `threshold × λ_max` are treated as zero.
pub(crate) fn pseudo_inverse(m: &DMatrix<f64>, threshold: f64) -> DMatrix<f64> {
    let n = m.nrows();
    if n == 0 {
        return DMatrix::zeros(0, 0);
    }
    let eigen = super::symmetric_eigen(m);
    let max = eigen.eigenvalues.max().max(0.0);
    let floor = threshold * max;
    let inverted = eigen
        .eigenvalues
        .map(|l| if l > floor && l > 0.0 { 1.0 / l } else { 0.0 });
    super::scale_columns(&eigen.eigenvectors, &inverted) * eigen.eigenvectors.transpose()
}

/// Marginalizes `eliminate` (see the module docs): the oracle every sparsified result is measured
/// against.
pub fn marginalize(
    graph: &PoseGraph,
    eliminate: &[VariableId],
    options: &SparsificationOptions,
) -> Result<DenseMarginal, SparsificationError> {
    options.validate()?;
    if eliminate.is_empty() {
        return Err(SparsificationError::NothingToEliminate);
    }
    let eliminated: BTreeSet<VariableId> = eliminate.iter().copied().collect();
    for &id in &eliminated {
        match graph.is_fixed(id) {
            None => return Err(SparsificationError::UnknownVariable(id)),
            Some(true) => return Err(SparsificationError::FixedVariable(id)),
            Some(false) => {}
        }
    }
    let removed: BTreeSet<ConstraintId> = eliminated
        .iter()
        .flat_map(|&id| graph.constraints_of(id).iter().copied())
        .collect();
    let mut blanket_set = BTreeSet::new();
    for &cid in &removed {
        let c = graph
            .constraint(cid)
            .ok_or(SparsificationError::UnknownConstraint(cid))?;
        for end in [c.from, c.to] {
            if !eliminated.contains(&end) {
                blanket_set.insert(end);
            }
        }
    }
    let eliminated: Vec<VariableId> = eliminated.into_iter().collect();
    let blanket: Vec<VariableId> = blanket_set.into_iter().collect();
    let n_e = eliminated.len();
    // Index: eliminated first, then blanket.
    let index: BTreeMap<VariableId, usize> = eliminated
        .iter()
        .chain(&blanket)
        .enumerate()
        .map(|(k, id)| (*id, k))
        .collect();
    let mut factors = Vec::with_capacity(removed.len());
    let mut union_find = UnionFind::new(index.len());
    for &cid in &removed {
        let c = graph
            .constraint(cid)
            .ok_or(SparsificationError::UnknownConstraint(cid))?;
        let (a, b) = (index[&c.from], index[&c.to]);
        union_find.union(a, b);
        factors.push(linear_factor(graph, c, options.robust_weighting, a, b)?);
    }

    let n_b = blanket.len();
    let mut information = DMatrix::zeros(3 * n_b, 3 * n_b);
    let mut gradient = DVector::zeros(3 * n_b);
    let mut groups: BTreeMap<usize, (Vec<usize>, Vec<usize>)> = BTreeMap::new();
    for k in 0..index.len() {
        let group = groups.entry(union_find.find(k)).or_default();
        if k < n_e {
            group.0.push(k);
        } else {
            group.1.push(k - n_e);
        }
    }
    let mut components = Vec::new();
    for (root, (e_part, b_part)) in &groups {
        if b_part.is_empty() {
            continue;
        }
        // Local blocks: the component's eliminated variables, then its blanket variables.
        let mut local = vec![None; index.len()];
        for (k, &v) in e_part.iter().enumerate() {
            local[v] = Some(k);
        }
        for (k, &v) in b_part.iter().enumerate() {
            local[n_e + v] = Some(e_part.len() + k);
        }
        let ne = 3 * e_part.len();
        let nb = 3 * b_part.len();
        let mut lambda = DMatrix::zeros(ne + nb, ne + nb);
        let mut g = DVector::zeros(ne + nb);
        for f in factors.iter().filter(|f| union_find.find(f.a) == *root) {
            f.accumulate(|k| local[k], &mut lambda, Some(&mut g));
        }
        let lambda_ee_pinv = pseudo_inverse(
            &lambda.view((0, 0), (ne, ne)).into_owned(),
            options.elimination_eigenvalue_threshold,
        );
        let lambda_be = lambda.view((ne, 0), (nb, ne));
        let gain = lambda_be * &lambda_ee_pinv;
        let marginal = lambda.view((ne, ne), (nb, nb)) - &gain * lambda_be.transpose();
        let marginal = 0.5 * (&marginal + marginal.transpose());
        let marginal_g = g.rows(ne, nb) - &gain * g.rows(0, ne);
        for (r, &br) in b_part.iter().enumerate() {
            for (c, &bc) in b_part.iter().enumerate() {
                information
                    .view_mut((3 * br, 3 * bc), (3, 3))
                    .copy_from(&marginal.view((3 * r, 3 * c), (3, 3)));
            }
            gradient
                .rows_mut(3 * br, 3)
                .copy_from(&marginal_g.rows(3 * r, 3));
        }
        components.push(b_part.clone());
    }
    components.sort();
    let linearization_point = blanket
        .iter()
        .map(|&id| {
            graph
                .pose(id)
                .ok_or(SparsificationError::UnknownVariable(id))
        })
        .collect::<Result<_, _>>()?;
    Ok(DenseMarginal {
        eliminated,
        blanket,
        linearization_point,
        removed_constraints: removed.into_iter().collect(),
        information,
        gradient,
        components,
    })
}
