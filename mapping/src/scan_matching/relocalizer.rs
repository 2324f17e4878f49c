//! Whole-map relocalization with no prior: where on this map, at which heading, is the robot?
//!
//! A full branch-and-bound search at the map's resolution is exact but slow on a building-sized map: the
//! number of rotations grows with the scan's range over the cell size (≈ 3,800 rotations for a 30 m scan on
//! 5 cm cells) and the number of top-level translation blocks with the map's area. The relocalizer therefore
//! searches coarse to fine:
//!
//! 1. **Coarse**: branch and bound over every position and rotation on a copy of the map downsampled by
//!    `coarse_factor` (each coarse cell holds the *maximum* probability of the fine cells it covers, so a
//!    pose that fits the fine map fits the coarse one at least as well). With factor 2 this has a quarter of
//!    the cells and half the rotations. It returns the best few distinct candidates whose coarse score
//!    reaches `coarse_min_score`.
//! 2. **Fine**: for each candidate, branch and bound on the full-resolution map within one coarse cell and
//!    one coarse rotation step around it, then least-squares refinement; the best fine result wins if it
//!    reaches `min_score`.
//!
//! What it costs: with one candidate this can miss a pose that only the fine map distinguishes (two
//! corridors whose coarse maps look alike), which is why several candidates are refined.

use nalgebra::{Point2, Vector2};
use serde::{Deserialize, Serialize};

use super::{
    FastCorrelativeScanMatcher, FastCorrelativeScanMatcherOptions, LeastSquaresScanMatcher,
    LeastSquaresScanMatcherOptions, MatchError, check_non_negative,
};
use crate::geometry::Rigid2;
use crate::grid::{MAX_PROBABILITY, MapLimits, ProbabilityGrid, UNKNOWN_VALUE};

/// Options of [`Relocalizer`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RelocalizerOptions {
    /// Fine cells per coarse cell along each axis (1 = search the full-resolution map directly). Default 2.
    pub coarse_factor: u32,
    /// Depth of the coarse branch-and-bound (the coarsest block is `2^depth` coarse cells). Default 7.
    pub coarse_branch_and_bound_depth: u32,
    /// Smallest coarse score (mean probability, 0.1–0.9) of a candidate worth refining. Default 0.55.
    pub coarse_min_score: f32,
    /// How many distinct coarse candidates are refined at most. Default 3.
    pub max_candidates: usize,
    /// Coarse candidates scoring more than this below the best coarse candidate are not looked for
    /// (score units, ≥ 0; infinite: every candidate reaching `coarse_min_score` competes for the
    /// `max_candidates` places). Default infinite.
    pub coarse_score_window: f32,
    /// Half-width (metres) of the full-resolution search around each coarse candidate; covers the coarse
    /// grid's ambiguity along corridors. Default 0.5 m.
    pub refine_linear_window: f64,
    /// Smallest fine score (mean probability, 0.1–0.9) accepted as a relocalization. Default 0.6.
    pub min_score: f32,
    /// Least-squares refinement of the fine match.
    pub least_squares: LeastSquaresScanMatcherOptions,
}

impl Default for RelocalizerOptions {
    fn default() -> Self {
        Self {
            coarse_factor: 2,
            coarse_branch_and_bound_depth: 7,
            coarse_min_score: 0.55,
            max_candidates: 3,
            coarse_score_window: f32::INFINITY,
            refine_linear_window: 0.5,
            min_score: 0.6,
            least_squares: LeastSquaresScanMatcherOptions::default(),
        }
    }
}

impl RelocalizerOptions {
    /// Checks the ranges of every field.
    pub fn validate(&self) -> Result<(), MatchError> {
        if self.coarse_factor == 0 || self.coarse_factor > 16 {
            return Err(MatchError::InvalidOption {
                field: "coarse_factor",
                reason: "must be in 1..=16",
            });
        }
        if self.max_candidates == 0 {
            return Err(MatchError::InvalidOption {
                field: "max_candidates",
                reason: "must be at least 1",
            });
        }
        check_non_negative("refine_linear_window", self.refine_linear_window)?;
        if self.coarse_score_window.is_nan() || self.coarse_score_window < 0.0 {
            return Err(MatchError::InvalidOption {
                field: "coarse_score_window",
                reason: "must be a non-negative score (or infinite)",
            });
        }
        for (field, score) in [
            ("coarse_min_score", self.coarse_min_score),
            ("min_score", self.min_score),
        ] {
            check_non_negative(field, f64::from(score))?;
            if score > MAX_PROBABILITY {
                return Err(MatchError::InvalidOption {
                    field,
                    reason: "must be at most 0.9 (the largest grid probability)",
                });
            }
        }
        FastCorrelativeScanMatcherOptions {
            branch_and_bound_depth: self.coarse_branch_and_bound_depth,
            ..FastCorrelativeScanMatcherOptions::default()
        }
        .validate()?;
        self.least_squares.validate()
    }
}

/// A relocalization result.
#[derive(Clone, Debug, PartialEq)]
pub struct Relocalization {
    /// `map_from_tracking` after refinement.
    pub pose: Rigid2,
    /// Fine branch-and-bound score of the winning candidate.
    pub score: f32,
    /// Coarse candidates that were refined.
    pub candidates_refined: usize,
    /// Fine score of the best refined candidate at a clearly different pose ([`clearly_different`] from
    /// the winner), if any: how ambiguous the match is (shelf rows and corridors repeat).
    pub runner_up_score: Option<f32>,
    /// The pose of that runner-up (before refinement).
    pub runner_up_pose: Option<Rigid2>,
    /// Every refined candidate reaching `min_score`, `(pose before least squares, fine score)`, best
    /// first (several may belong to one peak; see [`clearly_different`]).
    pub candidates: Vec<(Rigid2, f32)>,
    /// When the coarse search returned `max_candidates` peaks (the list was full, so peaks may have been
    /// left out): the lowest coarse score among them and its pose. A coarse cell holds the most probable
    /// of its fine cells, so no peak left out can score above this at full resolution either (up to the
    /// rotation step): a rival no search refined is bounded by it. `None` when every coarse peak reaching
    /// `coarse_min_score` was refined.
    pub unrefined_bound: Option<(Rigid2, f32)>,
}

/// A map prepared for relocalization: coarse and fine branch-and-bound matchers over it. Immutable and
/// `Sync`; build once per map version.
#[derive(Clone, Debug)]
pub struct Relocalizer {
    options: RelocalizerOptions,
    coarse: FastCorrelativeScanMatcher,
    fine: FastCorrelativeScanMatcher,
    fine_grid: ProbabilityGrid,
    fine_resolution: f64,
    coarse_resolution: f64,
}

/// `grid` downsampled by `factor`: each coarse cell holds the largest value of the known fine cells it covers
/// (unknown if none is known). Stored values grow with probability, so the maximum value is the maximum
/// probability.
pub fn max_downsampled(grid: &ProbabilityGrid, factor: u32) -> ProbabilityGrid {
    let limits = grid.limits();
    let f = i32::try_from(factor.max(1)).unwrap_or(1);
    let width = (limits.width + f - 1) / f;
    let height = (limits.height + f - 1) / f;
    let coarse_limits = MapLimits::new(
        limits.resolution * f64::from(f),
        limits.origin,
        width,
        height,
    );
    let mut coarse = ProbabilityGrid::new(coarse_limits);
    let fine = grid.values();
    let values = coarse.values_mut();
    for y in 0..limits.height {
        let row = y as usize * limits.width as usize;
        let coarse_row = (y / f) as usize * width as usize;
        for x in 0..limits.width {
            let v = fine[row + x as usize];
            if v != UNKNOWN_VALUE {
                let c = &mut values[coarse_row + (x / f) as usize];
                *c = (*c).max(v);
            }
        }
    }
    coarse
}

/// `grid` with each cell raised to the largest value of the known cells within `radius` cells of it
/// along each axis (a square max filter; unknown stays unknown only where the whole square is unknown).
/// Scoring against it forgives a point up to `radius` cells from where the map saw a surface: goods that
/// protrude a little more or less than when the map was made still count as hits.
pub fn max_filtered(grid: &ProbabilityGrid, radius: u32) -> ProbabilityGrid {
    if radius == 0 {
        return grid.clone();
    }
    let limits = grid.limits();
    let (width, height) = (limits.width as usize, limits.height as usize);
    let r = radius as usize;
    // Stored values grow with probability and UNKNOWN_VALUE is the smallest, so a plain max works.
    let source = grid.values();
    let mut rows = vec![UNKNOWN_VALUE; source.len()];
    for y in 0..height {
        let row = &source[y * width..(y + 1) * width];
        for x in 0..width {
            let window = &row[x.saturating_sub(r)..(x + r + 1).min(width)];
            rows[y * width + x] = window.iter().copied().max().unwrap_or(UNKNOWN_VALUE);
        }
    }
    let mut out = ProbabilityGrid::new(limits.clone());
    let values = out.values_mut();
    for x in 0..width {
        for y in 0..height {
            let (lo, hi) = (y.saturating_sub(r), (y + r + 1).min(height));
            values[y * width + x] = (lo..hi)
                .map(|yy| rows[yy * width + x])
                .max()
                .unwrap_or(UNKNOWN_VALUE);
        }
    }
    out
}

impl Relocalizer {
    /// Prepares `map` (validate `options` first).
    pub fn new(map: &ProbabilityGrid, options: RelocalizerOptions) -> Self {
        let coarse_grid = max_downsampled(map, options.coarse_factor);
        let coarse_resolution = coarse_grid.limits().resolution;
        let coarse = FastCorrelativeScanMatcher::new(
            &coarse_grid,
            FastCorrelativeScanMatcherOptions {
                branch_and_bound_depth: options.coarse_branch_and_bound_depth,
                ..FastCorrelativeScanMatcherOptions::default()
            },
        );
        let fine = FastCorrelativeScanMatcher::new(
            map,
            FastCorrelativeScanMatcherOptions {
                branch_and_bound_depth: 3,
                ..FastCorrelativeScanMatcherOptions::default()
            },
        );
        Self {
            options,
            coarse,
            fine,
            fine_grid: map.clone(),
            fine_resolution: map.limits().resolution,
            coarse_resolution,
        }
    }

    /// The options.
    pub fn options(&self) -> &RelocalizerOptions {
        &self.options
    }

    /// The full-resolution map it matches against.
    pub fn fine_grid(&self) -> &ProbabilityGrid {
        &self.fine_grid
    }

    /// Where `points` (in the tracking frame) fit the map best, if anywhere well enough.
    pub fn relocalize(&self, points: &[Point2<f32>]) -> Option<Relocalization> {
        let o = &self.options;
        let candidates = self.coarse.match_full_candidates(
            points,
            o.coarse_min_score,
            o.max_candidates,
            o.coarse_score_window,
        );
        if candidates.is_empty() {
            return None;
        }
        let unrefined_bound = (candidates.len() >= o.max_candidates)
            .then(|| candidates.last().map(|c| (c.pose, c.score)))
            .flatten();
        // One coarse cell (plus a fine cell) and one coarse rotation step around each candidate.
        let max_range = points
            .iter()
            .map(|p| f64::from(p.coords.norm()))
            .fold(self.coarse_resolution, f64::max);
        let coarse_step = 2.0 * (0.5 * self.coarse_resolution / max_range).asin();
        let refiner = LeastSquaresScanMatcher::new(o.least_squares.clone());
        let mut found_all: Vec<(Rigid2, f32)> = Vec::new();
        for candidate in &candidates {
            let Some(found) = self.fine.match_within(
                &candidate.pose,
                points,
                o.min_score,
                self.options
                    .refine_linear_window
                    .max(self.coarse_resolution + self.fine_resolution),
                1.5 * coarse_step,
            ) else {
                continue;
            };
            found_all.push((found.pose, found.score));
        }
        let &(best_pose, best_score) = found_all.iter().max_by(|a, b| a.1.total_cmp(&b.1))?;
        let runner_up = found_all
            .iter()
            .filter(|(pose, _)| clearly_different(pose, &best_pose))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .copied();
        let target: Vector2<f64> = best_pose.translation.vector;
        let (refined, _) = refiner.match_pose(&target, &best_pose, points, &self.fine_grid);
        found_all.sort_by(|a, b| b.1.total_cmp(&a.1));
        Some(Relocalization {
            pose: refined,
            score: best_score,
            candidates_refined: candidates.len(),
            runner_up_score: runner_up.map(|r| r.1),
            runner_up_pose: runner_up.map(|r| r.0),
            candidates: found_all,
            unrefined_bound,
        })
    }
}

/// Whether two poses are clearly different places for a relocalization (more than 1 m or 10° apart),
/// rather than one peak of the score.
pub fn clearly_different(a: &Rigid2, b: &Rigid2) -> bool {
    (a.translation.vector - b.translation.vector).norm() > 1.0
        || crate::geometry::normalize_angle(a.rotation.angle() - b.rotation.angle()).abs()
            > 10f64.to_radians()
}

/// A coarse score bound check used in tests: the coarse map never reads lower than the fine one.
#[cfg(test)]
fn coarse_reads_at_least_fine(
    fine: &ProbabilityGrid,
    coarse: &ProbabilityGrid,
    factor: i32,
) -> bool {
    let l = fine.limits();
    (0..l.height).all(|y| {
        (0..l.width).all(|x| {
            let c = crate::grid::CellIndex::new(x, y);
            let cc = crate::grid::CellIndex::new(x / factor, y / factor);
            !fine.is_known(&c) || coarse.probability(&cc) >= fine.probability(&c)
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Rigid2Ext as _, rigid2};
    use crate::grid::CellIndex;
    use crate::scan_matching::test_support::{room_grid, room_scan};

    #[test]
    fn max_filter_equals_brute_force() {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.1, Vector2::zeros(), 13, 9));
        for (k, (x, y)) in [(0, 0), (5, 4), (12, 8), (7, 1), (3, 7)]
            .into_iter()
            .enumerate()
        {
            grid.set_probability(&CellIndex::new(x, y), 0.3 + 0.1 * k as f32);
        }
        for radius in 0..4 {
            let filtered = max_filtered(&grid, radius);
            let r = radius as i32;
            for y in 0..9 {
                for x in 0..13 {
                    let expected = (-r..=r)
                        .flat_map(|dy| (-r..=r).map(move |dx| (x + dx, y + dy)))
                        .filter(|&(xx, yy)| (0..13).contains(&xx) && (0..9).contains(&yy))
                        .map(|(xx, yy)| grid.values()[(yy * 13 + xx) as usize])
                        .max()
                        .unwrap();
                    assert_eq!(
                        filtered.values()[(y * 13 + x) as usize],
                        expected,
                        "{x} {y} r {radius}"
                    );
                }
            }
        }
    }

    #[test]
    fn downsampling_keeps_maxima() {
        let grid = room_grid();
        for factor in [1, 2, 3] {
            let coarse = max_downsampled(&grid, factor as u32);
            assert!(coarse_reads_at_least_fine(&grid, &coarse, factor));
        }
    }

    #[test]
    fn finds_a_scan_anywhere_at_any_heading() {
        let grid = room_grid();
        let truth = rigid2(0.7, -0.4, 2.5);
        let points = room_scan(&truth);
        let relocalizer = Relocalizer::new(&grid, RelocalizerOptions::default());
        let found = relocalizer.relocalize(&points).expect("relocalized");
        assert!(
            (found.pose.translation.vector - truth.translation.vector).norm() < 0.05,
            "{found:?}"
        );
        assert!(
            crate::geometry::normalize_angle(found.pose.theta() - truth.theta()).abs() < 0.02,
            "{found:?}"
        );
    }

    #[test]
    fn a_symmetric_room_reports_its_ambiguity() {
        // A bare 6 m × 4 m rectangle looks the same turned by 180°: the runner-up ties with the winner.
        let limits = MapLimits::new(0.05, Vector2::new(-1.0, -1.0), 160, 120);
        let mut grid = ProbabilityGrid::new(limits.clone());
        let on_wall = |x: f64, y: f64| {
            let near = |v: f64, w: f64| (v - w).abs() < 0.05;
            ((near(x, 0.0) || near(x, 6.0)) && (-0.05..=4.05).contains(&y))
                || ((near(y, 0.0) || near(y, 4.0)) && (-0.05..=6.05).contains(&x))
        };
        for iy in 0..limits.height {
            for ix in 0..limits.width {
                let index = crate::grid::CellIndex::new(ix, iy);
                let c = limits.cell_center(&index);
                grid.set_probability(&index, if on_wall(c.x, c.y) { 0.9 } else { 0.1 });
            }
        }
        let robot = rigid2(2.0, 1.5, 0.3);
        let inverse = robot.inverse();
        let mut points = Vec::new();
        for k in 0..=60 {
            let t = f64::from(k) * 0.1;
            for w in [
                Point2::new(t, 0.0),
                Point2::new(t, 4.0),
                Point2::new(0.0, t * 4.0 / 6.0),
                Point2::new(6.0, t * 4.0 / 6.0),
            ] {
                points.push((inverse * w).cast::<f32>());
            }
        }
        let found = Relocalizer::new(&grid, RelocalizerOptions::default())
            .relocalize(&points)
            .expect("fits");
        let runner_up = found.runner_up_score.expect("the turned pose fits too");
        assert!(runner_up > found.score - 0.02, "{found:?}");

        // The lab-like room of the other tests is not symmetric: a clear margin.
        let truth = rigid2(0.7, -0.4, 2.5);
        let found = Relocalizer::new(&room_grid(), RelocalizerOptions::default())
            .relocalize(&room_scan(&truth))
            .expect("relocalized");
        assert!(
            found.runner_up_score.is_none_or(|r| r < found.score - 0.05),
            "{found:?}"
        );
    }

    #[test]
    fn refuses_a_scan_that_fits_nowhere() {
        let grid = room_grid();
        let options = RelocalizerOptions {
            min_score: 0.85,
            coarse_min_score: 0.85,
            ..RelocalizerOptions::default()
        };
        // A scan of a much larger room fits the small room nowhere.
        let points: Vec<Point2<f32>> = (0..200)
            .map(|k| {
                let a = k as f32 * 0.0314;
                Point2::new(20.0 * a.cos(), 20.0 * a.sin())
            })
            .collect();
        assert!(
            Relocalizer::new(&grid, options)
                .relocalize(&points)
                .is_none()
        );
    }

    #[test]
    fn options_are_checked() {
        assert!(RelocalizerOptions::default().validate().is_ok());
        let bad = RelocalizerOptions {
            coarse_factor: 0,
            ..RelocalizerOptions::default()
        };
        assert!(bad.validate().is_err());
        let bad = RelocalizerOptions {
            min_score: 0.95,
            ..RelocalizerOptions::default()
        };
        assert!(bad.validate().is_err());
    }
}
