//! Trajectory accuracy against ground truth: rigid alignment, ATE, and the paper's mileage rate of correct
//! localization (MRCL).

use std::collections::BTreeMap;

use nalgebra::{Rotation2, Vector2};
use serde::{Deserialize, Serialize};

use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle, rigid2};
use crate::sensor::Timestamp;

/// How far an estimated pose may be from the truth and still count.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseTolerance {
    /// Position error, metres.
    pub translation_m: f64,
    /// Heading error, degrees.
    pub rotation_deg: f64,
}

impl PoseTolerance {
    /// The paper's correct localization: within 0.3 m and 5° of the truth.
    pub const CORRECT: Self = Self {
        translation_m: 0.3,
        rotation_deg: 5.0,
    };

    /// Whether a pose `error_m` metres and `error_deg` degrees off is within the tolerance.
    pub fn accepts(&self, error_m: f64, error_deg: f64) -> bool {
        error_m <= self.translation_m && error_deg <= self.rotation_deg
    }
}

/// Position (m) and absolute heading (degrees) error of `map_from_base`, placed in the world through
/// `world_from_map`, against the truth `world_from_base`.
pub fn pose_error(
    world_from_map: &Rigid2,
    map_from_base: &Rigid2,
    world_from_base: &Rigid2,
) -> (f64, f64) {
    let estimated = world_from_map * map_from_base;
    let error = (estimated.translation.vector - world_from_base.translation.vector).norm();
    let rotation = normalize_angle(estimated.theta() - world_from_base.theta())
        .abs()
        .to_degrees();
    (error, rotation)
}

/// `world_from_map` aligning the positions of `estimate` (map frame) to those of `truth` (world frame)
/// at equal timestamps ([`rigid_alignment`]; identity when no stamps match).
pub fn align_to_truth(estimate: &[(Timestamp, Rigid2)], truth: &[(Timestamp, Rigid2)]) -> Rigid2 {
    let truth: BTreeMap<Timestamp, Rigid2> = truth.iter().copied().collect();
    let pairs: Vec<_> = estimate
        .iter()
        .filter_map(|(t, pose)| {
            let world = truth.get(t)?;
            Some((pose.translation.vector, world.translation.vector))
        })
        .collect();
    rigid_alignment(&pairs)
}

/// The rigid transform `b_from_a` minimizing `Σ |b_from_a · a_i − b_i|²` over the positions of the pairs
/// `(a_i, b_i)` (2D Kabsch, no scale); identity for no pairs.
pub fn rigid_alignment(pairs: &[(Vector2<f64>, Vector2<f64>)]) -> Rigid2 {
    if pairs.is_empty() {
        return Rigid2::identity();
    }
    let n = pairs.len() as f64;
    let mean_a = pairs.iter().map(|p| p.0).sum::<Vector2<f64>>() / n;
    let mean_b = pairs.iter().map(|p| p.1).sum::<Vector2<f64>>() / n;
    let (mut sin, mut cos) = (0.0, 0.0);
    for (a, b) in pairs {
        let (a, b) = (a - mean_a, b - mean_b);
        cos += a.dot(&b);
        sin += a.x * b.y - a.y * b.x;
    }
    let theta = sin.atan2(cos);
    let t = mean_b - Rotation2::new(theta) * mean_a;
    rigid2(t.x, t.y, theta)
}

/// Accuracy of one trajectory against ground truth in a given frame alignment.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct TrajectoryAccuracy {
    /// Poses matched to a truth pose by timestamp.
    pub matched: usize,
    /// RMS position error, metres.
    pub ate_rms_m: f64,
    /// Largest position error, metres.
    pub max_error_m: f64,
    /// Distance travelled (truth) while within the tolerance of the truth, over the whole distance
    /// travelled (1 when nothing moved).
    pub mrcl: f64,
    /// Truth distance travelled, metres.
    pub distance_m: f64,
}

/// Compares `estimate` (map frame) with `truth` (world frame) through `world_from_map`, pose by pose at
/// equal timestamps. A truth step counts toward MRCL when both of its ends are within `tolerance`; a
/// truth pose without an estimate counts as not localized (MRCL is over the whole truth distance), while
/// the ATE is over the matched poses only.
pub fn trajectory_accuracy(
    estimate: &[(Timestamp, Rigid2)],
    truth: &[(Timestamp, Rigid2)],
    world_from_map: &Rigid2,
    tolerance: &PoseTolerance,
) -> TrajectoryAccuracy {
    let mut accuracy = TrajectoryAccuracy::default();
    let (mut sum_squared, mut good_distance) = (0.0, 0.0);
    let mut last_correct = false;
    for (k, step) in errors_along_truth(estimate, truth, world_from_map).enumerate() {
        let correct = step.error.is_some_and(|(m, deg)| tolerance.accepts(m, deg));
        if let Some((error, _)) = step.error {
            accuracy.matched += 1;
            sum_squared += error * error;
            accuracy.max_error_m = accuracy.max_error_m.max(error);
        }
        if k > 0 {
            accuracy.distance_m += step.step_m;
            if correct && last_correct {
                good_distance += step.step_m;
            }
        }
        last_correct = correct;
    }
    if accuracy.matched > 0 {
        accuracy.ate_rms_m = (sum_squared / accuracy.matched as f64).sqrt();
    }
    accuracy.mrcl = if accuracy.distance_m > 0.0 {
        good_distance / accuracy.distance_m
    } else if accuracy.matched > 0 {
        1.0
    } else {
        0.0
    };
    accuracy
}

/// The distance (metres, truth) travelled while `estimate` was wrong: each truth step both of whose ends
/// have an estimate off by more than `wrong` (through `world_from_map`). A truth pose without an estimate
/// is a refusal, not a wrong answer: it counts in neither.
pub fn wrong_distance_m(
    estimate: &[(Timestamp, Rigid2)],
    truth: &[(Timestamp, Rigid2)],
    world_from_map: &Rigid2,
    wrong: &PoseTolerance,
) -> f64 {
    let mut distance = 0.0;
    let mut last_wrong = false;
    for (k, step) in errors_along_truth(estimate, truth, world_from_map).enumerate() {
        let is_wrong = step.error.is_some_and(|(m, deg)| !wrong.accepts(m, deg));
        if k > 0 && is_wrong && last_wrong {
            distance += step.step_m;
        }
        last_wrong = is_wrong;
    }
    distance
}

/// One truth pose on the walk along the truth that [`trajectory_accuracy`] and [`wrong_distance_m`] share.
struct TruthStep {
    /// Distance (m) from the previous truth pose (0 for the first).
    step_m: f64,
    /// The estimate's error at this pose, `(metres, degrees)` as [`pose_error`] gives it; `None` where the
    /// estimate has no pose at the truth's stamp.
    error: Option<(f64, f64)>,
}

/// The truth poses in order, each with its step from the one before and the estimate's error there.
fn errors_along_truth<'a>(
    estimate: &[(Timestamp, Rigid2)],
    truth: &'a [(Timestamp, Rigid2)],
    world_from_map: &'a Rigid2,
) -> impl Iterator<Item = TruthStep> + 'a {
    let estimate: BTreeMap<Timestamp, Rigid2> = estimate.iter().copied().collect();
    let mut last: Option<Rigid2> = None;
    truth.iter().map(move |(time, world_from_base)| {
        let step_m = last.map_or(0.0, |last| {
            (world_from_base.translation.vector - last.translation.vector).norm()
        });
        last = Some(*world_from_base);
        TruthStep {
            step_m,
            error: estimate
                .get(time)
                .map(|map_from_base| pose_error(world_from_map, map_from_base, world_from_base)),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alignment_recovers_a_rigid_transform() {
        let b_from_a = rigid2(3.0, -2.0, 0.7);
        let pairs: Vec<_> = (0..20)
            .map(|k| {
                let a = Vector2::new(f64::from(k).sin() * 5.0, f64::from(k) * 0.3);
                let b = (b_from_a * nalgebra::Point2::from(a)).coords;
                (a, b)
            })
            .collect();
        let found = rigid_alignment(&pairs);
        assert!((found.translation.vector - b_from_a.translation.vector).norm() < 1e-9);
        assert!((found.theta() - 0.7).abs() < 1e-9);
    }

    #[test]
    fn align_to_truth_pairs_equal_stamps_only() {
        let t = |k: i64| Timestamp(k * 1_000_000_000);
        let world_from_map = rigid2(1.0, 2.0, 0.3);
        let truth: Vec<_> = (0..10)
            .map(|k| (t(k), rigid2(k as f64, (k * k) as f64 * 0.1, 0.0)))
            .collect();
        // The estimate is the truth in the map frame, plus a stamp the truth lacks (far off: if it were
        // paired, the fit would move).
        let mut estimate: Vec<_> = truth
            .iter()
            .map(|(time, p)| (*time, world_from_map.inverse() * p))
            .collect();
        estimate.push((t(100), rigid2(50.0, 50.0, 0.0)));
        let found = align_to_truth(&estimate, &truth);
        assert!((found.translation.vector - world_from_map.translation.vector).norm() < 1e-9);
        assert!((found.theta() - 0.3).abs() < 1e-9);
        assert_eq!(align_to_truth(&[], &truth), Rigid2::identity());
    }

    #[test]
    fn pose_error_and_tolerance() {
        let (m, deg) = pose_error(
            &rigid2(1.0, 0.0, 0.0),
            &rigid2(0.0, 0.3, 0.1),
            &rigid2(1.0, 0.0, 0.0),
        );
        assert!((m - 0.3).abs() < 1e-12 && (deg - 0.1f64.to_degrees()).abs() < 1e-9);
        assert!(PoseTolerance::CORRECT.accepts(0.3, 5.0));
        assert!(!PoseTolerance::CORRECT.accepts(0.31, 0.0));
        assert!(!PoseTolerance::CORRECT.accepts(0.0, 5.1));
    }

    #[test]
    fn mrcl_counts_distance_while_localized() {
        let t = |k: i64| Timestamp(k * 1_000_000_000);
        let truth: Vec<_> = (0..11)
            .map(|k| (t(k), rigid2(k as f64, 0.0, 0.0)))
            .collect();
        // Correct for the first half, 1 m off afterwards.
        let estimate: Vec<_> = (0..11)
            .map(|k| (t(k), rigid2(k as f64, if k > 5 { 1.0 } else { 0.0 }, 0.0)))
            .collect();
        let a = trajectory_accuracy(
            &estimate,
            &truth,
            &Rigid2::identity(),
            &PoseTolerance::CORRECT,
        );
        assert_eq!(a.matched, 11);
        assert!((a.distance_m - 10.0).abs() < 1e-12);
        assert!((a.mrcl - 0.5).abs() < 1e-12, "{a:?}");
        assert!((a.max_error_m - 1.0).abs() < 1e-12);
        let perfect =
            trajectory_accuracy(&truth, &truth, &Rigid2::identity(), &PoseTolerance::CORRECT);
        assert!((perfect.mrcl - 1.0).abs() < 1e-12 && perfect.ate_rms_m == 0.0);
    }

    #[test]
    fn missing_estimates_count_as_not_localized() {
        let t = |k: i64| Timestamp(k * 1_000_000_000);
        let truth: Vec<_> = (0..11)
            .map(|k| (t(k), rigid2(k as f64, 0.0, 0.0)))
            .collect();
        // No estimate for the last 4 poses: 4 of the 10 m are not localized.
        let estimate: Vec<_> = truth[..7].to_vec();
        let a = trajectory_accuracy(
            &estimate,
            &truth,
            &Rigid2::identity(),
            &PoseTolerance::CORRECT,
        );
        assert_eq!(a.matched, 7);
        assert!((a.distance_m - 10.0).abs() < 1e-12);
        assert!((a.mrcl - 0.6).abs() < 1e-12, "{a:?}");
        assert!(a.ate_rms_m == 0.0);
    }
}
