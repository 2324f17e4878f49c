//! Where a session starts in the site map: one state machine for every shell (the offline `lifelong` and
//! `sessions` commands, the fleet agent and the server).
//!
//! A [`SessionStart`] is fed the session's nodes as LLO makes them ([`SessionStart::add_node`]) and, once
//! it has placed the session, the GLM matches of its nodes against the existing map
//! ([`SessionStart::add_match`]); it answers with [`SessionStartEvent`]s and the shell acts on them
//! (places the session in its map, commits or revokes it). It does no I/O and reads no clock; the
//! whole-map searches run on the calling thread through [`StartSearch`]'s public API.
//!
//! 1. **Hold-back.** The first [`SessionStartOptions::hold_back_nodes`] nodes are merged into one cloud
//!    and searched over the whole map ([`StartSearch::search`]: a near-tie with a clearly different pose
//!    is refused as ambiguous).
//! 2. **Retries.** While unplaced, the whole map is searched again with every node since the start (at
//!    most the latest [`SessionStartOptions::max_search_nodes`]) after `retry_every_n_nodes` nodes, then
//!    twice, four times ... as many, never more than [`SessionStartOptions::max_retry_interval_nodes`]
//!    apart ([`StartSearch::search_again`]: placed when the best pose fits the
//!    map well enough and beats every other candidate in the paired test over the route's blocks, or,
//!    where the whole route leaves a rival undecided, in pieces of
//!    [`SessionStartOptions::search_piece_m`] of route each refined on its own). Between them, every
//!    [`SessionStartOptions::recheck_every_n_nodes`] nodes, a cheap test of the last search's
//!    candidates against the grown route ([`StartSearch::route_decides`], whole and in the same pieces)
//!    brings the retry forward when the route already tells them apart. While the last search found
//!    nothing (no pose reached the score, or the best fit the map below its floor: the route lies
//!    largely off the map), the latest [`SessionStartOptions::recent_search_nodes`] nodes are searched
//!    every `retry_every_n_nodes` nodes, so that a session placed nowhere is placed soon after it drives
//!    onto mapped ground. After [`SessionStartOptions::give_up_after_nodes`] the session stops searching.
//! 3. **Probation.** A placement is tentative: the shell places the session so that GLM can match its
//!    nodes near their estimates, but its submaps stay out of the map robots relocalize against and it
//!    trims nothing. The map is told which nodes' scans the search fitted
//!    ([`StartPlacement::fitted_from`]): matches that would move those nodes beyond drift are refused
//!    there, not taken for an LLO slip to repair, so only the matches counted here can overturn a
//!    placement. It is committed once [`SessionStartOptions::probation_matches`] *independent*
//!    matches agree with it: matches of nodes that saw different things — at least
//!    [`SessionStartOptions::probation_min_separation_m`] apart along the route, or whose scans share at
//!    most [`SessionStartOptions::probation_max_view_overlap`] of what the other saw (a robot that turns
//!    sees new walls without driving) — and that saw something the cloud that placed it did not (that far
//!    past the node the placement was decided at, or as little overlap with that cloud), against at least
//!    [`SessionStartOptions::probation_min_submaps`] different submaps (by default one: what makes
//!    matches independent is the route and the view, and a finished submap spans tens of metres). A
//!    match agrees when the node pose it implies lies within `agreement_translation_m` (+
//!    `agreement_growth` per metre of route from the placement's node, for LLO's drift) and
//!    `agreement_rotation_rad` (+ `agreement_rotation_growth` per metre) of the node's pose under the
//!    placement: the same place at the scale of
//!    the look-alike places it must tell apart (an aisle pitch), while GLM refines the pose. Those matches
//!    are searched near the placement, so in a look-alike aisle they agree with a wrong one too: before
//!    committing, the session's route since the start must also fit the placement decisively better than
//!    every rival the placing search ranked below it ([`StartSearch::contest`],
//!    [`SessionStartOptions::probation_min_z`]; where that is undecided, the same test in pieces of the
//!    route, each refined on its own, may decide for the placement: `contest_piece_m`); a rival that fits
//!    decisively better revokes it.
//!    [`SessionStartOptions::probation_disagreements`] independent disagreeing matches, or
//!    `probation_timeout_m` of route without a commit, revoke the placement and searching resumes (a
//!    search that finds a revoked placement again is refused, unless its paired test reaches
//!    `probation_min_z`: matches revoked it, and the whole route now says it is the place).
//!    That test is made only once matches agree, and a wrong placement gets no match near a pose the robot
//!    is not at: while no match has agreed with a placement and the latest nodes fit the map below its
//!    floor there, the whole map is searched again after `retry_every_n_nodes` nodes on probation, then
//!    twice, four times ... as many, never more than
//!    [`SessionStartOptions::max_second_opinion_interval_nodes`] apart
//!    ([`SessionStartOptions::search_while_unconfirmed`]), and an answer elsewhere that the route fits
//!    decisively better replaces it. A look-alike aisle's first matches may agree with a wrong placement
//!    before the route leaves the look-alike part; with
//!    [`SessionStartOptions::second_opinion_after_agreement`] those searches go on after a match agreed.
//!
//! 4. **The session's end.** A placement still on probation is dropped with the session, unless it was
//!    the dock's and nothing disputed it ([`SessionStart::finish`],
//!    [`SessionStartOptions::commit_dock_placement_at_end`]): a robot that leaves its charger for ground
//!    the map does not show yet gets no match to confirm it, and what it mapped joins the map.
//!
//! The trade-off: a correct placement waits a few metres before its submaps update the map (the robot
//! still navigates with it), and matches searched near a wrong estimate in a look-alike aisle can agree
//! with it where the aisles look the same — probation catches a wrong placement only where the route
//! shows what tells the places apart.

use std::collections::VecDeque;

use nalgebra::Point2;

mod probation_timeline;
mod scan_view;
mod session_start_event;
mod session_start_options;

pub use self::probation_timeline::{
    ProbationContest, ProbationMatch, ProbationSecondOpinion, ProbationStep,
};
use self::scan_view::ScanView;
pub use self::session_start_event::{
    RevokeReason, SessionStartEvent, SessionStartState, StartPlacement,
};
pub use self::session_start_options::SessionStartOptions;
use super::relocalization::weakest_of_either;
use super::{
    LifelongEvent, LifelongMap, LifelongOptionsError, PriorCheck, RelocalizationOutcome,
    SessionRelocalization, StartAnswer, StartSearch,
};
use crate::geometry::{Rigid2, Rigid2Ext as _, normalize_angle};
use crate::pose_graph::SubmapId;

/// A match counted toward (or against) a placement: its node's route position, what its node saw (when
/// the node's scan is still held) and its submap.
#[derive(Clone, Debug)]
struct Counted {
    path_m: f64,
    view: Option<ScanView>,
    submap: SubmapId,
}

/// The session-start state machine (see the module docs).
pub struct SessionStart {
    options: SessionStartOptions,
    search: Option<StartSearch>,
    state: SessionStartState,
    /// Per node: `local_from_tracking` and the route length from the first node, metres.
    nodes: Vec<(Rigid2, f64)>,
    /// The latest nodes' `(local_from_tracking, points)`, while the session may still search.
    cloud: VecDeque<(Rigid2, Vec<Point2<f32>>)>,
    /// The node count at which the current search schedule started (0, or a revocation).
    schedule_start: usize,
    searches: usize,
    agreeing: Vec<Counted>,
    disagreeing: Vec<Counted>,
    revoked: Vec<Rigid2>,
    revocations: usize,
    /// The rivals of the search that made the current placement (`global_from_local`).
    rivals: Vec<Rigid2>,
    /// While searching: the best and the other candidates of the last refused search.
    candidates: Vec<Rigid2>,
    /// While searching: the last search answered `NotFound`.
    found_nothing: bool,
    /// What the cloud that made the current placement saw.
    placing_view: ScanView,
    /// Route position (metres) of the latest undecided contest of the current placement.
    contested_at_m: Option<f64>,
    /// Until it is checked: `map_from_tracking` where the robot believes its first node is (its dock).
    dock: Option<Rigid2>,
    /// The node count at which the dock is checked: `dock_check_nodes`, or `hold_back_nodes` once a
    /// contested check was deferred.
    dock_check_at: usize,
    /// The current placement is the dock's (its check agreed).
    placed_at_dock: bool,
    /// Every step of every probation so far ([`Self::probation_timeline`]).
    timeline: Vec<ProbationStep>,
}

impl SessionStart {
    /// A session that searches for its start. `search`: the map prepared for whole-map searches
    /// (`None` when there is no map yet: searches find nothing until [`Self::set_search`]).
    pub fn new(
        options: SessionStartOptions,
        search: Option<StartSearch>,
    ) -> Result<Self, LifelongOptionsError> {
        options.validate()?;
        Ok(Self {
            options,
            search,
            state: SessionStartState::Searching,
            nodes: Vec::new(),
            cloud: VecDeque::new(),
            schedule_start: 0,
            searches: 0,
            agreeing: Vec::new(),
            disagreeing: Vec::new(),
            revoked: Vec::new(),
            revocations: 0,
            rivals: Vec::new(),
            candidates: Vec::new(),
            found_nothing: false,
            placing_view: ScanView::default(),
            contested_at_m: None,
            dock: None,
            dock_check_at: 0,
            placed_at_dock: false,
            timeline: Vec::new(),
        })
    }

    /// A session that starts where the robot believes it is: `map_from_tracking` of its first node (where
    /// its last session ended, at its dock). That pose is checked with the first `dock_check_nodes` nodes
    /// ([`StartSearch::check_prior`]; with the first `hold_back_nodes` when a rival fits those few better:
    /// `defer_contested_dock_check`) and placed there on probation where the evidence agrees; elsewhere
    /// (the robot was carried, the dock moved) the session searches the whole map as [`Self::new`]'s does.
    pub fn from_dock(
        options: SessionStartOptions,
        search: Option<StartSearch>,
        map_from_tracking: Rigid2,
    ) -> Result<Self, LifelongOptionsError> {
        let mut start = Self::new(options, search)?;
        start.dock = Some(map_from_tracking);
        start.dock_check_at = start.options.dock_check_nodes;
        Ok(start)
    }

    /// A session placed elsewhere (a robot's prior, decided at its node `node`), on probation from the
    /// start; committed at once when `probation_matches` is 0. Returns the events of that decision.
    pub fn with_placement(
        options: SessionStartOptions,
        search: Option<StartSearch>,
        global_from_local: Rigid2,
        node: usize,
    ) -> Result<(Self, Vec<SessionStartEvent>), LifelongOptionsError> {
        let mut start = Self::new(options, search)?;
        let placement = StartPlacement {
            global_from_local,
            node,
            fitted_from: None,
            score: None,
            weakest_z: None,
            fit: None,
        };
        let events = start.place(placement, node);
        Ok((start, events))
    }

    /// [`Self::with_placement`] for a robot's dock placement (its own [`Self::from_dock`] check agreed
    /// there): [`Self::finish`] may commit it at the session's end, when the robot says it stands.
    pub fn with_dock_placement(
        options: SessionStartOptions,
        search: Option<StartSearch>,
        global_from_local: Rigid2,
        node: usize,
    ) -> Result<(Self, Vec<SessionStartEvent>), LifelongOptionsError> {
        let (mut start, events) = Self::with_placement(options, search, global_from_local, node)?;
        start.placed_at_dock = matches!(start.state, SessionStartState::Probation(_));
        Ok((start, events))
    }

    /// Hands over the map to search when the session was created without one.
    pub fn set_search(&mut self, search: StartSearch) {
        self.search = Some(search);
    }

    /// Whether a map to search is set.
    pub fn has_search(&self) -> bool {
        self.search.is_some()
    }

    /// Where the session stands.
    pub fn state(&self) -> SessionStartState {
        self.state
    }

    /// The current placement (on probation or committed).
    pub fn placement(&self) -> Option<StartPlacement> {
        match self.state {
            SessionStartState::Probation(p) | SessionStartState::Committed(p) => Some(p),
            _ => None,
        }
    }

    /// Whether the placement is committed.
    pub fn is_committed(&self) -> bool {
        matches!(self.state, SessionStartState::Committed(_))
    }

    /// Whole-map searches made so far.
    pub fn searches(&self) -> usize {
        self.searches
    }

    /// Placements revoked so far.
    pub fn revocations(&self) -> usize {
        self.revocations
    }

    /// Nodes added so far.
    pub fn nodes(&self) -> usize {
        self.nodes.len()
    }

    /// What every probation of the session went through so far, in order: each match judged while a
    /// placement was on probation, each test against the placement's rivals, how each probation ended
    /// (see [`ProbationStep`]). A record for reports; nothing reads it back.
    pub fn probation_timeline(&self) -> &[ProbationStep] {
        &self.timeline
    }

    /// Adds the session's next node (`local_from_tracking` and its points in the tracking frame) and runs
    /// whatever it makes due: the first search once `hold_back_nodes` are in, a retry, a probation
    /// timeout, giving up.
    pub fn add_node(
        &mut self,
        local_pose: Rigid2,
        points: Vec<Point2<f32>>,
    ) -> Vec<SessionStartEvent> {
        let path_m = self.nodes.last().map_or(0.0, |(last, length)| {
            length + (local_pose.translation.vector - last.translation.vector).norm()
        });
        self.nodes.push((local_pose, path_m));
        let node = self.nodes.len() - 1;
        match self.state {
            SessionStartState::Committed(_) | SessionStartState::GaveUp => Vec::new(),
            SessionStartState::Probation(placement) => {
                self.keep_cloud(local_pose, points);
                let timeout = self.options.probation_timeout_m;
                let past = path_m - self.path_at(placement.node).unwrap_or(path_m);
                let every = self.options.retry_every_n_nodes;
                if timeout > 0.0 && past > timeout {
                    self.revoke(placement, RevokeReason::Timeout, node)
                } else if self.options.search_while_unconfirmed
                    && (self.agreeing.is_empty() || self.options.second_opinion_after_agreement)
                    && every > 0
                    && node > placement.node
                    && is_scheduled_retry(
                        node - placement.node,
                        every,
                        self.options.max_second_opinion_interval_nodes,
                    )
                    && self.misfits(&placement)
                {
                    self.second_opinion(placement, node)
                } else {
                    Vec::new()
                }
            }
            SessionStartState::Searching => {
                self.keep_cloud(local_pose, points);
                match self.dock {
                    Some(dock) if node + 1 >= self.dock_check_at => {
                        self.dock = None;
                        let mut events = self.check_dock(dock, node);
                        if events.len() == 1 {
                            // Refused: the whole-map search is made as soon as it is due.
                            events.extend(self.search_if_due(node));
                        }
                        events
                    }
                    Some(_) => Vec::new(),
                    None => self.search_if_due(node),
                }
            }
        }
    }

    /// Feeds [`Self::add_match`] the matches among `events` (of `map`) that judge `session`'s placement:
    /// those of its nodes against other sessions' submaps ([`LifelongEvent::placement_match`]), in the
    /// map frame as the submaps now stand. Every shell that runs a session start on a [`LifelongMap`]
    /// judges its placement through this.
    pub fn add_matches_from(
        &mut self,
        map: &LifelongMap,
        session: u32,
        events: &[LifelongEvent],
    ) -> Vec<SessionStartEvent> {
        let mut decisions = Vec::new();
        for event in events {
            if let Some(closure) = event.placement_match(session)
                && let Some(submap_pose) = map.global().submap_pose(closure.submap)
            {
                decisions.extend(self.add_match(
                    closure.node.index as usize,
                    submap_pose * closure.submap_from_node,
                    closure.submap,
                ));
            }
        }
        decisions
    }

    /// A GLM match of the session's node `node` against the existing map, implying the node's map pose
    /// `map_from_node` (`world_from_tracking`), against `submap`. Counts only while on probation.
    pub fn add_match(
        &mut self,
        node: usize,
        map_from_node: Rigid2,
        submap: SubmapId,
    ) -> Vec<SessionStartEvent> {
        let SessionStartState::Probation(placement) = self.state else {
            return Vec::new();
        };
        let (Some(&(local_pose, path_m)), Some(placed_path)) =
            (self.nodes.get(node), self.path_at(placement.node))
        else {
            return Vec::new();
        };
        let expected = placement.global_from_local * local_pose;
        let route = (path_m - placed_path).abs();
        let translation = (map_from_node.translation.vector - expected.translation.vector).norm();
        let rotation = normalize_angle(map_from_node.theta() - expected.theta()).abs();
        let translation_tolerance =
            self.options.agreement_translation_m + self.options.agreement_growth * route;
        let rotation_tolerance =
            self.options.agreement_rotation_rad + self.options.agreement_rotation_growth * route;
        let agrees = translation <= translation_tolerance && rotation <= rotation_tolerance;
        let counted = Counted {
            path_m,
            view: self.view_of(node),
            submap,
        };
        let separation = self.options.probation_min_separation_m;
        let max_overlap = self.options.probation_max_view_overlap;
        let placing_view_overlap = counted
            .view
            .as_ref()
            .map(|view| view.overlap(&self.placing_view));
        let past_placement = path_m - placed_path >= separation
            || placing_view_overlap.is_some_and(|overlap| overlap < max_overlap);
        let side = if agrees {
            &self.agreeing
        } else {
            &self.disagreeing
        };
        let nearest_counted_m = side
            .iter()
            .map(|c| (c.path_m - path_m).abs())
            .min_by(f64::total_cmp);
        let is_independent = independent(side, &counted, separation, max_overlap);
        let counts = if agrees {
            past_placement && is_independent
        } else {
            is_independent
        };
        if counts {
            if agrees {
                self.agreeing.push(counted);
            } else {
                self.disagreeing.push(counted);
            }
        }
        let mut submaps: Vec<SubmapId> = self.agreeing.iter().map(|c| c.submap).collect();
        submaps.sort_unstable();
        submaps.dedup();
        let at_node = self.nodes.len().saturating_sub(1);
        self.timeline.push(ProbationStep::Match(ProbationMatch {
            at_node,
            node,
            submap,
            past_placing_m: path_m - placed_path,
            translation_m: translation,
            translation_tolerance_m: translation_tolerance,
            rotation_rad: rotation,
            rotation_tolerance_rad: rotation_tolerance,
            agrees,
            placing_view_overlap,
            past_placement,
            nearest_counted_m,
            independent: is_independent,
            counted: counts,
            agreeing: self.agreeing.len(),
            agreeing_submaps: submaps.len(),
            disagreeing: self.disagreeing.len(),
        }));
        if agrees {
            let min_submaps = self
                .options
                .probation_min_submaps
                .min(self.options.probation_matches);
            if self.agreeing.len() >= self.options.probation_matches && submaps.len() >= min_submaps
            {
                return match self.contest(placement, path_m, node) {
                    Contest::Upheld => {
                        self.state = SessionStartState::Committed(placement);
                        self.cloud.clear();
                        self.timeline.push(ProbationStep::Ended {
                            at_node,
                            outcome: "committed",
                        });
                        vec![SessionStartEvent::Committed { placement, node }]
                    }
                    Contest::Overturned => {
                        let last = self.nodes.len().saturating_sub(1);
                        self.revoke(placement, RevokeReason::Rival, last)
                    }
                    Contest::Undecided => Vec::new(),
                };
            }
        } else if counts && self.disagreeing.len() >= self.options.probation_disagreements {
            let last = self.nodes.len().saturating_sub(1);
            return self.revoke(placement, RevokeReason::Disagreement, last);
        }
        Vec::new()
    }

    /// The session ends. A placement still on probation that was the dock's
    /// (`commit_dock_placement_at_end`), with no disagreeing match and no rival of the dock check that the
    /// route fits decisively better (`probation_min_z`), is committed: the robot left its charger for
    /// ground the map does not show yet, and what it mapped there joins the map instead of being dropped.
    /// Any other placement on probation stays as it is (the shell drops it with the session). Returns the
    /// `Committed` event, decided at the last node, or nothing.
    pub fn finish(&mut self) -> Vec<SessionStartEvent> {
        let SessionStartState::Probation(placement) = self.state else {
            return Vec::new();
        };
        if !(self.options.commit_dock_placement_at_end
            && self.placed_at_dock
            && self.disagreeing.is_empty())
        {
            return Vec::new();
        }
        let min_z = self.options.probation_min_z;
        if let Some(search) = &self.search
            && min_z > 0.0
            && !self.rivals.is_empty()
            && search
                .contest(
                    self.cloud.make_contiguous(),
                    &placement.global_from_local,
                    &self.rivals,
                )
                .is_some_and(|z| z <= -min_z)
        {
            return Vec::new();
        }
        let node = self.nodes.len().saturating_sub(1);
        self.state = SessionStartState::Committed(placement);
        self.cloud.clear();
        self.timeline.push(ProbationStep::Ended {
            at_node: node,
            outcome: "committed",
        });
        vec![SessionStartEvent::Committed { placement, node }]
    }

    /// Whether the latest `recent_search_nodes` nodes fit the unfiltered map below its floor at `placement`
    /// ([`StartSearch::fit`], unrefined): the robot does not see what the map shows where the placement
    /// puts it.
    fn misfits(&mut self, placement: &StartPlacement) -> bool {
        let Some(search) = &self.search else {
            return false;
        };
        let scans = self.cloud.make_contiguous();
        let latest = &scans[scans
            .len()
            .saturating_sub(self.options.recent_search_nodes.max(1))..];
        search
            .fit(latest, &placement.global_from_local)
            .is_some_and(|fit| !search.fits(fit.sharp_score))
    }

    /// While no match has agreed with `placement` yet (or while it is on probation at all, with
    /// `second_opinion_after_agreement`), a whole-map search of the route since the start
    /// (of its latest `recent_search_nodes` where that finds nothing), decided as a retry. An answer away
    /// from the placement that the route fits decisively better ([`StartSearch::contest`],
    /// `probation_min_z`) replaces it: the placement is revoked (`Rival`) and the answer placed, on
    /// probation, with the revoked placement among its rivals.
    fn second_opinion(&mut self, placement: StartPlacement, node: usize) -> Vec<SessionStartEvent> {
        let Some(search) = &self.search else {
            return Vec::new();
        };
        let recent = self.options.recent_search_nodes;
        let scans = self.cloud.make_contiguous();
        let latest = scans
            .last()
            .map_or_else(Rigid2::identity, |(pose, _)| *pose);
        let piece_m = self.options.search_piece_m;
        let mut route_nodes = scans.len();
        let mut answer = search.search_again(scans, piece_m);
        if matches!(answer.outcome, RelocalizationOutcome::NotFound)
            && recent > 0
            && recent < scans.len()
        {
            route_nodes = recent;
            answer = search.search_again(&scans[scans.len() - recent..], piece_m);
        }
        self.searches += 1;
        let mut step = ProbationSecondOpinion {
            at_node: node,
            route_nodes,
            answer_offset: None,
            z: None,
            decision: "not_found",
        };
        let found = match answer.outcome {
            RelocalizationOutcome::Found(found) => found,
            RelocalizationOutcome::Ambiguous { .. } => {
                step.decision = "ambiguous";
                self.timeline.push(ProbationStep::SecondOpinion(step));
                return Vec::new();
            }
            RelocalizationOutcome::NotFound => {
                self.timeline.push(ProbationStep::SecondOpinion(step));
                return Vec::new();
            }
        };
        step.answer_offset = Some(rival_offset(
            &placement.global_from_local,
            &found.global_from_local,
            &latest,
        ));
        let same_place = self.same_place(
            &placement.global_from_local,
            &found.global_from_local,
            self.options.agreement_translation_m,
        );
        if same_place
            || (self.repeats_revoked(&found.global_from_local)
                && !self.overrules_revocation(answer.weakest_z))
        {
            step.decision = if same_place {
                "same_place"
            } else {
                "revoked_before"
            };
            self.timeline.push(ProbationStep::SecondOpinion(step));
            return Vec::new();
        }
        let z = search.contest(
            self.cloud.make_contiguous(),
            &found.global_from_local,
            &[placement.global_from_local],
        );
        step.z = z;
        if !z.is_some_and(|z| z >= self.options.probation_min_z) {
            step.decision = "undecided";
            self.timeline.push(ProbationStep::SecondOpinion(step));
            return Vec::new();
        }
        step.decision = "replaced";
        self.timeline.push(ProbationStep::SecondOpinion(step));
        let mut events = self.revoke(placement, RevokeReason::Rival, node);
        let mut rivals = answer.rivals;
        rivals.push(placement.global_from_local);
        let fitted_from = self.nodes.len() - route_nodes;
        events.extend(self.place_answer(
            &found,
            answer.weakest_z,
            answer.fit,
            rivals,
            node,
            fitted_from,
        ));
        events
    }

    /// Places the session on probation at a search's answer `found`, decided at `node` with the cloud of
    /// the nodes from `fitted_from`, with the search's other candidates as its `rivals`: the `Placed`
    /// event and what placing decides.
    fn place_answer(
        &mut self,
        found: &SessionRelocalization,
        weakest_z: Option<f64>,
        fit: Option<f32>,
        rivals: Vec<Rigid2>,
        node: usize,
        fitted_from: usize,
    ) -> Vec<SessionStartEvent> {
        let placement = StartPlacement {
            global_from_local: found.global_from_local,
            node,
            fitted_from: Some(fitted_from),
            score: Some(found.score),
            weakest_z,
            fit,
        };
        self.rivals = rivals;
        self.candidates.clear();
        let mut events = vec![SessionStartEvent::Placed(placement)];
        events.extend(self.place(placement, node));
        events
    }

    /// Tests `placement` against its search's rivals with the session's cloud (`probation_min_z`), at
    /// most once per `probation_min_separation_m` of route (`path_m`: the matched node's, `node`) while
    /// undecided.
    fn contest(&mut self, placement: StartPlacement, path_m: f64, node: usize) -> Contest {
        let min_z = self.options.probation_min_z;
        let mut step = ProbationContest {
            at_node: self.nodes.len().saturating_sub(1),
            node,
            route_nodes: self.cloud.len(),
            z: Vec::new(),
            piece_z: Vec::new(),
            min_z,
            decision: "upheld",
        };
        let (Some(search), false) = (&self.search, min_z == 0.0 || self.rivals.is_empty()) else {
            self.timeline.push(ProbationStep::Contest(step));
            return Contest::Upheld;
        };
        if self
            .contested_at_m
            .is_some_and(|at| path_m - at < self.options.probation_min_separation_m)
        {
            step.decision = "skipped";
            self.timeline.push(ProbationStep::Contest(step));
            return Contest::Undecided;
        }
        let scans = self.cloud.make_contiguous();
        step.z = search.contest_each(scans, &placement.global_from_local, &self.rivals);
        // `StartSearch::contest`: the weakest of the tests.
        let weakest = step.z.iter().flatten().copied().min_by(f64::total_cmp);
        let undecided = weakest.is_some_and(|z| z > -min_z && z < min_z);
        if undecided && self.options.contest_piece_m > 0.0 {
            step.piece_z = search.contest_each_in_pieces(
                scans,
                &placement.global_from_local,
                &self.rivals,
                self.options.contest_piece_m,
            );
        }
        // A rival is beaten by the whole route's test or by its pieces'.
        let weakest_beaten = weakest_of_either(&step.z, &step.piece_z);
        let (contest, decision) = match (weakest, weakest_beaten) {
            (None, _) => (Contest::Upheld, "upheld"),
            (Some(z), _) if z <= -min_z => (Contest::Overturned, "overturned"),
            (_, Some(z)) if z >= min_z => (Contest::Upheld, "upheld"),
            _ => {
                self.contested_at_m = Some(path_m);
                (Contest::Undecided, "undecided")
            }
        };
        step.decision = decision;
        self.timeline.push(ProbationStep::Contest(step));
        contest
    }

    /// What node `node` saw, while its scan is among the latest held in the cloud (`None` for a scan
    /// without points: it is no view of anything).
    fn view_of(&self, node: usize) -> Option<ScanView> {
        let first_held = self.nodes.len().checked_sub(self.cloud.len())?;
        let (pose, points) = self.cloud.get(node.checked_sub(first_held)?)?;
        (!points.is_empty()).then(|| ScanView::of([(pose, points.as_slice())]))
    }

    fn path_at(&self, node: usize) -> Option<f64> {
        self.nodes.get(node).map(|(_, path)| *path)
    }

    fn keep_cloud(&mut self, local_pose: Rigid2, points: Vec<Point2<f32>>) {
        if self.cloud.len() >= self.options.max_search_nodes {
            self.cloud.pop_front();
        }
        self.cloud.push_back((local_pose, points));
    }

    /// The first search at `hold_back_nodes`, retries on the doubling schedule, giving up.
    fn search_if_due(&mut self, node: usize) -> Vec<SessionStartEvent> {
        let count = node + 1;
        let since = count - self.schedule_start;
        let give_up = self.options.give_up_after_nodes;
        if give_up > 0 && since >= give_up {
            self.state = SessionStartState::GaveUp;
            self.cloud.clear();
            return vec![SessionStartEvent::GaveUp { node }];
        }
        let first = self.searches == 0 && count >= self.options.hold_back_nodes;
        let every = self.options.retry_every_n_nodes;
        let retry_step = self.searches > 0 && every > 0 && since.is_multiple_of(every);
        let scheduled =
            retry_step && is_scheduled_retry(since, every, self.options.max_retry_interval_nodes);
        let recent = self.options.recent_search_nodes;
        let arrival = retry_step && self.found_nothing && recent > 0;
        let recheck = self.options.recheck_every_n_nodes;
        let retry = scheduled
            || (self.searches > 0
                && recheck > 0
                && since.is_multiple_of(recheck)
                && self.candidates.len() > 1
                && self.search.as_ref().is_some_and(|search| {
                    search.route_decides(
                        self.cloud.make_contiguous(),
                        &self.candidates,
                        self.options.search_piece_m,
                    )
                }));
        if !(first || retry || arrival) {
            return Vec::new();
        }
        self.searches += 1;
        // The answer and how many of the latest nodes the cloud it came from held.
        let (answer, route_nodes) = match &self.search {
            None => (
                StartAnswer {
                    outcome: RelocalizationOutcome::NotFound,
                    best: None,
                    rivals: Vec::new(),
                    weakest_z: None,
                    fit: None,
                },
                0,
            ),
            Some(search) => {
                let scans = self.cloud.make_contiguous();
                let latest = &scans[scans.len().saturating_sub(recent)..];
                let piece_m = self.options.search_piece_m;
                if first {
                    (search.search(scans), scans.len())
                } else if retry {
                    let answer = search.search_again(scans, piece_m);
                    if matches!(answer.outcome, RelocalizationOutcome::NotFound)
                        && recent > 0
                        && latest.len() < scans.len()
                    {
                        (search.search_again(latest, piece_m), latest.len())
                    } else {
                        (answer, scans.len())
                    }
                } else {
                    (search.search_again(latest, piece_m), latest.len())
                }
            }
        };
        self.found_nothing = matches!(answer.outcome, RelocalizationOutcome::NotFound);
        // The cloud's frame is its first node's local frame, which the search resolves: `found` is
        // already `global_from_local` of the session's LLO frame.
        match answer.outcome {
            RelocalizationOutcome::Found(found)
                if !self.repeats_revoked(&found.global_from_local)
                    || self.overrules_revocation(answer.weakest_z) =>
            {
                let fitted_from = self.nodes.len() - route_nodes;
                self.place_answer(
                    &found,
                    answer.weakest_z,
                    answer.fit,
                    answer.rivals,
                    node,
                    fitted_from,
                )
            }
            outcome => {
                // A revoked placement is no candidate: the recheck would bring it back every time.
                self.candidates = answer
                    .best
                    .into_iter()
                    .chain(answer.rivals)
                    .filter(|c| !self.repeats_revoked(c))
                    .collect();
                vec![SessionStartEvent::Refused {
                    node,
                    outcome,
                    weakest_z: answer.weakest_z,
                    best: answer.best,
                    fit: answer.fit,
                }]
            }
        }
    }

    /// Checks the dock `map_from_tracking` (of the first node) with the cloud so far: a `DockChecked`
    /// event, followed by `Placed` (and what placing decides) where the evidence agrees.
    fn check_dock(&mut self, map_from_tracking: Rigid2, node: usize) -> Vec<SessionStartEvent> {
        let Some(&(first_local, _)) = self.nodes.first() else {
            return Vec::new();
        };
        let prior = map_from_tracking * first_local.inverse();
        let check: Option<PriorCheck> = self
            .search
            .as_ref()
            .and_then(|search| search.check_prior(self.cloud.make_contiguous(), &prior));
        let checked = SessionStartEvent::DockChecked {
            node,
            agreed: check.as_ref().is_some_and(|c| c.agrees),
            fit: check.as_ref().map(|c| c.fit),
            weakest_z: check.as_ref().and_then(|c| c.weakest_z),
        };
        if check.as_ref().is_some_and(|check| self.defers(check, node)) {
            self.dock = Some(map_from_tracking);
            self.dock_check_at = self.options.hold_back_nodes;
            return Vec::new();
        }
        match check {
            Some(check) if check.agrees => {
                let placement = StartPlacement {
                    global_from_local: check.global_from_local,
                    node,
                    fitted_from: Some(self.nodes.len() - self.cloud.len()),
                    score: None,
                    weakest_z: check.weakest_z,
                    fit: Some(check.fit),
                };
                self.rivals = check.rivals;
                self.candidates.clear();
                let mut events = vec![checked, SessionStartEvent::Placed(placement)];
                events.extend(self.place(placement, node));
                self.placed_at_dock = true;
                events
            }
            _ => vec![checked],
        }
    }

    /// Whether a dock `check` made at node `node` waits for the hold-back's cloud
    /// (`defer_contested_dock_check`): it agreed, a rival fits the few nodes better (short of refusing
    /// the dock), and the hold-back is still ahead.
    fn defers(&self, check: &PriorCheck, node: usize) -> bool {
        check.agrees
            && self.options.defer_contested_dock_check
            && check.weakest_z.is_some_and(|z| z < 0.0)
            && node + 1 < self.options.hold_back_nodes
    }

    /// Enters probation on `placement` (or commits it when no match is asked for); the `Placed` event
    /// is the caller's to emit.
    fn place(&mut self, placement: StartPlacement, node: usize) -> Vec<SessionStartEvent> {
        self.placed_at_dock = false;
        self.agreeing.clear();
        self.disagreeing.clear();
        self.placing_view = ScanView::of(
            self.cloud
                .iter()
                .map(|(pose, points)| (pose, points.as_slice())),
        );
        self.contested_at_m = None;
        if self.options.probation_matches == 0 {
            self.state = SessionStartState::Committed(placement);
            self.cloud.clear();
            return vec![SessionStartEvent::Committed { placement, node }];
        }
        self.state = SessionStartState::Probation(placement);
        let placed_node = self
            .cloud
            .back()
            .map_or_else(Rigid2::identity, |(pose, _)| *pose);
        let rival_offsets = self
            .rivals
            .iter()
            .map(|rival| rival_offset(&placement.global_from_local, rival, &placed_node))
            .collect();
        self.timeline.push(ProbationStep::Began {
            at_node: node,
            rival_offsets,
        });
        Vec::new()
    }

    fn revoke(
        &mut self,
        placement: StartPlacement,
        reason: RevokeReason,
        node: usize,
    ) -> Vec<SessionStartEvent> {
        self.revoked.push(placement.global_from_local);
        self.revocations += 1;
        self.timeline.push(ProbationStep::Ended {
            at_node: node,
            outcome: reason.as_str(),
        });
        self.rivals.clear();
        self.agreeing.clear();
        self.disagreeing.clear();
        self.state = SessionStartState::Searching;
        // Retries count again from here; the first search was made, so the next one is `search_again`.
        self.schedule_start = node + 1;
        self.searches = self.searches.max(1);
        vec![SessionStartEvent::Revoked {
            placement,
            reason,
            node,
        }]
    }

    /// Whether a search's paired test (`weakest_z`) is strong enough to place a session where a placement
    /// was revoked: it must reach `probation_min_z`, the route-wide test a placement passes before it is
    /// committed (never when that test is off or the search had no rival to test against).
    fn overrules_revocation(&self, weakest_z: Option<f64>) -> bool {
        let bar = self.options.probation_min_z;
        bar > 0.0 && weakest_z.is_some_and(|z| z >= bar)
    }

    /// Whether `global_from_local` puts the latest node within `revoked_radius_m` and
    /// `agreement_rotation_rad` of where a revoked placement put it.
    fn repeats_revoked(&self, global_from_local: &Rigid2) -> bool {
        self.revoked.iter().any(|revoked| {
            self.same_place(global_from_local, revoked, self.options.revoked_radius_m)
        })
    }

    /// Whether two placements (`global_from_local`) put the latest node within `radius_m` and
    /// `agreement_rotation_rad` of each other.
    fn same_place(&self, a: &Rigid2, b: &Rigid2, radius_m: f64) -> bool {
        let Some(&(local, _)) = self.nodes.last() else {
            return false;
        };
        let (here, there) = (a * local, b * local);
        (here.translation.vector - there.translation.vector).norm() <= radius_m
            && normalize_angle(here.theta() - there.theta()).abs()
                <= self.options.agreement_rotation_rad
    }
}

/// What [`SessionStart::contest`] decided.
enum Contest {
    /// The placement fits the route decisively better than every rival (or there is none to test).
    Upheld,
    /// A rival fits it decisively better.
    Overturned,
    /// Neither yet.
    Undecided,
}

/// Whether `candidate` is independent of every match in `counted`: at least `separation` metres from it
/// along the route, or less than `max_overlap` of its view seen by that match's node.
fn independent(
    counted: &[Counted],
    candidate: &Counted,
    separation: f64,
    max_overlap: f64,
) -> bool {
    counted.iter().all(|c| {
        (c.path_m - candidate.path_m).abs() >= separation
            || matches!((&candidate.view, &c.view), (Some(a), Some(b)) if a.overlap(b) < max_overlap)
    })
}

/// Where `rival` (a `global_from_local`) puts the robot at `local_pose`, seen from where `placed` puts
/// it: `[x, y]` metres and heading in degrees ([`ProbationStep::Began`]'s `rival_offsets`).
fn rival_offset(placed: &Rigid2, rival: &Rigid2, local_pose: &Rigid2) -> [f64; 3] {
    let offset = (placed * local_pose).inverse() * (rival * local_pose);
    [
        offset.translation.vector.x,
        offset.translation.vector.y,
        offset.rotation.angle().to_degrees(),
    ]
}

/// Whether a retry is due `since` nodes into the schedule: at `every`, then each time after as many nodes
/// as the schedule has run (20, 40, 80, 160 ...), but never more than `cap` nodes apart (0 = no cap:
/// with 40, 20, 40, 80, 120, 160 ...).
fn is_scheduled_retry(since: usize, every: usize, cap: usize) -> bool {
    let mut due = every;
    while due < since {
        due += if cap > 0 { due.min(cap) } else { due };
    }
    due == since
}

#[cfg(test)]
mod tests;
