//! Lifelong multi-session mapping: one site's map kept up to date by many sessions (robot runs) without
//! growing without bound (Zhao et al., "A General Framework for Lifelong Localization and Mapping in
//! Changing Environment", IROS 2021, §III–IV).
//!
//! A [`LifelongMap`] wraps [`GlobalSlam`](crate::global_slam::GlobalSlam) with one trajectory per session:
//!
//! 1. **Sessions.** The first session maps the site; its submaps are never trimmed. Every later session
//!    starts with a relocalized prior ([`relocalize_session_start`]) or, failing that, with none (its
//!    nodes are then matched against whole submaps until one match places it). Its nodes get GLM
//!    constraints to the older sessions' finished submaps, which is how it localizes, while LLO's fresh
//!    submaps join the graph.
//! 2. **Trimming** ([`SubmapTrimmerOptions`], `submap_trimmer.rs`). When a session ends, each stale
//!    submap (of an older session other than the first) whose cells are, for more than
//!    `min_covered_fraction` of them, covered by at least `K` fresher submaps is trimmed, cell by cell
//!    as Cartographer's overlapping-submaps trimmer counts coverage.
//! 3. **Sparsification** ([`TrimPolicy`]). A trimmed submap and the nodes that only it holds are
//!    marginalized and replaced by the Chow–Liu tree over their Markov blanket
//!    ([`crate::sparsification`], policy `clt`), or simply deleted with every constraint touching them
//!    (`delete`, Cartographer's behaviour). `keep` trims nothing (the graph grows without bound) and
//!    `frozen` never changes the first session's map (later sessions only localize against it and are
//!    dropped when they end). The trees are built at the optimum of the session's final optimization;
//!    by default nothing re-optimizes after the trims (the next session's optimizations do). With
//!    `optimize_every_n_sparsifications` ≥ 1 (the paper's 5) the graph is re-optimized, with at most
//!    `sparsification_max_iterations` steps, after a session's batch of trims once that many
//!    sparsifications have accumulated.
//!
//! Everything here is pure: no I/O, clocks or threads. Search jobs ([`LifelongMap::take_search_jobs`])
//! are run by the caller, anywhere, with [`LifelongMap::constraint_builder`].

mod lifelong_map;
mod live_anchor;
pub(crate) mod map_change;
mod map_matcher;
mod options;
mod relocalization;
mod relocalization_map;
mod session_start;
mod submap_render;
mod submap_trimmer;
#[cfg(test)]
mod tests;

pub use lifelong_map::{
    ConstraintKindCounts, GraphCounts, LifelongError, LifelongEvent, LifelongMap, LifelongMapState,
    SessionProgress,
};
pub use live_anchor::{LiveAnchor, LiveAnchorNoise};
pub use map_change::{
    CellChange, MAP_CHANGE_TOLERANCE_M, MapChange, OCCUPIED_PROBABILITY, map_change_rate,
};
pub use map_matcher::{GlobalSubmap, MapMatch, MapMatcher};
pub use options::{
    LifelongOptions, LifelongOptionsError, ParseTrimPolicyError, SubmapTrimmerOptions, TrimPolicy,
};
pub use relocalization::{
    CloudFit, PriorCheck, RelocalizationOptions, RelocalizationOutcome, SearchEvidence,
    SessionRelocalization, StartAnswer, StartSearch, relocalize_session_start,
};
pub use relocalization_map::{MapCells, render_relocalization_map};
pub use session_start::{
    ProbationContest, ProbationMatch, ProbationSecondOpinion, ProbationStep, RevokeReason,
    SessionStart, SessionStartEvent, SessionStartOptions, SessionStartState, StartPlacement,
};
pub use submap_render::{render_submaps_log_odds, render_submaps_max, render_submaps_newest};
pub use submap_trimmer::{PlacedGrid, covered_fraction};
