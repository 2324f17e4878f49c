//! GLM, global LiDAR matching: finds node-to-submap constraints with the branch-and-bound matcher and
//! refines them with the least-squares matcher, as Cartographer's `ConstraintBuilder2D` does.
//!
//! Work is described by [`SearchJob`] values and run by [`ConstraintBuilder::run`], which takes `&self`:
//! the shell may run many jobs on as many threads as it likes (this crate spawns none) and hands the
//! results back to [`super::GlobalSlam::add_search_results`].

use std::collections::BTreeMap;
use std::sync::Arc;

use nalgebra::Point2;
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
    /// (Cartographer's is 15 m): a finished submap holds twice LLO's `num_range_data` scans, about 34 m of
    /// a straight aisle at the default motion filter, and with 15 m the far half of such a submap was never
    /// matched, so nothing but LLO held a long aisle's heading (simulated store, session 0, seed 1:
    /// trajectory error 0.274 → 0.153 m RMS, 25 m gave 0.151, 30 m 0.165; seeds 2 and 3 gained 1 and 3 cm;
    /// Freiburg relations error equal or lower; see BENCHMARKS.md).
    pub max_constraint_distance: f64,
    /// Minimum branch-and-bound score (mean probability at the scan points) to accept a loop closure
    /// near the current estimate. Default 0.55.
    pub min_score: f32,
    /// Minimum score to accept a match searched over a whole submap with no prior (relocalization).
    /// Default 0.6.
    pub global_localization_min_score: f32,
    /// Standard deviation (m) of an accepted loop closure's translation. Default 0.03 m.
    pub loop_closure_translation_sigma: f64,
    /// Standard deviation (rad) of an accepted loop closure's rotation. Default 0.01 rad.
    pub loop_closure_rotation_sigma: f64,
    /// Huber threshold on the whitened loop-closure error (in standard deviations). Default 3.
    pub huber_scale: f64,
    /// Branch-and-bound search window and depth. Defaults here: 4 m, ±20°, depth 7.
    pub fast_correlative: FastCorrelativeScanMatcherOptions,
    /// Refinement of accepted matches.
    pub least_squares: LeastSquaresScanMatcherOptions,
}

impl Default for ConstraintBuilderOptions {
    fn default() -> Self {
        Self {
            sampling_ratio: 0.15,
            max_constraint_distance: 20.0,
            min_score: 0.55,
            global_localization_min_score: 0.6,
            loop_closure_translation_sigma: 0.03,
            loop_closure_rotation_sigma: 0.01,
            huber_scale: 3.0,
            // LLO drifts little over the 20 m a loop-closure candidate may be away, so a 4 m × ±20° window
            // finds the same closures as Cartographer's 7 m × ±30° at a third of the cost (CSAIL: 0.042 m
            // vs 0.041 m relations error, 10.6 s vs 36 s; see BENCHMARKS.md).
            fast_correlative: FastCorrelativeScanMatcherOptions {
                linear_search_window: 4.0,
                angular_search_window: 20f64.to_radians(),
                ..FastCorrelativeScanMatcherOptions::default()
            },
            least_squares: LeastSquaresScanMatcherOptions::default(),
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
        self.fast_correlative
            .validate()
            .map_err(|e| GlobalSlamOptionsError::Invalid(e.to_string()))?;
        self.least_squares
            .validate()
            .map_err(|e| GlobalSlamOptionsError::Invalid(e.to_string()))
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
}

/// A node-to-submap search to run.
#[derive(Clone, Debug)]
pub struct SearchJob {
    /// The submap to match against (must have been added with [`ConstraintBuilder::add_finished_submap`]).
    pub submap: SubmapId,
    /// The node to match.
    pub node: NodeId,
    /// The node's filtered scan points in its tracking frame.
    pub points: Arc<Vec<Point2<f32>>>,
    /// Prior estimate of the node in the submap frame; `None` searches the whole submap at every rotation.
    pub submap_from_node_estimate: Option<Rigid2>,
}

struct SubmapMatcher {
    local_from_submap: Rigid2,
    grid: Arc<ProbabilityGrid>,
    matcher: FastCorrelativeScanMatcher,
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

    /// Precomputes the branch-and-bound grids of a finished submap. `grid` is in the submap's trajectory
    /// local frame; `local_from_submap` is the submap's local pose.
    pub fn add_finished_submap(
        &mut self,
        id: SubmapId,
        local_from_submap: Rigid2,
        grid: Arc<ProbabilityGrid>,
    ) {
        let matcher = FastCorrelativeScanMatcher::new(&grid, self.options.fast_correlative.clone());
        self.matchers.insert(
            id,
            SubmapMatcher {
                local_from_submap,
                grid,
                matcher,
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

    /// Runs one search; `None` when the submap is unknown or no match reaches the minimum score.
    pub fn run(&self, job: &SearchJob) -> Option<LoopClosure> {
        let entry = self.matchers.get(&job.submap)?;
        let found = match &job.submap_from_node_estimate {
            Some(estimate) => {
                let initial = entry.local_from_submap * estimate;
                entry
                    .matcher
                    .match_near(&initial, &job.points, self.options.min_score)
            }
            None => entry
                .matcher
                .match_full(&job.points, self.options.global_localization_min_score),
        }?;
        let (refined, _summary) = self.least_squares.match_pose(
            &found.pose.translation.vector,
            &found.pose,
            &job.points,
            &entry.grid,
        );
        Some(LoopClosure {
            submap: job.submap,
            node: job.node,
            submap_from_node: entry.local_from_submap.inverse() * refined,
            score: found.score,
        })
    }
}
