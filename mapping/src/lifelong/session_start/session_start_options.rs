//! The options of the session start ([`super::SessionStart`]), their defaults and their checks.

use serde::Deserialize;

#[cfg(doc)]
use super::SessionStart;
use crate::lifelong::LifelongOptionsError;
#[cfg(doc)]
use crate::lifelong::StartSearch;

/// Options of [`SessionStart`].
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SessionStartOptions {
    /// Nodes held back and merged into the cloud of the first whole-map search (count ≥ 1). Default 10
    /// (about 2 m of driving).
    pub hold_back_nodes: usize,
    /// While unplaced, search the whole map again with every node since the start (or the last revocation)
    /// after this many nodes, then twice, four times ... as many (count; 0 = never retry). Default 20.
    /// Why: `docs/TUNING.md#ss-retry-every-n-nodes`.
    pub retry_every_n_nodes: usize,
    /// Between the scheduled retries, every this many nodes test whether the route now tells apart the last
    /// search's candidates ([`StartSearch::route_decides`]), and if so retry at once (count; 0 = never).
    /// Default 10 (about 2 m). Why: `docs/TUNING.md#ss-recheck-every-n-nodes`.
    pub recheck_every_n_nodes: usize,
    /// Most nodes (the latest) a retry's cloud holds (count ≥ `hold_back_nodes`). Default 400 (about
    /// 80 m of driving): beyond that LLO's drift across the cloud outgrows the match tolerance.
    pub max_search_nodes: usize,
    /// While the last search found nothing (`NotFound`, the fit floor's included), search with only the
    /// latest this many nodes every `retry_every_n_nodes` nodes and after a scheduled retry that found
    /// nothing (count; 0 = off). Default 40. Why: `docs/TUNING.md#ss-recent-search-nodes`.
    pub recent_search_nodes: usize,
    /// A session that starts where the robot's last session ended (its dock: [`SessionStart::from_dock`])
    /// checks that pose with the cloud of its first this many nodes ([`StartSearch::check_prior`]) before
    /// any whole-map search (count ≥ 1). Default 3 (about 0.5 m of driving).
    pub dock_check_nodes: usize,
    /// Stop searching after this many nodes without a placement (count; 0 = never): the session stays
    /// unplaced. Default 0.
    pub give_up_after_nodes: usize,
    /// Independent agreeing matches that commit a placement (count; 0 = commit as soon as placed).
    /// Default 3.
    pub probation_matches: usize,
    /// Two matches are independent when their nodes lie at least this far apart along the route; an
    /// agreeing match must also lie this far past the node the placement was decided at. Metres ≥ 0.
    /// Default 3 m.
    pub probation_min_separation_m: f64,
    /// ... or when less than this share of one node's scan (in cells of 0.3 m of the session's frame) was
    /// seen by the other's; an agreeing match is also past the placement when less than this share of its
    /// scan was seen by the cloud that placed it. Share 0–1 (0 = the route alone decides). Default 0.5:
    /// most of what it sees is new. Why: `docs/TUNING.md#ss-probation-max-view-overlap`.
    pub probation_max_view_overlap: f64,
    /// The agreeing matches that commit a placement must be of at least this many different submaps
    /// (count ≥ 1; capped by `probation_matches`). Default 2.
    pub probation_min_submaps: usize,
    /// A match agrees when the node position it implies lies within this of the node's position under the
    /// placement (plus `agreement_growth` per metre of route). Metres > 0. Default 1 m.
    /// Why: `docs/TUNING.md#ss-agreement-translation-m`.
    pub agreement_translation_m: f64,
    /// ... and its heading within this. Radians > 0. Default 5° (the wrong-placement bound of the scores).
    pub agreement_rotation_rad: f64,
    /// Growth of the translation tolerance per metre of route between the placement's node and the
    /// matched node (LLO's drift), metres per metre ≥ 0. Default 0.01.
    pub agreement_growth: f64,
    /// Growth of the rotation tolerance per metre of route between the placement's node and the matched
    /// node (LLO's heading drift), radians per metre ≥ 0. Default 0.2°/m, GLM's
    /// `angular_window_growth`. Why: `docs/TUNING.md#ss-agreement-rotation-growth`.
    pub agreement_rotation_growth: f64,
    /// Independent disagreeing matches that revoke a placement (count ≥ 1). Default 2: one false match
    /// does not undo a placement, two independent ones do.
    pub probation_disagreements: usize,
    /// Revoke a placement not committed after this much route past its node, metres (0 = never), and
    /// search again. Default 0. Why: `docs/TUNING.md#ss-probation-timeout-m`.
    pub probation_timeout_m: f64,
    /// A search answer within this distance (metres ≥ 0, at the latest node) and `agreement_rotation_rad` of
    /// a revoked placement is refused, unless its paired test against its weakest rival reaches
    /// `probation_min_z`. Default 1 m. Why: `docs/TUNING.md#ss-revoked-radius-m`.
    pub revoked_radius_m: f64,
    /// Before a placement is committed, the session's route must fit it better than each rival its search
    /// ranked below it by this paired test ([`StartSearch::contest`]); a rival as much better revokes it.
    /// Unitless (about standard errors; 0 = no test). Default 4. Why: `docs/TUNING.md#ss-probation-min-z`.
    pub probation_min_z: f64,
    /// Where the route's test against a rival is undecided, test it again in pieces of this much route,
    /// each refined on its own ([`StartSearch::contest_each_in_pieces`]); a rival the pieces beat by
    /// `probation_min_z` is beaten (only the whole route's test overturns). Metres ≥ 0 (0 = off).
    /// Default 4 m. Why: `docs/TUNING.md#ss-contest-piece-m`.
    pub contest_piece_m: f64,
    /// Where a retry's whole-map search leaves its best candidate undecided against some rival by the
    /// route's paired test, test those rivals again in pieces of this much route, each refined on its own
    /// ([`StartSearch::search_again`]); the session is placed (on probation) when each rival is beaten by
    /// either test. Metres ≥ 0 (0 = off). Default 4 m. Why: `docs/TUNING.md#ss-search-piece-m`.
    pub search_piece_m: f64,
    /// While a placement is on probation, no match has agreed with it yet and the latest
    /// `recent_search_nodes` nodes fit the map below `min_unfiltered_score` there, search the whole map
    /// again every `retry_every_n_nodes` nodes (the route since the start, decided as a retry); an answer
    /// elsewhere that the route fits better by `probation_min_z` replaces the placement. Default true.
    /// Why: `docs/TUNING.md#ss-search-while-unconfirmed`.
    pub search_while_unconfirmed: bool,
    /// A session placed at its dock ([`SessionStart::from_dock`], the check agreed) that ends still on
    /// probation, with no disagreeing match and no rival fitting its route decisively better, is committed
    /// at its end ([`SessionStart::finish`]). Default true. Why: `docs/TUNING.md#ss-commit-dock-at-end`.
    pub commit_dock_placement_at_end: bool,
    /// A dock check made before the hold-back whose dock a rival of the whole map fits better (paired z
    /// below 0, short of refusing it) is made again at `hold_back_nodes`, with that larger cloud, instead
    /// of placing the session at once. Default true. Why: `docs/TUNING.md#ss-defer-contested-dock-check`.
    pub defer_contested_dock_check: bool,
}

impl Default for SessionStartOptions {
    fn default() -> Self {
        Self {
            hold_back_nodes: 10,
            retry_every_n_nodes: 20,
            recheck_every_n_nodes: 10,
            max_search_nodes: 400,
            recent_search_nodes: 40,
            dock_check_nodes: 3,
            give_up_after_nodes: 0,
            probation_matches: 3,
            probation_min_separation_m: 3.0,
            probation_max_view_overlap: 0.5,
            probation_min_submaps: 2,
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
