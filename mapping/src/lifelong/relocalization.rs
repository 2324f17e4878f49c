//! Session-start relocalization: where a new session's LLO frame sits in the map, with no prior.
//!
//! The finished submaps are rendered into one grid in the map frame ([`render_relocalization_map`], each
//! cell as [`RelocalizationOptions::map_cells`] says: by default the newest view of it); the first
//! few scans of the session are merged into one cloud in the first scan's frame (LLO is accurate over a
//! few metres, and a wider cloud is far more distinctive than one scan); the coarse-to-fine
//! [`Relocalizer`] searches it over the whole grid and every rotation (branch and bound on a 4× coarser
//! max-grid, then on the full grid around the best few candidates; again on a 2× coarser one when the
//! first could not rank its candidates, see [`RelocalizationOptions::coarse_factors`]), scoring against the map max-filtered
//! by [`RelocalizationOptions::match_tolerance`] so that goods that moved a little still count, and the
//! winner is refined on the unfiltered map. A near-tie with a clearly different pose is refused
//! ([`RelocalizationOutcome::Ambiguous`]); [`StartSearch::search_again`] then searches again with every
//! scan since the start until one pose wins a paired per-point test. Cost: one precomputation over the
//! rendered map per coarse factor plus one coarse and a few local searches per attempt.

use nalgebra::Point2;

mod relocalization_options;
mod start_search;

pub use relocalization_options::RelocalizationOptions;
pub(in crate::lifelong) use start_search::weakest_of_either;
pub use start_search::{CloudFit, PriorCheck, SearchEvidence, StartSearch};

use super::LifelongMap;
use crate::geometry::Rigid2;
use crate::grid::ProbabilityGrid;
use crate::local_slam::voxel_filter;

/// Where a session starts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SessionRelocalization {
    /// `global_from_local` of the session's LLO frame.
    pub global_from_local: Rigid2,
    /// Branch-and-bound score of the merged cloud (against the map max-filtered by
    /// [`RelocalizationOptions::match_tolerance`]).
    pub score: f32,
}

/// What a relocalization attempt found, refusals included (for reports).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RelocalizationOutcome {
    /// Placed.
    Found(SessionRelocalization),
    /// The best pose reached `min_score` but a clearly different pose scored within `min_score_margin`.
    Ambiguous {
        /// Score of the best pose.
        score: f32,
        /// Score of the best clearly different pose.
        runner_up_score: f32,
        /// Where that pose lies in the best pose's frame: `[x, y, θ]` (m, m, rad) — along a corridor, a
        /// neighbouring aisle, turned around.
        runner_up_from_best: [f64; 3],
    },
    /// No pose reached `min_score`, or there was nothing to match (no map, no points).
    NotFound,
}

impl RelocalizationOutcome {
    /// The placement, if found.
    pub fn found(self) -> Option<SessionRelocalization> {
        match self {
            Self::Found(f) => Some(f),
            _ => None,
        }
    }
}

/// A session-start search's outcome and the rivals it ranked below its answer: where the session's
/// LLO frame would sit (`global_from_local`) at every other distinct candidate. Probation tests a
/// placement against them again once the session has driven on ([`StartSearch::contest`]).
#[derive(Clone, Debug, PartialEq)]
pub struct StartAnswer {
    /// What the search found.
    pub outcome: RelocalizationOutcome,
    /// `global_from_local` at the best candidate (placed or not; `None` when nothing was found).
    pub best: Option<Rigid2>,
    /// `global_from_local` at each other distinct candidate, best first (not refined).
    pub rivals: Vec<Rigid2>,
    /// The paired test of the best against the rival it beats least decisively, as the decision saw it
    /// ([`StartSearch::search_again`]'s; `None` for [`StartSearch::search`], which ranks by score
    /// margin, or without a rival).
    pub weakest_z: Option<f64>,
    /// How well the merged cloud fits the unfiltered map at the best pose (its mean probability, the
    /// score [`RelocalizationOptions::min_unfiltered_score`] is a floor for), as
    /// the search judged it; `None` without a candidate, and for [`StartSearch::search`] when it refused
    /// the best as ambiguous before judging its fit.
    pub fit: Option<f32>,
}

/// Finds `global_from_local` of a new session from its first scans, with no prior, against `map`'s
/// finished submaps (see the module docs). `scans` are `(local_from_tracking, points in the tracking
/// frame)` in LLO's frame, first scan first. `NotFound` when the map is empty, there are no points, or
/// no pose reaches `min_score`.
pub fn relocalize_session_start(
    map: &LifelongMap,
    scans: &[(Rigid2, Vec<Point2<f32>>)],
    options: &RelocalizationOptions,
) -> RelocalizationOutcome {
    match map.relocalization_map(options) {
        Some(grid) => relocalize_scans_in_grid(&grid, scans, options),
        None => RelocalizationOutcome::NotFound,
    }
}

/// The core of [`relocalize_session_start`] against a map-frame grid: merges `scans` (`(local_from_tracking, points in the tracking
/// frame)`, first scan first) into one cloud in the first scan's frame and relocalizes it with no prior.
/// Returns `global_from_local` of the scans' local frame.
fn relocalize_scans_in_grid(
    grid: &ProbabilityGrid,
    scans: &[(Rigid2, Vec<Point2<f32>>)],
    options: &RelocalizationOptions,
) -> RelocalizationOutcome {
    StartSearch::new(grid, options).search(scans).outcome
}

/// `scans` merged into one cloud in the first scan's frame (thinned to `voxel_size`), with
/// `first_from_local`.
fn merge_scans(
    scans: &[(Rigid2, Vec<Point2<f32>>)],
    voxel_size: f64,
) -> Option<(Rigid2, Vec<Point2<f32>>)> {
    let (first_pose, _) = scans.first()?;
    let first_from_local = first_pose.inverse();
    let mut cloud: Vec<Point2<f32>> = Vec::new();
    for (local_pose, points) in scans {
        let first_from_tracking = first_from_local * local_pose;
        cloud.extend(points.iter().map(|p| {
            (first_from_tracking * Point2::new(f64::from(p.x), f64::from(p.y))).cast::<f32>()
        }));
    }
    if voxel_size > 0.0 {
        cloud = voxel_filter(&cloud, voxel_size as f32);
    }
    (!cloud.is_empty()).then_some((first_from_local, cloud))
}

#[cfg(test)]
mod tests;
