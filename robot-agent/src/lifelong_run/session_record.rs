//! What one session lived, recorded as it happened, for scoring: [`SessionRecord`].

use mapping::geometry::Rigid2;
use mapping::metrics::{SessionTrack, StartRecord};
use mapping::sensor::Timestamp;

/// What one session lived, recorded as it happened: the robot's estimate at the time of each scan, the
/// placement it committed to, each node's match score against the map as it was then, and the
/// trajectory smoothed at the session's end. [`Self::track`] hands it to
/// [`mapping::metrics::score_session`].
#[derive(Clone, Debug, Default)]
pub struct SessionRecord {
    /// Session id.
    pub session: u32,
    /// Time of the session's first event.
    pub start_time: Timestamp,
    /// `map_from_base` of each matched scan as the robot estimated it at that scan: its node's pose as the
    /// robot had it right after the map took the node in (the graph's `global_from_local`, with the best match
    /// of each node against the older sessions' map since the last optimization or start decision fused
    /// in: `mapping::lifelong::LiveAnchor`), composed with LLO's motion since. Only scans while the session
    /// was placed (on probation — the robot navigates with a tentative placement too — or committed) have
    /// one (session 0: every scan).
    pub online: Vec<(Timestamp, Rigid2)>,
    /// `map_from_base` of each matched scan when the session ended (after its final optimization).
    pub smoothed: Vec<(Timestamp, Rigid2)>,
    /// What its session start decided: the placements the robot acted on, the one it committed to and
    /// each whole-map search's best (empty for session 0, which defines the map).
    pub start: StartRecord,
    /// Per node, in order, its branch-and-bound score ([`MatchScorer`], within the scoring's match window
    /// of the robot's estimate) against the map of the finished sessions rendered when the session
    /// started; 0 while the session was not placed.
    /// Empty for session 0 (no map before it).
    ///
    /// [`MatchScorer`]: mapping::metrics::MatchScorer
    pub match_scores: Vec<f64>,
}

impl SessionRecord {
    /// The record as [`mapping::metrics::score_session`] takes it, with the session's truth.
    pub fn track<'a>(&'a self, truth: &'a [(Timestamp, Rigid2)]) -> SessionTrack<'a> {
        SessionTrack {
            truth,
            start_time: self.start_time,
            online: &self.online,
            smoothed: &self.smoothed,
            placements: &self.start.placements,
            committed: self.start.committed,
            match_scores: &self.match_scores,
            search_bests: &self.start.search_bests,
        }
    }
}
