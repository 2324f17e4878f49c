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
//! have navigated in the wrong place. It is judged twice: over its first minute (was the robot placed
//! right?) and over the whole time it held (did it stay right?).

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

/// How long after its decision a placement is judged as a placement (seconds): the relations of this
/// first minute say whether the robot was put in the right place; those of the whole time it held say
/// whether it stayed localized (a session whose own trajectory tears later is wrong there, not here).
pub const PLACEMENT_WINDOW_S: f64 = 60.0;

/// The relations' judgement over one span of time.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SpanVerdict {
    /// Relations whose later scan fell in the span.
    pub relations: usize,
    /// Their median translation error at the time, metres (`None` without relations).
    pub median_trans_m: Option<f64>,
    /// Their median rotation error at the time, degrees.
    pub median_rot_deg: Option<f64>,
    /// Right, wrong, or unjudged.
    pub verdict: Verdict,
}

/// One placement the robot acted on, judged.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PlacementVerdict {
    /// The scan time that decided the placement.
    pub decided_at: Timestamp,
    /// Over the first [`PLACEMENT_WINDOW_S`] it held: was the robot placed right?
    pub placed: SpanVerdict,
    /// Over the whole time it held, until the next placement or the session's end: did the robot
    /// stay right?
    pub held: SpanVerdict,
}

fn judge_span<'a>(
    errors: impl Iterator<Item = &'a RelationError>,
    wrong: PoseTolerance,
) -> SpanVerdict {
    let (trans, rot): (Vec<f64>, Vec<f64>) = errors.map(|e| (e.trans_m, e.rot_deg)).unzip();
    if trans.is_empty() {
        return SpanVerdict {
            relations: 0,
            median_trans_m: None,
            median_rot_deg: None,
            verdict: Verdict::Unjudged,
        };
    }
    let (t, r) = (median(&trans), median(&rot));
    SpanVerdict {
        relations: trans.len(),
        median_trans_m: Some(t),
        median_rot_deg: Some(r),
        verdict: if t > wrong.translation_m || r > wrong.rotation_deg {
            Verdict::Wrong
        } else {
            Verdict::Right
        },
    }
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
            let first_window = in_effect.iter().copied().filter(|e| {
                e.t1.max(e.t2).seconds_since(placement.decided_at) <= PLACEMENT_WINDOW_S
            });
            PlacementVerdict {
                decided_at: placement.decided_at,
                placed: judge_span(first_window, wrong),
                held: judge_span(in_effect.iter().copied(), wrong),
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
        let kinds: Vec<Verdict> = verdicts.iter().map(|v| v.held.verdict).collect();
        assert_eq!(
            kinds,
            [Verdict::Wrong, Verdict::Right, Verdict::Unjudged],
            "{verdicts:?}"
        );
        assert_eq!(verdicts[0].held.relations, 3);
        assert_eq!(verdicts[0].held.median_trans_m, Some(2.9));
        assert_eq!(verdicts[1].held.relations, 3);
        assert_eq!(verdicts[1].held.median_rot_deg, Some(0.4));
        assert_eq!(verdicts[2].held.median_trans_m, None);
        // All within a minute of their placements: the same judgement.
        assert_eq!(verdicts[0].placed, verdicts[0].held);
    }

    #[test]
    fn a_session_placed_right_that_tears_later_is_placed_right_and_held_wrong() {
        let tolerance = PoseTolerance {
            translation_m: 0.5,
            rotation_deg: 5.0,
        };
        let mut errors = vec![error(1.0, 30.0, 0.03, 0.2), error(2.0, 50.0, 0.04, 0.3)];
        // Its own trajectory tears after 5 minutes.
        errors.extend((0..5).map(|k| error(3.0, 300.0 + f64::from(k), 4.0, 10.0)));
        let verdicts = judge_placements(&[placement(10.0)], &errors, tolerance);
        assert_eq!(verdicts[0].placed.verdict, Verdict::Right, "{verdicts:?}");
        assert_eq!(verdicts[0].held.verdict, Verdict::Wrong, "{verdicts:?}");
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
        assert_eq!(verdicts[0].held.verdict, Verdict::Wrong);
    }
}
