//! Pose-graph optimization that survives false loop closures: truncated least squares on the
//! constraints the caller marks as candidates for rejection (loop closures), reached from two starts.
//!
//! Objective: `F(x) = Σ_other ρ_c(s_c) + Σ_candidates min(s_c, c̄²)` with `s = eᵀΩe` — the candidates
//! carry [`RobustLoss::TruncatedLeastSquares`] at `c̄² = inlier_chi2`, every other constraint its own loss.
//! A candidate beyond the threshold costs a constant and pulls not at all; a graph whose candidates all
//! fit within it keeps its least-squares optimum exactly. Truncated least squares is flat beyond the
//! threshold, so what it finds depends on where it starts; two starts are tried:
//!
//! 1. **All-inlier track** — the least-squares start: the rotation-first guess or the given estimate,
//!    whichever has the lower χ² (see [`OptimizerOptions::rotation_first_initialization`]). If that
//!    start fits every candidate within the threshold, Levenberg–Marquardt on `F` from it; if every
//!    candidate still fits at the end, the graph holds a least-squares optimum of all its constraints
//!    and that is the answer: a clean graph costs one least-squares optimization. (The guess of each
//!    benchmark graph fits every one of its loop closures; with 100 or 1000 false closures 186 to 2515
//!    candidates lie beyond the threshold at the guess, bent by the false ones, and running
//!    Levenberg–Marquardt from there anyway cost up to 100 steps and never gave the lower `F` — so it
//!    is not run.)
//! 2. **Rejection track** — when track 1's start or end leaves a candidate beyond the threshold. From
//!    the given estimate (no rotation-first guess: with false closures it is bent by them), dynamic
//!    covariance scaling (Agarwal et al., ICRA 2013) at a small `Φ` on the candidates rejects the false
//!    ones while the odometry chain holds the graph; then Levenberg–Marquardt on `F` from there, so that
//!    the rejected closures lose the residual pull DCS leaves them, the true closures DCS down-weighted
//!    count fully again, and closures that fit again are taken back.
//!
//! When both tracks ran to the end, the one whose result has the lower `F` is kept. Constraints whose
//! weight falls below [`OptimizerOptions::prune_weight`] (every candidate beyond the threshold) are left
//! out of the sparse linear system, so a thousand rejected long-range closures add no fill-in to the
//! factorization.
//!
//! The trade-off: a false closure that happens to fit the graph — one whose χ² stays below the
//! threshold once the graph bends a little towards it — is an inlier of `F` and is kept; truncation
//! tells closures apart by how well they fit, not by where they come from.

use serde::Deserialize;
use thiserror::Error;

use super::constraint::{Constraint, RobustLoss};
use super::graph::PoseGraph;
use super::ids::VariableId;
use super::optimizer::{Optimizer, OptimizerOptions, OptimizerOptionsError, Termination};
use crate::geometry::Rigid2;

/// Options of the [`RobustOptimizer`].
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RobustOptimizerOptions {
    /// The truncation threshold `c̄²` on a candidate's squared Mahalanobis norm `eᵀΩe` (unitless, > 0):
    /// beyond it a candidate is rejected. Default 25. Why: `docs/TUNING.md#ropt-inlier-chi2`.
    pub inlier_chi2: f64,
    /// `Φ` of the rejection track's dynamic covariance scaling, on the squared Mahalanobis norm
    /// (unitless, > 0). Agarwal et al. use 1.
    pub rejection_phi: f64,
    /// Levenberg–Marquardt options of every stage; `rotation_first_initialization` applies to the
    /// all-inlier track only.
    pub optimizer: OptimizerOptions,
}

impl RobustOptimizerOptions {
    /// The defaults: threshold 25, `Φ` = 1, the optimizer's defaults with the rotation-first guess on.
    pub const DEFAULT: Self = Self {
        inlier_chi2: 25.0,
        rejection_phi: 1.0,
        optimizer: OptimizerOptions {
            rotation_first_initialization: true,
            ..OptimizerOptions::DEFAULT
        },
    };

    /// Checks that every field is usable.
    pub fn validate(&self) -> Result<(), RobustOptimizerOptionsError> {
        if !(self.inlier_chi2.is_finite() && self.inlier_chi2 > 0.0) {
            return Err(RobustOptimizerOptionsError::InlierChi2(self.inlier_chi2));
        }
        if !(self.rejection_phi.is_finite() && self.rejection_phi > 0.0) {
            return Err(RobustOptimizerOptionsError::RejectionPhi(
                self.rejection_phi,
            ));
        }
        Ok(self.optimizer.validate()?)
    }
}

impl Default for RobustOptimizerOptions {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Invalid [`RobustOptimizerOptions`].
#[derive(Debug, Error, Clone, PartialEq)]
pub enum RobustOptimizerOptionsError {
    /// `inlier_chi2` must be finite and positive.
    #[error("inlier_chi2 must be finite and positive, got {0}")]
    InlierChi2(f64),
    /// `rejection_phi` must be finite and positive.
    #[error("rejection_phi must be finite and positive, got {0}")]
    RejectionPhi(f64),
    /// The nested optimizer options are invalid.
    #[error(transparent)]
    Optimizer(#[from] OptimizerOptionsError),
}

/// Which track's result a [`RobustOptimizer`] kept.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RobustTrack {
    /// Every candidate fits: the least-squares optimum of the whole graph.
    AllInliers,
    /// The all-inlier track (its start fitted every candidate) ended with candidates beyond the
    /// threshold, and at a lower cost than the rejection track.
    Truncated,
    /// The rejection track (DCS, then truncated least squares) had the lower cost.
    Rejection,
}

/// What one [`RobustOptimizer::optimize`] call did.
#[derive(Clone, Debug, PartialEq)]
pub struct RobustOptimizationSummary {
    /// χ² of the whole graph before (robust losses ignored).
    pub initial_chi2: f64,
    /// χ² of the whole graph after, rejected candidates included.
    pub final_chi2: f64,
    /// The objective `F` after (candidates truncated at the threshold).
    pub final_cost: f64,
    /// Levenberg–Marquardt steps tried over all stages run (the rotation-first guess not counted).
    pub iterations: usize,
    /// Candidates (constraints the caller allowed to be rejected).
    pub candidates: usize,
    /// Candidates beyond the threshold at the end: the rejected ones.
    pub rejected: usize,
    /// Constraints left out of the linear system at the end of the kept track's last stage.
    pub pruned_constraints: usize,
    /// Whether the rejection track ran (the all-inlier track's start or end left a candidate beyond the
    /// threshold).
    pub rejection_track_ran: bool,
    /// The track kept.
    pub track: RobustTrack,
    /// How the kept track's last stage ended.
    pub termination: Termination,
}

/// Truncated-least-squares pose-graph optimizer over caller-chosen candidate constraints (see the
/// module docs). Keeps its [`Optimizer`], so a least-squares solve that follows the rotation-first
/// guess on the same structure reuses the guess's symbolic factorization.
#[derive(Debug)]
pub struct RobustOptimizer {
    options: RobustOptimizerOptions,
    /// Every stage's optimizer, without the rotation-first guess (taken, when configured, by
    /// [`Optimizer::initialize_rotation_first`] at the all-inlier track's start only).
    optimizer: Optimizer,
}

impl RobustOptimizer {
    /// An optimizer with these options (validated).
    pub fn new(options: RobustOptimizerOptions) -> Result<Self, RobustOptimizerOptionsError> {
        options.validate()?;
        let optimizer = Optimizer::new(OptimizerOptions {
            rotation_first_initialization: false,
            ..options.optimizer.clone()
        })?;
        Ok(Self { options, optimizer })
    }

    /// The options.
    pub fn options(&self) -> &RobustOptimizerOptions {
        &self.options
    }

    /// Minimises `F` (module docs) with the constraints for which `is_candidate` holds truncated,
    /// writing the kept track's poses into `graph`; the graph's constraints (and their losses) are left
    /// as they are.
    pub fn optimize(
        &mut self,
        graph: &mut PoseGraph,
        is_candidate: impl Fn(&Constraint) -> bool,
    ) -> RobustOptimizationSummary {
        let truncated = RobustLoss::TruncatedLeastSquares {
            threshold: self.options.inlier_chi2,
        };
        let dcs = RobustLoss::Dcs {
            phi: self.options.rejection_phi,
        };
        let candidates_get = |loss: RobustLoss| {
            let is_candidate = &is_candidate;
            move |c: &Constraint| if is_candidate(c) { loss } else { c.loss }
        };
        let candidates = graph.constraints().filter(|(_, c)| is_candidate(c)).count();
        let initial_chi2 = graph.chi2();
        let given = poses(graph);

        // 1. The all-inlier track, from the least-squares start, only if that start fits every candidate.
        if self.options.optimizer.rotation_first_initialization {
            self.optimizer.initialize_rotation_first(graph);
        }
        let mut iterations = 0;
        let mut first = None;
        if self.rejected(graph, &is_candidate) == 0 {
            let summary = self
                .optimizer
                .optimize_with_losses(graph, candidates_get(truncated));
            iterations += summary.iterations;
            if self.rejected(graph, &is_candidate) == 0 {
                return RobustOptimizationSummary {
                    initial_chi2,
                    final_chi2: summary.final_chi2,
                    final_cost: summary.final_cost,
                    iterations,
                    candidates,
                    rejected: 0,
                    pruned_constraints: summary.pruned_constraints,
                    rejection_track_ran: false,
                    track: RobustTrack::AllInliers,
                    termination: summary.termination,
                };
            }
            first = Some((poses(graph), summary));
        }

        // 2. The rejection track, from the given poses.
        set_poses(graph, &given);
        iterations += self
            .optimizer
            .optimize_with_losses(graph, candidates_get(dcs))
            .iterations;
        let mut summary = self
            .optimizer
            .optimize_with_losses(graph, candidates_get(truncated));
        iterations += summary.iterations;
        let mut track = RobustTrack::Rejection;
        if let Some((first_poses, first_summary)) = first
            && first_summary.final_cost <= summary.final_cost
        {
            set_poses(graph, &first_poses);
            summary = first_summary;
            track = RobustTrack::Truncated;
        }
        RobustOptimizationSummary {
            initial_chi2,
            final_chi2: summary.final_chi2,
            final_cost: summary.final_cost,
            iterations,
            candidates,
            rejected: self.rejected(graph, &is_candidate),
            pruned_constraints: summary.pruned_constraints,
            rejection_track_ran: true,
            track,
            termination: summary.termination,
        }
    }

    /// How many candidates of `graph` lie beyond the threshold at its poses.
    fn rejected(&self, graph: &PoseGraph, is_candidate: &impl Fn(&Constraint) -> bool) -> usize {
        graph
            .constraints()
            .filter(|(_, c)| is_candidate(c))
            .filter(|(_, c)| match (graph.pose(c.from), graph.pose(c.to)) {
                (Some(a), Some(b)) => c.chi2(&a, &b) > self.options.inlier_chi2,
                _ => false,
            })
            .count()
    }
}

/// The graph's poses, by variable.
fn poses(graph: &PoseGraph) -> Vec<(VariableId, Rigid2)> {
    graph.variables().map(|(id, pose, _)| (id, pose)).collect()
}

/// Puts back poses taken from this graph by [`poses`].
fn set_poses(graph: &mut PoseGraph, poses: &[(VariableId, Rigid2)]) {
    for &(id, pose) in poses {
        // Cannot fail: the ids came from this graph and the poses are finite.
        let _ = graph.set_pose(id, pose);
    }
}
