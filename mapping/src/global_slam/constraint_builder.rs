//! GLM, global LiDAR matching: finds node-to-submap constraints with the branch-and-bound matcher and
//! refines them with the least-squares matcher, as Cartographer's `ConstraintBuilder2D` does.
//!
//! Work is described by [`SearchJob`] values and run by [`ConstraintBuilder::run`], which takes `&self`:
//! the shell may run many jobs on as many threads as it likes (this crate spawns none) and hands the
//! results back to [`super::GlobalSlam::add_search_results`].

use std::collections::BTreeMap;
use std::sync::{Arc, OnceLock};

use nalgebra::{Matrix2, Matrix3, Point2};
use serde::Deserialize;

use super::GlobalSlamOptionsError;
use super::global_slam_options::check_sigma;
use crate::geometry::Rigid2;
use crate::grid::ProbabilityGrid;
use crate::pose_graph::{NodeId, SubmapId};
use crate::scan_matching::{
    FastCorrelativeScanMatcher, FastCorrelativeScanMatcherOptions, LeastSquaresScanMatcher,
    LeastSquaresScanMatcherOptions,
};

/// Loop-closure search settings.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ConstraintBuilderOptions {
    /// Fraction of candidate (node, submap) pairs that are searched, in `[0, 1]`. Default 0.15.
    pub sampling_ratio: f64,
    /// Pairs whose estimated node-to-submap-origin distance exceeds this (m) are not searched. Default 20 m
    /// (Cartographer's is 15 m). Why: `docs/TUNING.md#cb-max-constraint-distance`.
    pub max_constraint_distance: f64,
    /// Minimum branch-and-bound score (mean probability at the scan points) to accept a loop closure
    /// near the current estimate. Default 0.55.
    pub min_score: f32,
    /// Minimum score to accept a match searched over a whole submap with no prior (relocalization).
    /// Default 0.6.
    pub global_localization_min_score: f32,
    /// Refuse a match when a clearly different pose in its window ([`LoopClosure::runner_up_score`]) scores
    /// within this much of it (mean probability). Default 0.02. Why: `docs/TUNING.md#cb-min-score-margin`.
    pub min_score_margin: f32,
    /// Standard deviation (m) of an accepted loop closure's translation. Default 0.03 m.
    pub loop_closure_translation_sigma: f64,
    /// Standard deviation (rad) of an accepted loop closure's rotation. Default 0.01 rad.
    pub loop_closure_rotation_sigma: f64,
    /// Huber threshold on the whitened loop-closure error (in standard deviations). Default 1.
    /// Why: `docs/TUNING.md#cb-huber-scale`.
    pub huber_scale: f64,
    /// Branch-and-bound search window right after a loop closure (it grows with the path since, below) and
    /// depth. Defaults here: 1.5 m, ±15°, depth 7. Why: `docs/TUNING.md#cb-fast-correlative`.
    pub fast_correlative: FastCorrelativeScanMatcherOptions,
    /// How much the translation window grows per metre travelled since the trajectory's last loop closure
    /// (m/m). Default 0.05 (5 %). Why: `docs/TUNING.md#cb-linear-window-growth`.
    pub linear_window_growth: f64,
    /// How much the rotation window grows per metre travelled since the last loop closure (rad/m).
    /// Default 0.0035 (0.2°/m).
    pub angular_window_growth: f64,
    /// The translation window never grows beyond this (m). Default 20 m.
    pub max_linear_search_window: f64,
    /// Heading doubt (rad) an LLO recovery adds to the drift model: after LLO placed a scan by a recovery
    /// search (nothing near the prediction fitted), until the trajectory's next loop closure, the search
    /// window and the drift bound of its later nodes against submaps begun before the recovery grow by
    /// this rotation and by this much times the path since the recovery (m per m). 0 = off. Default
    /// 0.26 rad (15°, GLM's own angular window). Why: `docs/TUNING.md#cb-recovery-heading-doubt`.
    pub recovery_heading_doubt: f64,
    /// A loop closure only resets the window growth when its submap lies at least this far back along the
    /// trajectory (m). Default 20 m. Why: `docs/TUNING.md#cb-min-loop-length`.
    pub min_loop_length: f64,
    /// Refuse a match that moves its node farther than this (m) from its estimate plus `linear_window_growth`
    /// per metre since the last loop. Default 0.5 m. Why: `docs/TUNING.md#cb-max-innovation-translation`.
    pub max_innovation_translation: f64,
    /// … or rotates it more than this (rad), plus `angular_window_growth` per metre. Default 0.052 rad (3°).
    pub max_innovation_rotation: f64,
    /// A match refused as beyond drift is still used once matches of this many nodes (itself included),
    /// against at least two submaps, agree with it (count; 0 = never). Default 5.
    /// Why: `docs/TUNING.md#cb-beyond-drift-confirmations`.
    pub beyond_drift_confirmations: usize,
    /// A match that would move its node more than this (m) from its current estimate is used only once a
    /// match of another node agrees with it (see `agreement_path_length`). Default 0.5 m.
    pub max_unconfirmed_translation: f64,
    /// … or more than this (rad). Default 0.052 rad (3°).
    pub max_unconfirmed_rotation: f64,
    /// An unconfirmed match waits for a match of another node within this path distance (m) that agrees
    /// with it (the two closures and the trajectory between the nodes form a consistent cycle). Default 30 m.
    pub agreement_path_length: f64,
    /// Two matches agree when the cycle they close is off by less than this translation (m) plus 2 %
    /// of the path between their nodes … Default 0.15 m.
    /// Why: `docs/TUNING.md#cb-agreement-translation`.
    pub agreement_translation: f64,
    /// … and this rotation (rad). Default 0.035 rad (2°).
    pub agreement_rotation: f64,
    /// Two matches of one node that do not agree outvote each other only as rivals: where they put the
    /// node differs by more than this (m) or `rival_rotation`. Closer, they are one place seen through
    /// submaps the estimate does not yet hold consistent, and neither outvotes the other (each goes on to
    /// the drift and confirmation gates alone). 0 with `rival_rotation` 0: every match that does not agree
    /// is a rival. Default 0 (0.5 m and 3° measured on the robustness suite, not kept: it tore ACES `range4`).
    /// Why: `docs/TUNING.md#cb-rival-translation`.
    pub rival_translation: f64,
    /// … or this rotation (rad). Default 0.
    pub rival_rotation: f64,
    /// A match whose scan pins one translation direction less than this fraction as well as the other
    /// (eigenvalues of its least-squares information) lies in a corridor: a runner-up shifted along the
    /// corridor is the same place, not a rival. Default 0.1.
    pub degenerate_ratio: f64,
    /// The weakest translation direction of a match keeps at least this fraction of the strongest's
    /// information (see [`match_information`]). Default 0.01 (10× the sigma).
    pub min_information_ratio: f64,
    /// A windowed match whose best pose lies within this many cells of its translation window's boundary
    /// (count; 0 = never) is a slope the window cut rather than a peak it contained: the search is made
    /// again in a window twice as wide, and refused if that one's best is on its edge too. Default 0 (off;
    /// 2, the outermost ring and the one inside it, was measured and not kept).
    /// Why: `docs/TUNING.md#cb-window-edge-cells`.
    pub window_edge_cells: u32,
    /// Refinement of accepted matches. Defaults here: occupied space 20, translation 10, rotation 1.
    pub least_squares: LeastSquaresScanMatcherOptions,
}

impl Default for ConstraintBuilderOptions {
    fn default() -> Self {
        Self {
            sampling_ratio: 0.15,
            max_constraint_distance: 20.0,
            min_score: 0.55,
            global_localization_min_score: 0.6,
            min_score_margin: 0.02,
            loop_closure_translation_sigma: 0.03,
            loop_closure_rotation_sigma: 0.01,
            huber_scale: 1.0,
            // 1.5 m × ±15°, growing with the path since (below). Why: docs/TUNING.md#cb-fast-correlative.
            fast_correlative: FastCorrelativeScanMatcherOptions {
                linear_search_window: 1.5,
                angular_search_window: 15f64.to_radians(),
                ..FastCorrelativeScanMatcherOptions::default()
            },
            // Cartographer's constraint-builder weights. Why: docs/TUNING.md#cb-least-squares.
            least_squares: LeastSquaresScanMatcherOptions {
                occupied_space_weight: 20.0,
                translation_weight: 10.0,
                rotation_weight: 1.0,
                ..LeastSquaresScanMatcherOptions::default()
            },
            linear_window_growth: 0.05,
            angular_window_growth: 0.0035,
            max_linear_search_window: 20.0,
            recovery_heading_doubt: 0.26,
            min_loop_length: 20.0,
            max_innovation_translation: 0.5,
            max_innovation_rotation: 0.052,
            beyond_drift_confirmations: 5,
            max_unconfirmed_translation: 0.5,
            max_unconfirmed_rotation: 0.052,
            agreement_path_length: 30.0,
            agreement_translation: 0.15,
            agreement_rotation: 0.035,
            rival_translation: 0.0,
            rival_rotation: 0.0,
            degenerate_ratio: 0.1,
            min_information_ratio: 0.01,
            window_edge_cells: 0,
        }
    }
}

impl ConstraintBuilderOptions {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), GlobalSlamOptionsError> {
        if !(0.0..=1.0).contains(&self.sampling_ratio) {
            return Err(GlobalSlamOptionsError::RatioOutOfRange {
                name: "sampling_ratio",
                value: self.sampling_ratio,
            });
        }
        for (name, v) in [
            ("min_score", self.min_score),
            (
                "global_localization_min_score",
                self.global_localization_min_score,
            ),
            ("min_score_margin", self.min_score_margin),
            ("degenerate_ratio", self.degenerate_ratio as f32),
            ("min_information_ratio", self.min_information_ratio as f32),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(GlobalSlamOptionsError::RatioOutOfRange {
                    name,
                    value: f64::from(v),
                });
            }
        }
        check_sigma("max_constraint_distance", "m", self.max_constraint_distance)?;
        check_sigma(
            "loop_closure_translation_sigma",
            "m",
            self.loop_closure_translation_sigma,
        )?;
        check_sigma(
            "loop_closure_rotation_sigma",
            "rad",
            self.loop_closure_rotation_sigma,
        )?;
        check_sigma("huber_scale", "standard deviations", self.huber_scale)?;
        for (name, unit, value) in [
            ("linear_window_growth", "m/m", self.linear_window_growth),
            ("angular_window_growth", "rad/m", self.angular_window_growth),
            ("min_loop_length", "m", self.min_loop_length),
            ("agreement_path_length", "m", self.agreement_path_length),
            ("recovery_heading_doubt", "rad", self.recovery_heading_doubt),
            ("rival_translation", "m", self.rival_translation),
            ("rival_rotation", "rad", self.rival_rotation),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(GlobalSlamOptionsError::Invalid(format!(
                    "{name} must be a finite number of {unit} >= 0, got {value}"
                )));
            }
        }
        check_sigma(
            "max_linear_search_window",
            "m",
            self.max_linear_search_window,
        )?;
        check_sigma("agreement_translation", "m", self.agreement_translation)?;
        check_sigma(
            "max_innovation_translation",
            "m",
            self.max_innovation_translation,
        )?;
        check_sigma(
            "max_innovation_rotation",
            "rad",
            self.max_innovation_rotation,
        )?;
        check_sigma(
            "max_unconfirmed_translation",
            "m",
            self.max_unconfirmed_translation,
        )?;
        check_sigma(
            "max_unconfirmed_rotation",
            "rad",
            self.max_unconfirmed_rotation,
        )?;
        check_sigma("agreement_rotation", "rad", self.agreement_rotation)?;
        let matcher = |field| move |source| GlobalSlamOptionsError::ScanMatcher { field, source };
        self.fast_correlative
            .validate()
            .map_err(matcher("fast_correlative"))?;
        self.least_squares
            .validate()
            .map_err(matcher("least_squares"))
    }
}

/// One accepted node-to-submap match.
#[derive(Clone, Debug, PartialEq)]
pub struct LoopClosure {
    /// The submap matched against.
    pub submap: SubmapId,
    /// The node whose scan was matched.
    pub node: NodeId,
    /// The measured pose of the node in the submap's frame.
    pub submap_from_node: Rigid2,
    /// Branch-and-bound score of the match.
    pub score: f32,
    /// Score of the best clearly different pose in the same search window (another peak: more than
    /// [`crate::scan_matching::DISTINCT_TRANSLATION_CELLS`] cells or
    /// [`crate::scan_matching::DISTINCT_ROTATION_RAD`] away, and not along the corridor the match lies in),
    /// if any scored within [`RUNNER_UP_RANGE`] of `score` and reached `min_score`. A runner-up close to
    /// `score` means the scan fits two places about equally well.
    pub runner_up_score: Option<f32>,
    /// Information (1/m², 1/rad²) of the match over the error in the node's frame, shaped by what the
    /// scan pins: the loop-closure sigmas in its best-pinned direction, less along a corridor (see
    /// [`match_information`]). `None`: the options' fixed sigmas (matches made elsewhere).
    pub information: Option<Matrix3<f64>>,
}

/// The information of a scan match: the translation block follows the shape of the scan's own
/// least-squares information `scan_information` (over `(tx, ty, θ)` in the grid frame, see
/// [`crate::scan_matching::LeastSquaresSummary::scan_information`]), scaled so that its best-pinned
/// direction gets `1 / translation_sigma²`, and expressed in the node's frame (the pose graph's error
/// frame) through `grid_from_node`'s rotation; the rotation gets `1 / rotation_sigma²`. Along a featureless
/// corridor the scan pins the position across it but hardly along it, and so does the match. The weakest
/// direction keeps at least `min_ratio` of the strongest's information.
pub fn match_information(
    scan_information: &Matrix3<f64>,
    grid_from_node: &Rigid2,
    translation_sigma: f64,
    rotation_sigma: f64,
    min_ratio: f64,
) -> Matrix3<f64> {
    let eigen = translation_eigen(scan_information);
    let strongest = eigen.eigenvalues.max();
    let strong = 1.0 / (translation_sigma * translation_sigma);
    let shaped = if strongest > 0.0 && strongest.is_finite() {
        let mut values = eigen
            .eigenvalues
            .map(|l| (l / strongest).clamp(min_ratio, 1.0) * strong);
        if !values.iter().all(|v| v.is_finite()) {
            values = nalgebra::Vector2::repeat(strong);
        }
        eigen.eigenvectors * Matrix2::from_diagonal(&values) * eigen.eigenvectors.transpose()
    } else {
        Matrix2::identity() * strong
    };
    let r = grid_from_node.rotation.to_rotation_matrix().into_inner();
    let in_node = r.transpose() * shaped * r;
    let mut information = Matrix3::zeros();
    information.fixed_view_mut::<2, 2>(0, 0).copy_from(&in_node);
    information[(2, 2)] = 1.0 / (rotation_sigma * rotation_sigma);
    information
}

/// The eigen-decomposition of the translation block of a least-squares information over `(tx, ty, θ)`.
fn translation_eigen(information: &Matrix3<f64>) -> nalgebra::SymmetricEigen<f64, nalgebra::U2> {
    information
        .fixed_view::<2, 2>(0, 0)
        .into_owned()
        .symmetric_eigen()
}

/// The weakly and the strongly pinned translation directions (unit vectors, in `information`'s frame) of a
/// least-squares or match information over `(tx, ty, θ)`, if its translation block is degenerate: its
/// eigenvalues differ by more than `1 / degenerate_ratio` (a corridor, pinned across but hardly along).
pub(crate) fn weak_axis(
    information: &Matrix3<f64>,
    degenerate_ratio: f64,
) -> Option<(nalgebra::Vector2<f64>, nalgebra::Vector2<f64>)> {
    let eigen = translation_eigen(information);
    let (weak, strong) = if eigen.eigenvalues[0] <= eigen.eigenvalues[1] {
        (0, 1)
    } else {
        (1, 0)
    };
    (eigen.eigenvalues[strong] > 0.0
        && eigen.eigenvalues[weak].max(0.0) < degenerate_ratio * eigen.eigenvalues[strong])
        .then(|| {
            (
                eigen.eigenvectors.column(weak).into_owned(),
                eigen.eigenvectors.column(strong).into_owned(),
            )
        })
}

/// Whether `other` lies from `best` along `best`'s weakly pinned direction (a corridor's axis), so that it
/// is the same place seen with the along-corridor position unknown rather than another place: the
/// translation block's eigenvalues differ by more than `1 / degenerate_ratio`, the offset points within
/// 20° of the weak axis and the rotations differ by under 5°.
fn along_weak_axis(
    scan_information: &Matrix3<f64>,
    best: &Rigid2,
    other: &Rigid2,
    degenerate_ratio: f64,
) -> bool {
    let Some((axis, _)) = weak_axis(scan_information, degenerate_ratio) else {
        return false;
    };
    let offset = other.translation.vector - best.translation.vector;
    let turned = crate::geometry::normalize_angle(other.rotation.angle() - best.rotation.angle());
    offset.norm() > 0.0
        && axis.dot(&offset).abs() >= 20f64.to_radians().cos() * offset.norm()
        && turned.abs() < 5f64.to_radians()
}

/// Whether `best` lies within `edge_cells` cells of the boundary of the square window of half-width
/// `linear_window` (m) around `center`, searched in cells of `resolution` (m): the window's rings are
/// `ceil(linear_window / resolution)` cells out, and `best` is on one of its outer `edge_cells` rings.
fn on_window_edge(
    center: &Rigid2,
    best: &Rigid2,
    linear_window: f64,
    resolution: f64,
    edge_cells: u32,
) -> bool {
    if edge_cells == 0 || resolution.is_nan() || resolution <= 0.0 {
        return false;
    }
    let rings = (linear_window / resolution).ceil();
    let offset = best.translation.vector - center.translation.vector;
    let ring = (offset.x.abs().max(offset.y.abs()) / resolution).round();
    ring > rings - f64::from(edge_cells)
}

/// Rivals of a match are looked for down to this much below its score (score units): enough to report
/// near misses in the diagnostics, few enough that the second search stays cheap.
pub const RUNNER_UP_RANGE: f32 = 0.1;

/// An explicit search window for a [`SearchJob`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SearchWindow {
    /// Half-width of the square translation window, metres.
    pub linear_m: f64,
    /// Half-width of the rotation window, radians (at most π).
    pub angular_rad: f64,
}

/// A node-to-submap search to run.
#[derive(Clone, Debug, PartialEq)]
pub struct SearchJob {
    /// The submap to match against (must have been added with [`ConstraintBuilder::add_finished_submap`]).
    pub submap: SubmapId,
    /// The node to match.
    pub node: NodeId,
    /// The node's filtered scan points in its tracking frame.
    pub points: Arc<Vec<Point2<f32>>>,
    /// Prior estimate of the node in the submap frame; `None` searches the whole submap at every rotation.
    pub submap_from_node_estimate: Option<Rigid2>,
    /// The window around the estimate; `None`: the options' `fast_correlative` windows.
    pub window: Option<SearchWindow>,
}

struct SubmapMatcher {
    local_from_submap: Rigid2,
    grid: Arc<ProbabilityGrid>,
    /// The branch-and-bound grids, built at the submap's first search: a site restored to answer a
    /// query, or a submap no node comes near, never pays for them.
    matcher: OnceLock<FastCorrelativeScanMatcher>,
}

/// Branch-and-bound matchers of the finished submaps, and the search itself. `Sync`: jobs can run in
/// parallel.
pub struct ConstraintBuilder {
    options: ConstraintBuilderOptions,
    matchers: BTreeMap<SubmapId, SubmapMatcher>,
    least_squares: LeastSquaresScanMatcher,
}

impl ConstraintBuilder {
    /// A builder with no submaps.
    pub fn new(options: ConstraintBuilderOptions) -> Self {
        let least_squares = LeastSquaresScanMatcher::new(options.least_squares.clone());
        Self {
            options,
            matchers: BTreeMap::new(),
            least_squares,
        }
    }

    /// The options in use.
    pub fn options(&self) -> &ConstraintBuilderOptions {
        &self.options
    }

    /// Adds a finished submap to match against; its branch-and-bound grids are built at its first search.
    /// `grid` is in the submap's trajectory local frame; `local_from_submap` is the submap's local pose.
    pub fn add_finished_submap(
        &mut self,
        id: SubmapId,
        local_from_submap: Rigid2,
        grid: Arc<ProbabilityGrid>,
    ) {
        self.matchers.insert(
            id,
            SubmapMatcher {
                local_from_submap,
                grid,
                matcher: OnceLock::new(),
            },
        );
    }

    /// Forgets a submap (trimmed).
    pub fn remove_submap(&mut self, id: SubmapId) {
        self.matchers.remove(&id);
    }

    /// Whether a submap can be matched against.
    pub fn has_submap(&self, id: SubmapId) -> bool {
        self.matchers.contains_key(&id)
    }

    /// Runs one search; `None` when the submap is unknown, no match reaches the minimum score, or another
    /// peak scores within `min_score_margin` of the best.
    pub fn run(&self, job: &SearchJob) -> Option<LoopClosure> {
        let entry = self.matchers.get(&job.submap)?;
        let matcher = entry.matcher.get_or_init(|| {
            FastCorrelativeScanMatcher::new(&entry.grid, self.options.fast_correlative.clone())
        });
        let default_window = SearchWindow {
            linear_m: self.options.fast_correlative.linear_search_window,
            angular_rad: self.options.fast_correlative.angular_search_window,
        };
        let mut window = job.window.unwrap_or(default_window);
        // First the best pose alone (most searches find nothing and stop here, pruned as hard as one
        // search can be), then, for a match, its rivals: other peaks within `RUNNER_UP_RANGE` of it.
        let search = |window: SearchWindow, min_score: f32, count: usize| match &job
            .submap_from_node_estimate
        {
            Some(estimate) => matcher.match_within_candidates(
                &(entry.local_from_submap * estimate),
                &job.points,
                min_score,
                window.linear_m,
                window.angular_rad.min(std::f64::consts::PI),
                count,
            ),
            None => matcher.match_full_candidates(&job.points, min_score, count, f32::INFINITY),
        };
        let min_score = if job.submap_from_node_estimate.is_some() {
            self.options.min_score
        } else {
            self.options.global_localization_min_score
        };
        let mut found = *search(window, min_score, 1).first()?;
        // A best pose on the window's edge is a slope the window cut, not a peak: look once in a window
        // twice as wide, and refuse if its best is on that one's edge too.
        if let Some(estimate) = &job.submap_from_node_estimate {
            let center = entry.local_from_submap * estimate;
            let resolution = entry.grid.limits().resolution;
            let edge_cells = self.options.window_edge_cells;
            let on_edge = |best: &Rigid2, linear_m: f64| {
                on_window_edge(&center, best, linear_m, resolution, edge_cells)
            };
            if on_edge(&found.pose, window.linear_m) {
                window.linear_m *= 2.0;
                found = *search(window, min_score, 1).first()?;
                if on_edge(&found.pose, window.linear_m) {
                    return None;
                }
            }
        }
        let (refined, summary) = self.least_squares.match_pose(
            &found.pose.translation.vector,
            &found.pose,
            &job.points,
            &entry.grid,
        );
        // The runner-up: the best other peak that is not the same corridor position shifted along it.
        let runner_up_score = search(window, (found.score - RUNNER_UP_RANGE).max(min_score), 3)
            .iter()
            .skip(1)
            .find(|m| {
                !along_weak_axis(
                    &summary.scan_information,
                    &found.pose,
                    &m.pose,
                    self.options.degenerate_ratio,
                )
            })
            .map(|m| m.score);
        if runner_up_score.is_some_and(|r| r > found.score - self.options.min_score_margin) {
            return None;
        }
        let information = match_information(
            &summary.scan_information,
            &refined,
            self.options.loop_closure_translation_sigma,
            self.options.loop_closure_rotation_sigma,
            self.options.min_information_ratio,
        );
        Some(LoopClosure {
            submap: job.submap,
            node: job.node,
            submap_from_node: entry.local_from_submap.inverse() * refined,
            score: found.score,
            runner_up_score,
            information: Some(information),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;

    #[test]
    fn a_rival_distance_below_zero_is_refused_by_name() {
        assert!(ConstraintBuilderOptions::default().validate().is_ok());
        for options in [
            ConstraintBuilderOptions {
                rival_translation: -0.1,
                ..Default::default()
            },
            ConstraintBuilderOptions {
                rival_rotation: f64::NAN,
                ..Default::default()
            },
        ] {
            let error = options.validate().unwrap_err().to_string();
            assert!(error.contains("rival_"), "{error}");
        }
    }

    #[test]
    fn a_best_pose_on_the_windows_outer_rings_is_on_its_edge() {
        let center = rigid2(1.0, 2.0, 0.3);
        let at = |dx: f64, dy: f64| rigid2(1.0 + dx, 2.0 + dy, 0.3);
        // 1.5 m at 0.05 m: rings 0..=30.
        assert!(on_window_edge(&center, &at(1.5, 0.0), 1.5, 0.05, 2));
        assert!(on_window_edge(&center, &at(0.2, -1.45), 1.5, 0.05, 2));
        assert!(!on_window_edge(&center, &at(1.4, 1.4), 1.5, 0.05, 2));
        assert!(!on_window_edge(&center, &at(1.45, 0.0), 1.5, 0.05, 1));
        assert!(!on_window_edge(&center, &at(0.0, 0.0), 1.5, 0.05, 2));
        // A window not a whole number of cells: 1.52 m → 31 rings.
        assert!(on_window_edge(&center, &at(-1.55, 0.3), 1.52, 0.05, 1));
        assert!(!on_window_edge(&center, &at(-1.5, 0.3), 1.52, 0.05, 1));
        // Off.
        assert!(!on_window_edge(&center, &at(1.5, 0.0), 1.5, 0.05, 0));
    }

    /// A corridor along the grid's x axis: the scan pins y well and x hardly at all.
    fn corridor_information() -> Matrix3<f64> {
        Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 400.0, 50.0))
    }

    #[test]
    fn a_corridor_match_pins_across_the_corridor_only() {
        let sigma = 0.03;
        let (strong, weak) = (1.0 / (sigma * sigma), 0.01 / (sigma * sigma));
        let diagonal_is = |information: &Matrix3<f64>, x: f64, y: f64| {
            assert!(
                (information[(0, 0)] - x).abs() < 1e-3 && (information[(1, 1)] - y).abs() < 1e-3,
                "{information}"
            );
        };
        // The node faces along the corridor (heading 0): its x is along, y across.
        let along = match_information(
            &corridor_information(),
            &rigid2(0.0, 0.0, 0.0),
            sigma,
            0.01,
            0.01,
        );
        diagonal_is(&along, weak, strong);
        assert!((along[(2, 2)] - 1e4).abs() < 1e-6);
        // Turned by 90°, the node's x is across the corridor: the strong direction follows.
        let across = match_information(
            &corridor_information(),
            &rigid2(0.0, 0.0, std::f64::consts::FRAC_PI_2),
            sigma,
            0.01,
            0.01,
        );
        diagonal_is(&across, strong, weak);
        // A scan that pins both directions equally gets the fixed sigma in both.
        let room = match_information(
            &Matrix3::identity(),
            &rigid2(1.0, 2.0, 0.7),
            sigma,
            0.01,
            0.01,
        );
        assert!((room[(0, 0)] - room[(1, 1)]).abs() < 1e-6 && room[(0, 1)].abs() < 1e-6);
        // No information at all falls back to the fixed sigma rather than to zero or NaN.
        let none = match_information(&Matrix3::zeros(), &rigid2(0.0, 0.0, 0.0), sigma, 0.01, 0.01);
        assert!(none.iter().all(|v| v.is_finite()) && none[(0, 0)] > 0.0);
    }

    #[test]
    fn a_runner_up_along_the_corridor_is_the_same_place() {
        let info = corridor_information();
        let best = rigid2(2.0, 1.0, 0.0);
        assert!(along_weak_axis(&info, &best, &rigid2(2.6, 1.02, 0.01), 0.1));
        // Across the corridor, turned, or in a room that pins both directions: a rival.
        assert!(!along_weak_axis(&info, &best, &rigid2(2.0, 1.6, 0.0), 0.1));
        assert!(!along_weak_axis(&info, &best, &rigid2(2.6, 1.0, 0.3), 0.1));
        assert!(!along_weak_axis(
            &Matrix3::identity(),
            &best,
            &rigid2(2.6, 1.0, 0.0),
            0.1
        ));
    }
}
