//! What one session of a lifelong run lived, scored against the truth: the paper's measures (Zhao et al.,
//! IROS 2021, §V) as the robot experienced them.
//!
//! - **MRCL** (mileage rate of correct localization) from the robot's *own estimate at the time of each
//!   scan* — the pose it would have navigated with — over the whole distance the session drove; a scan
//!   without an estimate (the session not placed yet) counts as lost. The same measure of the trajectory
//!   smoothed when the session ended is kept beside it as `mrcl_smoothed`: it says how well the map
//!   explains the session after the fact, not what the robot knew.
//! - **Initialization** (CRI, over a run) as the robot lived it: the robot's first placement — the pose it
//!   started navigating with, tentative while the session is on probation — came within
//!   [`ScoringOptions::initialization_window_s`] of its first scan and was correct
//!   ([`ScoringOptions::correct`]), and no placement the robot acted on was wrong. Refused for longer, or
//!   placed wrong (a tentative placement later revoked included), is a failure. Probation protects the
//!   shared map, not the robot: the robot navigates with its tentative placement. How long the map took to
//!   take the session in is scored beside it (`initialized_committed`: the committed placement, correct and
//!   committed within the window).
//! - **Placement error**: the committed placement's error against the truth at the scan it placed, and
//!   whether the session was placed wrong ([`ScoringOptions::wrong_placement`]): any placement the robot
//!   acted on — tentative or committed — off by more than that tolerance.
//! - **AMS** (average matching score): the mean of the match scores of every scan of the session against
//!   the map as it was then (the caller scores them by branch and bound near the robot's estimate, see
//!   [`MatchScorer`](super::MatchScorer)); a scan the
//!   robot could not place scores 0, so a lost session counts as matching nothing instead of being left
//!   out.
//! - **MRCL ceiling**: the MRCL the session start's own searches allowed, from the first search whose
//!   best candidate was correct ([`SessionScore::mrcl_ceiling`]): what MRCL could reach with this search
//!   and no wrong placement.
//!
//! Everything is measured in the truth's (world) frame through `world_from_map`, the rigid alignment of
//! the mapping session to its truth ([`align_to_truth`](super::align_to_truth)).

use serde::{Deserialize, Serialize};

use super::{
    ScoringOptions, TrajectoryAccuracy, pose_error, trajectory_accuracy, wrong_distance_m,
};
use crate::geometry::Rigid2;
use crate::sensor::Timestamp;

/// The placement a session committed to: where it put one of its scans in the map, and when.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement {
    /// Scan time at which the session committed to the placement (for a session-start relocalization,
    /// the last of the scans it held back).
    pub decided_at: Timestamp,
    /// The scan the placement put in the map.
    pub time: Timestamp,
    /// Where it put it: `map_from_base` of that scan.
    pub map_from_base: Rigid2,
}

/// What one session lived, for [`score_session`]. Poses are `map_from_base` (map frame) or
/// `world_from_base` (truth), keyed by scan time.
#[derive(Clone, Copy, Debug)]
pub struct SessionTrack<'a> {
    /// The truth of every scan, time-ordered.
    pub truth: &'a [(Timestamp, Rigid2)],
    /// Time of the session's first scan (the initialization window starts there).
    pub start_time: Timestamp,
    /// The robot's own estimate at the time of each scan, for the scans it had one (placed by then).
    pub online: &'a [(Timestamp, Rigid2)],
    /// The estimate of each scan smoothed when the session ended.
    pub smoothed: &'a [(Timestamp, Rigid2)],
    /// Every placement the robot acted on, in the order it made them: each tentative placement of its
    /// session start, decided at the scan it was made at (the committed placement is one of them). Empty
    /// when it never was placed.
    pub placements: &'a [Placement],
    /// The placement the session committed to (probation passed), decided at the scan whose match
    /// committed it; `None` when it never committed.
    pub committed: Option<Placement>,
    /// The match score of each of its scans against the map as it was then (0 for a scan the robot could
    /// not place); empty when not measured (the mapping session, which has no map before it).
    pub match_scores: &'a [f64],
    /// Each whole-map search of the session start, in order: where its best candidate put the scan it
    /// was made at, decided at the scan the search ran at (`None`: no candidate). Empty when not
    /// recorded (the mapping session, shells that do not record searches).
    pub search_bests: &'a [Option<Placement>],
}

/// The scores of one session (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SessionScore {
    /// MRCL of the estimate the robot had at the time of each scan.
    pub mrcl: f64,
    /// MRCL of the trajectory smoothed at the session's end.
    pub mrcl_smoothed: f64,
    /// RMS position error of the estimates at the time of each scan, metres (over the scans that had one).
    pub ate_rms_m: f64,
    /// Largest of those errors, metres.
    pub max_error_m: f64,
    /// RMS position error of the smoothed trajectory, metres.
    pub ate_rms_smoothed_m: f64,
    /// Scans with an estimate at their time.
    pub localized_scans: usize,
    /// Distance the session drove (truth), metres.
    pub distance_m: f64,
    /// The robot's first placement came within the initialization window and was correct, and no
    /// placement it acted on was wrong (counts toward CRI).
    pub initialized: bool,
    /// The committed placement is correct and was committed within the initialization window.
    pub initialized_committed: bool,
    /// Position error of the committed placement, metres; `None` when never committed.
    pub placement_error_m: Option<f64>,
    /// Heading error of the committed placement, degrees; `None` when never committed.
    pub placement_error_deg: Option<f64>,
    /// Position error of the robot's first placement, metres; `None` when never placed.
    pub first_placement_error_m: Option<f64>,
    /// How long after its first scan the robot was first placed (had a pose to navigate with), seconds.
    pub placed_after_s: Option<f64>,
    /// How long after its first scan the session's placement was committed, seconds.
    pub committed_after_s: Option<f64>,
    /// Placements the robot acted on (more than one: a tentative placement was revoked and another made).
    pub placements: usize,
    /// A placement the robot acted on (tentative or committed) is off by more than
    /// [`ScoringOptions::wrong_placement`].
    pub wrong_placement: bool,
    /// Mileage rate of wrong localization: the share of the distance driven while the robot's estimate at
    /// the time was off by more than [`ScoringOptions::wrong_placement`] — it believed it knew where it was,
    /// and was wrong. Unlike `wrong_placement` it sees an estimate that went wrong after a right placement
    /// (matches on probation that moved it). Scans with no estimate (refusals) count in neither.
    pub mrwl: f64,
    /// Mean match score of every scan against the map as it was then; `None` when not measured.
    pub ams: Option<f64>,
    /// Scans that score.
    pub scored_scans: usize,
    /// The MRCL the session start's own evidence allowed: 1 − the share of the distance driven before
    /// the first whole-map search whose best candidate was correct ([`ScoringOptions::correct`]). Every
    /// search before it ranked a wrong pose best, so placing the session earlier meant placing it wrong
    /// or on a candidate the search ranked below a wrong one; the route driven until then is the evidence
    /// the search needed. A ceiling for this search and its schedule (the hold-back included), not for
    /// every method. 0 when no search's best was correct; `None` without recorded searches.
    pub mrcl_ceiling: Option<f64>,
    /// Good distance (metres within tolerance, estimate at the time) and its smoothed counterpart, kept to
    /// weigh MRCL over a run by distance (in the report, so that a resumed run weighs the sessions before
    /// it too).
    good_distance_m: [f64; 2],
    /// Distance driven while wrongly localized (estimate at the time), metres, to weigh `mrwl` over a run.
    wrong_distance_m: f64,
}

impl SessionScore {
    /// Distance driven while correctly localized (estimate at the time), metres.
    pub fn good_distance_m(&self) -> f64 {
        self.good_distance_m[0]
    }

    /// Distance driven while correctly localized by the smoothed trajectory, metres.
    pub fn good_distance_smoothed_m(&self) -> f64 {
        self.good_distance_m[1]
    }

    /// Distance driven while wrongly localized (estimate at the time, see `mrwl`), metres.
    pub fn wrong_distance_m(&self) -> f64 {
        self.wrong_distance_m
    }
}

/// The truth pose at `time`, or the nearest in time (truth is sampled at every scan, so this is exact
/// for scan times).
pub fn truth_at(truth: &[(Timestamp, Rigid2)], time: Timestamp) -> Option<Rigid2> {
    let i = truth.partition_point(|(t, _)| *t < time);
    let after = truth.get(i);
    let before = i.checked_sub(1).and_then(|j| truth.get(j));
    match (before, after) {
        (Some(b), Some(a)) => Some(if time.seconds_since(b.0) <= a.0.seconds_since(time) {
            b.1
        } else {
            a.1
        }),
        (Some(p), None) | (None, Some(p)) => Some(p.1),
        (None, None) => None,
    }
}

/// Distance along `truth` (time-ordered) up to the pose at `until` (inclusive).
fn distance_driven(truth: &[(Timestamp, Rigid2)], until: Timestamp) -> f64 {
    truth
        .windows(2)
        .take_while(|w| w[1].0 <= until)
        .map(|w| (w[1].1.translation.vector - w[0].1.translation.vector).norm())
        .sum()
}

/// AMS: the mean of the match scores of a session's scans (`None` for none).
pub fn average_match_score(match_scores: &[f64]) -> Option<f64> {
    (!match_scores.is_empty()).then(|| match_scores.iter().sum::<f64>() / match_scores.len() as f64)
}

/// Scores one session (see the module docs) in the truth's frame through `world_from_map`.
pub fn score_session(
    track: &SessionTrack<'_>,
    world_from_map: &Rigid2,
    options: &ScoringOptions,
) -> SessionScore {
    let online = trajectory_accuracy(track.online, track.truth, world_from_map, &options.correct);
    let wrong_distance_m = wrong_distance_m(
        track.online,
        track.truth,
        world_from_map,
        &options.wrong_placement,
    );
    let smoothed = trajectory_accuracy(
        track.smoothed,
        track.truth,
        world_from_map,
        &options.correct,
    );
    // (metres, degrees, seconds after the session's first scan) of a placement.
    let judge = |p: &Placement| {
        let truth = truth_at(track.truth, p.time)?;
        let (m, deg) = pose_error(world_from_map, &p.map_from_base, &truth);
        Some((m, deg, p.decided_at.seconds_since(track.start_time)))
    };
    let in_time_and_correct = |(m, deg, after): (f64, f64, f64)| {
        after <= options.initialization_window_s && options.correct.accepts(m, deg)
    };
    let committed = track.committed.as_ref().and_then(judge);
    let lived: Vec<(f64, f64, f64)> = track
        .placements
        .iter()
        .chain(track.committed.as_ref())
        .filter_map(judge)
        .collect();
    let first = track.placements.first().and_then(judge).or(committed);
    let wrong_placement = lived
        .iter()
        .any(|&(m, deg, _)| !options.wrong_placement.accepts(m, deg));
    let initialized = !wrong_placement && first.is_some_and(in_time_and_correct);
    let good = |a: &TrajectoryAccuracy| a.mrcl * a.distance_m;
    let mrcl_ceiling = (!track.search_bests.is_empty()).then(|| {
        let first_right = track
            .search_bests
            .iter()
            .flatten()
            .find(|p| judge(p).is_some_and(|(m, deg, _)| options.correct.accepts(m, deg)));
        first_right.map_or(0.0, |p| {
            // The whole truth distance, as MRCL counts it.
            let total = online.distance_m;
            if total > 0.0 {
                1.0 - distance_driven(track.truth, p.decided_at) / total
            } else {
                1.0
            }
        })
    });
    SessionScore {
        mrcl: online.mrcl,
        mrcl_smoothed: smoothed.mrcl,
        ate_rms_m: online.ate_rms_m,
        max_error_m: online.max_error_m,
        ate_rms_smoothed_m: smoothed.ate_rms_m,
        localized_scans: online.matched,
        distance_m: online.distance_m,
        initialized,
        initialized_committed: committed.is_some_and(in_time_and_correct),
        placement_error_m: committed.map(|p| p.0),
        placement_error_deg: committed.map(|p| p.1),
        first_placement_error_m: first.map(|p| p.0),
        placed_after_s: first.map(|p| p.2),
        committed_after_s: committed.map(|p| p.2),
        placements: track.placements.len().max(usize::from(committed.is_some())),
        wrong_placement,
        mrwl: if online.distance_m > 0.0 {
            wrong_distance_m / online.distance_m
        } else {
            0.0
        },
        ams: average_match_score(track.match_scores),
        scored_scans: track.match_scores.len(),
        mrcl_ceiling,
        good_distance_m: [good(&online), good(&smoothed)],
        wrong_distance_m,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;

    fn t(seconds: f64) -> Timestamp {
        Timestamp::from_secs_f64(seconds)
    }

    /// 11 scans one second apart driving 1 m/s along x from x = 0 (10 m).
    fn truth() -> Vec<(Timestamp, Rigid2)> {
        (0..=10)
            .map(|k| (t(f64::from(k)), rigid2(f64::from(k), 0.0, 0.0)))
            .collect()
    }

    fn placement_at(decided: f64, scan: f64, dx: f64, dtheta_deg: f64) -> Placement {
        Placement {
            decided_at: t(decided),
            time: t(scan),
            map_from_base: rigid2(scan + dx, 0.0, dtheta_deg.to_radians()),
        }
    }

    #[test]
    fn online_mrcl_counts_what_the_robot_had_not_what_smoothing_found() {
        let truth = truth();
        // The robot was 1 m off for its first 4 s (a wrong start it recovered from); smoothed at the end,
        // every pose is right.
        let online: Vec<_> = truth
            .iter()
            .map(|(time, p)| {
                let off = if time.as_secs_f64() < 4.5 { 1.0 } else { 0.0 };
                (*time, rigid2(p.translation.x, off, 0.0))
            })
            .collect();
        let track = SessionTrack {
            truth: &truth,
            start_time: t(0.0),
            online: &online,
            smoothed: &truth,
            placements: &[],
            committed: Some(placement_at(0.0, 0.0, 0.0, 0.0)),
            match_scores: &[],
            search_bests: &[],
        };
        let score = score_session(&track, &Rigid2::identity(), &ScoringOptions::DEFAULT);
        // Steps 4→5 .. 9→10 have both ends correct: 5 m of 10.
        assert!((score.mrcl - 0.5).abs() < 1e-12, "{score:?}");
        assert!((score.mrcl_smoothed - 1.0).abs() < 1e-12);
        assert!((score.good_distance_m() - 5.0).abs() < 1e-12);
        assert!((score.good_distance_smoothed_m() - 10.0).abs() < 1e-12);
        assert!((score.distance_m - 10.0).abs() < 1e-12);
        assert_eq!(score.localized_scans, 11);
        assert!((score.max_error_m - 1.0).abs() < 1e-12);
        assert_eq!(score.ams, None);
    }

    #[test]
    fn an_estimate_dragged_off_after_a_right_placement_is_driven_wrong_though_no_placement_was() {
        let truth = truth();
        // Placed right at 2 s (no estimate before: refused, not wrong); from 5 s the estimate is 4 m off
        // (matches on probation moved it), while the placement itself stays right.
        let online: Vec<_> = truth[2..]
            .iter()
            .map(|(time, p)| {
                let off = if time.as_secs_f64() > 4.5 { 4.0 } else { 0.0 };
                (*time, rigid2(p.translation.x, off, 0.0))
            })
            .collect();
        let placements = [placement_at(2.0, 2.0, 0.02, 0.0)];
        let track = SessionTrack {
            truth: &truth,
            start_time: t(0.0),
            online: &online,
            smoothed: &truth,
            placements: &placements,
            committed: None,
            match_scores: &[],
            search_bests: &[],
        };
        let score = score_session(&track, &Rigid2::identity(), &ScoringOptions::DEFAULT);
        assert!(!score.wrong_placement, "{score:?}");
        // Steps 5→6 .. 9→10 wrong: 5 m of 10; 0→2 refused and 2→4 right count in neither.
        assert!((score.mrwl - 0.5).abs() < 1e-12, "{score:?}");
        assert!((score.wrong_distance_m() - 5.0).abs() < 1e-12);
        assert!((score.mrcl - 0.2).abs() < 1e-12, "{score:?}");
        let run = crate::metrics::score_run(&[score]);
        assert!((run.mrwl - 0.5).abs() < 1e-12);
        assert_eq!((run.wrong_placements, run.wrong_estimate_sessions), (0, 1));
    }

    #[test]
    fn scans_before_placement_count_as_lost() {
        let truth = truth();
        // Placed at 6 s: no estimate before.
        let online: Vec<_> = truth[6..].to_vec();
        let track = SessionTrack {
            truth: &truth,
            start_time: t(0.0),
            online: &online,
            smoothed: &truth,
            placements: &[],
            committed: Some(placement_at(6.0, 6.0, 0.1, 0.0)),
            match_scores: &[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.8, 0.8, 0.8, 0.8, 0.8],
            search_bests: &[],
        };
        let score = score_session(&track, &Rigid2::identity(), &ScoringOptions::DEFAULT);
        assert!((score.mrcl - 0.4).abs() < 1e-12, "{score:?}");
        assert_eq!(score.localized_scans, 5);
        // 6 s after its start, within the 30 s window, 0.1 m off: initialized.
        assert!(score.initialized);
        assert!((score.placement_error_m.unwrap() - 0.1).abs() < 1e-9);
        assert!((score.placed_after_s.unwrap() - 6.0).abs() < 1e-9);
        assert!(!score.wrong_placement);
        // Every scan scores, the lost ones 0: (5 × 0.8) / 11.
        assert!((score.ams.unwrap() - 4.0 / 11.0).abs() < 1e-12);
        assert_eq!(score.scored_scans, 11);
    }

    #[test]
    fn the_mrcl_ceiling_starts_at_the_first_search_whose_best_was_right() {
        let truth = truth();
        let track_with = |search_bests: &[Option<Placement>]| {
            let track = SessionTrack {
                truth: &truth,
                start_time: t(0.0),
                online: &[],
                smoothed: &truth,
                placements: &[],
                committed: None,
                match_scores: &[],
                search_bests,
            };
            score_session(&track, &Rigid2::identity(), &ScoringOptions::DEFAULT).mrcl_ceiling
        };
        // Searches decided at 2 s (no candidate), 3 s (best 5 m off), 4 s (best 0.1 m off) and 8 s:
        // 4 m of the 10 driven before the first right best.
        let bests = [
            None,
            Some(placement_at(3.0, 3.0, 5.0, 0.0)),
            Some(placement_at(4.0, 2.0, 0.1, 0.0)),
            Some(placement_at(8.0, 8.0, 0.0, 0.0)),
        ];
        let ceiling = track_with(&bests).expect("searches recorded");
        assert!((ceiling - 0.6).abs() < 1e-12, "{ceiling}");
        // A best turned the wrong way is not right either.
        let turned = [Some(placement_at(4.0, 4.0, 0.0, 30.0)), bests[3]];
        let ceiling = track_with(&turned).expect("searches recorded");
        assert!((ceiling - 0.2).abs() < 1e-12, "{ceiling}");
        // No right best at all; no search recorded.
        assert_eq!(track_with(&bests[..2]), Some(0.0));
        assert_eq!(track_with(&[]), None);
    }

    #[test]
    fn initialization_needs_a_correct_placement_within_the_window() {
        let truth = truth();
        let options = ScoringOptions {
            initialization_window_s: 5.0,
            ..ScoringOptions::DEFAULT
        };
        let score_with = |placement: Option<Placement>| {
            let track = SessionTrack {
                truth: &truth,
                start_time: t(0.0),
                online: &[],
                smoothed: &[],
                placements: &[],
                committed: placement,
                match_scores: &[],
                search_bests: &[],
            };
            score_session(&track, &Rigid2::identity(), &options)
        };
        // Correct and in time.
        let s = score_with(Some(placement_at(2.0, 0.0, 0.2, 3.0)));
        assert!(s.initialized && !s.wrong_placement);
        assert!((s.placement_error_deg.unwrap() - 3.0).abs() < 1e-9);
        // Correct but decided too late.
        let s = score_with(Some(placement_at(6.0, 6.0, 0.0, 0.0)));
        assert!(!s.initialized && !s.wrong_placement);
        // In time, 0.4 m off: neither initialized nor wrong (0.3 < 0.4 ≤ 0.5).
        let s = score_with(Some(placement_at(1.0, 1.0, 0.4, 0.0)));
        assert!(!s.initialized && !s.wrong_placement);
        // In time, 0.6 m off: wrong.
        let s = score_with(Some(placement_at(1.0, 1.0, 0.6, 0.0)));
        assert!(!s.initialized && s.wrong_placement);
        // In place but turned 6°: wrong.
        let s = score_with(Some(placement_at(1.0, 1.0, 0.0, 6.0)));
        assert!(!s.initialized && s.wrong_placement);
        // Never placed: no error, not initialized, not a wrong placement.
        let s = score_with(None);
        assert!(!s.initialized && !s.wrong_placement);
        assert_eq!(s.placement_error_m, None);
        assert_eq!(s.placed_after_s, None);
    }

    #[test]
    fn initialization_is_the_first_placement_the_robot_acted_on() {
        let truth = truth();
        let score = |placements: &[Placement], committed: Option<Placement>| {
            let track = SessionTrack {
                truth: &truth,
                start_time: t(0.0),
                online: &[],
                smoothed: &[],
                placements,
                committed,
                match_scores: &[],
                search_bests: &[],
            };
            score_session(&track, &Rigid2::identity(), &ScoringOptions::DEFAULT)
        };
        // Placed tentatively at 2 s, 0.1 m off; committed (the same placement) at 40 s: the robot
        // navigated correctly from 2 s, the map took the session in late.
        let tentative = placement_at(2.0, 1.0, 0.1, 0.0);
        let committed = Placement {
            decided_at: t(40.0),
            ..tentative
        };
        let s = score(&[tentative], Some(committed));
        assert!(
            s.initialized && !s.initialized_committed && !s.wrong_placement,
            "{s:?}"
        );
        assert!((s.placed_after_s.unwrap() - 2.0).abs() < 1e-9);
        assert!((s.committed_after_s.unwrap() - 40.0).abs() < 1e-9);
        assert_eq!(s.placements, 1);
        // Placed on probation, never committed: still initialized (the robot had its pose).
        let s = score(&[tentative], None);
        assert!(s.initialized && s.placement_error_m.is_none());
        assert!((s.first_placement_error_m.unwrap() - 0.1).abs() < 1e-9);
        // A wrong tentative placement, revoked, then a correct one committed: the robot lived a wrong
        // placement.
        let wrong = placement_at(1.0, 1.0, 2.0, 0.0);
        let right = placement_at(8.0, 8.0, 0.0, 0.0);
        let s = score(&[wrong, right], Some(right));
        assert!(s.wrong_placement && !s.initialized, "{s:?}");
        assert!(s.placement_error_m.unwrap() < 1e-9);
        assert_eq!(s.placements, 2);
        // A correct first placement, revoked, then a wrong one committed: wrong.
        let s = score(&[right, wrong], Some(wrong));
        assert!(s.wrong_placement && !s.initialized);
    }

    #[test]
    fn placement_is_judged_in_the_world_frame() {
        let truth = truth();
        // The map is the world shifted by (−2, 1): a placement at map (3, −1) is at world (1, 0) = truth
        // at 1 s.
        let world_from_map = rigid2(2.0, -1.0, 0.0);
        let placement = Placement {
            decided_at: t(1.0),
            time: t(1.0),
            map_from_base: rigid2(-1.0, 1.0, 0.0),
        };
        let track = SessionTrack {
            truth: &truth,
            start_time: t(0.0),
            online: &[],
            smoothed: &[],
            placements: &[],
            committed: Some(placement),
            match_scores: &[],
            search_bests: &[],
        };
        let s = score_session(&track, &world_from_map, &ScoringOptions::DEFAULT);
        assert!(s.placement_error_m.unwrap() < 1e-9, "{s:?}");
        assert!(s.initialized);
        let s = score_session(&track, &Rigid2::identity(), &ScoringOptions::DEFAULT);
        assert!(s.wrong_placement && !s.initialized);
    }

    #[test]
    fn truth_at_takes_the_nearest_sample() {
        let truth = truth();
        let x_at = |seconds: f64| truth_at(&truth, t(seconds)).unwrap().translation.x;
        assert!((x_at(3.0) - 3.0).abs() < 1e-12);
        assert!((x_at(3.4) - 3.0).abs() < 1e-12);
        assert!((x_at(3.6) - 4.0).abs() < 1e-12);
        assert!((x_at(-1.0) - 0.0).abs() < 1e-12);
        assert!((x_at(99.0) - 10.0).abs() < 1e-12);
        assert!(truth_at(&[], t(1.0)).is_none());
    }
}
