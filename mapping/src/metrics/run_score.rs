//! The scores of a lifelong run over its localizing sessions (every session after the mapping one):
//! CRI, MRCL (weighted by distance), AMS mean and minimum, wrong placements.

use serde::Serialize;

use super::SessionScore;

/// A run's scores, from each localizing session's [`SessionScore`] (see [`score_run`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct RunScore {
    /// Sessions scored.
    pub sessions: usize,
    /// Correct initialization rate: initialized sessions over sessions (`None` for no session).
    pub cri: Option<f64>,
    /// Sessions initialized (the robot's first placement correct and within the window, none wrong).
    pub initialized: usize,
    /// The map's side of initialization: sessions whose committed placement is correct and was committed
    /// within the window, over sessions (`None` for no session).
    pub cri_committed: Option<f64>,
    /// Sessions that were placed at all (the robot had a pose).
    pub placed: usize,
    /// Sessions whose placement was committed.
    pub committed: usize,
    /// Sessions that acted on a wrong placement (tentative or committed).
    pub wrong_placements: usize,
    /// Mileage rate of wrong localization over the run, weighted by distance (see
    /// [`SessionScore::mrwl`]): the robot's estimate at the time off by more than the wrong-placement
    /// tolerance.
    pub mrwl: f64,
    /// Sessions whose robot drove some distance wrongly localized ([`SessionScore::mrwl`] > 0).
    pub wrong_estimate_sessions: usize,
    /// MRCL over the run from the estimate at the time of each scan: good distance over distance.
    pub mrcl: f64,
    /// The same from each session's trajectory smoothed at its end.
    pub mrcl_smoothed: f64,
    /// RMS position error of the estimates at the time of each scan, over every scan that had one, metres.
    pub ate_rms_m: f64,
    /// Mean of the sessions' AMS (`None` when no session measured one).
    pub ams_mean: Option<f64>,
    /// Smallest session AMS.
    pub ams_min: Option<f64>,
    /// Distance driven, metres.
    pub distance_m: f64,
    /// The sessions' [`SessionScore::mrcl_ceiling`] weighted by distance, over the sessions that have
    /// one (`None`: none has).
    pub mrcl_ceiling: Option<f64>,
}

/// Scores a run from the scores of its localizing sessions (not the mapping session: it defines the
/// map).
pub fn score_run(sessions: &[SessionScore]) -> RunScore {
    let n = sessions.len();
    let initialized = sessions.iter().filter(|s| s.initialized).count();
    let distance: f64 = sessions.iter().map(|s| s.distance_m).sum();
    let ratio = |good: f64| if distance > 0.0 { good / distance } else { 0.0 };
    let scans: usize = sessions.iter().map(|s| s.localized_scans).sum();
    let squared: f64 = sessions
        .iter()
        .map(|s| s.ate_rms_m * s.ate_rms_m * s.localized_scans as f64)
        .sum();
    let ams: Vec<f64> = sessions.iter().filter_map(|s| s.ams).collect();
    let ceilings: Vec<(f64, f64)> = sessions
        .iter()
        .filter_map(|s| Some((s.mrcl_ceiling?, s.distance_m)))
        .collect();
    let ceiling_distance: f64 = ceilings.iter().map(|(_, d)| d).sum();
    RunScore {
        sessions: n,
        cri: (n > 0).then(|| initialized as f64 / n as f64),
        initialized,
        cri_committed: (n > 0)
            .then(|| sessions.iter().filter(|s| s.initialized_committed).count() as f64 / n as f64),
        placed: sessions
            .iter()
            .filter(|s| s.placed_after_s.is_some())
            .count(),
        committed: sessions
            .iter()
            .filter(|s| s.placement_error_m.is_some())
            .count(),
        wrong_placements: sessions.iter().filter(|s| s.wrong_placement).count(),
        mrwl: ratio(sessions.iter().map(SessionScore::wrong_distance_m).sum()),
        wrong_estimate_sessions: sessions.iter().filter(|s| s.mrwl > 0.0).count(),
        mrcl: ratio(sessions.iter().map(SessionScore::good_distance_m).sum()),
        mrcl_smoothed: ratio(
            sessions
                .iter()
                .map(SessionScore::good_distance_smoothed_m)
                .sum(),
        ),
        ate_rms_m: if scans > 0 {
            (squared / scans as f64).sqrt()
        } else {
            0.0
        },
        ams_mean: (!ams.is_empty()).then(|| ams.iter().sum::<f64>() / ams.len() as f64),
        ams_min: ams.iter().copied().reduce(f64::min),
        distance_m: distance,
        mrcl_ceiling: (!ceilings.is_empty()).then(|| {
            if ceiling_distance > 0.0 {
                ceilings.iter().map(|(c, d)| c * d).sum::<f64>() / ceiling_distance
            } else {
                ceilings.iter().map(|(c, _)| c).sum::<f64>() / ceilings.len() as f64
            }
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Rigid2, rigid2};
    use crate::metrics::{Placement, ScoringOptions, SessionTrack, score_session};
    use crate::sensor::Timestamp;

    fn t(seconds: f64) -> Timestamp {
        Timestamp::from_secs_f64(seconds)
    }

    /// A session driving `length` metres along x at 1 m/s, localized correctly from `placed_at` seconds
    /// (its placement `dx` metres off), its scans scoring `score` once placed.
    fn session(length: u32, placed_at: Option<u32>, dx: f64, score: f64) -> SessionScore {
        let truth: Vec<_> = (0..=length)
            .map(|k| (t(f64::from(k)), rigid2(f64::from(k), 0.0, 0.0)))
            .collect();
        let from = placed_at.map_or(truth.len(), |p| (p as usize).min(truth.len()));
        let online: Vec<_> = truth[from..].to_vec();
        let scores: Vec<f64> = (0..truth.len())
            .map(|k| if k >= from { score } else { 0.0 })
            .collect();
        let placement = placed_at.map(|p| Placement {
            decided_at: t(f64::from(p)),
            time: t(f64::from(p)),
            map_from_base: rigid2(f64::from(p) + dx, 0.0, 0.0),
        });
        let track = SessionTrack {
            truth: &truth,
            start_time: t(0.0),
            online: &online,
            smoothed: &truth,
            placements: &[],
            committed: placement,
            match_scores: &scores,
            search_bests: &[],
        };
        score_session(&track, &Rigid2::identity(), &ScoringOptions::DEFAULT)
    }

    #[test]
    fn a_run_weighs_mrcl_by_distance_and_counts_every_session() {
        let sessions = [
            // 10 m, placed at once, correctly: 10 good metres, AMS 0.8.
            session(10, Some(0), 0.0, 0.8),
            // 50 m, placed after 40 s (too late for CRI), 0.2 m off: its last 10 m are good.
            session(50, Some(40), 0.2, 0.7),
            // 20 m, placed at 10 s but 2 m off: wrong, and the estimate (the truth from 10 s, since the
            // online track is the truth here) still scores 10 good metres.
            session(20, Some(10), 2.0, 0.6),
            // 40 m, never placed: nothing localized, every scan scores 0.
            session(40, None, 0.0, 0.9),
        ];
        let run = score_run(&sessions);
        assert_eq!(run.sessions, 4);
        assert_eq!(run.initialized, 1);
        assert!((run.cri.unwrap() - 0.25).abs() < 1e-12);
        assert!((run.cri_committed.unwrap() - 0.25).abs() < 1e-12);
        assert_eq!(run.placed, 3);
        assert_eq!(run.committed, 3);
        assert_eq!(run.wrong_placements, 1);
        assert!((run.distance_m - 120.0).abs() < 1e-9);
        assert!((run.mrcl - 30.0 / 120.0).abs() < 1e-9, "{run:?}");
        assert!((run.mrcl_smoothed - 1.0).abs() < 1e-9);
        // AMS: 0.8, 0.7 × 11/51, 0.6 × 11/21, 0 — the never-placed session is not left out.
        let expected = [0.8, 0.7 * 11.0 / 51.0, 0.6 * 11.0 / 21.0, 0.0];
        assert!((run.ams_mean.unwrap() - expected.iter().sum::<f64>() / 4.0).abs() < 1e-9);
        assert_eq!(run.ams_min, Some(0.0));
        // ATE over the localized scans: 11 + 11 + 11 scans, all exact.
        assert!(run.ate_rms_m.abs() < 1e-12);
    }

    #[test]
    fn no_sessions_score_nothing() {
        let run = score_run(&[]);
        assert_eq!(run.sessions, 0);
        assert_eq!(run.cri, None);
        assert_eq!(run.ams_mean, None);
        assert!(run.mrcl.abs() < f64::EPSILON);
    }
}
