//! What the session start decides ([`SessionStartEvent`]) and where it stands ([`SessionStartState`]).

use crate::geometry::Rigid2;
use crate::lifelong::RelocalizationOutcome;
#[cfg(doc)]
use crate::lifelong::{PriorCheck, StartAnswer, StartSearch};

/// A placement of the session: where its LLO frame sits in the map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StartPlacement {
    /// `global_from_local` of the session's LLO frame.
    pub global_from_local: Rigid2,
    /// Index (in the session, from 0) of the node at which it was decided.
    pub node: usize,
    /// Index of the first of the nodes (through `node`) whose scans the search fitted to the map at this
    /// placement (`None`: given by the caller, e.g. a robot's prior). The map is told
    /// ([`crate::global_slam::GlobalSlam::place_trajectory`]): the placement vouches for LLO between them.
    pub fitted_from: Option<usize>,
    /// Branch-and-bound score of the search that found it (`None`: given by the caller, e.g. a robot's
    /// prior).
    pub score: Option<f32>,
    /// The search's paired test against its weakest rival ([`StartAnswer::weakest_z`]).
    pub weakest_z: Option<f64>,
    /// How well the search's cloud fit the map at the placement ([`StartAnswer::fit`]).
    pub fit: Option<f32>,
}

impl StartPlacement {
    /// The first and last index of the nodes whose scans the search fitted (`fitted_from` through
    /// `node`), as the map takes them ([`crate::global_slam::GlobalSlam::place_trajectory`]); `None` for a
    /// placement given by the caller.
    pub fn fitted_nodes(&self) -> Option<(u32, u32)> {
        let first = u32::try_from(self.fitted_from?).ok()?;
        Some((first, u32::try_from(self.node).ok()?))
    }
}

/// Why a placement was revoked.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RevokeReason {
    /// Independent matches disagreed with it.
    Disagreement,
    /// Nothing confirmed it within `probation_timeout_m`.
    Timeout,
    /// A rival of its search fit the session's route decisively better (`probation_min_z`).
    Rival,
}

impl RevokeReason {
    /// The reason's name in reports: `disagreement`, `timeout` or `rival`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Disagreement => "disagreement",
            Self::Timeout => "timeout",
            Self::Rival => "rival",
        }
    }
}

/// What [`SessionStart`] decided; the shell acts on it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SessionStartEvent {
    /// A whole-map search did not place the session (ambiguous, nothing found, or a revoked placement
    /// found again); searching goes on.
    Refused {
        /// The node the search was made at.
        node: usize,
        /// What the search found (`Found` only when it repeated a revoked placement).
        outcome: RelocalizationOutcome,
        /// Its paired test against the best's weakest rival ([`StartAnswer::weakest_z`]).
        weakest_z: Option<f64>,
        /// `global_from_local` at its best candidate ([`StartAnswer::best`]), for reports.
        best: Option<Rigid2>,
        /// How well the cloud fit the map at its best candidate ([`StartAnswer::fit`]), for reports.
        fit: Option<f32>,
    },
    /// The pose the robot believed it started at (its dock) was checked ([`StartSearch::check_prior`]):
    /// where the evidence agreed, a `Placed` event follows; where it did not, the session searches the
    /// whole map as any other does.
    DockChecked {
        /// The node the check was made at.
        node: usize,
        /// Whether the evidence agreed with the dock.
        agreed: bool,
        /// How well the cloud fit the map at the dock ([`PriorCheck::fit`]).
        fit: Option<f32>,
        /// The dock's weakest paired test against the whole map's other candidates.
        weakest_z: Option<f64>,
    },
    /// Placed tentatively: place the session in the map, on probation (its submaps stay out of the
    /// relocalization map and it trims nothing).
    Placed(StartPlacement),
    /// The placement is confirmed: commit it.
    Committed {
        /// The placement.
        placement: StartPlacement,
        /// The node whose match committed it.
        node: usize,
    },
    /// The placement was revoked: un-place the session; searching resumes.
    Revoked {
        /// The placement.
        placement: StartPlacement,
        /// Why.
        reason: RevokeReason,
        /// The node at which it was revoked.
        node: usize,
    },
    /// The session stopped searching (`give_up_after_nodes`); it stays unplaced.
    GaveUp {
        /// The node at which it gave up.
        node: usize,
    },
}

/// Where a [`SessionStart`] stands.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SessionStartState {
    /// Holding nodes back, or searching between retries.
    Searching,
    /// Placed, not yet confirmed.
    Probation(StartPlacement),
    /// Placed and confirmed (final).
    Committed(StartPlacement),
    /// Stopped searching, unplaced (final).
    GaveUp,
}
