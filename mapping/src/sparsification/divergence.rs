//! Kullback–Leibler divergences between the exact marginal and an approximation of it.
//!
//! For Gaussians `p = N(μ_p, Σ_p)` and `q = N(μ_q, Λ_q⁻¹)` of dimension `k`,
//!
//! ```text
//! KL(p‖q) = ½ [ tr(Λ_q Σ_p) − k + ln det Λ_p − ln det Λ_q + (μ_q − μ_p)ᵀ Λ_q (μ_q − μ_p) ]   (nats)
//! ```
//!
//! Both are gauge-fixed the same way (the same variables held), which makes the value independent of
//! the choice: relative constraints annihilate the same rigid-motion directions, so holding another
//! variable changes both by the same linear map, under which KL is invariant.

use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{DMatrix, DVector};

use super::marginalization::{linear_factor, marginalize};
use super::options::SparsificationOptions;
use super::{SparsificationError, UnionFind};
use crate::pose_graph::{Constraint, PoseGraph, VariableId};

/// `KL(p‖q)` from `q`'s information, `p`'s covariance and `ln det Λ_p`; `+∞` if `Λ_q` is not positive
/// definite (`q` leaves a direction free that `p` determines).
pub(crate) fn gaussian_kl_divergence(
    information_q: &DMatrix<f64>,
    covariance_p: &DMatrix<f64>,
    log_det_information_p: f64,
) -> f64 {
    let k = information_q.nrows();
    if k == 0 {
        return 0.0;
    }
    let Some(cholesky) = information_q.clone().cholesky() else {
        return f64::INFINITY;
    };
    let log_det_q: f64 = 2.0 * cholesky.l().diagonal().iter().map(|d| d.ln()).sum::<f64>();
    let trace = information_q.component_mul(covariance_p).sum();
    (0.5 * (trace - k as f64 + log_det_information_p - log_det_q)).max(0.0)
}

/// `KL(p‖q)` in nats (covariance and mean terms), where `p` is the exact marginal of `graph` over every variable that remains after
/// eliminating `eliminate`, and `q` is the remaining graph with the constraints touching the eliminated
/// variables replaced by `replacement` (the tree of [`super::sparsify`], or nothing for
/// [`super::delete`]). Both are linearised at the graph's current estimate, each with its mean one
/// Gauss–Newton step away (`μ = −Λ⁻¹ g`), so the mean term `½ Δμᵀ Λ_q Δμ` counts too; the gauge is fixed by the
/// graph's fixed variables, or else by the smallest variable of each connected component.
///
/// Returns `+∞` when `q` leaves poses undetermined that `p` determines (e.g. deleting the only link
/// between two parts of the graph).
///
/// Dense: `O(n³)` in the number of remaining variables, meant for tests and benchmarks on graphs of
/// up to a few hundred poses.
pub fn kl_divergence(
    graph: &PoseGraph,
    eliminate: &[VariableId],
    replacement: &[Constraint],
    options: &SparsificationOptions,
) -> Result<f64, SparsificationError> {
    let marginal = marginalize(graph, eliminate, options)?;
    let eliminated: BTreeSet<VariableId> = marginal.eliminated.iter().copied().collect();
    let remaining: Vec<(VariableId, bool)> = graph
        .variables()
        .filter(|(id, _, _)| !eliminated.contains(id))
        .map(|(id, _, fixed)| (id, fixed))
        .collect();
    let index: BTreeMap<VariableId, usize> = remaining
        .iter()
        .enumerate()
        .map(|(k, (id, _))| (*id, k))
        .collect();
    let n = remaining.len();

    let mut kept = Vec::new();
    let mut p_components = UnionFind::new(n);
    let mut q_components = UnionFind::new(n);
    for (_, c) in graph.constraints() {
        if eliminated.contains(&c.from) || eliminated.contains(&c.to) {
            continue;
        }
        let (a, b) = (index[&c.from], index[&c.to]);
        p_components.union(a, b);
        q_components.union(a, b);
        kept.push(linear_factor(graph, c, options.robust_weighting, a, b)?);
    }
    for members in &marginal.components {
        for pair in members.windows(2) {
            p_components.union(
                index[&marginal.blanket[pair[0]]],
                index[&marginal.blanket[pair[1]]],
            );
        }
    }
    let mut replaced = Vec::with_capacity(replacement.len());
    for c in replacement {
        for end in [c.from, c.to] {
            if eliminated.contains(&end) {
                return Err(SparsificationError::TouchesEliminated(end));
            }
            if !index.contains_key(&end) {
                return Err(SparsificationError::UnknownVariable(end));
            }
        }
        let (a, b) = (index[&c.from], index[&c.to]);
        q_components.union(a, b);
        replaced.push(linear_factor(graph, c, options.robust_weighting, a, b)?);
    }

    // Gauge: fixed variables, or each component's smallest variable when none of it is fixed.
    let mut anchored = BTreeSet::new();
    for (k, (_, fixed)) in remaining.iter().enumerate() {
        if *fixed {
            anchored.insert(p_components.find(k));
        }
    }
    let mut block = vec![None; n];
    let mut dimension = 0;
    for (k, (_, fixed)) in remaining.iter().enumerate() {
        if *fixed || anchored.insert(p_components.find(k)) {
            continue;
        }
        block[k] = Some(dimension);
        dimension += 1;
    }
    // q must not split a component of p that it cannot anchor.
    let mut q_anchored = BTreeSet::new();
    for (k, (_, fixed)) in remaining.iter().enumerate() {
        if *fixed || block[k].is_none() {
            q_anchored.insert(q_components.find(k));
        }
    }
    if (0..n).any(|k| !q_anchored.contains(&q_components.find(k))) {
        return Ok(f64::INFINITY);
    }

    let k = 3 * dimension;
    let mut rest = DMatrix::zeros(k, k);
    let mut rest_gradient = DVector::zeros(k);
    for f in &kept {
        f.accumulate(|v| block[v], &mut rest, Some(&mut rest_gradient));
    }
    let mut gradient_p = rest_gradient.clone();
    let mut gradient_q = rest_gradient;
    let mut information_p = rest.clone();
    for (r, &br) in marginal.blanket.iter().enumerate() {
        let Some(row) = block[index[&br]] else {
            continue;
        };
        for (c, &bc) in marginal.blanket.iter().enumerate() {
            let Some(col) = block[index[&bc]] else {
                continue;
            };
            let mut view = information_p.fixed_view_mut::<3, 3>(3 * row, 3 * col);
            view += marginal.information.fixed_view::<3, 3>(3 * r, 3 * c);
        }
        let mut view = gradient_p.fixed_rows_mut::<3>(3 * row);
        view += marginal.gradient.fixed_rows::<3>(3 * r);
    }
    let mut information_q = rest;
    for f in &replaced {
        f.accumulate(|v| block[v], &mut information_q, Some(&mut gradient_q));
    }
    let cholesky_p = information_p
        .clone()
        .cholesky()
        .ok_or(SparsificationError::SingularMarginal)?;
    let log_det_p: f64 = 2.0
        * cholesky_p
            .l()
            .diagonal()
            .iter()
            .map(|d| d.ln())
            .sum::<f64>();
    let Some(cholesky_q) = information_q.clone().cholesky() else {
        return Ok(f64::INFINITY);
    };
    let log_det_q: f64 = 2.0
        * cholesky_q
            .l()
            .diagonal()
            .iter()
            .map(|d| d.ln())
            .sum::<f64>();
    // tr(Λ_q Σ_p) − k = tr((Λ_q − Λ_p) Σ_p), and Λ_q − Λ_p only has rows on the touched blocks.
    let difference = &information_q - &information_p;
    let touched: Vec<usize> = (0..k)
        .filter(|&r| difference.row(r).iter().any(|v| *v != 0.0))
        .collect();
    let mut unit = DMatrix::zeros(k, touched.len());
    for (c, &r) in touched.iter().enumerate() {
        unit[(r, c)] = 1.0;
    }
    let covariance_columns = cholesky_p.solve(&unit);
    let mut trace = 0.0;
    for (c, &r) in touched.iter().enumerate() {
        trace += difference
            .row(r)
            .dot(&covariance_columns.column(c).transpose());
    }
    // The means: one Gauss–Newton step from the linearization point for each.
    let mean_difference = cholesky_q.solve(&gradient_q) - cholesky_p.solve(&gradient_p);
    let mean_term = mean_difference.dot(&(&information_q * &mean_difference));
    Ok((0.5 * (trace + log_det_p - log_det_q + mean_term)).max(0.0))
}
