//! Was a session placed right? Judged on a real recording, where there is no pose truth, by the
//! benchmark's relations that tie a scan of the session to a scan of an earlier one.
//!
//! A relation's error *at the time* compares the robot's estimate of its later scan, as the robot had
//! it at that scan, with the earlier scan's pose in the site map **as the map stood at that same moment**:
//! the map the robot was placed on. (Comparing it with the earlier scan's estimate at the earlier scan's
//! own time mixes the placement with the earlier session's drift before its loops closed, and cannot tell
//! a wrong placement from an early map.) A placement the robot acted on, from the scan that decided it
//! until the next placement, is wrong when the median error of its relations exceeds
//! [`ScoringOptions::wrong_placement`](super::ScoringOptions) (0.5 m or 5° by default): the robot would
//! have navigated in the wrong place.

use serde::Serialize;

use super::relations_metric::median;
use super::{Placement, PoseTolerance, RelationError};
use crate::sensor::Timestamp;

/// What the relations say of one placement.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    /// The median error is within the tolerance.
    Right,
    /// The median error exceeds it.
    Wrong,
    /// No relation falls while the placement was in effect.
    Unjudged,
}

/// One placement the robot acted on, judged.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PlacementVerdict {
    /// The scan time that decided the placement.
    pub decided_at: Timestamp,
    /// Relations whose later scan fell while the placement was in effect.
    pub relations: usize,
    /// Their median translation error at the time, metres (`None` without relations).
    pub median_trans_m: Option<f64>,
    /// Their median rotation error at the time, degrees.
    pub median_rot_deg: Option<f64>,
    /// Right, wrong, or unjudged.
    pub verdict: Verdict,
}

/// Judges each of `placements` (in the order they were decided) by the relation errors at the time
/// whose later stamp falls from its decision until the next placement's (see the module docs).
pub fn judge_placements(
    placements: &[Placement],
    errors_at_the_time: &[RelationError],
    wrong: PoseTolerance,
) -> Vec<PlacementVerdict> {
    placements
        .iter()
        .enumerate()
        .map(|(k, placement)| {
            let until = placements.get(k + 1).map(|next| next.decided_at);
            let in_effect: Vec<&RelationError> = errors_at_the_time
                .iter()
                .filter(|e| {
                    let later = e.t1.max(e.t2);
                    later >= placement.decided_at && until.is_none_or(|u| later < u)
                })
                .collect();
            let trans: Vec<f64> = in_effect.iter().map(|e| e.trans_m).collect();
            let rot: Vec<f64> = in_effect.iter().map(|e| e.rot_deg).collect();
            let (median_trans_m, median_rot_deg, verdict) = if in_effect.is_empty() {
                (None, None, Verdict::Unjudged)
            } else {
                let (t, r) = (median(&trans), median(&rot));
                let verdict = if t > wrong.translation_m || r > wrong.rotation_deg {
                    Verdict::Wrong
                } else {
                    Verdict::Right
                };
                (Some(t), Some(r), verdict)
            };
            PlacementVerdict {
                decided_at: placement.decided_at,
                relations: in_effect.len(),
                median_trans_m,
                median_rot_deg,
                verdict,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Rigid2;

    fn s(secs: f64) -> Timestamp {
        Timestamp::from_secs_f64(secs)
    }

    fn placement(decided_at: f64) -> Placement {
        Placement {
            decided_at: s(decided_at),
            time: s(decided_at),
            map_from_base: Rigid2::identity(),
        }
    }

    fn error(earlier: f64, later: f64, trans_m: f64, rot_deg: f64) -> RelationError {
        RelationError {
            t1: s(earlier),
            t2: s(later),
            trans_m,
            rot_deg,
        }
    }

    #[test]
    fn each_placement_is_judged_by_the_median_of_the_relations_while_it_held() {
        let tolerance = PoseTolerance {
            translation_m: 0.5,
            rotation_deg: 5.0,
        };
        // Placed at 10 s (wrong: 3 m off), revoked and placed again at 20 s (right), and a third
        // placement at 40 s with no relation after it.
        let placements = [placement(10.0), placement(20.0), placement(40.0)];
        let errors = [
            error(1.0, 12.0, 3.0, 1.0),
            error(2.0, 15.0, 2.9, 1.0),
            // One stray relation does not move the median.
            error(3.0, 16.0, 0.1, 0.5),
            // Relation stamps in either order: the later one decides.
            error(25.0, 4.0, 0.05, 0.4),
            error(5.0, 30.0, 0.07, 6.0),
            error(6.0, 31.0, 0.02, 0.3),
            // Before any placement: the robot had no estimate to judge.
            error(1.0, 5.0, 9.0, 9.0),
        ];
        let verdicts = judge_placements(&placements, &errors, tolerance);
        let kinds: Vec<Verdict> = verdicts.iter().map(|v| v.verdict).collect();
        assert_eq!(
            kinds,
            [Verdict::Wrong, Verdict::Right, Verdict::Unjudged],
            "{verdicts:?}"
        );
        assert_eq!(verdicts[0].relations, 3);
        assert_eq!(verdicts[0].median_trans_m, Some(2.9));
        assert_eq!(verdicts[1].relations, 3);
        assert_eq!(verdicts[1].median_rot_deg, Some(0.4));
        assert_eq!(verdicts[2].median_trans_m, None);
    }

    #[test]
    fn a_rotation_beyond_the_tolerance_alone_is_wrong() {
        let verdicts = judge_placements(
            &[placement(0.0)],
            &[error(-5.0, 1.0, 0.1, 7.0)],
            PoseTolerance {
                translation_m: 0.5,
                rotation_deg: 5.0,
            },
        );
        assert_eq!(verdicts[0].verdict, Verdict::Wrong);
    }
}
