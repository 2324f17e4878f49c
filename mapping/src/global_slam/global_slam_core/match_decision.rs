//! What GLM decided about each match when it arrived: which acceptance rule decided it. Every search result
//! that reaches the rules gets exactly one [`MatchDecided`] (see [`super::GlobalSlamEvent::MatchDecided`]),
//! so a shell can measure each rule as the test it is — how many of the matches it let through, held or
//! refused were right — against a reference trajectory (`metrics::judge_matches`).

use serde::Serialize;

use super::Acceptance;
use crate::geometry::Rigid2;
use crate::global_slam::LoopClosure;

/// The rule that decided a match on arrival.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MatchDecision {
    /// Refused: another match of the same node, at another place, had more matches agreeing with it, or
    /// none of its node's other matches agreed with it.
    Outvoted,
    /// Added to the graph at once: within the drift LLO can explain and near the node's estimate.
    Accepted,
    /// Held: it moves its node farther than drift explains (`max_innovation_*`), and waits for matches of
    /// more nodes against more submaps to agree with it (`beyond_drift_confirmations`).
    HeldBeyondDrift,
    /// It completed such a chorus: it and the held matches agreeing with it were added to the graph.
    ConfirmedBeyondDrift,
    /// Refused: beyond drift, of a node whose scan fitted its trajectory's placement, against another
    /// trajectory's submap: the placement vouches for the LLO such a chorus would repair
    /// ([`super::GlobalSlam::place_trajectory`]).
    RefusedByPlacement,
    /// Held: within drift but far from the estimate (`max_unconfirmed_*`), it waits for a match of another
    /// node to agree with it (`agreement_*`).
    HeldUnconfirmed,
    /// It agreed with held matches: it and they were added to the graph.
    Confirmed,
}

impl MatchDecision {
    /// Every decision, in the order reports list them.
    pub const ALL: [Self; 7] = [
        Self::Accepted,
        Self::Confirmed,
        Self::ConfirmedBeyondDrift,
        Self::HeldUnconfirmed,
        Self::HeldBeyondDrift,
        Self::RefusedByPlacement,
        Self::Outvoted,
    ];

    /// The decision's name in reports and CSV files (snake case).
    pub fn name(self) -> &'static str {
        match self {
            Self::Outvoted => "outvoted",
            Self::Accepted => "accepted",
            Self::HeldBeyondDrift => "held_beyond_drift",
            Self::ConfirmedBeyondDrift => "confirmed_beyond_drift",
            Self::RefusedByPlacement => "refused_by_placement",
            Self::HeldUnconfirmed => "held_unconfirmed",
            Self::Confirmed => "confirmed",
        }
    }
}

/// One match and what GLM decided about it on arrival. A held match that a later one confirms joins the
/// graph then (its [`Acceptance::confirmed_by_agreement`] set); whether a match ended in the graph,
/// retracted or never used is read from [`super::GlobalSlam::loop_closure_checks`] at the end.
#[derive(Clone, Debug, PartialEq)]
pub struct MatchDecided {
    /// The match as the search returned it.
    pub closure: LoopClosure,
    /// How far it would move its node from the estimate of the moment.
    pub acceptance: Acceptance,
    /// The match's pose of its node relative to the node's estimate of the moment, in the estimate's frame
    /// (the frame of the match's information): the innovation as a vector, not only its size.
    pub innovation: Rigid2,
    /// The rule that decided it.
    pub decision: MatchDecision,
}
