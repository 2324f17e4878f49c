//! The search a session start runs against one rendered map ([`StartSearch`]): every attempt with no
//! prior, its evidence (how decisively the best pose beats the others), and the checks of a prior or a
//! placement against the session's cloud (see the parent module's docs).

use nalgebra::Point2;

use super::{
    RelocalizationOptions, RelocalizationOutcome, SessionRelocalization, StartAnswer, merge_scans,
};
use crate::geometry::{Rigid2, Rigid2Ext as _};
use crate::grid::ProbabilityGrid;
use crate::local_slam::voxel_filter;
use crate::scan_matching::{
    LeastSquaresScanMatcher, PairedBlocks, RealTimeCorrelativeScanMatcher,
    RealTimeCorrelativeScanMatcherOptions, Relocalizer, RelocalizerOptions, blocked_paired_z,
    clearly_different, max_filtered, mean_probability,
};

/// What [`StartSearch::evidence`] found: the best pose and how decisively it beats the others.
#[derive(Clone, Debug, PartialEq)]
pub struct SearchEvidence {
    /// `global_from_local` of the scans' local frame at the whole cloud's best pose, refined on the
    /// unfiltered map: the pose every test of [`StartSearch::decide`] is about, and its answer.
    pub global_from_local: Rigid2,
    /// `global_from_local` with the first scan alone refined on the unfiltered map from where the cloud
    /// put it (the same as `global_from_local` for one scan): a check of the cloud's pose at its start.
    /// (Answering this pose instead placed 2 Intel and 6 MIT CSAIL 10 s stacks 0.16–0.21 m off whose
    /// clouds were within 0.07 m; the reverse happened once, an Intel cloud 0.24 m off.)
    pub first_scan_global_from_local: Rigid2,
    /// How far (metres) the first scan's own refinement moved it from where the whole cloud put it: two
    /// estimates of one pose (0 for one scan).
    pub first_scan_shift_m: f64,
    /// Branch-and-bound score of the best pose (on the max-filtered map).
    pub score: f32,
    /// Mean probability of the cloud's points at the best pose on the unfiltered map (what candidates are
    /// ranked by).
    pub sharp_score: f32,
    /// The best clearly different candidate: its score on the unfiltered map and where it lies in the best pose's frame,
    /// `[x, y, θ]` (m, m, rad).
    pub runner_up: Option<(f32, [f64; 3])>,
    /// The other distinct candidate the best pose beats least decisively: the paired statistic (per point
    /// from [`StartSearch::evidence`], per [`RelocalizationOptions::route_block_m`] block in
    /// [`StartSearch::search_again`]), its score and its offset as in `runner_up`.
    pub weakest: Option<(f64, f32, [f64; 3])>,
    /// Distinct candidates reaching `min_score`, the best included.
    pub distinct_candidates: usize,
    /// `global_from_local` at each other distinct candidate (refined on the unfiltered map), best first.
    pub rivals: Vec<Rigid2>,
    /// Points of the merged, thinned cloud.
    pub cloud_points: usize,
}

/// How well the merged cloud of some scans fits the map at one given pose ([`StartSearch::fit`]): what a
/// search could at best find there (for reports: is the truth's fit good at all?).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudFit {
    /// Mean probability of the cloud's points on the unfiltered map (as [`SearchEvidence::sharp_score`]).
    pub sharp_score: f32,
    /// Share of the points on cells the map observed (free or occupied), 0–1.
    pub known_fraction: f64,
    /// Share of the points within [`RelocalizationOptions::match_tolerance`] of a cell the map holds as
    /// more likely occupied than not, 0–1: how much of the cloud the map's walls explain there.
    pub hit_fraction: f64,
    /// Points of the merged, thinned cloud.
    pub cloud_points: usize,
}

/// What [`StartSearch::check_prior`] found at a pose the robot believes it starts at (its dock: where its
/// last session ended).
#[derive(Clone, Debug, PartialEq)]
pub struct PriorCheck {
    /// Whether the evidence agrees with the prior: the cloud, refined from the prior on the unfiltered
    /// map, fits it at least `min_unfiltered_score`, and no candidate of a whole-map search fits it
    /// decisively better (the paired test at [`StartSearch::search_again`]'s bar). Near-tied candidates
    /// do not refuse it: there the prior decides.
    pub agrees: bool,
    /// `global_from_local` at the prior refined with the cloud on the unfiltered map.
    pub global_from_local: Rigid2,
    /// How well the cloud fits the map there (mean probability on the unfiltered map).
    pub fit: f32,
    /// The weakest paired test of the refined prior against the whole-map search's other distinct
    /// candidates (positive: the prior fits better); `None` when the search found no other.
    pub weakest_z: Option<f64>,
    /// `global_from_local` at each of those other candidates: the rivals probation contests.
    pub rivals: Vec<Rigid2>,
}

/// Session-start relocalization that can wait out an ambiguous start.
///
/// In a store of look-alike aisles the first metres of a session often fit two or more places equally well
/// (see [`RelocalizationOptions::min_score_margin`]). A `StartSearch` holds the map prepared once for the
/// session; [`Self::search_again`] searches it with the cloud of every scan since the start. As the robot
/// drives on — to an aisle end, a pillar, a cross aisle — the cloud stops fitting the wrong places, and the
/// session is placed once the best pose fits decisively better than every other candidate (a paired
/// per-point test, [`RelocalizationOptions::min_disambiguation_z`]; a mean-score margin is diluted as the
/// cloud grows). Each search covers the whole map, so the right place is always among the candidates;
/// tracking only the first search's few candidates instead placed sessions in wrong aisles whenever the
/// truth was not among them.
pub struct StartSearch {
    /// One per [`RelocalizationOptions::coarse_factors`], in order (never empty).
    relocalizers: Vec<Relocalizer>,
    /// The unfiltered map, when the search runs on a max-filtered copy.
    sharp: Option<ProbabilityGrid>,
    options: RelocalizationOptions,
}

impl StartSearch {
    /// Prepares `grid` (a map-frame rendering of the site's submaps) for searches with `options`.
    pub fn new(grid: &ProbabilityGrid, options: &RelocalizationOptions) -> Self {
        let tolerance_cells = (options.match_tolerance / grid.limits().resolution).round() as u32;
        let tolerant = (tolerance_cells > 0).then(|| max_filtered(grid, tolerance_cells));
        let relocalizers = options
            .coarse_factors
            .iter()
            .chain(options.coarse_factors.is_empty().then_some(&2))
            .map(|&coarse_factor| {
                Relocalizer::new(
                    tolerant.as_ref().unwrap_or(grid),
                    RelocalizerOptions {
                        coarse_factor,
                        coarse_score_window: options.candidate_score_window,
                        coarse_branch_and_bound_depth: options.branch_and_bound_depth,
                        min_score: options.min_score,
                        max_candidates: options.max_candidates.max(1),
                        least_squares: options.least_squares.clone(),
                        ..RelocalizerOptions::default()
                    },
                )
            })
            .collect();
        Self {
            relocalizers,
            sharp: tolerant.is_some().then(|| grid.clone()),
            options: options.clone(),
        }
    }

    /// Searches the whole map for `scans` (`(local_from_tracking, points)`, first scan first); refuses
    /// a best pose whose runner-up scores within `min_score_margin` (`Ambiguous`), and one that fits the
    /// unfiltered map below `min_unfiltered_score` (`NotFound`, with its `fit`).
    pub fn search(&self, scans: &[(Rigid2, Vec<Point2<f32>>)]) -> StartAnswer {
        let not_found = StartAnswer {
            outcome: RelocalizationOutcome::NotFound,
            best: None,
            rivals: Vec::new(),
            weakest_z: None,
            fit: None,
        };
        let Some((first_from_local, cloud)) = merge_scans(scans, self.options.voxel_size) else {
            return not_found;
        };
        let Some(found) = self.relocalize(&cloud) else {
            return not_found;
        };
        let rivals = distinct(found.candidates)
            .into_iter()
            .filter(|(pose, _)| clearly_different(pose, &found.pose))
            .map(|(pose, _)| pose * first_from_local)
            .collect();
        let best = Some(found.pose * first_from_local);
        if let (Some(runner_up_score), Some(runner_up_pose)) =
            (found.runner_up_score, found.runner_up_pose)
            && runner_up_score >= found.score - self.options.min_score_margin
        {
            let offset = found.pose.inverse() * runner_up_pose;
            return StartAnswer {
                outcome: RelocalizationOutcome::Ambiguous {
                    score: found.score,
                    runner_up_score,
                    runner_up_from_best: [
                        offset.translation.x,
                        offset.translation.y,
                        offset.theta(),
                    ],
                },
                best,
                rivals,
                weakest_z: None,
                fit: None,
            };
        }
        // Every answer must fit the unfiltered map (`min_unfiltered_score`), as retries and one-shot
        // answers must: a cloud from ground the map never saw reaches `min_score` on the max-filtered map
        // somewhere (ACES in 3 sessions: a first search placed a session 19 m off at fit 0.27).
        let sharpened = self.sharpen(&cloud, &found.pose);
        let fit = mean_probability(self.sharp_grid(), &cloud, &sharpened) as f32;
        if fit < self.options.min_unfiltered_score {
            return StartAnswer {
                outcome: RelocalizationOutcome::NotFound,
                best,
                rivals,
                weakest_z: None,
                fit: Some(fit),
            };
        }
        StartAnswer {
            outcome: RelocalizationOutcome::Found(SessionRelocalization {
                global_from_local: sharpened * first_from_local,
                score: found.score,
            }),
            best,
            rivals,
            weakest_z: None,
            fit: Some(fit),
        }
    }

    /// Checks the prior `global_from_local` of `scans` (`(local_from_tracking, points)`, first scan first)
    /// against the map (see [`PriorCheck`]): the robot starts where it believes it is unless the evidence
    /// says otherwise. `None` when there are no points.
    pub fn check_prior(
        &self,
        scans: &[(Rigid2, Vec<Point2<f32>>)],
        prior: &Rigid2,
    ) -> Option<PriorCheck> {
        let (first_from_local, cloud) = merge_scans(scans, self.options.voxel_size)?;
        let grid = self.sharp_grid();
        // Where the robot believes it is, searched within LLO's and GLM's usual error of a last pose, then
        // refined like every candidate.
        let window = RealTimeCorrelativeScanMatcher::new(RealTimeCorrelativeScanMatcherOptions {
            linear_search_window: self.options.prior_window_m,
            angular_search_window: self.options.prior_window_rad,
            translation_delta_cost_weight: 0.0,
            rotation_delta_cost_weight: 0.0,
        });
        let (searched, _) = window.match_pose(&(prior * first_from_local.inverse()), &cloud, grid);
        let at_prior = refine_on_sharp_map(grid, &cloud, &searched, &self.options);
        let fit = mean_probability(grid, &cloud, &at_prior) as f32;
        let bar = self.disambiguation_z(scans.len());
        let block_m = self.options.route_block_m;
        // The whole map's candidates, each refined on the unfiltered map; one that refines onto the prior
        // is the prior.
        let rivals: Vec<Rigid2> = self
            .relocalize(&cloud)
            .map(|found| distinct(found.candidates))
            .unwrap_or_default()
            .into_iter()
            .map(|(pose, _)| self.sharpen(&cloud, &pose))
            .filter(|pose| clearly_different(pose, &at_prior))
            .collect();
        let tests: Vec<f64> = rivals
            .iter()
            .map(|rival| blocked_paired_z(grid, &cloud, &at_prior, rival, block_m))
            .collect();
        let weakest_z = tests.iter().copied().min_by(f64::total_cmp);
        let agrees = fit >= self.options.min_unfiltered_score && tests.iter().all(|z| *z > -bar);
        Some(PriorCheck {
            agrees,
            global_from_local: at_prior * first_from_local,
            fit,
            weakest_z,
            rivals: rivals.iter().map(|r| r * first_from_local).collect(),
        })
    }

    /// The paired test's bar for a cloud of `scans` scans: `min_disambiguation_z`, or
    /// `long_route_min_disambiguation_z` past `long_route_scans`.
    pub(super) fn disambiguation_z(&self, scans: usize) -> f64 {
        if scans > self.options.long_route_scans {
            self.options.long_route_min_disambiguation_z
        } else {
            self.options.min_disambiguation_z
        }
    }

    /// Searches the whole map again for `scans` — the same first scan as [`Self::search`] and every scan
    /// since — and places the session when the best pose fits the unfiltered map at least
    /// `min_unfiltered_score` and decisively better than every other distinct candidate (the paired test,
    /// [`Self::disambiguation_z`]), or is the only one reaching `min_score`.
    /// `Ambiguous` otherwise; `NotFound` when nothing reaches `min_score` or the fit is below the floor.
    /// (Its mean-score margin is not asked: it is diluted as the cloud grows.)
    ///
    /// With `piece_m` > 0, where the route's paired test leaves the best undecided against some rival, the
    /// same test is made in pieces of `piece_m` metres of route, each refined on its own
    /// ([`Self::contest_each_in_pieces`]): LLO's drift bends a long route, which one rigid pose fits only
    /// in part. A rival is beaten when either test reaches [`Self::disambiguation_z`], and the best is
    /// placed when every rival is (`weakest_z` is then the weakest rival's stronger test).
    pub fn search_again(&self, scans: &[(Rigid2, Vec<Point2<f32>>)], piece_m: f64) -> StartAnswer {
        let evidence = self.evidence_in_blocks(scans, self.options.route_block_m);
        let min_z = self.disambiguation_z(scans.len());
        let mut outcome = self.decide_with(
            evidence.as_ref(),
            &Decision {
                min_score_margin: None,
                min_z,
                max_first_scan_shift: None,
            },
        );
        let mut weakest_z = evidence.as_ref().and_then(|e| e.weakest).map(|(z, _, _)| z);
        if let (RelocalizationOutcome::Ambiguous { .. }, Some(e)) = (outcome, &evidence)
            && piece_m > 0.0
        {
            let best = &e.global_from_local;
            let whole = self.contest_each(scans, best, &e.rivals);
            let pieces = self.contest_each_in_pieces(scans, best, &e.rivals, piece_m);
            let weakest = weakest_of_either(&whole, &pieces);
            if whole.len() == e.rivals.len() && weakest.is_none_or(|z| z >= min_z) {
                outcome = RelocalizationOutcome::Found(SessionRelocalization {
                    global_from_local: e.global_from_local,
                    score: e.score,
                });
                weakest_z = weakest;
            }
        }
        StartAnswer {
            outcome,
            best: evidence.as_ref().map(|e| e.global_from_local),
            weakest_z,
            fit: evidence.as_ref().map(|e| e.sharp_score),
            rivals: evidence.map(|e| e.rivals).unwrap_or_default(),
        }
    }

    /// Whether the route `scans` now tells `candidates` (`global_from_local`, from an earlier search)
    /// apart: each refined with the merged cloud on the unfiltered map, the best-fitting one fits at least
    /// `min_unfiltered_score` and beats every other clearly different one by
    /// [`Self::disambiguation_z`] ([`blocked_paired_z`] over `route_block_m` blocks). A cheap test between
    /// whole-map searches — no search, a few refinements — that says when a search is worth making now:
    /// it decides nothing itself, since the truth may not be among the candidates.
    ///
    /// With `piece_m` > 0, a candidate the whole route leaves undecided against the leader is tested again
    /// in pieces of `piece_m` metres of route, as [`Self::search_again`] tests its rivals: the recheck
    /// then says a search is worth making exactly where that search could decide.
    pub fn route_decides(
        &self,
        scans: &[(Rigid2, Vec<Point2<f32>>)],
        candidates: &[Rigid2],
        piece_m: f64,
    ) -> bool {
        let Some((first_from_local, cloud)) = merge_scans(scans, self.options.voxel_size) else {
            return false;
        };
        let local_from_first = first_from_local.inverse();
        let grid = self.sharp_grid();
        let mut refined: Vec<(Rigid2, f64)> = candidates
            .iter()
            .map(|c| {
                let pose = self.sharpen(&cloud, &(c * local_from_first));
                (pose, mean_probability(grid, &cloud, &pose))
            })
            .collect();
        refined.sort_by(|a, b| b.1.total_cmp(&a.1));
        let Some(&(leader, fit)) = refined.first() else {
            return false;
        };
        if fit < f64::from(self.options.min_unfiltered_score) {
            return false;
        }
        let min_z = self.disambiguation_z(scans.len());
        let mut pieces = None;
        refined[1..]
            .iter()
            .filter(|(other, _)| clearly_different(&leader, other))
            .all(|(other, _)| {
                blocked_paired_z(grid, &cloud, &leader, other, self.options.route_block_m) >= min_z
                    || (piece_m > 0.0
                        && self.pieces_z(
                            pieces.get_or_insert_with(|| {
                                route_pieces(scans, piece_m, self.options.voxel_size)
                            }),
                            &leader,
                            other,
                        ) >= min_z)
            })
    }

    /// The weakest paired test ([`blocked_paired_z`]) of the session placed at `global_from_local` against each
    /// of `rivals` (`global_from_local` too), with the merged cloud of `scans` (as [`Self::search`]
    /// merges them); each pose is first refined with that cloud on the unfiltered map, and a rival that
    /// refines onto the placement is no rival. Positive: the placement fits better; negative: that rival
    /// does. `None` when there are no points or no rival remains.
    pub fn contest(
        &self,
        scans: &[(Rigid2, Vec<Point2<f32>>)],
        global_from_local: &Rigid2,
        rivals: &[Rigid2],
    ) -> Option<f64> {
        self.contest_each(scans, global_from_local, rivals)
            .into_iter()
            .flatten()
            .min_by(f64::total_cmp)
    }

    /// [`Self::contest`]'s paired test against each of `rivals`, in their order (`None` for a rival that
    /// refines onto the placement); empty when there are no points.
    pub fn contest_each(
        &self,
        scans: &[(Rigid2, Vec<Point2<f32>>)],
        global_from_local: &Rigid2,
        rivals: &[Rigid2],
    ) -> Vec<Option<f64>> {
        self.contest_each_by(scans, global_from_local, rivals, |cloud, placed, rival| {
            blocked_paired_z(
                self.sharp_grid(),
                cloud,
                placed,
                rival,
                self.options.route_block_m,
            )
        })
    }

    /// [`Self::contest_each`] judged in pieces: the route cut every `piece_m` metres (of route, in the
    /// scans' local frame), each piece refined on its own from where the whole cloud's refinement put the
    /// placement and from where it put each rival, and the differences of every piece summed into the same
    /// `route_block_m` blocks ([`PairedBlocks`]). LLO's drift bends a long route, which one rigid pose fits
    /// only in part; each piece is refined where it is, at the placement and at the rival alike. The
    /// order and the `None`s are [`Self::contest_each`]'s; empty when there are no points or `piece_m` ≤ 0.
    pub fn contest_each_in_pieces(
        &self,
        scans: &[(Rigid2, Vec<Point2<f32>>)],
        global_from_local: &Rigid2,
        rivals: &[Rigid2],
        piece_m: f64,
    ) -> Vec<Option<f64>> {
        if piece_m <= 0.0 {
            return Vec::new();
        }
        let pieces = route_pieces(scans, piece_m, self.options.voxel_size);
        self.contest_each_by(scans, global_from_local, rivals, |_, placed, rival| {
            self.pieces_z(&pieces, placed, rival)
        })
    }

    /// The paired test of `placed` against `rival` (both `global_from_first`) over `pieces` of route
    /// ([`route_pieces`]), each piece refined on its own from either pose, the differences summed into
    /// `route_block_m` blocks ([`PairedBlocks`]).
    fn pieces_z(&self, pieces: &[Vec<Point2<f32>>], placed: &Rigid2, rival: &Rigid2) -> f64 {
        let mut blocks = PairedBlocks::new(self.options.route_block_m);
        for piece in pieces {
            let at_placement = self.sharpen(piece, placed);
            let at_rival = self.sharpen(piece, rival);
            blocks.add(self.sharp_grid(), piece, &at_placement, &at_rival);
        }
        blocks.z()
    }

    /// The contests' common part: the merged cloud of `scans`, the placement and each rival refined with it
    /// on the unfiltered map, and `test(cloud, placed, rival)` for each rival clearly different from the
    /// placement (`None` for one that refined onto it); empty when there are no points.
    fn contest_each_by(
        &self,
        scans: &[(Rigid2, Vec<Point2<f32>>)],
        global_from_local: &Rigid2,
        rivals: &[Rigid2],
        test: impl Fn(&[Point2<f32>], &Rigid2, &Rigid2) -> f64,
    ) -> Vec<Option<f64>> {
        let Some((first_from_local, cloud)) = merge_scans(scans, self.options.voxel_size) else {
            return Vec::new();
        };
        let local_from_first = first_from_local.inverse();
        let placed = self.sharpen(&cloud, &(global_from_local * local_from_first));
        rivals
            .iter()
            .map(|rival| self.sharpen(&cloud, &(rival * local_from_first)))
            .map(|rival| clearly_different(&placed, &rival).then(|| test(&cloud, &placed, &rival)))
            .collect()
    }

    /// Whether a fit (a [`CloudFit::sharp_score`]) reaches `min_unfiltered_score`.
    pub fn fits(&self, fit: f32) -> bool {
        fit >= self.options.min_unfiltered_score
    }

    /// Searches the whole map for `scans` like [`Self::search_again`] and returns the evidence behind a
    /// decision instead of a decision: the best pose, its margin over the best clearly different pose and
    /// the weakest paired test against any other distinct candidate. `None` when nothing reaches
    /// `min_score` or there is nothing to match.
    pub fn evidence(&self, scans: &[(Rigid2, Vec<Point2<f32>>)]) -> Option<SearchEvidence> {
        self.evidence_in_blocks(scans, 0.0)
    }

    /// [`Self::evidence`] with its paired tests over `block_m` blocks ([`blocked_paired_z`]).
    fn evidence_in_blocks(
        &self,
        scans: &[(Rigid2, Vec<Point2<f32>>)],
        block_m: f64,
    ) -> Option<SearchEvidence> {
        let (first_from_local, cloud) = merge_scans(scans, self.options.voxel_size)?;
        let found = self.relocalize(&cloud)?;
        let grid = self.sharp_grid();
        // Candidates found on the max-filtered map are only known to within the tolerance, and many score
        // alike there: refine each on the unfiltered map and rank them by how well they fit it.
        let mut sharpened: Vec<(Rigid2, f32, f64)> = distinct(found.candidates)
            .into_iter()
            .map(|(pose, score)| {
                let pose = self.sharpen(&cloud, &pose);
                (pose, score, mean_probability(grid, &cloud, &pose))
            })
            .collect();
        sharpened.sort_by(|a, b| b.2.total_cmp(&a.2));
        // Two candidates refined onto one peak are one candidate.
        let mut candidates: Vec<(Rigid2, f32, f64)> = Vec::new();
        for c in sharpened {
            if candidates.iter().all(|k| clearly_different(&k.0, &c.0)) {
                candidates.push(c);
            }
        }
        let &(best_pose, best_score, best_sharp) = candidates.first()?;
        let offset = |other: &Rigid2| {
            let o = best_pose.inverse() * other;
            [o.translation.x, o.translation.y, o.theta()]
        };
        let runner_up = candidates
            .get(1)
            .map(|(pose, _, sharp)| (*sharp as f32, offset(pose)));
        let weakest = candidates[1..]
            .iter()
            .map(|(other, _, sharp)| {
                (
                    blocked_paired_z(grid, &cloud, &best_pose, other, block_m),
                    *sharp as f32,
                    offset(other),
                )
            })
            .min_by(|a, b| a.0.total_cmp(&b.0));
        // LLO drifts over a long stack, which bends the cloud: the first scan alone, refined on the
        // unfiltered map from where the cloud put it, checks the cloud's pose at the stack's start.
        let first_pose = if scans.len() > 1 {
            let first = &scans[0].1;
            let points = if self.options.voxel_size > 0.0 {
                voxel_filter(first, self.options.voxel_size as f32)
            } else {
                first.clone()
            };
            refine_on_sharp_map(grid, &points, &best_pose, &self.options)
        } else {
            best_pose
        };
        Some(SearchEvidence {
            global_from_local: best_pose * first_from_local,
            first_scan_global_from_local: first_pose * first_from_local,
            first_scan_shift_m: (first_pose.translation.vector - best_pose.translation.vector)
                .norm(),
            score: best_score,
            sharp_score: best_sharp as f32,
            runner_up,
            weakest,
            distinct_candidates: candidates.len(),
            rivals: candidates[1..]
                .iter()
                .map(|(pose, _, _)| pose * first_from_local)
                .collect(),
            cloud_points: cloud.len(),
        })
    }

    /// The strict decision on [`Self::evidence`], for a one-shot answer that cannot wait for more data:
    /// placed only when the best pose both scores clearly above every clearly different pose on the
    /// unfiltered map (`min_score_margin`) and fits decisively better than every other distinct candidate
    /// (the paired test, `min_answer_z`); `Ambiguous` otherwise, `NotFound` without evidence or
    /// when the best pose fits the unfiltered map worse than `min_unfiltered_score`.
    /// (The session start's [`Self::search`] applies only the margin, and [`Self::search_again`] the
    /// floor and the paired test at [`Self::disambiguation_z`]: a session placed there is still on probation,
    /// and [`Self::contest`] tests it again against the rivals it beat.)
    pub fn decide(&self, evidence: Option<&SearchEvidence>) -> RelocalizationOutcome {
        self.decide_with(
            evidence,
            &Decision {
                min_score_margin: Some(self.options.min_score_margin),
                min_z: self.options.min_answer_z,
                max_first_scan_shift: Some(self.options.max_first_scan_shift),
            },
        )
    }

    /// The tests of [`Self::decide`] that `decision` asks for; the floor `min_unfiltered_score` always.
    fn decide_with(
        &self,
        evidence: Option<&SearchEvidence>,
        decision: &Decision,
    ) -> RelocalizationOutcome {
        let Some(e) = evidence.filter(|e| e.sharp_score >= self.options.min_unfiltered_score)
        else {
            return RelocalizationOutcome::NotFound;
        };
        let ambiguous = |(runner_up_score, runner_up_from_best): (f32, [f64; 3])| {
            RelocalizationOutcome::Ambiguous {
                score: e.score,
                runner_up_score,
                runner_up_from_best,
            }
        };
        if let (Some(margin), Some(runner_up)) = (decision.min_score_margin, e.runner_up)
            && runner_up.0 >= e.sharp_score - margin
        {
            return ambiguous(runner_up);
        }
        if let Some((z, score, offset)) = e.weakest
            && z < decision.min_z
        {
            return ambiguous((score, offset));
        }
        if let Some(max_shift) = decision.max_first_scan_shift
            && e.first_scan_shift_m > max_shift
        {
            // The first scan's own pose is the rival: the cloud's pose fits the cloud, it the scan.
            let o = e.global_from_local.inverse() * e.first_scan_global_from_local;
            return ambiguous((e.sharp_score, [o.translation.x, o.translation.y, o.theta()]));
        }
        RelocalizationOutcome::Found(SessionRelocalization {
            global_from_local: e.global_from_local,
            score: e.score,
        })
    }

    /// How the merged cloud of `scans` (as [`Self::evidence`] merges it) fits the map with the scans'
    /// local frame at `global_from_local`; `None` when there are no points.
    pub fn fit(
        &self,
        scans: &[(Rigid2, Vec<Point2<f32>>)],
        global_from_local: &Rigid2,
    ) -> Option<CloudFit> {
        let (first_from_local, cloud) = merge_scans(scans, self.options.voxel_size)?;
        let pose = global_from_local * first_from_local.inverse();
        let sharp = self.sharp_grid();
        let tolerant = self.relocalizers[0].fine_grid();
        let share = |keep: &dyn Fn(Point2<f64>) -> bool| {
            let kept = cloud
                .iter()
                .filter(|p| keep(pose * Point2::new(f64::from(p.x), f64::from(p.y))))
                .count();
            kept as f64 / cloud.len() as f64
        };
        Some(CloudFit {
            sharp_score: mean_probability(sharp, &cloud, &pose) as f32,
            known_fraction: share(&|w| sharp.is_known(&sharp.limits().cell_index(&w))),
            hit_fraction: share(&|w| tolerant.probability(&tolerant.limits().cell_index(&w)) > 0.5),
            cloud_points: cloud.len(),
        })
    }

    /// The whole-map search for `cloud`, thinned to at most `max_search_points` for it.
    fn relocalize(&self, cloud: &[Point2<f32>]) -> Option<crate::scan_matching::Relocalization> {
        let thinned = thinned_to(
            cloud,
            self.options.max_search_points,
            self.options.voxel_size,
        );
        let mut found = None;
        for relocalizer in &self.relocalizers {
            found = relocalizer.relocalize(&thinned);
            let inconclusive = found.as_ref().is_some_and(|f| {
                f.unrefined_bound
                    .is_some_and(|(_, bound)| bound >= f.score - self.options.min_score_margin)
            });
            if !inconclusive {
                break;
            }
        }
        found
    }

    /// The unfiltered map: the one candidates are refined and compared on.
    fn sharp_grid(&self) -> &ProbabilityGrid {
        self.sharp
            .as_ref()
            .unwrap_or(self.relocalizers[0].fine_grid())
    }

    /// `pose` found on the max-filtered map, refined on the unfiltered one (without a filtered copy the
    /// relocalizer already refined on the map itself).
    fn sharpen(&self, cloud: &[Point2<f32>], pose: &Rigid2) -> Rigid2 {
        match &self.sharp {
            Some(sharp) => refine_on_sharp_map(sharp, cloud, pose, &self.options),
            None => *pose,
        }
    }
}

/// The weakest rival's stronger test: per rival, the larger of its whole-route z (`whole`) and its pieces' z
/// (`pieces`, same order, may be shorter or empty when the pieces were not tested); rivals whose whole-route
/// test is `None` (refined onto the placement) are no rivals. `None` when no rival remains.
pub(in crate::lifelong) fn weakest_of_either(
    whole: &[Option<f64>],
    pieces: &[Option<f64>],
) -> Option<f64> {
    whole
        .iter()
        .enumerate()
        .filter_map(|(i, z)| {
            let piece = pieces.get(i).copied().flatten();
            z.map(|z| piece.map_or(z, |piece| z.max(piece)))
        })
        .min_by(f64::total_cmp)
}

/// Which tests a decision on [`SearchEvidence`] asks for (see [`StartSearch::decide`]).
struct Decision {
    /// The margin over the best clearly different pose on the unfiltered map, if asked.
    min_score_margin: Option<f32>,
    /// The paired test against every other distinct candidate.
    min_z: f64,
    /// The first scan's shift from the cloud's pose, if asked.
    max_first_scan_shift: Option<f64>,
}

/// `cloud` (already thinned to `voxel_size` metres, or not at all when 0) thinned with ever coarser voxels
/// (×1.25 each time, from `voxel_size` or 5 cm) until at most `max_points` remain (or the voxels reach
/// [`MAX_SEARCH_VOXEL_M`]).
pub(super) fn thinned_to(
    cloud: &[Point2<f32>],
    max_points: usize,
    voxel_size: f64,
) -> Vec<Point2<f32>> {
    let mut thinned = cloud.to_vec();
    let mut size = voxel_size.max(0.05) as f32;
    while thinned.len() > max_points && size < MAX_SEARCH_VOXEL_M {
        size *= 1.25;
        thinned = voxel_filter(cloud, size);
    }
    thinned
}

/// The points of `scans` (`(local_from_tracking, points)`) in the first scan's frame, as [`merge_scans`]
/// puts them, cut into pieces of `piece_m` metres of route (the distance between consecutive scans'
/// origins), each thinned to `voxel_size` (0: not at all); empty pieces are left out.
fn route_pieces(
    scans: &[(Rigid2, Vec<Point2<f32>>)],
    piece_m: f64,
    voxel_size: f64,
) -> Vec<Vec<Point2<f32>>> {
    let Some((first_pose, _)) = scans.first() else {
        return Vec::new();
    };
    let first_from_local = first_pose.inverse();
    let mut pieces: Vec<Vec<Point2<f32>>> = Vec::new();
    let mut piece: Vec<Point2<f32>> = Vec::new();
    let (mut route_m, mut piece_start_m) = (0.0, 0.0);
    let mut previous = first_pose.translation.vector;
    for (local_pose, points) in scans {
        route_m += (local_pose.translation.vector - previous).norm();
        previous = local_pose.translation.vector;
        if route_m - piece_start_m >= piece_m {
            pieces.push(std::mem::take(&mut piece));
            piece_start_m = route_m;
        }
        let first_from_tracking = first_from_local * local_pose;
        piece.extend(points.iter().map(|p| {
            (first_from_tracking * Point2::new(f64::from(p.x), f64::from(p.y))).cast::<f32>()
        }));
    }
    pieces.push(piece);
    pieces
        .into_iter()
        .map(|piece| {
            if voxel_size > 0.0 {
                voxel_filter(&piece, voxel_size as f32)
            } else {
                piece
            }
        })
        .filter(|piece| !piece.is_empty())
        .collect()
}

/// Coarsest voxels [`thinned_to`] uses, metres: beyond this a cloud no longer has a room's shape.
const MAX_SEARCH_VOXEL_M: f32 = 2.0;

/// `candidates` (best first) without those not [`clearly_different`] from a better one.
fn distinct(candidates: Vec<(Rigid2, f32)>) -> Vec<(Rigid2, f32)> {
    let mut kept: Vec<(Rigid2, f32)> = Vec::new();
    for (pose, score) in candidates {
        if kept.iter().all(|(k, _)| clearly_different(k, &pose)) {
            kept.push((pose, score));
        }
    }
    kept
}

/// A pose found on the max-filtered map is only known to within the tolerance: search a window of that
/// size (and ±2°) on the unfiltered map, then refine by least squares.
fn refine_on_sharp_map(
    grid: &ProbabilityGrid,
    cloud: &[Point2<f32>],
    pose: &Rigid2,
    options: &RelocalizationOptions,
) -> Rigid2 {
    let window = RealTimeCorrelativeScanMatcher::new(RealTimeCorrelativeScanMatcherOptions {
        linear_search_window: options.match_tolerance + grid.limits().resolution,
        angular_search_window: 2f64.to_radians(),
        translation_delta_cost_weight: 0.0,
        rotation_delta_cost_weight: 0.0,
    });
    let (searched, _) = window.match_pose(pose, cloud, grid);
    let (refined, _) = LeastSquaresScanMatcher::new(options.least_squares.clone()).match_pose(
        &searched.translation.vector,
        &searched,
        cloud,
        grid,
    );
    refined
}
