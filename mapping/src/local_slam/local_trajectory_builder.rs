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
    Submap, SubmapRef, SubmapsOptions, adaptive_voxel_filter,
};
use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle};
use crate::scan_matching::{
    LeastSquaresScanMatcher, LeastSquaresScanMatcherOptions, RealTimeCorrelativeScanMatcher,
    RealTimeCorrelativeScanMatcherOptions,
};
use crate::sensor::{ImuReading, OdometryReading, RangeConversionOptions, RangeData, Timestamp};

/// Every LLO setting.
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
    /// Only points within this range (metres) take part in the correlative search; the least-squares
    /// refinement still uses all of them. Far points set the search's rotation step (one cell at the
    /// farthest point), so a 25 m LiDAR costs 2.5× the rotations of a 10 m cut for no gain in a coarse
    /// initial guess. If fewer than `min_num_returns` points are that close, all are used. 0 = no cut.
    /// Default 10 m.
    pub correlative_max_range: f32,
    /// Least-squares refinement weights.
    pub least_squares: LeastSquaresScanMatcherOptions,
    /// The least-squares refinement pulls the translation toward the prediction (odometry, or constant
    /// velocity), which carries the motion where the scan cannot see it (corridors), unless the
    /// correlative search turned the pose more than this (radians) away from the prediction: odometry is
    /// then wrong at this scan and the correlative result is the target. Default 1°; 0 = always the
    /// correlative result, π = always the prediction.
    pub max_odometry_target_disagreement: f64,
    /// When a scan becomes a node.
    pub motion_filter: MotionFilterOptions,
    /// Submap size and resolution.
    pub submaps: SubmapsOptions,
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
            least_squares: LeastSquaresScanMatcherOptions::default(),
            max_odometry_target_disagreement: 1f64.to_radians(),
            motion_filter: MotionFilterOptions::default(),
            submaps: SubmapsOptions::default(),
        }
    }
}

/// Invalid [`LocalTrajectoryBuilderOptions`].
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("invalid LLO option: {0}")]
pub struct LocalTrajectoryBuilderOptionsError(String);

impl LocalTrajectoryBuilderOptions {
    /// Checks every nested option.
    pub fn validate(&self) -> Result<(), LocalTrajectoryBuilderOptionsError> {
        let err = |e: &dyn std::fmt::Display| LocalTrajectoryBuilderOptionsError(e.to_string());
        self.real_time_correlative.validate().map_err(|e| err(&e))?;
        if !(self.correlative_max_range.is_finite() && self.correlative_max_range >= 0.0) {
            return Err(err(&"correlative_max_range must be finite and >= 0"));
        }
        self.least_squares.validate().map_err(|e| err(&e))?;
        if !(self.max_odometry_target_disagreement >= 0.0
            && self.max_odometry_target_disagreement.is_finite())
        {
            return Err(err(
                &"max_odometry_target_disagreement must be finite and >= 0",
            ));
        }
        self.submaps
            .range_data_inserter
            .validate()
            .map_err(|e| err(&e))?;
        let rc = &self.range_conversion;
        if !(rc.min_range >= 0.0
            && rc.max_range > rc.min_range
            && rc.missing_data_ray_length >= 0.0)
        {
            return Err(err(
                &"range_conversion: need 0 ≤ min_range < max_range and missing_data_ray_length ≥ 0",
            ));
        }
        if !(self.submaps.resolution > 0.0 && self.submaps.resolution.is_finite())
            || self.submaps.num_range_data == 0
        {
            return Err(err(
                &"submaps: resolution must be positive and num_range_data at least 1",
            ));
        }
        let av = &self.adaptive_voxel_filter;
        if !(av.max_length > 0.0 && av.max_range > 0.0) {
            return Err(err(
                &"adaptive_voxel_filter: max_length and max_range must be positive",
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

/// The outcome of one matched scan.
#[derive(Clone, Debug)]
pub struct MatchingResult {
    /// Scan time.
    pub time: Timestamp,
    /// `local_from_tracking`.
    pub local_pose: Rigid2,
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
    correlative: RealTimeCorrelativeScanMatcher,
    least_squares: LeastSquaresScanMatcher,
    last_pose: Option<Rigid2>,
    dropped: usize,
}

impl LocalTrajectoryBuilder {
    /// A builder with no submaps; the first scan defines the local frame's origin.
    pub fn new(options: LocalTrajectoryBuilderOptions) -> Self {
        Self {
            extrapolator: PoseExtrapolator::new(),
            active: ActiveSubmaps::new(options.submaps.clone()),
            motion_filter: MotionFilter::new(options.motion_filter.clone()),
            correlative: RealTimeCorrelativeScanMatcher::new(options.real_time_correlative.clone()),
            least_squares: LeastSquaresScanMatcher::new(options.least_squares.clone()),
            options,
            last_pose: None,
            dropped: 0,
        }
    }

    /// Adds a wheel-odometry reading.
    pub fn add_odometry(&mut self, reading: &OdometryReading) {
        self.extrapolator.add_odometry(reading);
    }

    /// Adds an IMU reading.
    pub fn add_imu(&mut self, reading: &ImuReading) {
        self.extrapolator.add_imu(reading);
    }

    /// The active submaps (for rendering an unfinished map).
    pub fn active_submaps(&self) -> &ActiveSubmaps {
        &self.active
    }

    /// Scans dropped (too few hits, or time went backwards) plus sensor readings the extrapolator refused.
    pub fn num_rejected(&self) -> usize {
        self.dropped + self.extrapolator.rejected()
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
        let predicted = self.extrapolator.extrapolate(time);
        let filtered =
            adaptive_voxel_filter(&range_data.returns, &self.options.adaptive_voxel_filter);
        let pose = match self.active.matching_submap() {
            Some(submap) => {
                let (initial, center) = if self.options.use_correlative_scan_matching {
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
                            &filtered[..]
                        }
                    } else {
                        &filtered[..]
                    };
                    // Widen the angular window by the rotation the prediction claims: wheel odometry is
                    // least trustworthy in turns (CSAIL: −46° reported where the scans say −21°).
                    let claimed = self.last_pose.map_or(0.0, |last| {
                        normalize_angle(predicted.theta() - last.theta()).abs()
                    });
                    let base = &self.options.real_time_correlative;
                    let widened;
                    let matcher = if claimed > 1e-3 {
                        widened = RealTimeCorrelativeScanMatcher::new(
                            RealTimeCorrelativeScanMatcherOptions {
                                angular_search_window: (base.angular_search_window + claimed)
                                    .min(std::f64::consts::PI),
                                ..base.clone()
                            },
                        );
                        &widened
                    } else {
                        &self.correlative
                    };
                    let (mut best, best_score) =
                        matcher.match_pose(&predicted, correlative_points, &submap.grid);
                    let mut center = predicted;
                    // Wheel odometry sometimes stalls and then jumps (CSAIL: frozen for 0.8 s in a turn, then
                    // +85° at once). When the constant-velocity prediction disagrees by more than half the
                    // window, search around it too and keep the better match.
                    let velocity = self.extrapolator.extrapolate_constant_velocity(time);
                    if normalize_angle(velocity.theta() - predicted.theta()).abs()
                        > 0.5 * base.angular_search_window
                    {
                        let (pose, score) = self.correlative.match_pose(
                            &velocity,
                            correlative_points,
                            &submap.grid,
                        );
                        if score > best_score {
                            (best, center) = (pose, velocity);
                        }
                    }
                    (best, center)
                } else {
                    (predicted, predicted)
                };
                // Like Cartographer, the refinement is pulled toward the predicted translation (the
                // centre of the correlative search): where the scan cannot see the motion (along a
                // corridor) odometry carries it. Where the scan turned the pose away from the prediction,
                // odometry is wrong at this scan (CSAIL: yaw jumps in turns) and so is its translation:
                // the correlative result is the target then.
                let disagreement = normalize_angle(initial.theta() - center.theta()).abs();
                let target = if disagreement > self.options.max_odometry_target_disagreement {
                    initial.translation.vector
                } else {
                    center.translation.vector
                };
                let (refined, _) =
                    self.least_squares
                        .match_pose(&target, &initial, &filtered, &submap.grid);
                let finite = refined.translation.vector.iter().all(|v| v.is_finite())
                    && refined.theta().is_finite();
                if finite { refined } else { initial }
            }
            None => predicted,
        };
        self.extrapolator.add_pose(time, pose);
        self.last_pose = Some(pose);
        if self.motion_filter.is_similar(time, &pose) {
            return Some(MatchingResult {
                time,
                local_pose: pose,
                insertion: None,
            });
        }
        let (inserted, finished) = self.active.insert(&range_data.transformed(&pose));
        Some(MatchingResult {
            time,
            local_pose: pose,
            insertion: Some(InsertionResult {
                node: TrajectoryNodeData {
                    time,
                    local_pose: pose,
                    filtered_points: filtered,
                },
                insertion_submaps: inserted,
                finished_submaps: finished,
            }),
        })
    }
}
