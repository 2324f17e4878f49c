//! Real-time correlative scan matching: Olson, "Real-Time Correlative Scan Matching", ICRA 2009.
//!
//! Exhaustive search over a small window of rotations × whole-cell translations around a prior pose. Each
//! rotated scan is computed and discretized once (see `correlative.rs`), then every translation costs one
//! integer add and one grid read per point. The score of a candidate is the mean grid probability at its
//! points, multiplied by `exp(−(w_t·‖Δt‖ + w_r·|Δθ|)²)` so that, among equally good fits, the one closest
//! to the prior wins (as Cartographer does).
//!
//! Trade-off: robust to poor priors within the window (no local minima), but the cost grows with
//! window area × angular range × points, and the result is only as fine as one cell and one angular step.
//! Refine it with [`LeastSquaresScanMatcher`](super::LeastSquaresScanMatcher).

use nalgebra::Point2;
use serde::{Deserialize, Serialize};

use super::correlative::SearchSpace;
use super::{MatchError, check_non_negative};
use crate::geometry::Rigid2;
use crate::grid::{ProbabilityGrid, value_to_probability};

/// Options of [`RealTimeCorrelativeScanMatcher`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RealTimeCorrelativeScanMatcherOptions {
    /// Half-width in metres of the square translation window searched around the prior. Default 0.1 m.
    pub linear_search_window: f64,
    /// Half-width in radians of the rotation window searched around the prior. Default 20° (0.349 rad).
    pub angular_search_window: f64,
    /// Weight (1/m) of the translation distance from the prior in the score penalty. Default 0.1.
    pub translation_delta_cost_weight: f64,
    /// Weight (1/rad) of the rotation distance from the prior in the score penalty. Default 0.1.
    pub rotation_delta_cost_weight: f64,
}

impl Default for RealTimeCorrelativeScanMatcherOptions {
    fn default() -> Self {
        Self {
            linear_search_window: 0.1,
            angular_search_window: 20f64.to_radians(),
            translation_delta_cost_weight: 0.1,
            rotation_delta_cost_weight: 0.1,
        }
    }
}

impl RealTimeCorrelativeScanMatcherOptions {
    /// Checks that every field is finite and non-negative.
    pub fn validate(&self) -> Result<(), MatchError> {
        check_non_negative("linear_search_window", self.linear_search_window)?;
        check_non_negative("angular_search_window", self.angular_search_window)?;
        if self.angular_search_window > std::f64::consts::PI {
            return Err(MatchError::InvalidOption {
                field: "angular_search_window",
                reason: "must be at most π",
            });
        }
        check_non_negative(
            "translation_delta_cost_weight",
            self.translation_delta_cost_weight,
        )?;
        check_non_negative(
            "rotation_delta_cost_weight",
            self.rotation_delta_cost_weight,
        )
    }
}

/// Exhaustive correlative scan matcher around a prior pose. Stateless apart from its options; `Sync`.
#[derive(Clone, Debug)]
pub struct RealTimeCorrelativeScanMatcher {
    options: RealTimeCorrelativeScanMatcherOptions,
}

impl RealTimeCorrelativeScanMatcher {
    /// A matcher with the given options (validate them first; invalid values give meaningless results).
    pub fn new(options: RealTimeCorrelativeScanMatcherOptions) -> Self {
        Self { options }
    }

    /// The options.
    pub fn options(&self) -> &RealTimeCorrelativeScanMatcherOptions {
        &self.options
    }

    /// Searches the window around `initial` (`grid_from_tracking`) for the pose that maximizes the penalized
    /// score, and returns that pose with its penalized score (mean probability × distance penalty, in
    /// `(0, 0.9]`). With no points, returns `initial` and score 0.
    pub fn match_pose(
        &self,
        initial: &Rigid2,
        points: &[Point2<f32>],
        grid: &ProbabilityGrid,
    ) -> (Rigid2, f32) {
        let [result] =
            self.match_pose_nested(initial, points, grid, [self.options.angular_search_window]);
        result
    }

    /// [`Self::match_pose`] for several angular windows (radians, each at most π; the options' own is not
    /// used) around the same `initial`, in one pass over the widest: one result per window, each equal to
    /// `match_pose` with that window. A narrower window's candidates are a subset of the widest's (the
    /// same rotations `k · step`, the same translations), scored the same and visited in the same order.
    pub fn match_pose_nested<const N: usize>(
        &self,
        initial: &Rigid2,
        points: &[Point2<f32>],
        grid: &ProbabilityGrid,
        angular_windows: [f64; N],
    ) -> [(Rigid2, f32); N] {
        if points.is_empty() {
            return [(*initial, 0.0); N];
        }
        let o = &self.options;
        let limits = grid.limits();
        let widest = angular_windows.iter().copied().fold(0.0, f64::max);
        let space = SearchSpace::around(initial, points, limits, o.linear_search_window, widest);
        // Rotation k of the space is `(k − reach[widest]) · step`; it belongs to window i when within reach[i].
        let reach = angular_windows.map(|w| SearchSpace::rotations_reach(points, limits, w));
        let widest_reach = reach.iter().copied().max().unwrap_or(0);
        let (width, height) = (limits.width, limits.height);
        let values = grid.values();
        let inv_n = 1.0 / points.len() as f64;
        let mut best = [(0usize, 0i32, 0i32, f64::NEG_INFINITY); N];
        for k in 0..space.num_scans() {
            let offset = (k as i64 - widest_reach).abs();
            let scan = space.scan(k);
            let bounds = space.bounds(k);
            let rotation_cost = o.rotation_delta_cost_weight * space.angle(k).abs();
            for dy in bounds.min_y..=bounds.max_y {
                for dx in bounds.min_x..=bounds.max_x {
                    let mut sum = 0.0f32;
                    for c in scan {
                        let (x, y) = (c.x.wrapping_add(dx), c.y.wrapping_add(dy));
                        let value = if x >= 0 && y >= 0 && x < width && y < height {
                            values[y as usize * width as usize + x as usize]
                        } else {
                            0
                        };
                        sum += value_to_probability(value);
                    }
                    let cost = o.translation_delta_cost_weight * space.offset_metres(dx, dy).norm()
                        + rotation_cost;
                    let score = f64::from(sum) * inv_n * (-cost * cost).exp();
                    for (b, &r) in best.iter_mut().zip(&reach) {
                        if offset <= r && score > b.3 {
                            *b = (k, dx, dy, score);
                        }
                    }
                }
            }
        }
        best.map(|(k, dx, dy, score)| (space.pose(k, dx, dy), score as f32))
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector2;
    use rand::{Rng as _, SeedableRng as _};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::geometry::{Rigid2Ext as _, rigid2};
    use crate::grid::MapLimits;
    use crate::scan_matching::mean_probability;
    use crate::scan_matching::test_support::{room_grid, room_scan};

    fn random_grid(rng: &mut Pcg64, w: i32, h: i32) -> ProbabilityGrid {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.1, Vector2::new(-1.0, -0.5), w, h));
        for v in grid.values_mut() {
            if rng.random_bool(0.7) {
                *v = rng.random_range(1..=32767);
            }
        }
        grid
    }

    /// Scores every candidate of the same discretized set by transforming the points with the candidate
    /// pose in floating point (no precomputed rotations or cell offsets).
    fn brute_force(
        options: &RealTimeCorrelativeScanMatcherOptions,
        initial: &Rigid2,
        points: &[Point2<f32>],
        grid: &ProbabilityGrid,
    ) -> f64 {
        let space = SearchSpace::around(
            initial,
            points,
            grid.limits(),
            options.linear_search_window,
            options.angular_search_window,
        );
        let mut best = f64::NEG_INFINITY;
        for k in 0..space.num_scans() {
            let b = space.bounds(k);
            for dx in b.min_x..=b.max_x {
                for dy in b.min_y..=b.max_y {
                    let pose = space.pose(k, dx, dy);
                    let dt = (pose.translation.vector - initial.translation.vector).norm();
                    let dtheta = space.angle(k).abs();
                    let cost = options.translation_delta_cost_weight * dt
                        + options.rotation_delta_cost_weight * dtheta;
                    best = best.max(mean_probability(grid, points, &pose) * (-cost * cost).exp());
                }
            }
        }
        best
    }

    /// A random 30 × 25 grid, 12 points within 1 m and an initial pose with its heading within
    /// ±`max_heading` radians, drawn from `seed`.
    fn random_case(seed: u64, max_heading: f64) -> (ProbabilityGrid, Vec<Point2<f32>>, Rigid2) {
        let mut rng = Pcg64::seed_from_u64(seed);
        let grid = random_grid(&mut rng, 30, 25);
        let points: Vec<Point2<f32>> = (0..12)
            .map(|_| Point2::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)))
            .collect();
        let initial = rigid2(
            rng.random_range(0.0..1.5),
            rng.random_range(0.0..1.5),
            rng.random_range(-max_heading..max_heading),
        );
        (grid, points, initial)
    }

    #[test]
    fn nested_windows_equal_separate_searches_bit_for_bit() {
        for seed in 0..6 {
            let (grid, points, initial) = random_case(seed, 1.0);
            let windows = [0.7, 0.25, 0.02];
            let matcher = |w: f64| {
                RealTimeCorrelativeScanMatcher::new(RealTimeCorrelativeScanMatcherOptions {
                    linear_search_window: 0.3,
                    angular_search_window: w,
                    translation_delta_cost_weight: 0.5,
                    rotation_delta_cost_weight: 0.3,
                })
            };
            let nested = matcher(0.0).match_pose_nested(&initial, &points, &grid, windows);
            for (w, (pose, score)) in windows.iter().zip(nested) {
                let (alone, alone_score) = matcher(*w).match_pose(&initial, &points, &grid);
                assert_eq!(pose, alone, "seed {seed}, window {w}");
                assert_eq!(
                    score.to_bits(),
                    alone_score.to_bits(),
                    "seed {seed}, window {w}"
                );
            }
        }
    }

    #[test]
    fn equals_brute_force_on_random_grids() {
        for seed in 0..4 {
            let (grid, points, initial) = random_case(seed, 3.0);
            let options = RealTimeCorrelativeScanMatcherOptions {
                linear_search_window: 0.35,
                angular_search_window: 0.3,
                translation_delta_cost_weight: 0.5,
                rotation_delta_cost_weight: 0.3,
            };
            let matcher = RealTimeCorrelativeScanMatcher::new(options.clone());
            let (pose, score) = matcher.match_pose(&initial, &points, &grid);
            let expected = brute_force(&options, &initial, &points, &grid);
            assert!(
                (f64::from(score) - expected).abs() < 1e-5,
                "seed {seed}: {score} vs {expected}"
            );
            // The returned pose really has the returned score.
            let dt = (pose.translation.vector - initial.translation.vector).norm();
            let dtheta = (pose.theta() - initial.theta()).abs();
            let dtheta = dtheta.min(std::f64::consts::TAU - dtheta);
            let cost = options.translation_delta_cost_weight * dt
                + options.rotation_delta_cost_weight * dtheta;
            let rescored = mean_probability(&grid, &points, &pose) * (-cost * cost).exp();
            assert!((rescored - f64::from(score)).abs() < 1e-5);
        }
    }

    #[test]
    fn recovers_a_known_offset() {
        let grid = room_grid();
        let truth = rigid2(1.05, 0.8, 0.3);
        let points = room_scan(&truth);
        let matcher =
            RealTimeCorrelativeScanMatcher::new(RealTimeCorrelativeScanMatcherOptions::default());
        let initial = rigid2(1.12, 0.72, 0.38);
        let (pose, score) = matcher.match_pose(&initial, &points, &grid);
        assert!(
            (pose.translation.vector - truth.translation.vector).norm() < 0.051,
            "{pose:?}"
        );
        assert!((pose.theta() - truth.theta()).abs() < 0.01, "{pose:?}");
        assert!(score > 0.6, "score {score}");
        let (_, initial_score) = (initial, mean_probability(&grid, &points, &initial));
        assert!(f64::from(score) > initial_score);
    }

    #[test]
    fn empty_scan_returns_the_prior() {
        let grid = room_grid();
        let matcher =
            RealTimeCorrelativeScanMatcher::new(RealTimeCorrelativeScanMatcherOptions::default());
        let initial = rigid2(1.0, 2.0, 0.5);
        assert_eq!(matcher.match_pose(&initial, &[], &grid), (initial, 0.0));
    }

    #[test]
    fn validate_rejects_bad_options() {
        assert!(
            RealTimeCorrelativeScanMatcherOptions::default()
                .validate()
                .is_ok()
        );
        let bad = RealTimeCorrelativeScanMatcherOptions {
            linear_search_window: -1.0,
            ..Default::default()
        };
        assert!(matches!(
            bad.validate(),
            Err(MatchError::InvalidOption {
                field: "linear_search_window",
                ..
            })
        ));
        let bad = RealTimeCorrelativeScanMatcherOptions {
            angular_search_window: f64::NAN,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
    }
}
