//! The options of session-start relocalization: the rendered map, the search and its refusals.

use serde::Deserialize;

#[cfg(doc)]
use super::start_search::thinned_to;
#[cfg(doc)]
use super::{SearchEvidence, StartSearch, relocalize_session_start};
use crate::lifelong::{LifelongOptionsError, MapCells};
use crate::scan_matching::LeastSquaresScanMatcherOptions;
#[cfg(doc)]
use crate::scan_matching::RelocalizerOptions;

/// Options of [`relocalize_session_start`].
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RelocalizationOptions {
    /// Cell size of the rendered map, metres. Default 0.05 m (the submaps').
    pub resolution: f64,
    /// How the rendered map values a cell the submaps disagree on ([`MapCells`]). Default `newest`.
    /// Why: `docs/TUNING.md#reloc-map-cells`.
    pub map_cells: MapCells,
    /// Voxel size the merged cloud is thinned to, metres (0: no thinning). Default 0.15 m.
    /// Why: `docs/TUNING.md#reloc-voxel-size`.
    pub voxel_size: f64,
    /// Most points of the merged cloud the whole-map search places (count ≥ 1; a larger cloud is thinned with
    /// coarser voxels, [`thinned_to`]). Default 200. Why: `docs/TUNING.md#reloc-max-search-points`.
    pub max_search_points: usize,
    /// Minimum branch-and-bound score (mean probability at the points) to accept. Default 0.6.
    pub min_score: f32,
    /// Depth of the branch-and-bound precomputation. Default 7.
    pub branch_and_bound_depth: u32,
    /// The whole-map searches tried in turn, as map cells per coarse-grid cell along each axis (each
    /// 1..=16; at least one). Default `[4, 2]`. Why: `docs/TUNING.md#reloc-coarse-factors`.
    pub coarse_factors: Vec<u32>,
    /// Coarse-grid score below the best past which whole-map candidates are not looked for, score units ≥ 0
    /// (`inf`: no bound). Default infinite. Why: `docs/TUNING.md#reloc-candidate-score-window`.
    pub candidate_score_window: f32,
    /// Refuse a match whose runner-up scores within this much of it (score units; 0 = accept ties).
    /// Default 0.03. Why: `docs/TUNING.md#reloc-min-score-margin`.
    pub min_score_margin: f32,
    /// How far (metres) a point may fall from a surface the map saw and still count as a hit while
    /// searching (0: cell-exactly). Default 0.15 m. Why: `docs/TUNING.md#reloc-match-tolerance`.
    pub match_tolerance: f64,
    /// Paired z a retry's best candidate must reach against every other (clouds of at most
    /// `long_route_scans` scans). Default 3. Why: `docs/TUNING.md#reloc-min-disambiguation-z`.
    pub min_disambiguation_z: f64,
    /// The paired test's bar (as `min_disambiguation_z`) for a cloud of more than `long_route_scans` scans.
    /// Unitless. Default 4. Why: `docs/TUNING.md#reloc-long-route-min-disambiguation-z`.
    pub long_route_min_disambiguation_z: f64,
    /// Clouds of more scans (one per node) than this are tested at `long_route_min_disambiguation_z`.
    /// Count. Default 200 (about 40 m of driving in the simulated store).
    pub long_route_scans: usize,
    /// Block size of the route's paired tests ([`crate::scan_matching::blocked_paired_z`]), metres ≥ 0
    /// (0: per point). Default 1.2 m. Why: `docs/TUNING.md#reloc-route-block-m`.
    pub route_block_m: f64,
    /// The paired test of `min_disambiguation_z` for a one-shot answer ([`StartSearch::decide`]). Unitless.
    /// Default 4. Why: `docs/TUNING.md#reloc-min-answer-z`.
    pub min_answer_z: f64,
    /// Smallest mean probability of the cloud at the best pose on the unfiltered map for a one-shot answer
    /// ([`StartSearch::decide`]). Default 0.4. Why: `docs/TUNING.md#reloc-min-unfiltered-score`.
    pub min_unfiltered_score: f32,
    /// Largest [`SearchEvidence::first_scan_shift_m`] (metres) of a one-shot answer. Default 0.18 m.
    /// Why: `docs/TUNING.md#reloc-max-first-scan-shift`.
    pub max_first_scan_shift: f64,
    /// Distinct coarse candidates refined at full resolution (count ≥ 1; see [`RelocalizerOptions`]).
    /// Default 8. Why: `docs/TUNING.md#reloc-max-candidates`.
    pub max_candidates: usize,
    /// Half-width of the window searched around a prior pose ([`StartSearch::check_prior`]: a robot's
    /// last pose, at its dock), metres ≥ 0. Default 0.5 m.
    pub prior_window_m: f64,
    /// ... and its angular half-width, radians in [0, π]. Default 10°.
    pub prior_window_rad: f64,
    /// Refinement of the match.
    pub least_squares: LeastSquaresScanMatcherOptions,
}

impl Default for RelocalizationOptions {
    fn default() -> Self {
        Self {
            resolution: 0.05,
            map_cells: MapCells::default(),
            voxel_size: 0.15,
            max_search_points: 200,
            min_score: 0.6,
            branch_and_bound_depth: 7,
            coarse_factors: vec![4, 2],
            candidate_score_window: f32::INFINITY,
            max_candidates: 8,
            min_score_margin: 0.03,
            match_tolerance: 0.15,
            min_disambiguation_z: 3.0,
            long_route_min_disambiguation_z: 4.0,
            long_route_scans: 200,
            route_block_m: 1.2,
            min_answer_z: 4.0,
            min_unfiltered_score: 0.4,
            max_first_scan_shift: 0.18,
            prior_window_m: 0.5,
            prior_window_rad: 10f64.to_radians(),
            least_squares: LeastSquaresScanMatcherOptions::default(),
        }
    }
}

impl RelocalizationOptions {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), LifelongOptionsError> {
        if !(self.resolution.is_finite() && self.resolution > 0.0) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "resolution",
                reason: "must be a positive number of metres",
            });
        }
        if !(self.voxel_size.is_finite() && self.voxel_size >= 0.0) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "voxel_size",
                reason: "must be a non-negative number of metres",
            });
        }
        if self.coarse_factors.is_empty()
            || self.coarse_factors.iter().any(|f| !(1..=16).contains(f))
        {
            return Err(LifelongOptionsError::OutOfRange {
                field: "coarse_factors",
                reason: "must list at least one factor, each in 1..=16",
            });
        }
        if self.candidate_score_window.is_nan() || self.candidate_score_window < 0.0 {
            return Err(LifelongOptionsError::OutOfRange {
                field: "candidate_score_window",
                reason: "must be a non-negative score (or inf)",
            });
        }
        if self.max_search_points == 0 {
            return Err(LifelongOptionsError::OutOfRange {
                field: "max_search_points",
                reason: "must be at least 1",
            });
        }
        if !(self.match_tolerance.is_finite() && (0.0..=1.0).contains(&self.match_tolerance)) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "match_tolerance",
                reason: "must be in [0, 1] metres",
            });
        }
        if !(self.min_disambiguation_z.is_finite() && self.min_disambiguation_z > 0.0) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "min_disambiguation_z",
                reason: "must be a positive number",
            });
        }
        if !(self.long_route_min_disambiguation_z.is_finite()
            && self.long_route_min_disambiguation_z > 0.0)
        {
            return Err(LifelongOptionsError::OutOfRange {
                field: "long_route_min_disambiguation_z",
                reason: "must be a positive number",
            });
        }
        if !(self.route_block_m.is_finite() && self.route_block_m >= 0.0) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "route_block_m",
                reason: "must be a non-negative number of metres",
            });
        }
        if !(0.0..=1.0).contains(&self.min_score_margin) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "min_score_margin",
                reason: "must be in [0, 1]",
            });
        }
        if !(self.min_answer_z.is_finite() && self.min_answer_z > 0.0) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "min_answer_z",
                reason: "must be a positive number",
            });
        }
        if !(self.max_first_scan_shift.is_finite() && self.max_first_scan_shift >= 0.0) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "max_first_scan_shift",
                reason: "must be a non-negative number of metres",
            });
        }
        if !(0.0..=1.0).contains(&self.min_unfiltered_score) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "min_unfiltered_score",
                reason: "must be in [0, 1]",
            });
        }
        if !(0.0..=1.0).contains(&self.min_score) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "min_score",
                reason: "must be in [0, 1]",
            });
        }
        if !(self.prior_window_m.is_finite() && self.prior_window_m >= 0.0) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "prior_window_m",
                reason: "must be a non-negative number of metres",
            });
        }
        if !(0.0..=std::f64::consts::PI).contains(&self.prior_window_rad) {
            return Err(LifelongOptionsError::OutOfRange {
                field: "prior_window_rad",
                reason: "must be in [0, π] radians",
            });
        }
        self.least_squares
            .validate()
            .map_err(|_| LifelongOptionsError::OutOfRange {
                field: "least_squares",
                reason: "is invalid",
            })
    }
}
