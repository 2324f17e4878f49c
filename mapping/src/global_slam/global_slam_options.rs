//! Options of the global SLAM back end.

use serde::Deserialize;

use super::ConstraintBuilderOptions;
use crate::pose_graph::OptimizerOptions;

/// Invalid [`GlobalSlamOptions`].
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GlobalSlamOptionsError {
    /// A standard deviation is not a positive finite number.
    #[error("{name} must be a positive finite number of {unit}, got {value}")]
    NonPositiveSigma {
        /// Option name.
        name: &'static str,
        /// Its unit.
        unit: &'static str,
        /// Offending value.
        value: f64,
    },
    /// A ratio is outside `[0, 1]`.
    #[error("{name} must be in [0, 1], got {value}")]
    RatioOutOfRange {
        /// Option name.
        name: &'static str,
        /// Offending value.
        value: f64,
    },
    /// Another option is invalid.
    #[error("{0}")]
    Invalid(String),
}

/// How LLO's nodes and submaps become a pose graph, and how often it is optimized.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GlobalSlamOptions {
    /// Optimize the graph every this many new nodes (0: only when asked). Default 90 (one submap's worth).
    pub optimize_every_n_nodes: usize,
    /// Standard deviation (m) of a node's translation relative to a submap it was inserted into, as given by
    /// LLO's scan-to-submap matching. Default 0.5 m: loose, so that the graph's shape comes from the chain
    /// of consecutive nodes and the loop closures, and a submap LLO bent a little does not drag its nodes
    /// (Freiburg recordings, session 9: Intel 0.041 → 0.033 m, loop-closure precision up on all three).
    pub intra_submap_translation_sigma: f64,
    /// Standard deviation (rad) of that relative rotation. Default 0.1 rad.
    pub intra_submap_rotation_sigma: f64,
    /// Standard deviation (m) of the translation between consecutive nodes of a trajectory, from LLO's
    /// relative motion. Default 0.02 m.
    pub odometry_translation_sigma: f64,
    /// Standard deviation (rad) of the rotation between consecutive nodes. Default 0.01 rad. The
    /// constraint is plain least squares: a robust (Huber) chain let a few agreeing wrong closures kink
    /// it at one step instead of being refused by it, and changed nothing on the robustness suite
    /// (BENCHMARKS.md, "Session 25").
    pub odometry_rotation_sigma: f64,
    /// After every optimization, an accepted loop closure whose χ² (`eᵀΩe` with its own information,
    /// unitless) still exceeds this is taken out of the graph, and the graph is optimized again without
    /// it: the odometry chain and the other closures together refuse it (a look-alike place, or several
    /// matches that agreed on the wrong one). A retracted closure the graph fits again later is put back.
    /// 0 = never. Default 6 (2.4σ on one axis; the closures' 3 cm / 0.57° sigmas put the loop-closure
    /// precision bounds, 0.2 m and 1°, at χ² ≈ 3 on rotation alone). Freiburg recordings (relations
    /// error; share of the map's closures within 0.2 m and 1°), none → 9 (session 11) → 6 (session 12):
    /// Intel 0.0320 → 0.0313 → 0.0314 m and 0.912 → 0.973 → 0.984, CSAIL 0.0341 → 0.0343 → 0.0340 m and
    /// 0.975 → 0.993 → 1.000, ACES 0.0356 → 0.0358 → 0.0359 m and 0.978 → 0.994 → 0.998; at 25: Intel
    /// 0.0313 m, 0.944; at 4 and 5: Intel 0.0318 and 0.0316 m, 0.998 and 0.994, but 4–5× the wall time
    /// (more closures retracted and put back, each a re-optimization).
    pub loop_closure_retraction_chi2: f64,
    /// For a trajectory started with no prior on a map that already holds others (see
    /// `GlobalSlam::start_trajectory`): every this many nodes (count; 0 = never), match the node
    /// against every finished submap of the placed trajectories with no prior, until a match places the
    /// trajectory. Default 0: sessions of a lifelong map are placed by `lifelong::SessionStart` (a
    /// whole-map search with an ambiguity test, then probation), not by a single scan's full-submap match.
    /// (It was 10, and a lifelong configuration that set any other `[lifelong.global]` field silently
    /// turned this on again: the 25-session store then placed session 6 51 m off from one scan.)
    pub unanchored_search_every_n_nodes: usize,
    /// Once some trajectories are settled (a lifelong map's ended sessions; see
    /// `GlobalSlam::set_trajectory_settled`), an optimization moves only the unsettled trajectories, the
    /// endpoints of constraints added or changed since the last optimization, and the variables within
    /// this many constraints of those (count); the rest of the graph holds where the last optimization
    /// left it. `None` (the default): every optimization is whole. Off by default because on the
    /// 25-session store (seed 1, session 14) one hop bent one session's smoothed trajectory 1.6 m at its
    /// end (session 15: smoothed MRCL 0.40, map change rate 0.28 instead of 0.20) although its online
    /// estimate was right; with faer's eigendecompositions the whole-graph refinement is cheap enough.
    pub settled_region_hops: Option<usize>,
    /// Loop-closure search (GLM).
    pub constraint_builder: ConstraintBuilderOptions,
    /// Sparse Levenberg-Marquardt settings.
    pub optimizer: OptimizerOptions,
}

impl Default for GlobalSlamOptions {
    fn default() -> Self {
        Self {
            optimize_every_n_nodes: 90,
            intra_submap_translation_sigma: 0.5,
            intra_submap_rotation_sigma: 0.1,
            odometry_translation_sigma: 0.02,
            odometry_rotation_sigma: 0.01,
            loop_closure_retraction_chi2: 6.0,
            unanchored_search_every_n_nodes: 0,
            settled_region_hops: None,
            constraint_builder: ConstraintBuilderOptions::default(),
            optimizer: OptimizerOptions::default(),
        }
    }
}

pub(crate) fn check_sigma(
    name: &'static str,
    unit: &'static str,
    value: f64,
) -> Result<(), GlobalSlamOptionsError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(GlobalSlamOptionsError::NonPositiveSigma { name, unit, value })
    }
}

impl GlobalSlamOptions {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), GlobalSlamOptionsError> {
        check_sigma(
            "intra_submap_translation_sigma",
            "m",
            self.intra_submap_translation_sigma,
        )?;
        check_sigma(
            "intra_submap_rotation_sigma",
            "rad",
            self.intra_submap_rotation_sigma,
        )?;
        check_sigma(
            "odometry_translation_sigma",
            "m",
            self.odometry_translation_sigma,
        )?;
        check_sigma(
            "odometry_rotation_sigma",
            "rad",
            self.odometry_rotation_sigma,
        )?;
        if !(self.loop_closure_retraction_chi2.is_finite()
            && self.loop_closure_retraction_chi2 >= 0.0)
        {
            return Err(GlobalSlamOptionsError::Invalid(format!(
                "loop_closure_retraction_chi2 must be a finite number >= 0, got {}",
                self.loop_closure_retraction_chi2
            )));
        }
        self.constraint_builder.validate()?;
        self.optimizer
            .validate()
            .map_err(|e| GlobalSlamOptionsError::Invalid(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_sigmas_are_named() {
        assert_eq!(GlobalSlamOptions::default().validate(), Ok(()));
        let bad = GlobalSlamOptions {
            odometry_rotation_sigma: 0.0,
            ..Default::default()
        };
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("odometry_rotation_sigma"), "{err}");
    }
}
