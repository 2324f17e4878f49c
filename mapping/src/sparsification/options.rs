//! Options of [`super::sparsify`] and of the divergence computations.

use serde::Deserialize;
use thiserror::Error;

/// How each edge of the Chow–Liu tree becomes a relative-pose constraint.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
pub enum EdgeModel {
    /// Gauge-invariant Chow–Liu: the tree is the minimum spanning tree of the relative-pose entropies
    /// `½ ln det Σ_rel(i, j)` over the whole blanket, and each edge carries the marginal covariance of the
    /// relative pose `x_i⁻¹ ⊕ x_j` (the conditional `p(x_j | x_i)` with the gauge held at `x_i`). Among
    /// all trees of relative-pose constraints this is the KL-minimal one (see the module docs); it does
    /// not depend on a root.
    RelativeMarginal,
    /// The root-shifted recipe of the design notes: fix the root `r` (the blanket's smallest id), run
    /// Chow–Liu on the mutual information of the other blanket poses, map each conditional
    /// `Σ_c|p` (which also conditions on `r`) to a relative-pose constraint `p → c`, and join the tree's
    /// own root `c₀` (the pose best determined relative to `r`) to `r`. Exact when `r` is a leaf of a
    /// tree-shaped marginal; otherwise the `r`-conditioning makes edges over-confident.
    Conditional,
}

/// How a robust (non-[`crate::pose_graph::RobustLoss::Trivial`]) constraint enters the dense marginal.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
pub enum RobustWeighting {
    /// Scale its information by its iteratively-reweighted-least-squares weight `ρ'(eᵀΩe)` at the
    /// current estimate: the local Gaussian the optimizer itself uses. A loop closure that the robust
    /// loss has down-weighted as an outlier stays down-weighted in the (trivial-loss) tree constraints,
    /// instead of coming back at full confidence for good.
    Irls,
    /// Use its information as if its loss were trivial.
    Ignore,
}

/// Which mean the tree constraints' measurements encode.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
pub enum TreeMean {
    /// Choose the measurements so that, at the linearization point, the tree pulls on the blanket with
    /// exactly the gradient of the exact marginal (`Λ_tree δ = −g_B`). Replacing the removed
    /// constraints then leaves an optimized graph at its optimum (to first order), so the map does not
    /// jump when a submap is trimmed, and the whole-graph means of the exact and the sparsified
    /// posteriors coincide. But where the tree keeps much less information than the clique in the
    /// direction the gradient pulls, `δ = −Λ_tree⁻¹ g_B` is large: the tree's measurements lie far from
    /// the poses, first order no longer holds, and the graph slides (see `docs/TUNING.md#sp-tree-mean`).
    MatchGradient,
    /// Use the exact marginal's own mean (`Λ_B δ = −g_B`, one Gauss–Newton step of the clique from the
    /// estimate): KL-optimal for the blanket marginal taken alone, and close to the poses wherever the
    /// clique pins them; the tree's weaker information then pulls the rest of the graph a little. The
    /// default. Why: `docs/TUNING.md#sp-tree-mean`.
    MatchMarginalMean,
}

/// Options of Chow–Liu sparsification (and of [`super::kl_divergence`]).
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SparsificationOptions {
    /// How tree edges become constraints.
    pub edge_model: EdgeModel,
    /// Which mean the tree's measurements encode. Default `MatchMarginalMean`.
    /// Why: `docs/TUNING.md#sp-tree-mean`.
    pub tree_mean: TreeMean,
    /// How robust constraints touching the eliminated variables are linearised.
    pub robust_weighting: RobustWeighting,
    /// `Λ_EE` (the eliminated variables' information) is inverted by symmetric eigen-decomposition;
    /// eigenvalues below this fraction of the largest are treated as zero (Moore–Penrose
    /// pseudo-inverse): directions of the eliminated poses that no constraint determines pass no
    /// information to the blanket. Unitless, in `[0, 1)`.
    pub elimination_eigenvalue_threshold: f64,
    /// The gauge-fixed blanket marginal `Λ_B` counts as rank-deficient in the eigen-directions whose
    /// eigenvalue is below this fraction of the largest. Those eigenvalues are raised to the threshold
    /// before covariances are taken (a vanishingly weak, relative — never absolute — regularisation),
    /// and the marginal mean does not move along them. Unitless, in `(0, 1)`.
    pub marginal_eigenvalue_threshold: f64,
}

impl SparsificationOptions {
    /// The defaults.
    pub const DEFAULT: Self = Self {
        edge_model: EdgeModel::RelativeMarginal,
        tree_mean: TreeMean::MatchMarginalMean,
        robust_weighting: RobustWeighting::Irls,
        elimination_eigenvalue_threshold: 1e-12,
        marginal_eigenvalue_threshold: 1e-12,
    };

    /// Checks that every field is usable.
    pub fn validate(&self) -> Result<(), SparsificationOptionsError> {
        let t = self.elimination_eigenvalue_threshold;
        if !(t.is_finite() && (0.0..1.0).contains(&t)) {
            return Err(SparsificationOptionsError::EliminationEigenvalueThreshold(
                t,
            ));
        }
        let t = self.marginal_eigenvalue_threshold;
        if !(t.is_finite() && t > 0.0 && t < 1.0) {
            return Err(SparsificationOptionsError::MarginalEigenvalueThreshold(t));
        }
        Ok(())
    }
}

impl Default for SparsificationOptions {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// An unusable [`SparsificationOptions`] field.
#[derive(Debug, Error, Clone, Copy, PartialEq)]
pub enum SparsificationOptionsError {
    /// `elimination_eigenvalue_threshold` must be finite and in `[0, 1)`.
    #[error("elimination_eigenvalue_threshold must be in [0, 1), got {0}")]
    EliminationEigenvalueThreshold(f64),
    /// `marginal_eigenvalue_threshold` must be finite and in `(0, 1)`.
    #[error("marginal_eigenvalue_threshold must be in (0, 1), got {0}")]
    MarginalEigenvalueThreshold(f64),
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_thresholds_are_rejected() {
        assert_eq!(SparsificationOptions::default().validate(), Ok(()));
        let bad = SparsificationOptions {
            marginal_eigenvalue_threshold: 0.0,
            ..SparsificationOptions::DEFAULT
        };
        assert!(matches!(
            bad.validate(),
            Err(SparsificationOptionsError::MarginalEigenvalueThreshold(_))
        ));
        let bad = SparsificationOptions {
            elimination_eigenvalue_threshold: f64::NAN,
            ..SparsificationOptions::DEFAULT
        };
        assert!(bad.validate().is_err());
    }
}
