//! Options of the global SLAM back end.

use serde::Deserialize;

use super::ConstraintBuilderOptions;
use crate::pose_graph::{OptimizerOptions, OptimizerOptionsError};
use crate::scan_matching::MatchError;

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
    /// The optimizer's options are invalid.
    #[error("optimizer: {0}")]
    Optimizer(#[from] OptimizerOptionsError),
    /// A scan matcher's options are invalid (`fast_correlative` or `least_squares` of the constraint
    /// builder).
    #[error("constraint_builder.{field}: {source}")]
    ScanMatcher {
        /// Which matcher's options.
        field: &'static str,
        /// Why.
        source: MatchError,
    },
}

/// How LLO's nodes and submaps become a pose graph, and how often it is optimized.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GlobalSlamOptions {
    /// Optimize the graph every this many new nodes (0: only when asked). Default 90 (one submap's worth).
    pub optimize_every_n_nodes: usize,
    /// Standard deviation (m) of a node's translation relative to a submap it was inserted into, from LLO's
    /// scan-to-submap matching. Default 0.5 m. Why: `docs/TUNING.md#gs-intra-submap-translation-sigma`.
    pub intra_submap_translation_sigma: f64,
    /// Standard deviation (rad) of that relative rotation. Default 0.1 rad.
    pub intra_submap_rotation_sigma: f64,
    /// Growth of `intra_submap_translation_sigma` with the path (m) LLO drove from the submap's first node to
    /// the node (m per m, added in quadrature): a submap is rigid in the graph but LLO drifted while it built
    /// it. Default 0 (measured, not yet a default). Why: `docs/TUNING.md#gs-intra-submap-sigma-per-m`.
    pub intra_submap_translation_sigma_per_m: f64,
    /// The same growth of `intra_submap_rotation_sigma` (rad per m). Default 0.
    pub intra_submap_rotation_sigma_per_m: f64,
    /// Growth of `intra_submap_translation_sigma` with the path from the submap's first node (m per m,
    /// added in quadrature), instead of `intra_submap_translation_sigma_per_m`, in a submap a confirmed
    /// correction says LLO bent: one built along the correction's drift path, for as long as one of the
    /// correction's matches is in the graph (see `SubmapBend`). 0 with `bent_submap_rotation_sigma_per_m`
    /// 0: no submap is ever bent. Default 0.1 m/m (since session 86: judged on three draws a side of the
    /// robustness suite and on the 25-session store). Why: `docs/TUNING.md#gs-bent-submap-sigma-per-m`.
    pub bent_submap_translation_sigma_per_m: f64,
    /// The same growth of `intra_submap_rotation_sigma` in a bent submap (rad per m). Default 0.01.
    pub bent_submap_rotation_sigma_per_m: f64,
    /// With m > 0, a bend grows at m times the drift rate its correction measured (the median innovation
    /// of its matches over the drift path, translation and rotation apart), capped by
    /// `bent_submap_*_sigma_per_m`, instead of at those rates; 0: at those rates. Unitless. Default 0
    /// (measured, not a default). Why: `docs/TUNING.md#gs-bend-drift-rate-multiple`.
    pub bend_drift_rate_multiple: f64,
    /// Standard deviation (m) of the translation between consecutive nodes of a trajectory, from LLO's
    /// relative motion. Default 0.02 m.
    pub odometry_translation_sigma: f64,
    /// Standard deviation (rad) of the rotation between consecutive nodes. Default 0.01 rad. The chain is
    /// plain least squares. Why: `docs/TUNING.md#gs-odometry-huber-scale`.
    pub odometry_rotation_sigma: f64,
    /// Retract an accepted loop closure whose χ² (`eᵀΩe`, unitless) exceeds this after an optimization (put
    /// back once it fits); 0 = never. Default 6. Why: `docs/TUNING.md#gs-loop-closure-retraction-chi2`.
    pub loop_closure_retraction_chi2: f64,
    /// A correction confirmed by agreement (matches far from their estimates) stays in the graph, whatever
    /// retraction says, while this many of its trajectory's next nodes judge it by their own matches
    /// (count; 0 = never: retraction alone judges it). Default 20.
    /// Why: `docs/TUNING.md#gs-correction-probation-nodes`.
    pub correction_probation_nodes: usize,
    /// Later nodes whose matches agree with a correction on probation to keep it (never retracted while
    /// its trajectory runs), or, with none agreeing, disagree with it to retract it at once (count, at
    /// least 1). Default 2.
    pub correction_probation_matches: usize,
    /// For a trajectory started with no prior (`GlobalSlam::start_trajectory`), match a node against every
    /// placed finished submap every this many nodes (count; 0 = never). Default 0.
    /// Why: `docs/TUNING.md#gs-unanchored-search-every-n-nodes`.
    pub unanchored_search_every_n_nodes: usize,
    /// Once trajectories are settled (`GlobalSlam::set_trajectory_settled`), optimize only the unsettled ones
    /// and what lies within this many constraints (count) of what changed; 0 = the whole graph. Default 3.
    /// Why: `docs/TUNING.md#gs-settled-region-hops`.
    pub settled_region_hops: usize,
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
            intra_submap_translation_sigma_per_m: 0.0,
            intra_submap_rotation_sigma_per_m: 0.0,
            bent_submap_translation_sigma_per_m: 0.1,
            bent_submap_rotation_sigma_per_m: 0.01,
            bend_drift_rate_multiple: 0.0,
            odometry_translation_sigma: 0.02,
            odometry_rotation_sigma: 0.01,
            loop_closure_retraction_chi2: 6.0,
            correction_probation_nodes: 20,
            correction_probation_matches: 2,
            unanchored_search_every_n_nodes: 0,
            settled_region_hops: 3,
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
        for (name, value) in [
            (
                "intra_submap_translation_sigma_per_m",
                self.intra_submap_translation_sigma_per_m,
            ),
            (
                "intra_submap_rotation_sigma_per_m",
                self.intra_submap_rotation_sigma_per_m,
            ),
            (
                "bent_submap_translation_sigma_per_m",
                self.bent_submap_translation_sigma_per_m,
            ),
            (
                "bent_submap_rotation_sigma_per_m",
                self.bent_submap_rotation_sigma_per_m,
            ),
            ("bend_drift_rate_multiple", self.bend_drift_rate_multiple),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(GlobalSlamOptionsError::Invalid(format!(
                    "{name} must be a finite number >= 0, got {value}"
                )));
            }
        }
        if !(self.loop_closure_retraction_chi2.is_finite()
            && self.loop_closure_retraction_chi2 >= 0.0)
        {
            return Err(GlobalSlamOptionsError::Invalid(format!(
                "loop_closure_retraction_chi2 must be a finite number >= 0, got {}",
                self.loop_closure_retraction_chi2
            )));
        }
        if self.correction_probation_matches == 0 {
            return Err(GlobalSlamOptionsError::Invalid(
                "correction_probation_matches must be at least 1".to_owned(),
            ));
        }
        self.constraint_builder.validate()?;
        Ok(self.optimizer.validate()?)
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
        let bad = GlobalSlamOptions {
            intra_submap_rotation_sigma_per_m: -0.01,
            ..Default::default()
        };
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("intra_submap_rotation_sigma_per_m"), "{err}");
        let bad = GlobalSlamOptions {
            bent_submap_translation_sigma_per_m: f64::INFINITY,
            ..Default::default()
        };
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("bent_submap_translation_sigma_per_m"), "{err}");
    }

    // Reference: issue 35 — errors keep their `source()` chain instead of being turned into strings.
    #[test]
    fn a_bad_nested_option_keeps_its_own_error_as_the_source() {
        use std::error::Error as _;
        let bad_optimizer = GlobalSlamOptions {
            optimizer: OptimizerOptions {
                initial_lambda: -1.0,
                ..OptimizerOptions::default()
            },
            ..GlobalSlamOptions::default()
        };
        let err = bad_optimizer.validate().unwrap_err();
        assert!(
            matches!(err, GlobalSlamOptionsError::Optimizer(_)),
            "{err:?}"
        );
        let source = err.source().expect("the optimizer's error");
        assert!(source.downcast_ref::<OptimizerOptionsError>().is_some());
        assert!(err.to_string().starts_with("optimizer: "), "{err}");

        let mut bad_matcher = GlobalSlamOptions::default();
        bad_matcher
            .constraint_builder
            .least_squares
            .translation_weight = -1.0;
        let err = bad_matcher.validate().unwrap_err();
        assert!(
            matches!(
                err,
                GlobalSlamOptionsError::ScanMatcher {
                    field: "least_squares",
                    ..
                }
            ),
            "{err:?}"
        );
        let source = err.source().expect("the matcher's error");
        assert!(source.downcast_ref::<MatchError>().is_some());
        assert!(
            err.to_string()
                .starts_with("constraint_builder.least_squares: "),
            "{err}"
        );
    }
}
