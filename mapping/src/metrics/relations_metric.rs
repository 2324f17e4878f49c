//! The relations metric of Kümmerle et al. 2009 ("On measuring the accuracy of SLAM algorithms"), as
//! computed by the benchmark's reference tool: for every relation, take the estimated poses nearest in
//! time to `t1` and `t2` (within 0.1 s), form the estimated relative motion, subtract the reference
//! component-wise (angles wrapped), and report the mean and standard deviation of the absolute and
//! squared translational and rotational errors. The standard deviation is the population one (÷N).
//! Where a trajectory has no pose that near a stamp (a slow scanner), the pose is interpolated between
//! its neighbours (see [`MAX_INTERPOLATION_SPAN_S`]); the recordings' own runs never need it.

use serde::Serialize;

use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle, rigid2};
use crate::io::relations::Relation;
use crate::sensor::Timestamp;

/// Largest allowed gap between a relation stamp and the nearest estimated pose, seconds.
const MAX_TIME_GAP_S: f64 = 0.1;
/// A relation stamp is a scan's stamp (the Freiburg files: exactly, MIT CSAIL within 5 µs); a pose
/// further away than this (seconds) is another scan's, which in a fast turn differs by degrees even
/// within [`MAX_TIME_GAP_S`] (Intel with scans 0.7 s apart: 0.13 m mean at the nearest scans within
/// 0.1 s, 0.026 m at the relations' own scans).
pub const SCAN_STAMP_TOLERANCE_S: f64 = 0.001;
/// Where no pose is within [`MAX_TIME_GAP_S`], the two around the stamp are interpolated if at most this far apart
/// (seconds): a slow scanner's trajectory is scored at the stamps it has no scan for.
pub const MAX_INTERPOLATION_SPAN_S: f64 = 1.5;

/// A relation whose translational error exceeds this (metres) is counted as torn.
pub const TORN_TRANSLATION_M: f64 = 0.3;
/// A relation whose rotational error exceeds this (degrees) is counted as torn.
pub const TORN_ROTATION_DEG: f64 = 3.0;

/// Aggregated relation errors.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RelationsErrorStats {
    /// Relations scored.
    pub count: usize,
    /// Relations skipped because no estimated pose lies within 0.1 s of `t1` or `t2` and none can be
    /// interpolated there (see [`MAX_INTERPOLATION_SPAN_S`]).
    pub unmatched: usize,
    /// Mean absolute translational error, metres.
    pub trans_abs_mean_m: f64,
    /// Standard deviation of the absolute translational error, metres.
    pub trans_abs_std_m: f64,
    /// Mean squared translational error, m².
    pub trans_sq_mean_m2: f64,
    /// Median absolute translational error, metres (robust to the few long-span outliers that dominate
    /// the mean when one loop is missed).
    pub trans_abs_median_m: f64,
    /// Mean absolute rotational error, degrees.
    pub rot_abs_mean_deg: f64,
    /// Standard deviation of the absolute rotational error, degrees.
    pub rot_abs_std_deg: f64,
    /// Mean squared rotational error, deg².
    pub rot_sq_mean_deg2: f64,
    /// Median absolute rotational error, degrees.
    pub rot_abs_median_deg: f64,
    /// Largest translational error of any relation, metres: a tear shows here even when the mean
    /// hides it among thousands of short relations.
    pub trans_abs_max_m: f64,
    /// Largest rotational error of any relation, degrees.
    pub rot_abs_max_deg: f64,
    /// Relations over [`TORN_TRANSLATION_M`] or [`TORN_ROTATION_DEG`].
    pub torn: usize,
    /// `torn` as a share of the relations scored (0..1).
    pub torn_share: f64,
}

/// The estimated pose at `t`: the nearest one within [`MAX_TIME_GAP_S`], as the benchmark's tool takes
/// it; where there is none (scans dropped, a slow scanner), the pose interpolated between the estimates
/// just before and after `t` if they are at most [`MAX_INTERPOLATION_SPAN_S`] apart.
pub fn pose_at(poses: &[(Timestamp, Rigid2)], t: Timestamp) -> Option<Rigid2> {
    if let Some(nearest) = nearest_within(poses, t, MAX_TIME_GAP_S) {
        return Some(nearest);
    }
    let i = poses.partition_point(|(s, _)| *s < t);
    let ((ta, a), (tb, b)) = (poses.get(i.checked_sub(1)?)?, poses.get(i)?);
    let span = tb.seconds_since(*ta);
    if !(span > 0.0 && span <= MAX_INTERPOLATION_SPAN_S) {
        return None;
    }
    let f = t.seconds_since(*ta) / span;
    let step = a.inverse() * b;
    let translation = step.translation.vector * f;
    Some(a * rigid2(translation.x, translation.y, f * step.theta()))
}

/// The estimated pose at the scan stamped `t` (within [`SCAN_STAMP_TOLERANCE_S`]), never interpolated
/// and never a neighbouring scan's: the pose of a scan the engine had (`None` where it had none).
pub fn pose_at_scan(poses: &[(Timestamp, Rigid2)], t: Timestamp) -> Option<Rigid2> {
    nearest_within(poses, t, SCAN_STAMP_TOLERANCE_S)
}

/// The estimated pose nearest `t`, if it lies within `gap_s` seconds.
fn nearest_within(poses: &[(Timestamp, Rigid2)], t: Timestamp, gap_s: f64) -> Option<Rigid2> {
    let i = poses.partition_point(|(s, _)| *s < t);
    [i.checked_sub(1), Some(i)]
        .into_iter()
        .flatten()
        .filter_map(|k| poses.get(k))
        .min_by_key(|(s, _)| (s.0 - t.0).abs())
        .filter(|(s, _)| (s.seconds_since(t)).abs() <= gap_s)
        .map(|(_, p)| *p)
}

fn mean_std(values: &[f64]) -> (f64, f64) {
    if values.is_empty() {
        return (0.0, 0.0);
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

pub(crate) fn median(values: &[f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let n = sorted.len();
    if n % 2 == 1 {
        sorted[n / 2]
    } else {
        0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
    }
}

/// The error of one relation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct RelationError {
    /// The relation's first stamp.
    pub t1: Timestamp,
    /// Its second stamp.
    pub t2: Timestamp,
    /// Absolute translational error, metres.
    pub trans_m: f64,
    /// Absolute rotational error, degrees.
    pub rot_deg: f64,
}

/// The error of every relation that has estimated poses at both stamps (within 0.1 s, or interpolated
/// over at most [`MAX_INTERPOLATION_SPAN_S`]), in the relations' order (the others are left out): where
/// in time a trajectory tears.
pub fn relation_errors(
    poses: &[(Timestamp, Rigid2)],
    relations: &[Relation],
) -> Vec<RelationError> {
    relations
        .iter()
        .filter_map(|r| {
            Some(relation_error(
                r,
                &pose_at(poses, r.t1)?,
                &pose_at(poses, r.t2)?,
            ))
        })
        .collect()
}

/// The error of one relation given the estimated poses at its two stamps (`at_t1`, `at_t2`, in one
/// frame).
pub fn relation_error(relation: &Relation, at_t1: &Rigid2, at_t2: &Rigid2) -> RelationError {
    let estimate = at_t1.inverse() * at_t2;
    let dx = estimate.x() - relation.delta.x();
    let dy = estimate.y() - relation.delta.y();
    let dth = normalize_angle(estimate.theta() - relation.delta.theta());
    RelationError {
        t1: relation.t1,
        t2: relation.t2,
        trans_m: dx.hypot(dy),
        rot_deg: dth.abs().to_degrees(),
    }
}

/// Statistics of relation errors computed elsewhere (see [`relations_error`]); `unmatched` is the
/// number of relations that had no error.
pub fn relation_error_stats(errors: &[RelationError], unmatched: usize) -> RelationsErrorStats {
    let trans: Vec<f64> = errors.iter().map(|e| e.trans_m).collect();
    let rot: Vec<f64> = errors.iter().map(|e| e.rot_deg).collect();
    let torn = errors
        .iter()
        .filter(|e| e.trans_m > TORN_TRANSLATION_M || e.rot_deg > TORN_ROTATION_DEG)
        .count();
    let (trans_abs_mean_m, trans_abs_std_m) = mean_std(&trans);
    let (rot_abs_mean_deg, rot_abs_std_deg) = mean_std(&rot);
    let sq = |v: &[f64]| {
        if v.is_empty() {
            0.0
        } else {
            v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64
        }
    };
    RelationsErrorStats {
        count: trans.len(),
        unmatched,
        trans_abs_mean_m,
        trans_abs_std_m,
        trans_sq_mean_m2: sq(&trans),
        trans_abs_median_m: median(&trans),
        rot_abs_mean_deg,
        rot_abs_std_deg,
        rot_sq_mean_deg2: sq(&rot),
        rot_abs_median_deg: median(&rot),
        trans_abs_max_m: trans.iter().copied().fold(0.0, f64::max),
        rot_abs_max_deg: rot.iter().copied().fold(0.0, f64::max),
        torn,
        torn_share: if trans.is_empty() {
            0.0
        } else {
            torn as f64 / trans.len() as f64
        },
    }
}

/// Scores a trajectory (sorted by time) against reference relations.
pub fn relations_error(
    poses: &[(Timestamp, Rigid2)],
    relations: &[Relation],
) -> RelationsErrorStats {
    let errors = relation_errors(poses, relations);
    relation_error_stats(&errors, relations.len() - errors.len())
}

/// [`relations_error`] over only the relations whose two stamps are both scans the engine estimated (see
/// [`pose_at_scan`]): the trajectory scored on the scans the engine had. A
/// trajectory with scans dropped (a slow scanner) is otherwise scored partly at interpolated poses, whose
/// error (the robot turns between scans, the interpolation does not) is a floor no engine goes below;
/// relations with a stamp the engine had no scan for count as `unmatched`.
pub fn relations_error_at_scans(
    poses: &[(Timestamp, Rigid2)],
    relations: &[Relation],
) -> RelationsErrorStats {
    let errors: Vec<RelationError> = relations
        .iter()
        .filter_map(|r| {
            Some(relation_error(
                r,
                &pose_at_scan(poses, r.t1)?,
                &pose_at_scan(poses, r.t2)?,
            ))
        })
        .collect();
    relation_error_stats(&errors, relations.len() - errors.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn trajectory() -> Vec<(Timestamp, Rigid2)> {
        (0..20)
            .map(|i| {
                (
                    Timestamp(i * 1_000_000_000),
                    rigid2(i as f64, 0.5 * i as f64, 0.1 * i as f64),
                )
            })
            .collect()
    }

    #[test]
    fn exact_relations_score_zero_and_perturbations_score_what_they_are() {
        let poses = trajectory();
        let mut relations: Vec<Relation> = (0..19)
            .map(|i| Relation {
                t1: poses[i].0,
                t2: poses[i + 1].0,
                delta: poses[i].1.inverse() * poses[i + 1].1,
            })
            .collect();
        let exact = relations_error(&poses, &relations);
        assert_eq!(exact.count, 19);
        assert!(exact.trans_abs_mean_m < 1e-12 && exact.rot_abs_mean_deg < 1e-9);

        // Shift every reference by 3 cm along x and 1° in yaw.
        for r in &mut relations {
            r.delta = rigid2(
                r.delta.x() + 0.03,
                r.delta.y(),
                r.delta.theta() + 1f64.to_radians(),
            );
        }
        let shifted = relations_error(&poses, &relations);
        assert!((shifted.trans_abs_mean_m - 0.03).abs() < 1e-9);
        assert!(shifted.trans_abs_std_m < 1e-9);
        assert!((shifted.trans_sq_mean_m2 - 0.0009).abs() < 1e-9);
        assert!((shifted.rot_abs_mean_deg - 1.0).abs() < 1e-9);
        assert!((shifted.trans_abs_median_m - 0.03).abs() < 1e-9);
        assert!((shifted.rot_abs_median_deg - 1.0).abs() < 1e-9);
        assert_eq!(shifted.torn, 0);

        // One relation torn by 0.5 m, one by 4°: both counted, the largest errors reported.
        relations[3].delta = rigid2(
            relations[3].delta.x() + 0.47,
            relations[3].delta.y(),
            relations[3].delta.theta(),
        );
        relations[7].delta = rigid2(
            relations[7].delta.x(),
            relations[7].delta.y(),
            relations[7].delta.theta() + 3f64.to_radians(),
        );
        let torn = relations_error(&poses, &relations);
        assert_eq!(torn.torn, 2);
        assert!((torn.torn_share - 2.0 / 19.0).abs() < 1e-12);
        assert!((torn.trans_abs_max_m - 0.5).abs() < 1e-9);
        assert!((torn.rot_abs_max_deg - 4.0).abs() < 1e-9);
    }

    #[test]
    fn the_median_ignores_one_large_outlier() {
        assert!((median(&[0.01, 5.0, 0.02]) - 0.02).abs() < 1e-12);
        assert!((median(&[0.04, 0.01, 9.0, 0.02]) - 0.03).abs() < 1e-12);
        assert!(median(&[]).abs() < 1e-12);
    }

    #[test]
    fn stamps_between_poses_are_interpolated_and_those_beyond_the_trajectory_unmatched() {
        let poses = trajectory();
        // Halfway between the poses at 0 s and 1 s, interpolated along the step between them.
        let step = poses[0].1.inverse() * poses[1].1;
        let half = rigid2(0.5 * step.x(), 0.5 * step.y(), 0.5 * step.theta());
        let relations = vec![
            Relation {
                t1: Timestamp(50_000_000),
                t2: Timestamp(1_000_000_000),
                delta: poses[0].1.inverse() * poses[1].1,
            },
            Relation {
                t1: Timestamp(0),
                t2: Timestamp(500_000_000),
                delta: half,
            },
            Relation {
                t1: Timestamp(500_000_000),
                t2: Timestamp(25_000_000_000),
                delta: Rigid2::identity(),
            },
        ];
        let e = relations_error(&poses, &relations);
        assert_eq!((e.count, e.unmatched), (2, 1));
        assert!(
            e.trans_abs_mean_m < 1e-12 && e.rot_abs_mean_deg < 1e-9,
            "{e:?}"
        );
    }

    #[test]
    fn scored_at_scans_only_relations_whose_stamps_are_both_scans_count() {
        let poses = trajectory();
        let relations = vec![
            // Both stamps are scans: scored (exactly right here).
            Relation {
                t1: Timestamp(0),
                t2: Timestamp(1_000_000_000),
                delta: poses[0].1.inverse() * poses[1].1,
            },
            // One stamp 50 ms from a scan: the benchmark's rule takes that scan's pose, not here.
            Relation {
                t1: Timestamp(50_000_000),
                t2: Timestamp(2_000_000_000),
                delta: poses[0].1.inverse() * poses[2].1,
            },
            // One stamp halfway between two scans: interpolated by `relations_error`, not scored here.
            Relation {
                t1: Timestamp(0),
                t2: Timestamp(500_000_000),
                delta: Rigid2::identity(),
            },
        ];
        let all = relations_error(&poses, &relations);
        let at_scans = relations_error_at_scans(&poses, &relations);
        assert_eq!((all.count, all.unmatched), (3, 0));
        assert_eq!((at_scans.count, at_scans.unmatched), (1, 2));
        assert!(at_scans.trans_abs_mean_m < 1e-12, "{at_scans:?}");
        assert!(all.trans_abs_mean_m > 0.1, "{all:?}");
    }
}
