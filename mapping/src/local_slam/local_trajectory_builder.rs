//! LLO's per-scan pipeline: predict, filter, match against the active submap, insert.
//!
//! For each scan (already in the tracking frame): the extrapolator predicts the pose from odometry/IMU;
//! the adaptive voxel filter thins the hits; a real-time correlative search around the prediction
//! finds a robust initial pose (it tolerates odometry that is wrong by many degrees in a turn, which a
//! purely local refinement does not); least-squares refinement against the bicubic-interpolated older
//! active submap gives the final pose; the motion filter decides whether the scan becomes a node and is
//! inserted into both active submaps.

use nalgebra::Point2;
use serde::{Deserialize, Serialize};

use super::{
    ActiveSubmaps, AdaptiveVoxelFilterOptions, MotionFilter, MotionFilterOptions, PoseExtrapolator,
    PoseExtrapolatorOptions, Submap, SubmapRef, SubmapsOptions, adaptive_voxel_filter,
};
use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle};
use crate::grid::{ProbabilityGrid, RangeDataInserterOptionsError};
use crate::scan_matching::{
    LeastSquaresScanMatcher, LeastSquaresScanMatcherOptions, MatchError,
    RealTimeCorrelativeScanMatcher, RealTimeCorrelativeScanMatcherOptions, paired_z,
};
use crate::sensor::{ImuReading, OdometryReading, RangeConversionOptions, RangeData, Timestamp};

/// Every LLO setting.
#[allow(
    clippy::struct_excessive_bools,
    reason = "independent documented switches of a configuration file, not a state"
)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LocalTrajectoryBuilderOptions {
    /// How raw ranges become hits and free-space rays.
    pub range_conversion: RangeConversionOptions,
    /// Scans with fewer hits than this are not matched (count). Default 10.
    pub min_num_returns: usize,
    /// Thinning of the points used for matching.
    pub adaptive_voxel_filter: AdaptiveVoxelFilterOptions,
    /// Run the real-time correlative search before refinement. Default true.
    pub use_correlative_scan_matching: bool,
    /// Correlative search window and penalties.
    pub real_time_correlative: RealTimeCorrelativeScanMatcherOptions,
    /// Only points within this range (metres) take part in the correlative search (all of them if fewer than
    /// `min_num_returns` are); 0 = no cut. Default 10 m. Why: `docs/TUNING.md#llo-correlative-max-range`.
    pub correlative_max_range: f32,
    /// Half-width (radians) of the window around the prediction, plus `trusted_window_per_radian` × its
    /// claimed rotation, in which the prediction is trusted: a match outside replaces the best inside only
    /// when it fits better by `min_deviation_z` ([`paired_z`]). Default 10°.
    /// Why: `docs/TUNING.md#llo-trusted-angular-window`.
    pub trusted_angular_window: f64,
    /// Growth of the trusted window with the claimed rotation (radians per radian). Default 0.25.
    pub trusted_window_per_radian: f64,
    /// Half-width (radians) of the window around the predicted rotation, plus `trusted_window_per_radian` ×
    /// the claimed rotation, where odometry is the answer unless the scan says otherwise: the trusted
    /// window's best match replaces the best one inside this window only when it fits better by
    /// `min_anchored_z` ([`paired_z`]). 0 = off (the trusted window's best is taken). Default 1°.
    /// Why: `docs/TUNING.md#llo-anchored-angular-window`.
    pub anchored_angular_window: f64,
    /// How much better (paired statistic) the trusted window's best match must fit than the best one in the
    /// anchored window to be taken. Default 2.
    pub min_anchored_z: f64,
    /// How much better (paired statistic, see [`paired_z`]) a match outside the trusted window must fit
    /// than the best one inside it to be taken. Default 4.
    pub min_deviation_z: f64,
    /// Apply the paired test (`min_deviation_z`) where the trusted window's best match scores below
    /// `min_recovery_score` too. Default true (false: there a fit of the wider windows of at least
    /// `min_recovery_score` wins without it). Why: `docs/TUNING.md#llo-min-recovery-score`.
    pub paired_test_where_trusted_misfits: bool,
    /// Below this best correlative score (mean probability) the search is repeated over every rotation; also
    /// the floor of a fit in the trusted window. Default 0.35. Why: `docs/TUNING.md#llo-min-recovery-score`.
    pub min_recovery_score: f64,
    /// How much better (paired statistic) a recovery search (over every rotation, or the shifted window)
    /// must fit than the best match near the prediction. Default 6. Why: `docs/TUNING.md#llo-min-recovery-z`.
    pub min_recovery_z: f64,
    /// The odometry as a prior on the search over every rotation (radians > 0; 0 = off): a pose that turns
    /// `Δθ` away from the prediction must fit better by `√(min_recovery_z² + (Δθ / this)²)`, so a corridor
    /// flipped 180° needs far more support than a turn the wheels missed by a few degrees. Default 15°.
    /// Why: `docs/TUNING.md#llo-every-rotation-prior`.
    pub every_rotation_prior: f64,
    /// Half-width (metres) of a translation window searched, in the trusted angular window, where nothing
    /// near the prediction fits (best score below `min_recovery_score`); 0 = off. Default 0.5 m.
    /// Why: `docs/TUNING.md#llo-recovery-linear-window`.
    pub recovery_linear_window: f64,
    /// Insert a scan placed by a recovery search (over every rotation, or the shifted window) into the
    /// submaps at once. Default false: it steers the next prediction and is held back; the next scan
    /// is placed both from it and from the odometry's prediction, and the recovery stands (both scans go
    /// in) only if its placement fits better by `min_deviation_z` ([`paired_z`]), or the odometry's needs
    /// a recovery too and fits no better by as much; else it is dropped and the odometry's placement
    /// taken. Why: `docs/TUNING.md#llo-insert-recovered-scans`.
    pub insert_recovered_scans: bool,
    /// Insert a scan into the submaps when the wheel odometry reported exactly no motion since the previous
    /// scan although readings arrived and the two scans before it moved apart by more than the motion
    /// filter's thresholds (a stalled stream repeats its last pose, then carries the backlog at once).
    /// Default true. False: such a scan, matched from a prediction that misses the motion, is reported but
    /// kept out of the map the next scans match, and the next scan, predicted across the backlog, goes in
    /// as usual (measured, refused). Why: `docs/TUNING.md#llo-insert-while-odometry-stalls`.
    pub insert_while_odometry_stalls: bool,
    /// Least-squares refinement weights.
    pub least_squares: LeastSquaresScanMatcherOptions,
    /// The least-squares refinement pulls the translation toward the prediction unless the correlative search
    /// turned the pose more than this (radians) away from it: 0 = always the correlative result, π = always
    /// the prediction. Default 1°. Why: `docs/TUNING.md#llo-max-odometry-target-disagreement`.
    pub max_odometry_target_disagreement: f64,
    /// How the next scan's pose is predicted.
    pub pose_extrapolator: PoseExtrapolatorOptions,
    /// When a scan becomes a node.
    pub motion_filter: MotionFilterOptions,
    /// Submap size and resolution.
    pub submaps: SubmapsOptions,
}

/// The paired statistic a pose of the search over every rotation, turned `turn` (radians) away from the
/// prediction, must reach over the best match near the prediction (see
/// [`LocalTrajectoryBuilderOptions::every_rotation_prior`]).
fn every_rotation_min_z(options: &LocalTrajectoryBuilderOptions, turn: f64) -> f64 {
    if options.every_rotation_prior > 0.0 {
        options
            .min_recovery_z
            .hypot(turn.abs() / options.every_rotation_prior)
    } else {
        options.min_recovery_z
    }
}

impl Default for LocalTrajectoryBuilderOptions {
    fn default() -> Self {
        Self {
            range_conversion: RangeConversionOptions::default(),
            min_num_returns: 10,
            adaptive_voxel_filter: AdaptiveVoxelFilterOptions::default(),
            use_correlative_scan_matching: true,
            real_time_correlative: RealTimeCorrelativeScanMatcherOptions::default(),
            correlative_max_range: 10.0,
            trusted_angular_window: 10f64.to_radians(),
            trusted_window_per_radian: 0.25,
            anchored_angular_window: 1f64.to_radians(),
            min_anchored_z: 2.0,
            min_deviation_z: 4.0,
            paired_test_where_trusted_misfits: true,
            min_recovery_score: 0.35,
            min_recovery_z: 6.0,
            every_rotation_prior: 15f64.to_radians(),
            recovery_linear_window: 0.5,
            insert_recovered_scans: false,
            insert_while_odometry_stalls: true,
            least_squares: LeastSquaresScanMatcherOptions::default(),
            max_odometry_target_disagreement: 1f64.to_radians(),
            pose_extrapolator: PoseExtrapolatorOptions::default(),
            motion_filter: MotionFilterOptions::default(),
            submaps: SubmapsOptions::default(),
        }
    }
}

/// Invalid [`LocalTrajectoryBuilderOptions`].
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LocalTrajectoryBuilderOptionsError {
    /// An option of LLO itself.
    #[error("invalid LLO option: {0}")]
    Invalid(String),
    /// A scan matcher's options (`real_time_correlative` or `least_squares`).
    #[error("invalid LLO option: {field}: {source}")]
    ScanMatcher {
        /// Which matcher's options.
        field: &'static str,
        /// Why.
        source: MatchError,
    },
    /// The submaps' range data inserter's options (`submaps.range_data_inserter`).
    #[error("invalid LLO option: submaps.range_data_inserter: {0}")]
    RangeDataInserter(#[source] RangeDataInserterOptionsError),
}

impl LocalTrajectoryBuilderOptions {
    /// Checks every nested option.
    pub fn validate(&self) -> Result<(), LocalTrajectoryBuilderOptionsError> {
        let err = |e: &str| LocalTrajectoryBuilderOptionsError::Invalid(e.to_owned());
        let matcher =
            |field| move |source| LocalTrajectoryBuilderOptionsError::ScanMatcher { field, source };
        self.real_time_correlative
            .validate()
            .map_err(matcher("real_time_correlative"))?;
        if !(self.correlative_max_range.is_finite() && self.correlative_max_range >= 0.0) {
            return Err(err("correlative_max_range must be finite and >= 0"));
        }
        for (name, value) in [
            ("min_recovery_score", self.min_recovery_score),
            ("min_recovery_z", self.min_recovery_z),
            ("every_rotation_prior", self.every_rotation_prior),
            ("recovery_linear_window", self.recovery_linear_window),
            ("trusted_angular_window", self.trusted_angular_window),
            ("trusted_window_per_radian", self.trusted_window_per_radian),
            ("anchored_angular_window", self.anchored_angular_window),
            ("min_anchored_z", self.min_anchored_z),
            ("min_deviation_z", self.min_deviation_z),
            (
                "pose_extrapolator.min_velocity_span_per_horizon",
                self.pose_extrapolator.min_velocity_span_per_horizon,
            ),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return Err(LocalTrajectoryBuilderOptionsError::Invalid(format!(
                    "{name} must be finite and >= 0"
                )));
            }
        }
        self.least_squares
            .validate()
            .map_err(matcher("least_squares"))?;
        if !(self.max_odometry_target_disagreement >= 0.0
            && self.max_odometry_target_disagreement.is_finite())
        {
            return Err(err(
                "max_odometry_target_disagreement must be finite and >= 0",
            ));
        }
        self.submaps
            .range_data_inserter
            .validate()
            .map_err(LocalTrajectoryBuilderOptionsError::RangeDataInserter)?;
        let rc = &self.range_conversion;
        if !(rc.min_range >= 0.0
            && rc.max_range > rc.min_range
            && rc.missing_data_ray_length >= 0.0)
        {
            return Err(err(
                "range_conversion: need 0 ≤ min_range < max_range and missing_data_ray_length ≥ 0",
            ));
        }
        if !(self.submaps.resolution > 0.0 && self.submaps.resolution.is_finite())
            || self.submaps.num_range_data == 0
            || !(self.submaps.max_path_m >= 0.0 && self.submaps.max_path_m.is_finite())
        {
            return Err(err(
                "submaps: resolution must be positive, num_range_data at least 1 and max_path_m finite and \
                 not negative",
            ));
        }
        let av = &self.adaptive_voxel_filter;
        if !(av.max_length > 0.0 && av.max_range > 0.0) {
            return Err(err(
                "adaptive_voxel_filter: max_length and max_range must be positive",
            ));
        }
        Ok(())
    }
}

/// What global SLAM needs of a node.
#[derive(Clone, Debug)]
pub struct TrajectoryNodeData {
    /// Scan time.
    pub time: Timestamp,
    /// `local_from_tracking`.
    pub local_pose: Rigid2,
    /// The voxel-filtered hits in the tracking frame (what GLM matches).
    pub filtered_points: Vec<Point2<f32>>,
    /// A recovery search ([`CorrelativeBranch::is_recovery`]) placed this scan or one since the previous
    /// node: LLO's heading may have broken here (see `recovery_heading_doubt` of GLM's options).
    pub recovered: bool,
}

/// A scan that became a node.
#[derive(Clone, Debug)]
pub struct InsertionResult {
    /// The node.
    pub node: TrajectoryNodeData,
    /// The submaps it was inserted into.
    pub insertion_submaps: Vec<SubmapRef>,
    /// Submaps this insertion finished, moved out.
    pub finished_submaps: Vec<(usize, Submap)>,
}

/// A node as LLO hands it to global SLAM (`GlobalSlam::add_node`).
#[derive(Clone, Debug)]
pub struct LloNode {
    /// Scan time.
    pub time: Timestamp,
    /// `local_from_tracking`.
    pub local_pose: Rigid2,
    /// The voxel-filtered hits in the tracking frame (what GLM matches).
    pub points: Vec<Point2<f32>>,
    /// `(index, local_from_submap)` of the submaps it went into (indices per trajectory).
    pub insertion_submaps: Vec<(usize, Rigid2)>,
    /// `(index, grid)` of the submaps its insertion finished.
    pub finished_submaps: Vec<(usize, ProbabilityGrid)>,
    /// See [`TrajectoryNodeData::recovered`].
    pub recovered: bool,
}

impl InsertionResult {
    /// What global SLAM takes of it.
    pub fn into_llo_node(self) -> LloNode {
        LloNode {
            time: self.node.time,
            local_pose: self.node.local_pose,
            points: self.node.filtered_points,
            insertion_submaps: self
                .insertion_submaps
                .iter()
                .map(|s| (s.index, s.local_pose))
                .collect(),
            finished_submaps: self
                .finished_submaps
                .into_iter()
                .map(|(index, submap)| (index, submap.grid))
                .collect(),
            recovered: self.node.recovered,
        }
    }
}

/// Which search of the correlative match placed a scan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CorrelativeBranch {
    /// No correlative search: the first scan, or `use_correlative_scan_matching` off.
    Prediction,
    /// The trusted angular window around the prediction.
    Trusted,
    /// The anchored window at the predicted rotation, where the trusted window's best match did not fit
    /// clearly better (`anchored_angular_window`).
    Anchored,
    /// The wide window around the prediction, or the base window around the constant-velocity one.
    Alternative,
    /// The search over every rotation, where nothing near the prediction fitted.
    EveryRotation,
    /// The `recovery_linear_window` search, where nothing near the prediction fitted.
    Shifted,
}

impl CorrelativeBranch {
    /// Whether a recovery search (nothing near the prediction fitted) placed the scan.
    pub fn is_recovery(self) -> bool {
        matches!(self, Self::EveryRotation | Self::Shifted)
    }
}

/// The outcome of one matched scan.
#[derive(Clone, Debug)]
pub struct MatchingResult {
    /// Scan time.
    pub time: Timestamp,
    /// `local_from_tracking`.
    pub local_pose: Rigid2,
    /// Which search placed it.
    pub branch: CorrelativeBranch,
    /// This scan retracted a held recovered scan (`insert_recovered_scans` false): placed from the
    /// odometry's hypothesis, it won (see `insert_recovered_scans`), and the held scan was dropped.
    pub retracted: bool,
    /// Present when the scan passed the motion filter and was inserted.
    pub insertion: Option<InsertionResult>,
}

/// LLO for one trajectory.
#[derive(Debug)]
pub struct LocalTrajectoryBuilder {
    options: LocalTrajectoryBuilderOptions,
    extrapolator: PoseExtrapolator,
    active: ActiveSubmaps,
    motion_filter: MotionFilter,
    least_squares: LeastSquaresScanMatcher,
    last_pose: Option<Rigid2>,
    dropped: usize,
    /// A scan placed by a recovery search, waiting for the next scan to decide between it and odometry.
    held: Option<HeldRecovery>,
    /// A recovery search placed a scan since the last node (see [`TrajectoryNodeData::recovered`]).
    recovered_since_node: bool,
}

/// A scan placed by a recovery search and held out of the submaps (`insert_recovered_scans` false), with
/// the odometry's hypothesis it contradicts: the prediction state as it was before the first held scan.
#[derive(Debug)]
struct HeldRecovery {
    /// The held scan in the local frame.
    range_data: RangeData,
    /// The extrapolator before the recovered pose was added (still fed odometry and IMU).
    extrapolator: PoseExtrapolator,
    /// The last pose before it.
    last_pose: Option<Rigid2>,
}

impl LocalTrajectoryBuilder {
    /// A builder with no submaps; the first scan defines the local frame's origin.
    pub fn new(options: LocalTrajectoryBuilderOptions) -> Self {
        Self {
            extrapolator: PoseExtrapolator::with_options(options.pose_extrapolator.clone()),
            active: ActiveSubmaps::new(options.submaps.clone()),
            motion_filter: MotionFilter::new(options.motion_filter.clone()),
            least_squares: LeastSquaresScanMatcher::new(options.least_squares.clone()),
            options,
            last_pose: None,
            dropped: 0,
            held: None,
            recovered_since_node: false,
        }
    }

    /// Adds a wheel-odometry reading.
    pub fn add_odometry(&mut self, reading: &OdometryReading) {
        self.extrapolator.add_odometry(reading);
        if let Some(held) = &mut self.held {
            held.extrapolator.add_odometry(reading);
        }
    }

    /// Adds an IMU reading.
    pub fn add_imu(&mut self, reading: &ImuReading) {
        self.extrapolator.add_imu(reading);
        if let Some(held) = &mut self.held {
            held.extrapolator.add_imu(reading);
        }
    }

    /// The active submaps (for rendering an unfinished map).
    pub fn active_submaps(&self) -> &ActiveSubmaps {
        &self.active
    }

    /// Scans dropped (too few hits, or time went backwards) plus sensor readings the extrapolator refused.
    pub fn num_rejected(&self) -> usize {
        self.dropped + self.extrapolator.rejected()
    }

    /// The correlative search: returns the initial pose for least squares, the centre of the search
    /// it came from (the odometry prediction, or the constant-velocity one when odometry stalled) and the
    /// search that found it.
    ///
    /// The best match within the trusted window around the prediction is the answer unless a match
    /// elsewhere in the wide window (or around the constant-velocity prediction) fits the scan clearly
    /// better (see [`LocalTrajectoryBuilderOptions::trusted_angular_window`]).
    fn correlative_match(
        &self,
        (extrapolator, last_pose): (&PoseExtrapolator, Option<Rigid2>),
        predicted: &Rigid2,
        time: Timestamp,
        points: &[Point2<f32>],
        grid: &ProbabilityGrid,
    ) -> (Rigid2, Rigid2, CorrelativeBranch) {
        let o = &self.options;
        let base = &o.real_time_correlative;
        let claimed_rotation = last_pose.map_or(0.0, |last| {
            normalize_angle(predicted.theta() - last.theta()).abs()
        });
        let search = |center: &Rigid2, angular_search_window: f64| {
            RealTimeCorrelativeScanMatcher::new(RealTimeCorrelativeScanMatcherOptions {
                angular_search_window: angular_search_window.min(std::f64::consts::PI),
                ..base.clone()
            })
            .match_pose(center, points, grid)
        };
        // Wheel odometry is least trustworthy in turns (CSAIL: −46° reported where the scans say −21°):
        // the wide window spans the whole claimed rotation.
        let wide_window = base.angular_search_window + claimed_rotation;
        let trusted_window = (o.trusted_angular_window
            + o.trusted_window_per_radian * claimed_rotation)
            .min(wide_window);
        // Odometry is evidence too: a rotation away from its prediction, inside the trusted window, needs
        // the scan's support over the best match at the predicted rotation (a scan that sees little, a
        // 4-m scanner in a hall, otherwise turns LLO by a few degrees a scan where it barely constrains
        // the rotation).
        let anchored_window = (o.anchored_angular_window
            + o.trusted_window_per_radian * claimed_rotation)
            .min(trusted_window);
        // The three windows share their centre: one pass over the widest scores all three.
        let pi = std::f64::consts::PI;
        let [wide, trusted, anchored] = RealTimeCorrelativeScanMatcher::new(base.clone())
            .match_pose_nested(
                predicted,
                points,
                grid,
                [wide_window, trusted_window, anchored_window].map(|w| w.min(pi)),
            );
        let (trusted, trusted_branch) = if o.anchored_angular_window > 0.0
            && anchored_window < trusted_window
            && normalize_angle(trusted.0.theta() - predicted.theta()).abs() > anchored_window
        {
            if trusted.1 > anchored.1
                && paired_z(grid, points, &trusted.0, &anchored.0) >= o.min_anchored_z
            {
                (trusted, CorrelativeBranch::Trusted)
            } else {
                (anchored, CorrelativeBranch::Anchored)
            }
        } else {
            (trusted, CorrelativeBranch::Trusted)
        };
        let mut alternatives = Vec::with_capacity(2);
        if wide_window > trusted_window {
            alternatives.push((wide, *predicted));
        }
        // Wheel odometry sometimes stalls and then jumps (CSAIL: frozen for 0.8 s in a turn, then +85° at
        // once). When the constant-velocity prediction disagrees by more than half the base window, search
        // around it too.
        let velocity = extrapolator.extrapolate_constant_velocity(time);
        if normalize_angle(velocity.theta() - predicted.theta()).abs()
            > 0.5 * base.angular_search_window
        {
            alternatives.push((search(&velocity, base.angular_search_window), velocity));
        }
        let best_alternative = alternatives
            .into_iter()
            .max_by(|((_, a), _), ((_, b), _)| a.total_cmp(b));
        let clearly_better = |(pose, score): &(Rigid2, f32), min_z: f64| {
            *score > trusted.1 && paired_z(grid, points, pose, &trusted.0) >= min_z
        };
        let best_score = best_alternative.map_or(trusted.1, |((_, s), _)| s.max(trusted.1));
        if f64::from(best_score) < o.min_recovery_score {
            // Nothing near the prediction fits: the robot may have slipped farther than the base window
            // reaches, or turned where the odometry did not see it. Search both ways; the better fit wins.
            let shifted = (o.recovery_linear_window > base.linear_search_window)
                .then(|| {
                    RealTimeCorrelativeScanMatcher::new(RealTimeCorrelativeScanMatcherOptions {
                        linear_search_window: o.recovery_linear_window,
                        angular_search_window: trusted_window.min(std::f64::consts::PI),
                        ..base.clone()
                    })
                    .match_pose(predicted, points, grid)
                })
                .filter(|shifted| {
                    f64::from(shifted.1) >= o.min_recovery_score
                        && clearly_better(shifted, o.min_recovery_z)
                });
            let recovery = search(predicted, std::f64::consts::PI);
            let turn = normalize_angle(recovery.0.theta() - predicted.theta());
            let recovery =
                clearly_better(&recovery, every_rotation_min_z(o, turn)).then_some(recovery);
            match (shifted, recovery) {
                // A shifted match is its own refinement target: the prediction's translation is what
                // it corrects.
                (Some(shifted), recovery) if recovery.is_none_or(|r| shifted.1 >= r.1) => {
                    return (shifted.0, shifted.0, CorrelativeBranch::Shifted);
                }
                (_, Some(recovery)) => {
                    return (recovery.0, *predicted, CorrelativeBranch::EveryRotation);
                }
                _ => {}
            }
        }
        // The paired test protects a fit near the prediction from a slightly better one farther away.
        // Where the trusted window found no fit at all, a fit farther away wins without it unless
        // `paired_test_where_trusted_misfits`.
        let misfit_wins =
            !o.paired_test_where_trusted_misfits && f64::from(trusted.1) < o.min_recovery_score;
        match best_alternative {
            Some((alternative, center))
                if (misfit_wins && f64::from(alternative.1) >= o.min_recovery_score)
                    || clearly_better(&alternative, o.min_deviation_z) =>
            {
                (alternative.0, center, CorrelativeBranch::Alternative)
            }
            _ => (trusted.0, *predicted, trusted_branch),
        }
    }

    /// Places a scan against `grid` from one prediction state (`extrapolator` and the last pose): the
    /// correlative search around the prediction, then least-squares refinement.
    fn place(
        &self,
        state: (&PoseExtrapolator, Option<Rigid2>),
        time: Timestamp,
        filtered: &[Point2<f32>],
        grid: &ProbabilityGrid,
    ) -> (Rigid2, CorrelativeBranch) {
        let predicted = state.0.extrapolate(time);
        let (initial, center, branch) = if self.options.use_correlative_scan_matching {
            let max_range = self.options.correlative_max_range;
            let near: Vec<Point2<f32>>;
            let correlative_points = if max_range > 0.0 {
                let max_squared = max_range * max_range;
                near = filtered
                    .iter()
                    .copied()
                    .filter(|p| p.coords.norm_squared() <= max_squared)
                    .collect();
                if near.len() >= self.options.min_num_returns {
                    &near[..]
                } else {
                    filtered
                }
            } else {
                filtered
            };
            self.correlative_match(state, &predicted, time, correlative_points, grid)
        } else {
            (predicted, predicted, CorrelativeBranch::Prediction)
        };
        // Like Cartographer, the refinement is pulled toward the predicted translation (the centre of the
        // correlative search): where the scan cannot see the motion (along a corridor) odometry carries
        // it. Where the scan turned the pose away from the prediction, odometry is wrong at this scan
        // (CSAIL: yaw jumps in turns) and so is its translation: the correlative result is the target then.
        let disagreement = normalize_angle(initial.theta() - center.theta()).abs();
        let target = if disagreement > self.options.max_odometry_target_disagreement {
            initial.translation.vector
        } else {
            center.translation.vector
        };
        let (refined, _) = self
            .least_squares
            .match_pose(&target, &initial, filtered, grid);
        let finite =
            refined.translation.vector.iter().all(|v| v.is_finite()) && refined.theta().is_finite();
        (if finite { refined } else { initial }, branch)
    }

    /// Matches and maybe inserts one scan given in the tracking frame. `None` when the scan was dropped.
    pub fn add_range_data(
        &mut self,
        time: Timestamp,
        range_data: &RangeData,
    ) -> Option<MatchingResult> {
        if range_data.returns.len() < self.options.min_num_returns
            || self.extrapolator.last_pose_time().is_some_and(|t| time < t)
        {
            self.dropped += 1;
            return None;
        }
        let filtered =
            adaptive_voxel_filter(&range_data.returns, &self.options.adaptive_voxel_filter);
        let mut retracted = false;
        let (pose, branch) = match self.active.matching_submap() {
            Some(submap) => {
                let steered = self.place(
                    (&self.extrapolator, self.last_pose),
                    time,
                    &filtered,
                    &submap.grid,
                );
                match &self.held {
                    // The first scan after a held recovery decides between it and the odometry's
                    // hypothesis, placed from each. The odometry's placement wins unless the recovered
                    // one fits clearly better (the paired test every match away from the odometry
                    // passes); where the odometry's placement needs a recovery itself, the held one
                    // stands unless the odometry's fits clearly better.
                    Some(held) if !steered.1.is_recovery() => {
                        let plain = self.place(
                            (&held.extrapolator, held.last_pose),
                            time,
                            &filtered,
                            &submap.grid,
                        );
                        let z = |better: &Rigid2, other: &Rigid2| {
                            paired_z(&submap.grid, &filtered, better, other)
                        };
                        let min_z = self.options.min_deviation_z;
                        let stands = if plain.1.is_recovery() {
                            z(&plain.0, &steered.0) < min_z
                        } else {
                            z(&steered.0, &plain.0) >= min_z
                        };
                        if stands {
                            steered
                        } else {
                            retracted = true;
                            plain
                        }
                    }
                    _ => steered,
                }
            }
            None => (
                self.extrapolator.extrapolate(time),
                CorrelativeBranch::Prediction,
            ),
        };
        if retracted && let Some(held) = self.held.take() {
            self.extrapolator = held.extrapolator;
            self.last_pose = held.last_pose;
        }
        self.recovered_since_node |= branch.is_recovery();
        let not_inserted = MatchingResult {
            time,
            local_pose: pose,
            branch,
            retracted,
            insertion: None,
        };
        // A recovered pose steers the next prediction but is held out of the submaps until the next scan
        // decides between it and the odometry: a wrong recovery must not become part of the map the next
        // scans match. Another recovery replaces the held scan; the odometry's hypothesis stays the one
        // from before the first.
        if branch.is_recovery() && !self.options.insert_recovered_scans {
            let transformed = range_data.transformed(&pose);
            match &mut self.held {
                Some(held) => held.range_data = transformed,
                None => {
                    self.held = Some(HeldRecovery {
                        range_data: transformed,
                        extrapolator: self.extrapolator.clone(),
                        last_pose: self.last_pose,
                    });
                }
            }
            self.extrapolator.add_pose(time, pose);
            self.last_pose = Some(pose);
            return Some(not_inserted);
        }
        // A stall: the odometry froze although the robot was moving (the last two scans moved farther
        // apart than the motion filter's thresholds); a robot standing still is not stalled.
        let filter = &self.options.motion_filter;
        let stalled = !self.options.insert_while_odometry_stalls
            && self.extrapolator.last_motion().is_some_and(|m| {
                m.translation.vector.norm() > filter.max_distance_meters
                    || normalize_angle(m.theta()).abs() > filter.max_angle_radians
            })
            && self
                .extrapolator
                .last_pose_time()
                .is_some_and(|last| self.extrapolator.odometry_frozen(last, time));
        self.extrapolator.add_pose(time, pose);
        self.last_pose = Some(pose);
        let confirmed = self.held.take().map(|held| held.range_data);
        if confirmed.is_none() && (stalled || self.motion_filter.is_similar(time, &pose)) {
            return Some(not_inserted);
        }
        let mut finished = Vec::new();
        if let Some(confirmed) = confirmed {
            // Not a node of its own: its points are in the submaps, and this scan's node follows.
            finished = self.active.insert(&confirmed).1;
            self.motion_filter.accept(time, &pose);
        }
        let (inserted, finished_now) = self.active.insert(&range_data.transformed(&pose));
        finished.extend(finished_now);
        Some(MatchingResult {
            insertion: Some(InsertionResult {
                node: TrajectoryNodeData {
                    time,
                    local_pose: pose,
                    filtered_points: filtered,
                    recovered: std::mem::take(&mut self.recovered_since_node),
                },
                insertion_submaps: inserted,
                finished_submaps: finished,
            }),
            ..not_inserted
        })
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector2;
    use simulator::RayCaster;

    use super::*;
    use crate::geometry::rigid2;
    use crate::local_slam::test_support::room;

    /// A 180° scan (1° beams, 20 m) from `world_from_tracking`, in the tracking frame.
    fn scan(room: &RayCaster, world_from_tracking: &Rigid2) -> RangeData {
        let origin = Point2::from(world_from_tracking.translation.vector);
        let mut returns = Vec::new();
        for k in 0..180 {
            let angle = (f64::from(k) - 89.5).to_radians();
            let direction = world_from_tracking.rotation * Vector2::new(angle.cos(), angle.sin());
            if let Some(range) = room.cast(&origin, &direction, 20.0) {
                let local = Vector2::new(angle.cos(), angle.sin()) * range;
                returns.push(Point2::new(local.x as f32, local.y as f32));
            }
        }
        RangeData {
            origin: Vector2::zeros(),
            returns,
            misses: Vec::new(),
        }
    }

    /// The robot turns in place at (4, 3), one scan per second, through `headings` (degrees) while
    /// odometry reports `reported`. Returns the heading error (degrees) at the last scan.
    fn turn_in_place_error(
        options: LocalTrajectoryBuilderOptions,
        headings: &[f64],
        reported: &[f64],
    ) -> f64 {
        let room = room();
        let mut llo = LocalTrajectoryBuilder::new(options);
        let mut pose = Rigid2::identity();
        for (k, (truth, odometry)) in headings.iter().zip(reported).enumerate() {
            let time = Timestamp::from_secs_f64(k as f64);
            let odom = rigid2(4.0, 3.0, odometry.to_radians());
            llo.add_odometry(&OdometryReading { time, pose: odom });
            let world_from_tracking = rigid2(4.0, 3.0, truth.to_radians());
            let result = llo
                .add_range_data(time, &scan(&room, &world_from_tracking))
                .expect("scan matched");
            pose = result.local_pose;
        }
        // The local frame starts at the first scan's pose (heading 0).
        let last = headings.last().copied().unwrap_or(0.0);
        (normalize_angle(pose.theta()) - last.to_radians())
            .to_degrees()
            .abs()
    }

    /// Odometry reports the first three turns of 10° and then stalls while the robot turns 40° more (as
    /// Intel's bursty odometry does at one scan per second).
    fn stalled_turn_error(options: LocalTrajectoryBuilderOptions) -> f64 {
        turn_in_place_error(
            options,
            &[0.0, 10.0, 20.0, 30.0, 70.0],
            &[0.0, 10.0, 20.0, 30.0, 30.0],
        )
    }

    #[test]
    fn a_scan_that_fits_nowhere_near_a_stalled_odometry_is_found_by_the_recovery_search() {
        let error = stalled_turn_error(LocalTrajectoryBuilderOptions::default());
        assert!(error < 1.5, "heading error {error}°");
        // Without the recovery search the 40° the odometry missed lie outside every window.
        let without = stalled_turn_error(LocalTrajectoryBuilderOptions {
            min_recovery_score: 0.0,
            ..LocalTrajectoryBuilderOptions::default()
        });
        assert!(without > 10.0, "heading error without recovery {without}°");
    }

    /// The robot turns in place +10° per scan; at the last scan odometry claims it turned 70° the other
    /// way (Intel at t = 1676.9 s: −72° claimed where the scans say about +7°).
    fn wrong_way_turn_error(options: LocalTrajectoryBuilderOptions) -> f64 {
        turn_in_place_error(
            options,
            &[0.0, 10.0, 20.0, 30.0, 40.0],
            &[0.0, 10.0, 20.0, 30.0, -40.0],
        )
    }

    #[test]
    fn where_the_trusted_window_fits_nowhere_a_fit_farther_away_wins_without_the_paired_test() {
        // A paired test no match can pass: only the trusted window's failure to fit lets the wide
        // window's match in.
        let unpassable = LocalTrajectoryBuilderOptions {
            min_deviation_z: 1e9,
            ..before_session_34()
        };
        let error = wrong_way_turn_error(unpassable.clone());
        assert!(error < 1.5, "heading error {error}°");
        // Where the trusted window fits (its floor lowered to 0), the paired test decides, and fails.
        let trusted_always_fits = wrong_way_turn_error(LocalTrajectoryBuilderOptions {
            min_recovery_score: 0.0,
            ..unpassable.clone()
        });
        assert!(
            trusted_always_fits > 10.0,
            "heading error {trusted_always_fits}°"
        );
        // Asked to, the paired test decides there too, and fails.
        let paired_everywhere = wrong_way_turn_error(LocalTrajectoryBuilderOptions {
            paired_test_where_trusted_misfits: true,
            min_recovery_z: 1e9,
            ..unpassable
        });
        assert!(
            paired_everywhere > 10.0,
            "heading error {paired_everywhere}°"
        );
        // Without the paired test there, the right rotation is taken, and so it is with the paired test
        // where it can pass (the default).
        let without = wrong_way_turn_error(before_session_34());
        assert!(without < 1.5, "heading error {without}°");
        let default = wrong_way_turn_error(LocalTrajectoryBuilderOptions::default());
        assert!(default < 1.5, "heading error {default}°");
    }

    /// The robot drives +0.2 m along x per scan from (3, 4); at the last scan it slips `slip` metres
    /// forward and as many to the left and turns 6°, and the odometry sees none of it (the robustness
    /// suite's slips: 0.2–0.5 m, 3–8°). Returns the position error (metres) at that scan.
    fn unseen_slip_error(options: LocalTrajectoryBuilderOptions, slip: f64) -> f64 {
        unseen_slip(options, slip, 11)[10].0
    }

    /// [`unseen_slip_error`]'s run over `scans` scans (the slip stays, the odometry never sees it): each
    /// scan's position error (metres), the search that placed it and, if it was inserted, whether its
    /// node is marked `recovered`.
    fn unseen_slip(
        options: LocalTrajectoryBuilderOptions,
        slip: f64,
        scans: u32,
    ) -> Vec<(f64, CorrelativeBranch, Option<bool>)> {
        let room = room();
        let mut llo = LocalTrajectoryBuilder::new(options);
        let mut results = Vec::new();
        for k in 0..scans {
            let time = Timestamp::from_secs_f64(f64::from(k));
            let forward = 0.2 * f64::from(k);
            llo.add_odometry(&OdometryReading {
                time,
                pose: rigid2(forward, 0.0, 0.0),
            });
            let (slipped, turn) = if k >= 10 {
                (slip, if slip > 0.0 { 6f64.to_radians() } else { 0.0 })
            } else {
                (0.0, 0.0)
            };
            let world_from_tracking = rigid2(3.0 + forward + slipped, 4.0 + slipped, turn);
            let result = llo
                .add_range_data(time, &scan(&room, &world_from_tracking))
                .expect("scan matched");
            // The local frame starts at the first scan's pose (3, 4), heading 0.
            let truth = Vector2::new(forward + slipped, slipped);
            let error = (result.local_pose.translation.vector - truth).norm();
            let recovered = result.insertion.map(|i| i.node.recovered);
            results.push((error, result.branch, recovered));
        }
        results
    }

    /// The shifted search and held-back recovered scans (defaults since session 34).
    fn shifted_search() -> LocalTrajectoryBuilderOptions {
        LocalTrajectoryBuilderOptions {
            recovery_linear_window: 0.5,
            insert_recovered_scans: false,
            ..LocalTrajectoryBuilderOptions::default()
        }
    }

    /// The LLO defaults before session 34 (`docs/candidates/s28.toml`), which each option of sessions
    /// 29–34 was measured against.
    fn before_session_34() -> LocalTrajectoryBuilderOptions {
        LocalTrajectoryBuilderOptions {
            anchored_angular_window: 0.0,
            paired_test_where_trusted_misfits: false,
            recovery_linear_window: 0.0,
            insert_recovered_scans: true,
            pose_extrapolator: PoseExtrapolatorOptions {
                min_velocity_span_per_horizon: 0.0,
                ..PoseExtrapolatorOptions::default()
            },
            ..LocalTrajectoryBuilderOptions::default()
        }
    }

    #[test]
    fn a_slip_beyond_the_base_window_is_found_by_the_recovery_translation_window() {
        // 0.3 m forward and 0.3 m aside: every wall misses the prediction's ±0.1-m window.
        let error = unseen_slip_error(shifted_search(), 0.3);
        assert!(error < 0.05, "position error {error} m");
        let without = unseen_slip_error(before_session_34(), 0.3);
        assert!(
            without > 0.15,
            "position error without the window {without} m"
        );
        // A scan that fits near the prediction never searches farther.
        let small = unseen_slip_error(shifted_search(), 0.0);
        assert!(small < 0.05, "position error {small} m");
    }

    #[test]
    fn a_recovered_scan_is_inserted_once_the_next_scan_confirms_it() {
        let run = unseen_slip(shifted_search(), 0.3, 12);
        assert!(
            run[..10].iter().all(|r| r.2 != Some(true)),
            "no recovery before the slip"
        );
        let (error, branch, inserted) = run[10];
        assert_eq!(branch, CorrelativeBranch::Shifted);
        assert_eq!(inserted, None, "held back until confirmed");
        assert!(error < 0.05, "position error {error} m");
        // The next scan fits near the prediction made from it: both go into the submaps, and its node
        // carries the recovery for GLM.
        let (error, branch, inserted) = run[11];
        assert_eq!(branch, CorrelativeBranch::Trusted);
        assert_eq!(inserted, Some(true), "confirmed, marked recovered");
        assert!(error < 0.05, "position error {error} m");
        // Inserted at once when asked.
        let at_once = unseen_slip(
            LocalTrajectoryBuilderOptions {
                insert_recovered_scans: true,
                ..shifted_search()
            },
            0.3,
            11,
        );
        assert_eq!(at_once[10].2, Some(true));
    }

    /// The robot turns in place at (4, 3), +10° per scan, and odometry sees every turn; scan 4 holds what
    /// the scanner saw at −50° (a scan stamped 0.5 s late, as Intel's bursts deliver some). Returns each
    /// scan's heading error (degrees), search, whether it retracted a held scan and whether it was inserted.
    fn late_stamped_scan(
        options: LocalTrajectoryBuilderOptions,
    ) -> Vec<(f64, CorrelativeBranch, bool, bool)> {
        let room = room();
        let mut llo = LocalTrajectoryBuilder::new(options);
        (0..8)
            .map(|k| {
                let time = Timestamp::from_secs_f64(f64::from(k));
                let heading = 10.0 * f64::from(k);
                llo.add_odometry(&OdometryReading {
                    time,
                    pose: rigid2(4.0, 3.0, heading.to_radians()),
                });
                let seen = if k == 4 { -50.0 } else { heading };
                let result = llo
                    .add_range_data(time, &scan(&room, &rigid2(4.0, 3.0, seen.to_radians())))
                    .expect("scan matched");
                let error = normalize_angle(result.local_pose.theta() - heading.to_radians())
                    .to_degrees()
                    .abs();
                (
                    error,
                    result.branch,
                    result.retracted,
                    result.insertion.is_some(),
                )
            })
            .collect()
    }

    #[test]
    fn a_held_recovery_the_odometry_explains_as_well_is_dropped() {
        let held_back = LocalTrajectoryBuilderOptions {
            insert_recovered_scans: false,
            ..before_session_34()
        };
        let run = late_stamped_scan(held_back);
        // The late scan is placed where it was seen (90° from the prediction) and held out of the map.
        let (error, branch, _, inserted) = run[4];
        assert_eq!(branch, CorrelativeBranch::EveryRotation);
        assert!((error - 90.0).abs() < 1.5, "late scan at {error}° from now");
        assert!(!inserted);
        // The scans after it are where the odometry says, and the one that decided retracted the
        // recovery: from the odometry's hypothesis it needed none.
        assert!(run[5..].iter().any(|r| r.2), "{run:?}");
        for (k, (error, ..)) in run.iter().enumerate().skip(5) {
            assert!(*error < 1.5, "scan {k}: heading error {error}°");
        }
        // A recovery the odometry's hypothesis also needs stands: after an unseen slip the held scan and
        // the deciding one both go in, where they are.
        let slip = unseen_slip(shifted_search(), 0.3, 12);
        assert!(slip[10].2.is_none() && slip[11].2.is_some(), "{slip:?}");
        assert!(slip[10].0 < 0.05 && slip[11].0 < 0.05, "{slip:?}");
        // Nothing is retracted where nothing is held.
        assert!(!late_stamped_scan(before_session_34()).iter().any(|r| r.2));
    }

    /// Heading errors (degrees) of a scan of every `every_nth` beam with ±10 cm of range noise, matched
    /// against a submap of one full clean scan from the same pose while odometry reports no motion: one
    /// error per noise seed.
    fn sparse_noisy_scan_errors(
        options: &LocalTrajectoryBuilderOptions,
        every_nth: usize,
    ) -> Vec<f64> {
        use rand::{Rng as _, SeedableRng as _};
        let room = room();
        let pose = rigid2(4.0, 4.5, 0.0);
        (0..20)
            .map(|seed| {
                let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
                let mut llo = LocalTrajectoryBuilder::new(options.clone());
                let mut add = |k: u32, data: RangeData| {
                    let time = Timestamp::from_secs_f64(f64::from(k) * 0.2);
                    llo.add_odometry(&OdometryReading { time, pose });
                    llo.add_range_data(time, &data).expect("scan matched")
                };
                add(0, scan(&room, &pose));
                let mut data = scan(&room, &pose);
                data.returns = data.returns.into_iter().step_by(every_nth).collect();
                for p in &mut data.returns {
                    let noise: f32 = rng.random_range(-0.1..0.1);
                    p.coords *= 1.0 + noise / p.coords.norm();
                }
                let result = add(1, data);
                normalize_angle(result.local_pose.theta())
                    .to_degrees()
                    .abs()
            })
            .collect()
    }

    /// Turns in place at (4, 3), one scan per second, 15° a scan, while the odometry stalls at the fourth
    /// scan (its readings repeat the third's pose, then carry the backlog). Returns, per scan, whether it
    /// was inserted.
    fn inserted_through_a_stall(options: LocalTrajectoryBuilderOptions) -> Vec<bool> {
        let room = room();
        let mut llo = LocalTrajectoryBuilder::new(options);
        let reported = [0.0, 15.0, 30.0, 30.0, 60.0, 75.0];
        let mut inserted = Vec::new();
        for (k, odometry) in reported.iter().enumerate() {
            let time = Timestamp::from_secs_f64(k as f64);
            if k > 0 {
                // A reading half-way, as a stream at 2 Hz would send: frozen too during the stall.
                let halfway = if k == 3 { 30.0 } else { odometry - 7.5 };
                llo.add_odometry(&OdometryReading {
                    time: Timestamp::from_secs_f64(k as f64 - 0.5),
                    pose: rigid2(4.0, 3.0, f64::to_radians(halfway)),
                });
            }
            llo.add_odometry(&OdometryReading {
                time,
                pose: rigid2(4.0, 3.0, odometry.to_radians()),
            });
            let world_from_tracking = rigid2(4.0, 3.0, (15.0 * k as f64).to_radians());
            let result = llo
                .add_range_data(time, &scan(&room, &world_from_tracking))
                .expect("scan matched");
            inserted.push(result.insertion.is_some());
        }
        inserted
    }

    #[test]
    fn a_scan_matched_while_the_odometry_stalls_stays_out_of_the_map_when_asked() {
        let held_out = LocalTrajectoryBuilderOptions {
            insert_while_odometry_stalls: false,
            ..LocalTrajectoryBuilderOptions::default()
        };
        let inserted = inserted_through_a_stall(held_out.clone());
        assert_eq!(inserted, [true, true, true, false, true, true]);
        let inserted = inserted_through_a_stall(LocalTrajectoryBuilderOptions::default());
        assert_eq!(inserted, [true; 6]);
        // A robot standing still is not stalled: the motion filter still lets a scan in every 5 s.
        let room = room();
        let mut llo = LocalTrajectoryBuilder::new(held_out);
        let still: Vec<bool> = (0..7)
            .map(|k| {
                let time = Timestamp::from_secs_f64(f64::from(k));
                llo.add_odometry(&OdometryReading {
                    time,
                    pose: rigid2(4.0, 3.0, 0.0),
                });
                llo.add_range_data(time, &scan(&room, &rigid2(4.0, 3.0, 0.0)))
                    .expect("scan matched")
                    .insertion
                    .is_some()
            })
            .collect();
        assert_eq!(still, [true, false, false, false, false, false, true]);
    }

    #[test]
    fn a_rotation_the_scan_barely_supports_does_not_outweigh_the_odometry() {
        // Exact odometry, a scan of 15 points with ±10 cm of noise: on some seeds the trusted window's best
        // match lies 1.7–2° away by chance; the anchored window keeps the odometry's rotation there.
        let with = sparse_noisy_scan_errors(&LocalTrajectoryBuilderOptions::default(), 12);
        let trusted_only = LocalTrajectoryBuilderOptions {
            anchored_angular_window: 0.0,
            ..LocalTrajectoryBuilderOptions::default()
        };
        let without = sparse_noisy_scan_errors(&trusted_only, 12);
        let far = |errors: &[f64]| errors.iter().filter(|e| **e > 1.6).count();
        assert_eq!(far(&with), 0, "anchored: {with:.2?}");
        assert!(far(&without) >= 2, "trusted window only: {without:.2?}");
    }

    #[test]
    fn the_search_over_every_rotation_needs_more_support_the_farther_it_turns_from_the_odometry() {
        let options = LocalTrajectoryBuilderOptions::default();
        let min_z = |degrees: f64| every_rotation_min_z(&options, degrees.to_radians());
        assert!((min_z(0.0) - options.min_recovery_z).abs() < 1e-12);
        assert!(min_z(10.0) < 6.2, "{}", min_z(10.0));
        assert!((min_z(-180.0) - 6f64.hypot(12.0)).abs() < 1e-9);
        assert!(min_z(90.0) < min_z(180.0));
        let off = LocalTrajectoryBuilderOptions {
            every_rotation_prior: 0.0,
            ..options
        };
        assert!((every_rotation_min_z(&off, std::f64::consts::PI) - 6.0).abs() < 1e-12);
    }

    #[test]
    fn negative_or_nan_judging_options_are_refused() {
        for broken in [
            LocalTrajectoryBuilderOptions {
                min_deviation_z: -1.0,
                ..Default::default()
            },
            LocalTrajectoryBuilderOptions {
                trusted_angular_window: f64::NAN,
                ..Default::default()
            },
            LocalTrajectoryBuilderOptions {
                min_recovery_score: f64::INFINITY,
                ..Default::default()
            },
        ] {
            assert!(broken.validate().is_err());
        }
        for max_path_m in [-1.0, f64::NAN, f64::INFINITY] {
            let mut broken = LocalTrajectoryBuilderOptions::default();
            broken.submaps.max_path_m = max_path_m;
            let error = broken.validate().unwrap_err();
            assert!(error.to_string().contains("max_path_m"), "{error}");
        }
        assert!(LocalTrajectoryBuilderOptions::default().validate().is_ok());
    }

    // Reference: issue 35 item 6 — a nested option's own error stays the source, named by its field.
    #[test]
    fn a_bad_nested_option_keeps_its_own_error_as_the_source() {
        let mut options = LocalTrajectoryBuilderOptions::default();
        options.real_time_correlative.linear_search_window = -1.0;
        let error = options.validate().unwrap_err();
        let source = std::error::Error::source(&error).expect("the matcher's error");
        assert!(source.is::<MatchError>(), "{source:?}");
        assert!(
            error.to_string().contains("real_time_correlative: ")
                && error.to_string().contains("linear_search_window"),
            "{error}"
        );
        let mut options = LocalTrajectoryBuilderOptions::default();
        options.submaps.range_data_inserter.hit_probability = 0.2;
        let error = options.validate().unwrap_err();
        let source = std::error::Error::source(&error).expect("the inserter's error");
        assert!(source.is::<RangeDataInserterOptionsError>(), "{source:?}");
    }
}
