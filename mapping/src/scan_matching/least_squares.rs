//! Least-squares scan matching: refines a pose by Levenberg–Marquardt on a bicubically interpolated grid,
//! the "Ceres scan matcher" of Hess et al., "Real-Time Loop Closure in 2D LIDAR SLAM", ICRA 2016, §IV-C.
//!
//! Parameters `x = (tx, ty, θ)` of `grid_from_tracking`; the cost is `½ Σ rᵢ²` over the residuals
//!
//! * occupied space, one per point: `w_o/√N · (1 − P(T(x)·pᵢ))` with `P` the [`InterpolatedGrid`];
//! * translation: `w_t · (t − t_target)` (two residuals), pulling toward the predicted translation;
//! * rotation: `w_r · (θ − θ_initial)`.
//!
//! The 3×3 normal equations `(JᵀJ + λ·diag JᵀJ) δ = −Jᵀr` are accumulated point by point (no Jacobian
//! matrix, no allocation) and solved by Cholesky; λ follows Nielsen's update. Stops on a relative cost
//! decrease below `function_tolerance`, a step below `parameter_tolerance`, a vanishing gradient, or after
//! `max_iterations`.
//!
//! Trade-off: sub-cell accurate and cheap (a few iterations × N bicubic lookups), but local — it converges
//! to the nearest minimum, so it needs a prior within a few cells (odometry, extrapolation, or a
//! correlative matcher). Its result is not a quality measure; use a correlative score for that.

use nalgebra::{Matrix3, Point2, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use super::{InterpolatedGrid, MatchError, check_non_negative, check_positive};
use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle, rigid2};
use crate::grid::ProbabilityGrid;

/// Options of [`LeastSquaresScanMatcher`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LeastSquaresScanMatcherOptions {
    /// Weight (unitless) of the occupied-space residuals; it is divided by √N so the scan as a whole weighs
    /// the same whatever its point count. Default 1.
    pub occupied_space_weight: f64,
    /// Weight (1/m) of the residual pulling the translation toward the target translation. Default 3.
    /// Why: `docs/TUNING.md#ls-translation-weight`.
    pub translation_weight: f64,
    /// Weight (1/rad) of the residual pulling the rotation toward the initial rotation. Default 10.
    /// Why: `docs/TUNING.md#ls-rotation-weight`.
    pub rotation_weight: f64,
    /// Maximum number of Levenberg–Marquardt iterations (accepted or rejected steps). Default 20.
    pub max_iterations: u32,
    /// Converged when an accepted step lowers the cost by less than this fraction of it. Default 1e-6.
    pub function_tolerance: f64,
    /// Converged when a step is shorter than this fraction of `‖(tx, ty, θ)‖` (m and rad mixed, as Ceres
    /// does). Default 1e-8.
    pub parameter_tolerance: f64,
}

impl Default for LeastSquaresScanMatcherOptions {
    fn default() -> Self {
        Self {
            occupied_space_weight: 1.0,
            translation_weight: 3.0,
            rotation_weight: 10.0,
            max_iterations: 20,
            function_tolerance: 1e-6,
            parameter_tolerance: 1e-8,
        }
    }
}

impl LeastSquaresScanMatcherOptions {
    /// Checks that weights and tolerances are finite and non-negative and that at least one iteration is
    /// allowed.
    pub fn validate(&self) -> Result<(), MatchError> {
        check_non_negative("occupied_space_weight", self.occupied_space_weight)?;
        check_non_negative("translation_weight", self.translation_weight)?;
        check_non_negative("rotation_weight", self.rotation_weight)?;
        check_non_negative("function_tolerance", self.function_tolerance)?;
        check_non_negative("parameter_tolerance", self.parameter_tolerance)?;
        check_positive("max_iterations", f64::from(self.max_iterations))
    }
}

/// What the optimization did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LeastSquaresSummary {
    /// Cost `½ Σ r²` at the initial pose.
    pub initial_cost: f64,
    /// Cost at the returned pose (never above `initial_cost`).
    pub final_cost: f64,
    /// Levenberg–Marquardt iterations run, accepted or rejected.
    pub iterations: u32,
    /// Whether a tolerance was met before `max_iterations`.
    pub converged: bool,
    /// `JᵀJ` of the occupied-space residuals alone at the returned pose (the priors left out), over
    /// `(tx, ty, θ)` in the grid frame: how well the scan itself pins each direction. Along a featureless
    /// corridor its translation block has a near-zero eigenvalue along the corridor.
    pub scan_information: Matrix3<f64>,
}

/// Levenberg–Marquardt scan-to-grid refinement. Stateless apart from its options; `Sync`.
#[derive(Clone, Debug)]
pub struct LeastSquaresScanMatcher {
    options: LeastSquaresScanMatcherOptions,
}

/// Cost, `JᵀJ` and `Jᵀr` at one parameter vector.
struct Linearization {
    cost: f64,
    jtj: Matrix3<f64>,
    jtr: Vector3<f64>,
}

/// The problem data that stay fixed during one match.
struct Problem<'a> {
    grid: InterpolatedGrid<'a>,
    points: &'a [Point2<f32>],
    occupied_scale: f64,
    translation_weight: f64,
    rotation_weight: f64,
    target_translation: Vector2<f64>,
    target_rotation: f64,
}

impl Problem<'_> {
    /// `JᵀJ` of the occupied-space residuals at `x`.
    fn scan_information(&self, x: &Vector3<f64>) -> Matrix3<f64> {
        Problem {
            translation_weight: 0.0,
            rotation_weight: 0.0,
            ..*self
        }
        .linearize(x)
        .jtj
    }

    fn linearize(&self, x: &Vector3<f64>) -> Linearization {
        let (sin, cos) = x.z.sin_cos();
        let mut cost = 0.0;
        let mut jtj = Matrix3::zeros();
        let mut jtr = Vector3::zeros();
        let s = self.occupied_scale;
        if s > 0.0 {
            for p in self.points {
                let (px, py) = (f64::from(p.x), f64::from(p.y));
                let q = Point2::new(cos * px - sin * py + x.x, sin * px + cos * py + x.y);
                let (probability, gradient) = self.grid.evaluate(&q);
                let r = s * (1.0 - probability);
                // d(T·p)/dθ = (−sin·px − cos·py, cos·px − sin·py).
                let d_theta =
                    gradient.x * (-sin * px - cos * py) + gradient.y * (cos * px - sin * py);
                let j = Vector3::new(-s * gradient.x, -s * gradient.y, -s * d_theta);
                cost += r * r;
                jtr += j * r;
                jtj += j * j.transpose();
            }
        }
        let wt = self.translation_weight;
        let rt = (x.xy() - self.target_translation) * wt;
        cost += rt.norm_squared();
        jtr.x += wt * rt.x;
        jtr.y += wt * rt.y;
        jtj[(0, 0)] += wt * wt;
        jtj[(1, 1)] += wt * wt;
        let wr = self.rotation_weight;
        let rr = wr * (x.z - self.target_rotation);
        cost += rr * rr;
        jtr.z += wr * rr;
        jtj[(2, 2)] += wr * wr;
        Linearization {
            cost: 0.5 * cost,
            jtj,
            jtr,
        }
    }
}

/// Smallest diagonal damping term, so λ acts even on directions the cost does not constrain.
const MIN_DIAGONAL: f64 = 1e-6;
/// Below this gradient (max norm) the pose is a stationary point.
const GRADIENT_TOLERANCE: f64 = 1e-10;
/// Initial Levenberg–Marquardt damping (relative to the diagonal of JᵀJ).
const INITIAL_LAMBDA: f64 = 1e-4;

impl LeastSquaresScanMatcher {
    /// A matcher with the given options (validate them first; invalid values give meaningless results).
    pub fn new(options: LeastSquaresScanMatcherOptions) -> Self {
        Self { options }
    }

    /// The options.
    pub fn options(&self) -> &LeastSquaresScanMatcherOptions {
        &self.options
    }

    /// Refines `initial` (`grid_from_tracking`) so that `points` land on high grid probability, pulled
    /// toward `target_translation` (metres, grid frame) and `initial`'s rotation. Returns the refined pose
    /// (rotation normalized to `(−π, π]`) and a summary.
    pub fn match_pose(
        &self,
        target_translation: &Vector2<f64>,
        initial: &Rigid2,
        points: &[Point2<f32>],
        grid: &ProbabilityGrid,
    ) -> (Rigid2, LeastSquaresSummary) {
        let o = &self.options;
        let occupied_scale = if points.is_empty() {
            0.0
        } else {
            o.occupied_space_weight / (points.len() as f64).sqrt()
        };
        let problem = Problem {
            grid: InterpolatedGrid::new(grid),
            points,
            occupied_scale,
            translation_weight: o.translation_weight,
            rotation_weight: o.rotation_weight,
            target_translation: *target_translation,
            target_rotation: initial.theta(),
        };
        let mut x = initial.to_xytheta();
        let mut current = problem.linearize(&x);
        let initial_cost = current.cost;
        let mut lambda = INITIAL_LAMBDA;
        let mut nu = 2.0;
        let mut iterations = 0;
        let mut converged = false;
        while iterations < o.max_iterations {
            if current.jtr.amax() <= GRADIENT_TOLERANCE {
                converged = true;
                break;
            }
            iterations += 1;
            let mut a = current.jtj;
            for i in 0..3 {
                a[(i, i)] += lambda * a[(i, i)].max(MIN_DIAGONAL);
            }
            let Some(cholesky) = a.cholesky() else {
                lambda *= nu;
                nu *= 2.0;
                continue;
            };
            let delta = -cholesky.solve(&current.jtr);
            if delta.norm() <= o.parameter_tolerance * (x.norm() + o.parameter_tolerance) {
                converged = true;
                break;
            }
            let candidate_x = x + delta;
            let candidate = problem.linearize(&candidate_x);
            let actual = current.cost - candidate.cost;
            // Decrease predicted by the Gauss–Newton model: −gᵀδ − ½ δᵀ JᵀJ δ.
            let predicted = -delta.dot(&current.jtr) - 0.5 * delta.dot(&(current.jtj * delta));
            if actual > 0.0 && predicted > 0.0 {
                let rho = actual / predicted;
                lambda *= (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0);
                nu = 2.0;
                let previous_cost = current.cost;
                x = candidate_x;
                current = candidate;
                if actual <= o.function_tolerance * previous_cost {
                    converged = true;
                    break;
                }
            } else {
                lambda *= nu;
                nu *= 2.0;
            }
        }
        let summary = LeastSquaresSummary {
            initial_cost,
            final_cost: current.cost,
            iterations,
            converged,
            scan_information: problem.scan_information(&x),
        };
        (rigid2(x.x, x.y, normalize_angle(x.z)), summary)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::MapLimits;
    use crate::scan_matching::test_support::{room_grid, room_scan};

    fn pure_matching() -> LeastSquaresScanMatcherOptions {
        LeastSquaresScanMatcherOptions {
            translation_weight: 0.0,
            rotation_weight: 0.0,
            ..Default::default()
        }
    }

    #[test]
    fn recovers_a_perturbed_pose() {
        let grid = room_grid();
        for (truth, offset) in [
            (rigid2(2.5, 2.0, 0.2), (0.04, -0.03, 0.03)),
            (rigid2(4.2, 1.1, -2.0), (-0.03, -0.04, -0.04)),
            (rigid2(1.3, 4.1, 3.0), (0.035, 0.035, 0.05)),
        ] {
            let points = room_scan(&truth);
            let initial = rigid2(
                truth.x() + offset.0,
                truth.y() + offset.1,
                truth.theta() + offset.2,
            );
            let matcher = LeastSquaresScanMatcher::new(pure_matching());
            let (pose, summary) =
                matcher.match_pose(&initial.translation.vector, &initial, &points, &grid);
            let error = pose.inverse() * truth;
            assert!(
                error.translation.vector.norm() < 0.005,
                "{truth:?}: {pose:?} {summary:?}"
            );
            assert!(
                error.rotation.angle().abs() < 0.005,
                "{truth:?}: {pose:?} {summary:?}"
            );
            assert!(summary.final_cost < summary.initial_cost);
            assert!(summary.iterations >= 1 && summary.iterations <= 20);
        }
    }

    #[test]
    fn default_weights_with_a_good_target_recover_the_pose() {
        let grid = room_grid();
        let truth = rigid2(3.1, 2.4, -0.7);
        let points = room_scan(&truth);
        let initial = rigid2(3.13, 2.38, -0.69);
        let matcher = LeastSquaresScanMatcher::new(LeastSquaresScanMatcherOptions::default());
        let (pose, summary) =
            matcher.match_pose(&truth.translation.vector, &initial, &points, &grid);
        assert!(
            (pose.translation.vector - truth.translation.vector).norm() < 0.005,
            "{pose:?}"
        );
        assert!((pose.theta() - truth.theta()).abs() < 0.01, "{pose:?}");
        assert!(summary.converged, "{summary:?}");
    }

    #[test]
    fn without_map_information_the_regularizers_decide() {
        // An all-unknown grid is flat: only the translation and rotation residuals act.
        let grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::zeros(), 50, 50));
        let points = room_scan(&rigid2(0.0, 0.0, 0.0));
        let target = Vector2::new(1.2, 0.7);
        let initial = rigid2(1.0, 1.0, 0.4);
        let matcher = LeastSquaresScanMatcher::new(LeastSquaresScanMatcherOptions::default());
        let (pose, summary) = matcher.match_pose(&target, &initial, &points, &grid);
        assert!((pose.translation.vector - target).norm() < 1e-6, "{pose:?}");
        assert!((pose.theta() - 0.4).abs() < 1e-9);
        // Every point reads the minimum probability: the occupied-space cost is the constant ½·(1 − 0.1)².
        assert!(summary.converged, "{summary:?}");
        assert!(
            (summary.final_cost - 0.5 * 0.81).abs() < 1e-6,
            "{summary:?}"
        );
    }

    #[test]
    fn translation_weight_pulls_toward_the_target() {
        let grid = room_grid();
        let truth = rigid2(2.5, 2.0, 0.2);
        let points = room_scan(&truth);
        let target = truth.translation.vector + Vector2::new(0.03, 0.02);
        let mut previous = f64::INFINITY;
        for weight in [0.0, 3.0, 30.0, 1e4] {
            let matcher = LeastSquaresScanMatcher::new(LeastSquaresScanMatcherOptions {
                translation_weight: weight,
                ..Default::default()
            });
            let (pose, _) = matcher.match_pose(&target, &truth, &points, &grid);
            let distance = (pose.translation.vector - target).norm();
            assert!(
                distance < previous,
                "weight {weight}: {distance} ≥ {previous}"
            );
            previous = distance;
        }
        assert!(previous < 1e-3);
    }

    #[test]
    fn rotation_weight_holds_the_initial_rotation() {
        let grid = room_grid();
        let truth = rigid2(2.5, 2.0, 0.2);
        let points = room_scan(&truth);
        let initial = rigid2(2.5, 2.0, 0.23);
        let solve = |rotation_weight| {
            let matcher = LeastSquaresScanMatcher::new(LeastSquaresScanMatcherOptions {
                rotation_weight,
                ..pure_matching()
            });
            matcher
                .match_pose(&initial.translation.vector, &initial, &points, &grid)
                .0
        };
        let free = solve(0.0);
        let held = solve(1e4);
        assert!((free.theta() - 0.2).abs() < 0.005, "{free:?}");
        assert!((held.theta() - 0.23).abs() < 1e-3, "{held:?}");
    }

    #[test]
    fn validate_rejects_bad_options() {
        assert!(LeastSquaresScanMatcherOptions::default().validate().is_ok());
        let bad = LeastSquaresScanMatcherOptions {
            max_iterations: 0,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
        let bad = LeastSquaresScanMatcherOptions {
            translation_weight: f64::INFINITY,
            ..Default::default()
        };
        assert!(bad.validate().is_err());
    }
}
