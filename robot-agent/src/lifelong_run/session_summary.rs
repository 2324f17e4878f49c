//! What happened in one session, for the report: [`SessionSummary`] and the figures it holds.

use mapping::lifelong::{GraphCounts, ProbationStep};
use mapping::sensor::Timestamp;
use serde::Serialize;

/// One optimization's figures in a [`SessionSummary`].
#[derive(Clone, Debug, Serialize)]
pub struct OptimizationFigures {
    /// Levenberg-Marquardt steps tried.
    pub iterations: usize,
    /// Steps accepted.
    pub accepted_steps: usize,
    /// χ² before and after (robust losses ignored).
    pub chi2: [f64; 2],
    /// Why it stopped.
    pub termination: String,
    /// Poses it moved.
    pub free_variables: usize,
    /// Values stored for its Cholesky factor, fill-in included: with `free_variables`, what each step
    /// costs.
    pub factor_nonzeros: usize,
}

impl SessionSummary {
    /// Levenberg-Marquardt steps tried at the session's end (each one numeric factorization), over every
    /// optimization `finish_ms` covers.
    pub fn finish_iterations(&self) -> usize {
        self.finish_optimizations.iter().map(|o| o.iterations).sum()
    }

    /// The largest Cholesky factor (values stored) of the session end's optimizations; 0 if none
    /// factorized.
    pub fn finish_factor_nonzeros(&self) -> usize {
        self.finish_optimizations
            .iter()
            .map(|o| o.factor_nonzeros)
            .max()
            .unwrap_or(0)
    }
}

/// The check of a robot's dock at a session's start ([`SessionStartEvent::DockChecked`]).
///
/// [`SessionStartEvent::DockChecked`]: mapping::lifelong::SessionStartEvent::DockChecked
#[derive(Clone, Debug, Serialize)]
pub struct DockCheckFigures {
    /// Whether the evidence agreed with the dock (the session was placed there, on probation).
    pub agreed: bool,
    /// How well the first nodes' cloud fit the map at the dock (mean probability).
    pub fit: Option<f32>,
    /// The dock's weakest paired test against the whole map's other candidates (positive: the dock fits
    /// better).
    pub weakest_z: Option<f64>,
}

/// One whole-map search of a session start in a [`SessionSummary`].
#[derive(Clone, Debug, Serialize)]
pub struct SearchFigures {
    /// The node it was made at (index in the session).
    pub node: usize,
    /// `placed`, `ambiguous`, `not_found` or `revoked_again` (it found a revoked placement).
    pub outcome: &'static str,
    /// Its paired test of the best against the weakest rival (`None` for the first search, which ranks
    /// by score margin).
    pub weakest_z: Option<f64>,
    /// How well its cloud fit the map at its best candidate (mean probability on the unfiltered map, the
    /// score the fit floor `min_unfiltered_score` judges; `None` without a candidate, or where the
    /// first search refused its best as ambiguous by score margin before judging the fit).
    pub fit: Option<f32>,
    /// How far its best candidate (the placement, for `placed`) put the session's latest node from the
    /// truth, metres (filled in by the scoring shell; `None` without a candidate or truth).
    pub best_error_m: Option<f64>,
}

/// One step of the session start's probation ([`ProbationStep`]: a match judged, a test against the
/// placement's rivals, a whole-map search made while it misfit, the probation's end) and when it was taken.
#[derive(Clone, Debug, Serialize)]
pub struct ProbationStepFigures {
    /// Time of the session's latest node when it was taken, seconds after the session's first event
    /// (the clock of the scores' `placed_after_s` and `committed_after_s`).
    pub time_s: Option<f64>,
    /// The step, as the session start recorded it.
    #[serde(flatten)]
    pub step: ProbationStep,
}

impl ProbationStepFigures {
    /// `steps` ([`SessionStart::probation_timeline`]) timed by their latest node's time (`node_times`,
    /// by node index) after `start_time`.
    ///
    /// [`SessionStart::probation_timeline`]: mapping::lifelong::SessionStart::probation_timeline
    pub fn timed(
        steps: &[ProbationStep],
        node_times: &[Timestamp],
        start_time: Timestamp,
    ) -> Vec<Self> {
        steps
            .iter()
            .map(|step| {
                let at_node = match step {
                    ProbationStep::Began { at_node, .. } | ProbationStep::Ended { at_node, .. } => {
                        *at_node
                    }
                    ProbationStep::Match(m) => m.at_node,
                    ProbationStep::Contest(c) => c.at_node,
                    ProbationStep::SecondOpinion(o) => o.at_node,
                };
                Self {
                    time_s: node_times
                        .get(at_node)
                        .map(|time| time.seconds_since(start_time)),
                    step: step.clone(),
                }
            })
            .collect()
    }
}

/// What happened in one session.
#[derive(Clone, Debug, Default, Serialize)]
pub struct SessionSummary {
    /// Session id (0, 1, …).
    pub session: u32,
    /// First data time of the session's span.
    pub start_time: Timestamp,
    /// Scans in the span.
    pub scans: usize,
    /// Nodes the session added.
    pub nodes_added: usize,
    /// Whether the first whole-map search (after the hold-back) placed the session (always false for
    /// session 0).
    pub relocalized: bool,
    /// Whole-map searches after the first (retries while the session was unplaced).
    pub relocalization_retries: usize,
    /// The node index at which a retry placed the session (tentatively), if one did.
    pub placed_by_retry_at_node: Option<usize>,
    /// The node index at which the session's placement was committed (probation passed), if it was.
    pub committed_at_node: Option<usize>,
    /// Placements revoked during the session (probation failed: `disagreement` or `timeout`), in order.
    pub revoked: Vec<String>,
    /// Whether the session ended with its placement still on probation (then dropped, like an unplaced
    /// session).
    pub ended_on_probation: bool,
    /// The time of that node: the session was not localized before it.
    pub placed_at_time: Option<Timestamp>,
    /// Its branch-and-bound score.
    pub relocalization_score: Option<f32>,
    /// Why session-start relocalization was refused: `ambiguous` (a clearly different pose scored within
    /// the margin), `not_found` (nothing reached the minimum score); `None` when it placed the session.
    pub relocalization_refused: Option<String>,
    /// When refused as ambiguous, the best and the runner-up scores.
    pub relocalization_ambiguity: Option<[f32; 2]>,
    /// When refused as ambiguous, the runner-up pose in the best pose's frame `[x, y, θ]` (m, m, rad).
    pub relocalization_runner_up_from_best: Option<[f64; 3]>,
    /// Wall time of the first whole-map search, milliseconds.
    pub relocalization_ms: f64,
    /// Wall time of every whole-map search of the session, milliseconds.
    pub relocalization_ms_total: f64,
    /// Distance (m) between the relocalized pose of the session's first node and its final estimate
    /// (how far off relocalization was, judged by the finished map).
    pub relocalization_offset_m: Option<f64>,
    /// Whether the session ended placed in the map with its placement committed.
    pub placed: bool,
    /// GLM constraints accepted during the session between its nodes and older sessions' submaps.
    pub cross_session_closures: usize,
    /// GLM constraints accepted during the session in all.
    pub closures: usize,
    /// Stale submaps trimmed when the session ended.
    pub trimmed: usize,
    /// The session's own submaps dropped when it ended, since it does not update the map (never placed;
    /// `frozen`).
    pub dropped: usize,
    /// Nodes removed with them.
    pub nodes_trimmed: usize,
    /// Chow–Liu tree constraints added in their place.
    pub tree_edges: usize,
    /// Mean KL divergence (nats) of the trims that measured one (`clt`: over each blanket).
    pub trim_kld_mean: Option<f64>,
    /// Mean score of the closures accepted during the session, within it and against older sessions.
    pub ams: f64,
    /// Mean score of the accepted matches of the session's nodes against older sessions' submaps (the
    /// paper's AMS: how well the session matches the map it localizes in); `None` when there was none.
    pub cross_session_ams: Option<f64>,
    /// Graph size after the session ended.
    pub counts: GraphCounts,
    /// Wall time of pose graph refinement at the session's end (`finish_session`: the final
    /// optimization, trimming, sparsification, as the server runs it), milliseconds.
    pub finish_ms: f64,
    /// CPU time of that refinement on the thread that ran it, milliseconds (what it costs, however
    /// loaded the machine is; `None` where the platform does not report it).
    pub finish_cpu_ms: Option<f64>,
    /// Each optimization `finish_ms` covers, in order (the session's final one, then, where
    /// `optimize_every_n_sparsifications` ≥ 1, one after its trims once that many have accumulated):
    /// where the steps went.
    pub finish_optimizations: Vec<OptimizationFigures>,
    /// Every whole-map search of the session start, in order: what it answered and how decisively.
    pub searches: Vec<SearchFigures>,
    /// What the session start's probations went through, step by step: each match of the session's
    /// nodes against older sessions judged while its placement was on probation (agreed? counted? held
    /// back by which condition?), each test of the route against the placement's rivals, each end.
    pub probation_timeline: Vec<ProbationStepFigures>,
    /// Where the session started from the robot's dock ([`SessionInput::from_dock`]): the check of it.
    ///
    /// [`SessionInput::from_dock`]: super::SessionInput::from_dock
    pub dock_check: Option<DockCheckFigures>,
    /// Time of the session's first node (the one relocalization places).
    pub first_node_time: Option<Timestamp>,
    /// Global pose `[x, y, θ]` (m, m, rad) relocalization gave the session's first node.
    pub relocalized_first_pose: Option<[f64; 3]>,
    /// Peak resident memory of the process when the session ended, MB (Linux only).
    pub peak_rss_mb: Option<f64>,
    /// Resident memory of the process when the session ended, MB (Linux only): unlike the peak, it
    /// falls when memory is given back, so a trend over sessions shows in it.
    pub rss_mb: Option<f64>,
}
