//! The options of the session start ([`super::SessionStart`]), their defaults and their checks.

use serde::Deserialize;

#[cfg(doc)]
use super::SessionStart;
use crate::lifelong::LifelongOptionsError;
#[cfg(doc)]
use crate::lifelong::StartSearch;

/// Options of [`SessionStart`].
#[allow(
    clippy::struct_excessive_bools,
    reason = "independent documented switches of a configuration file, not a state"
)]
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SessionStartOptions {
    /// Nodes held back and merged into the cloud of the first whole-map search (count ≥ 1). Default 10
    /// (about 2 m of driving).
    pub hold_back_nodes: usize,
    /// While unplaced, search the whole map again after this many nodes, then twice, four times ... as
    /// many (count; 0 = never retry). Default 20. Why: `docs/TUNING.md#ss-retry-every-n-nodes`.
    pub retry_every_n_nodes: usize,
    /// Longest gap between two scheduled retries (count; 0 = the doubling is never capped): once
    /// doubling would leave more nodes than this between retries, retry every this many nodes. Default 40
    /// (about 8 m of driving). Why: `docs/TUNING.md#ss-max-retry-interval-nodes`.
    pub max_retry_interval_nodes: usize,
    /// Between retries, every this many nodes retry at once if the route now tells the last search's
    /// candidates apart (count; 0 = never). Default 10. Why: `docs/TUNING.md#ss-recheck-every-n-nodes`.
    pub recheck_every_n_nodes: usize,
    /// Most nodes (the latest) a retry's cloud holds (count ≥ `hold_back_nodes`). Default 400 (about
    /// 80 m of driving): beyond that LLO's drift across the cloud outgrows the match tolerance.
    pub max_search_nodes: usize,
    /// While the last search found nothing, also search with only the latest this many nodes (count;
    /// 0 = off). Default 40. Why: `docs/TUNING.md#ss-recent-search-nodes`.
    pub recent_search_nodes: usize,
    /// Nodes whose cloud checks a dock start ([`SessionStart::from_dock`]: where the last session ended)
    /// by [`StartSearch::check_prior`] before any whole-map search (count ≥ 1). Default 3 (about 0.5 m).
    pub dock_check_nodes: usize,
    /// Stop searching after this many nodes without a placement (count; 0 = never): the session stays
    /// unplaced. Default 0.
    pub give_up_after_nodes: usize,
    /// Independent agreeing matches that commit a placement (count; 0 = commit as soon as placed).
    /// Default 3.
    pub probation_matches: usize,
    /// Route (metres ≥ 0) between two matches' nodes that makes them independent, and that an agreeing
    /// match's node must lie past the node the placement was decided at. Default 3 m.
    pub probation_min_separation_m: f64,
    /// ... or when less than this share of one node's scan was seen by the other's (share 0–1; 0 = the
    /// route alone decides). Default 0.5. Why: `docs/TUNING.md#ss-probation-max-view-overlap`.
    pub probation_max_view_overlap: f64,
    /// The agreeing matches that commit a placement must be of at least this many different submaps
    /// (count ≥ 1; capped by `probation_matches`). Default 1: independence is the route's and the view's
    /// (`probation_min_separation_m`, `probation_max_view_overlap`), not the submap's. Why:
    /// `docs/TUNING.md#ss-probation-min-submaps`.
    pub probation_min_submaps: usize,
    /// Distance (metres > 0, plus `agreement_growth` per metre of route) within which a match agrees with
    /// the placement. Default 1 m. Why: `docs/TUNING.md#ss-agreement-translation-m`.
    pub agreement_translation_m: f64,
    /// ... and its heading within this. Radians > 0. Default 5° (the wrong-placement bound of the scores).
    pub agreement_rotation_rad: f64,
    /// Growth of the translation tolerance per metre of route between the placement's node and the
    /// matched node (LLO's drift), metres per metre ≥ 0. Default 0.01.
    pub agreement_growth: f64,
    /// Rotation tolerance's growth per metre of route past the placement's node (LLO's heading drift),
    /// radians per metre ≥ 0. Default 0.2°/m. Why: `docs/TUNING.md#ss-agreement-rotation-growth`.
    pub agreement_rotation_growth: f64,
    /// Independent disagreeing matches that revoke a placement (count ≥ 1). Default 2: one false match
    /// does not undo a placement, two independent ones do.
    pub probation_disagreements: usize,
    /// Revoke a placement not committed after this much route past its node, metres (0 = never), and
    /// search again. Default 0. Why: `docs/TUNING.md#ss-probation-timeout-m`.
    pub probation_timeout_m: f64,
    /// A search answer this close to a revoked placement (metres ≥ 0) is refused unless its paired test
    /// reaches `probation_min_z`. Default 1 m. Why: `docs/TUNING.md#ss-revoked-radius-m`.
    pub revoked_radius_m: f64,
    /// Paired z by which the route must fit a placement better than each rival before it is committed
    /// ([`StartSearch::contest`]; 0 = no test). Default 4. Why: `docs/TUNING.md#ss-probation-min-z`.
    pub probation_min_z: f64,
    /// Piece length (metres of route ≥ 0; 0 = off) when probation tests a rival the whole route leaves
    /// undecided again in pieces. Default 4 m. Why: `docs/TUNING.md#ss-contest-piece-m`.
    pub contest_piece_m: f64,
    /// Piece length (metres of route ≥ 0; 0 = off) when a retry tests a rival the whole route leaves
    /// undecided again in pieces. Default 4 m. Why: `docs/TUNING.md#ss-search-piece-m`.
    pub search_piece_m: f64,
    /// Search the whole map again while a placement on probation has no agreeing match and its latest nodes
    /// fit the map poorly there. Default true. Why: `docs/TUNING.md#ss-search-while-unconfirmed`.
    pub search_while_unconfirmed: bool,
    /// Those searches come after `retry_every_n_nodes` nodes on probation, then twice, four times ... as
    /// many, never more than this many nodes apart (count; 0 = the doubling is never capped;
    /// `retry_every_n_nodes` = every `retry_every_n_nodes`). Default 80 (about 16 m of driving): a wrong
    /// placement that a look-alike part of the route agreed with is replaced when the route has left that
    /// part, not after a doubled interval the session may never reach. Why: `docs/TUNING.md#ss-max-second-opinion-interval-nodes`.
    pub max_second_opinion_interval_nodes: usize,
    /// Those searches go on after a match agreed with the placement too (a look-alike aisle's first matches
    /// may agree with a wrong placement before the route leaves the look-alike part). Default true. Why:
    /// `docs/TUNING.md#ss-second-opinion-after-agreement`.
    pub second_opinion_after_agreement: bool,
    /// Commit at its end ([`SessionStart::finish`]) a dock placement still on probation that nothing
    /// disputes. Default true. Why: `docs/TUNING.md#ss-commit-dock-at-end`.
    pub commit_dock_placement_at_end: bool,
    /// Check a dock a whole-map rival fits better (short of refusing it) again at `hold_back_nodes` instead
    /// of placing at once. Default true. Why: `docs/TUNING.md#ss-defer-contested-dock-check`.
    pub defer_contested_dock_check: bool,
}

impl Default for SessionStartOptions {
    fn default() -> Self {
        Self {
            hold_back_nodes: 10,
            retry_every_n_nodes: 20,
            max_retry_interval_nodes: 40,
            recheck_every_n_nodes: 10,
            max_search_nodes: 400,
            recent_search_nodes: 40,
            dock_check_nodes: 3,
            give_up_after_nodes: 0,
            probation_matches: 3,
            probation_min_separation_m: 3.0,
            probation_max_view_overlap: 0.5,
            probation_min_submaps: 1,
            agreement_translation_m: 1.0,
            agreement_rotation_rad: 5f64.to_radians(),
            agreement_growth: 0.01,
            agreement_rotation_growth: 0.2f64.to_radians(),
            probation_disagreements: 2,
            probation_timeout_m: 0.0,
            revoked_radius_m: 1.0,
            probation_min_z: 4.0,
            contest_piece_m: 4.0,
            search_piece_m: 4.0,
            search_while_unconfirmed: true,
            max_second_opinion_interval_nodes: 80,
            second_opinion_after_agreement: true,
            commit_dock_placement_at_end: true,
            defer_contested_dock_check: true,
        }
    }
}

impl SessionStartOptions {
    /// Checks every field.
    pub fn validate(&self) -> Result<(), LifelongOptionsError> {
        let out_of_range = |field, reason| Err(LifelongOptionsError::OutOfRange { field, reason });
        if self.hold_back_nodes == 0 {
            return out_of_range("hold_back_nodes", "must be at least 1");
        }
        if self.max_search_nodes < self.hold_back_nodes {
            return out_of_range("max_search_nodes", "must be at least hold_back_nodes");
        }
        if !(1..=self.max_search_nodes).contains(&self.dock_check_nodes) {
            return out_of_range(
                "dock_check_nodes",
                "must be at least 1 and at most max_search_nodes",
            );
        }
        let non_negative = |v: f64| v.is_finite() && v >= 0.0;
        if !non_negative(self.probation_min_separation_m) {
            return out_of_range(
                "probation_min_separation_m",
                "must be a non-negative number of metres",
            );
        }
        if !(0.0..=1.0).contains(&self.probation_max_view_overlap) {
            return out_of_range("probation_max_view_overlap", "must be a share from 0 to 1");
        }
        if self.probation_min_submaps == 0 {
            return out_of_range("probation_min_submaps", "must be at least 1");
        }
        if !(self.agreement_translation_m.is_finite() && self.agreement_translation_m > 0.0) {
            return out_of_range(
                "agreement_translation_m",
                "must be a positive number of metres",
            );
        }
        if !(self.agreement_rotation_rad.is_finite() && self.agreement_rotation_rad > 0.0) {
            return out_of_range(
                "agreement_rotation_rad",
                "must be a positive number of radians",
            );
        }
        if !non_negative(self.agreement_growth) {
            return out_of_range("agreement_growth", "must be non-negative");
        }
        if !non_negative(self.agreement_rotation_growth) {
            return out_of_range("agreement_rotation_growth", "must be non-negative");
        }
        if self.probation_disagreements == 0 {
            return out_of_range("probation_disagreements", "must be at least 1");
        }
        if !non_negative(self.probation_timeout_m) {
            return out_of_range(
                "probation_timeout_m",
                "must be a non-negative number of metres",
            );
        }
        if !non_negative(self.revoked_radius_m) {
            return out_of_range(
                "revoked_radius_m",
                "must be a non-negative number of metres",
            );
        }
        if !non_negative(self.probation_min_z) {
            return out_of_range("probation_min_z", "must be a non-negative number");
        }
        if !non_negative(self.contest_piece_m) {
            return out_of_range("contest_piece_m", "must be a non-negative number of metres");
        }
        if !non_negative(self.search_piece_m) {
            return out_of_range("search_piece_m", "must be a non-negative number of metres");
        }
        Ok(())
    }
}
