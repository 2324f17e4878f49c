//! What a placement's probation went through, step by step ([`ProbationStep`]): each GLM match
//! [`SessionStart::add_match`] judged — whether it agreed, whether it counted toward the commit and, if
//! not, which condition held it back — each test of the route against the placement's rivals
//! ([`StartSearch::contest`], each rival's z), each whole-map search made while the placement misfit and
//! whether and why it replaced it, and how the probation ended.
//!
//! [`SessionStart`] keeps these steps as it decides ([`SessionStart::probation_timeline`]), so every
//! shell reports the same account of why a placement was committed when it was, or not at all. They
//! record decisions, they make none: keeping them changes nothing the state machine decides. Steps are
//! kept only while a placement is on probation, so a session keeps at most one per match of its
//! probation.
//!
//! [`SessionStart`]: super::SessionStart
//! [`SessionStart::add_match`]: super::SessionStart::add_match
//! [`SessionStart::probation_timeline`]: super::SessionStart::probation_timeline
//! [`StartSearch::contest`]: crate::lifelong::StartSearch::contest

use serde::Serialize;

use crate::pose_graph::SubmapId;

/// One step of a placement's probation, in the order [`super::SessionStart`] took it.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "step", rename_all = "snake_case")]
pub enum ProbationStep {
    /// A placement began its probation.
    Began {
        /// The session's latest node (index in the session) when it began: the node it was decided at.
        at_node: usize,
        /// The rivals of the search that placed it, which the route must beat before the commit: where
        /// each puts the robot at the placing node, seen from where the placement puts it (`[x, y]` metres
        /// and heading in degrees), in the order the contests' z follow.
        rival_offsets: Vec<[f64; 3]>,
    },
    /// A GLM match of one of the session's nodes against an older session's submap was judged.
    Match(ProbationMatch),
    /// The session's route was tested against the placement's rivals before a commit.
    Contest(ProbationContest),
    /// The whole map was searched again while the placement's latest nodes misfit the map there
    /// (`search_while_unconfirmed`).
    SecondOpinion(ProbationSecondOpinion),
    /// The probation ended.
    Ended {
        /// The session's latest node when it ended.
        at_node: usize,
        /// `committed`, or the revocation's reason ([`super::RevokeReason::as_str`]: `disagreement`,
        /// `timeout`, `rival`).
        outcome: &'static str,
    },
}

/// How [`super::SessionStart::add_match`] judged one match while the session was on probation.
#[allow(
    clippy::struct_excessive_bools,
    reason = "the verdicts of the independent tests a match passes or fails, for reports, not a state"
)]
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ProbationMatch {
    /// The session's latest node when the match arrived.
    pub at_node: usize,
    /// The matched node (index in the session).
    pub node: usize,
    /// The older session's submap it matched.
    pub submap: SubmapId,
    /// Route from the placement's node to the matched node, metres (negative: before it).
    pub past_placing_m: f64,
    /// How far the match put the node from its pose under the placement, metres.
    pub translation_m: f64,
    /// The tolerance it was judged by (`agreement_translation_m` + growth), metres.
    pub translation_tolerance_m: f64,
    /// How far the match turned the node from its heading under the placement, radians.
    pub rotation_rad: f64,
    /// The tolerance it was judged by (`agreement_rotation_rad` + growth), radians.
    pub rotation_tolerance_rad: f64,
    /// Whether it agreed with the placement (both within their tolerances).
    pub agrees: bool,
    /// Share of the matched node's view the cloud that placed the session saw (`None` once the node's
    /// scan is no longer held).
    pub placing_view_overlap: Option<f64>,
    /// Whether it saw something the placing cloud did not (`probation_min_separation_m` past the
    /// placement's node, or less than `probation_max_view_overlap` of its view seen by that cloud). An
    /// agreeing match counts only when it is.
    pub past_placement: bool,
    /// Route to the nearest match already counted on its side (agreeing or disagreeing), metres.
    pub nearest_counted_m: Option<f64>,
    /// Whether it is independent of every match already counted on its side.
    pub independent: bool,
    /// Whether it counted: toward the commit (agreeing, past the placement, independent) or toward
    /// revoking it (disagreeing, independent).
    pub counted: bool,
    /// Agreeing matches counted so far, this one included.
    pub agreeing: usize,
    /// Different submaps among them.
    pub agreeing_submaps: usize,
    /// Disagreeing matches counted so far, this one included.
    pub disagreeing: usize,
}

/// One whole-map search made while a placement was on probation and its latest nodes misfit the map
/// there, and why it did or did not replace the placement.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ProbationSecondOpinion {
    /// The session's latest node when it was made.
    pub at_node: usize,
    /// Nodes of the route it searched (the latest `recent_search_nodes` where the whole route found
    /// nothing).
    pub route_nodes: usize,
    /// Where its answer puts the robot at the latest node, seen from where the placement puts it (`[x, y]`
    /// metres and heading in degrees); `None` when it found nothing.
    pub answer_offset: Option<[f64; 3]>,
    /// The paired test of the session's route, the answer against the placement (positive where the
    /// answer fits better); `None` where no test was made or it could not be.
    pub z: Option<f64>,
    /// `not_found`, `ambiguous` (two places fit the route within the search's margin), `same_place` (the
    /// answer is the placement), `revoked_before` (a placement revoked earlier, below the bar that
    /// overrules a revocation), `undecided` (`z` below `probation_min_z`) or `replaced`.
    pub decision: &'static str,
}

/// One test of the session's route against the placement's rivals ([`crate::lifelong::StartSearch::contest`]),
/// made once enough agreeing matches of enough submaps are counted.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ProbationContest {
    /// The session's latest node when it was made.
    pub at_node: usize,
    /// The node whose match brought it.
    pub node: usize,
    /// Nodes of the route it tested (the latest `max_search_nodes`).
    pub route_nodes: usize,
    /// The paired test against each rival, in the rivals' order: positive where the placement fits the
    /// route better; `None` for a rival that sharpened onto the placement itself. Empty when no test was
    /// made (`skipped` or `upheld` without one).
    pub z: Vec<Option<f64>>,
    /// The same test in pieces of `contest_piece_m` of route, in the rivals' order; empty when it was not
    /// made (the whole route's test decided, or `contest_piece_m` is 0).
    pub piece_z: Vec<Option<f64>>,
    /// The bar (`probation_min_z`).
    pub min_z: f64,
    /// `upheld` (the commit follows: every rival beaten by `z` or `piece_z`), `overturned` (a rival's `z`
    /// revokes it), `undecided`, or `skipped`: an
    /// undecided test was made less than `probation_min_separation_m` of route before.
    pub decision: &'static str,
}
