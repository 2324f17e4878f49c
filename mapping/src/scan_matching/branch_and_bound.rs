//! Branch-and-bound correlative scan matching: Hess, Kohler, Rapp, Andor, "Real-Time Loop Closure in 2D LIDAR
//! SLAM", ICRA 2016, §V (Cartographer's fast correlative scan matcher), on Olson's discretized search space.
//!
//! The candidate set is the same as the real-time correlative matcher's — rotations at the angular step of
//! the scan's farthest point × whole-cell translations — but far larger windows (metres, or the whole grid
//! and all rotations). A node of depth `d` stands for the `2^d × 2^d` block of translations starting at its
//! offset for one rotation; its score, read from the depth-`d` precomputation grid, bounds the score of every
//! leaf in the block. The search is depth-first: the top-level nodes (depth `D`) are sorted by bound, each
//! node's (up to) four children are scored and visited best first, and a node is pruned as soon as its bound
//! cannot beat the best leaf found so far (nor reach `min_score`). Leaves are scored exactly on the original
//! grid, so the result is the exact maximum over the candidate set. Scores are integer sums (see
//! `LEAF_SCALE`), so bounds and leaves compare exactly, and a node's summation stops as soon as the points
//! left cannot lift it to the best leaf.
//!
//! Trade-off: the precomputation grids cost `O(D · cells)` time and about `D` bytes per cell (plus padding)
//! once per grid, and the matcher is immutable — rebuild it if the grid changes. In exchange a search
//! touches only a small fraction of the candidates when one pose clearly fits best; in clutter with
//! loose bounds it degrades gracefully toward exhaustive search.

use nalgebra::Point2;
use serde::{Deserialize, Serialize};

use super::correlative::SearchSpace;
use super::precomputation_grid::{MAX_GRID_VALUE, MAX_QUANTIZED, PrecomputationGrid, build_stack};
use super::{MatchError, check_non_negative};
use crate::geometry::{Rigid2, rigid2};
use crate::grid::{CellIndex, MAX_PROBABILITY, MIN_PROBABILITY, MapLimits, ProbabilityGrid};

/// Largest accepted [`FastCorrelativeScanMatcherOptions::branch_and_bound_depth`].
pub const MAX_BRANCH_AND_BOUND_DEPTH: u32 = 16;

/// Options of [`FastCorrelativeScanMatcher`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FastCorrelativeScanMatcherOptions {
    /// Half-width in metres of the square translation window searched by
    /// [`FastCorrelativeScanMatcher::match_near`]. Default 7 m.
    pub linear_search_window: f64,
    /// Half-width in radians of the rotation window searched by [`FastCorrelativeScanMatcher::match_near`].
    /// Default 30° (0.524 rad).
    pub angular_search_window: f64,
    /// Number of precomputation grids; the coarsest groups `2^depth × 2^depth` translations. 0 means
    /// exhaustive search. Default 7 (128 cells, 6.4 m at 5 cm).
    pub branch_and_bound_depth: u32,
}

impl Default for FastCorrelativeScanMatcherOptions {
    fn default() -> Self {
        Self {
            linear_search_window: 7.0,
            angular_search_window: 30f64.to_radians(),
            branch_and_bound_depth: 7,
        }
    }
}

impl FastCorrelativeScanMatcherOptions {
    /// Checks the windows (finite, non-negative, angular at most π) and the depth (at most
    /// [`MAX_BRANCH_AND_BOUND_DEPTH`]).
    pub fn validate(&self) -> Result<(), MatchError> {
        check_non_negative("linear_search_window", self.linear_search_window)?;
        check_non_negative("angular_search_window", self.angular_search_window)?;
        if self.angular_search_window > std::f64::consts::PI {
            return Err(MatchError::InvalidOption {
                field: "angular_search_window",
                reason: "must be at most π",
            });
        }
        if self.branch_and_bound_depth > MAX_BRANCH_AND_BOUND_DEPTH {
            return Err(MatchError::InvalidOption {
                field: "branch_and_bound_depth",
                reason: "must be at most 16",
            });
        }
        Ok(())
    }
}

/// A scan matching result.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Match {
    /// `grid_from_tracking`.
    pub pose: Rigid2,
    /// Mean grid probability at the scan's points under `pose`, in `[MIN_PROBABILITY, MAX_PROBABILITY]`.
    pub score: f32,
}

/// Leaf scores are `Σ (v − 1)` over stored values `v` and bounds `Σ q` over quantized values `q`; both are
/// scaled to the common unit `(MAX_PROBABILITY − MIN_PROBABILITY) / (32766 · 255)` so they compare exactly.
const LEAF_SCALE: u64 = MAX_QUANTIZED as u64;
const BOUND_SCALE: u64 = (MAX_GRID_VALUE - 1) as u64;
const UNITS_PER_PROBABILITY_RANGE: f64 = (LEAF_SCALE * BOUND_SCALE) as f64;

/// One node of the search tree: a rotation index, a translation offset (cells) and the score (in the units
/// above) of the node — exact for a leaf, an upper bound otherwise.
#[derive(Clone, Copy, Debug, Default)]
struct Candidate {
    scan: usize,
    dx: i32,
    dy: i32,
    units: u64,
}

/// Branch-and-bound scan matcher against one immutable grid. Owns a copy of the grid values and its
/// precomputation grids; `Sync`, so one matcher can serve several threads.
#[derive(Clone, Debug)]
pub struct FastCorrelativeScanMatcher {
    options: FastCorrelativeScanMatcherOptions,
    limits: MapLimits,
    values: Vec<u16>,
    /// Depths `1..=branch_and_bound_depth`.
    levels: Vec<PrecomputationGrid>,
}

impl FastCorrelativeScanMatcher {
    /// Precomputes the multi-resolution maximum grids of `grid` (validate `options` first; the depth is
    /// clamped to [`MAX_BRANCH_AND_BOUND_DEPTH`]).
    pub fn new(grid: &ProbabilityGrid, options: FastCorrelativeScanMatcherOptions) -> Self {
        let depth = options
            .branch_and_bound_depth
            .min(MAX_BRANCH_AND_BOUND_DEPTH);
        Self {
            levels: build_stack(grid, depth),
            options,
            limits: grid.limits().clone(),
            values: grid.values().to_vec(),
        }
    }

    /// The options.
    pub fn options(&self) -> &FastCorrelativeScanMatcherOptions {
        &self.options
    }

    /// The geometry of the grid matched against.
    pub fn limits(&self) -> &MapLimits {
        &self.limits
    }

    /// Bytes held for cells: the grid copy (2 per cell) plus the precomputation grids (1 per padded cell).
    pub fn memory_bytes(&self) -> usize {
        2 * self.values.len()
            + self
                .levels
                .iter()
                .map(PrecomputationGrid::memory_bytes)
                .sum::<usize>()
    }

    /// The best pose within the options' linear and angular windows around `initial` (`grid_from_tracking`),
    /// if its score reaches `min_score`.
    pub fn match_near(
        &self,
        initial: &Rigid2,
        points: &[Point2<f32>],
        min_score: f32,
    ) -> Option<Match> {
        self.search(&self.near_space(initial, points), min_score)
    }

    /// Up to `count` distinct poses within explicit windows (`linear_window` metres, `angular_window`
    /// radians) around `initial`, best first, each reaching `min_score` (peaks as in
    /// [`Self::match_full_candidates`]). The first result equals [`Self::match_within`]'s; the second is
    /// the runner-up a loop closure must beat.
    pub fn match_within_candidates(
        &self,
        initial: &Rigid2,
        points: &[Point2<f32>],
        min_score: f32,
        linear_window: f64,
        angular_window: f64,
        count: usize,
    ) -> Vec<Match> {
        let mut space =
            SearchSpace::around(initial, points, &self.limits, linear_window, angular_window);
        space.shrink_to_fit(&self.limits);
        self.search_many(&space, min_score, count.max(1))
    }

    /// The best pose within explicit windows (`linear_window` metres, `angular_window` radians) around
    /// `initial`, if its score reaches `min_score`: [`Self::match_near`] with per-call windows.
    pub fn match_within(
        &self,
        initial: &Rigid2,
        points: &[Point2<f32>],
        min_score: f32,
        linear_window: f64,
        angular_window: f64,
    ) -> Option<Match> {
        self.match_within_candidates(initial, points, min_score, linear_window, angular_window, 1)
            .into_iter()
            .next()
    }

    /// The best pose anywhere on the grid, at any rotation (no prior), if its score reaches `min_score`.
    pub fn match_full(&self, points: &[Point2<f32>], min_score: f32) -> Option<Match> {
        self.search(&self.full_space(points), min_score)
    }

    /// Up to `count` distinct poses anywhere on the grid, best first, each reaching `min_score` and
    /// scoring within `score_window` of the best (score units; `f32::INFINITY`: no such bound). Leaves
    /// within [`DISTINCT_TRANSLATION_CELLS`] cells and [`DISTINCT_ROTATION_RAD`] of a better one belong to
    /// the same peak and are not returned separately. The first result equals [`Self::match_full`]'s.
    ///
    /// The window is what makes a whole-map search for rivals affordable on a large map: without it
    /// every branch that might hold the `count`-th best peak is explored, and on a store of look-alike
    /// shelves that is most of the map; with it, branches that cannot come within `score_window` of the
    /// best leaf found so far are cut. The result equals the unbounded search's, less the candidates
    /// below the best by more than the window.
    pub fn match_full_candidates(
        &self,
        points: &[Point2<f32>],
        min_score: f32,
        count: usize,
        score_window: f32,
    ) -> Vec<Match> {
        self.search_bounded(
            &self.full_space(points),
            min_score,
            count.max(1),
            score_window,
        )
    }

    /// The candidate set of [`Self::match_near`].
    fn near_space(&self, initial: &Rigid2, points: &[Point2<f32>]) -> SearchSpace {
        let mut space = SearchSpace::around(
            initial,
            points,
            &self.limits,
            self.options.linear_search_window,
            self.options.angular_search_window,
        );
        space.shrink_to_fit(&self.limits);
        space
    }

    /// The candidate set of [`Self::match_full`]: all rotations, centred on the grid's centre, every
    /// translation at which the scan overlaps the grid.
    fn full_space(&self, points: &[Point2<f32>]) -> SearchSpace {
        let limits = &self.limits;
        let size = f64::from(limits.width.max(0)) + f64::from(limits.height.max(0));
        let center = limits.origin
            + nalgebra::Vector2::new(f64::from(limits.width), f64::from(limits.height))
                * (0.5 * limits.resolution);
        // Covers every offset at which some point can land on the grid; shrink_to_fit trims the rest.
        let max_range = points
            .iter()
            .map(|p| f64::from(p.coords.norm()))
            .fold(0.0, f64::max);
        let window = (size + 4.0) * limits.resolution + max_range;
        let mut space =
            SearchSpace::full_circle(&rigid2(center.x, center.y, 0.0), points, limits, window);
        space.shrink_to_fit(limits);
        space
    }

    fn search(&self, space: &SearchSpace, min_score: f32) -> Option<Match> {
        self.search_many(space, min_score, 1).into_iter().next()
    }

    fn search_many(&self, space: &SearchSpace, min_score: f32, count: usize) -> Vec<Match> {
        self.search_bounded(space, min_score, count, f32::INFINITY)
    }

    fn search_bounded(
        &self,
        space: &SearchSpace,
        min_score: f32,
        count: usize,
        score_window: f32,
    ) -> Vec<Match> {
        let n = space.num_points();
        if n == 0 {
            return Vec::new();
        }
        let units_of = |score: f64| {
            score / f64::from(MAX_PROBABILITY - MIN_PROBABILITY)
                * UNITS_PER_PROBABILITY_RANGE
                * n as f64
        };
        let threshold = units_of(f64::from(min_score - MIN_PROBABILITY));
        // Rounded down: the bound never cuts a leaf the window admits.
        let window_units = if score_window.is_finite() && score_window >= 0.0 {
            units_of(f64::from(score_window)).floor() as u64
        } else {
            u64::MAX
        };
        let mut search = Search {
            matcher: self,
            space,
            min_units: threshold.ceil().max(0.0) as u64,
            window_units,
            best: Vec::with_capacity(count + 1),
            count,
        };
        let depth = self.levels.len() as u32;
        let step = 1usize << depth;
        let mut top = Vec::new();
        for k in 0..space.num_scans() {
            let b = space.bounds(k);
            if b.is_empty() {
                continue;
            }
            for dy in (b.min_y..=b.max_y).step_by(step) {
                for dx in (b.min_x..=b.max_x).step_by(step) {
                    if let Some(units) = search.score(depth, k, dx, dy) {
                        top.push(Candidate {
                            scan: k,
                            dx,
                            dy,
                            units,
                        });
                    }
                }
            }
        }
        top.sort_unstable_by_key(|c| std::cmp::Reverse(c.units));
        search.descend(&top, depth);
        // Leaves offered before a better best was found may lie below its window.
        let floor = search
            .best
            .first()
            .map_or(0, |top| top.units.saturating_sub(window_units));
        search
            .best
            .iter()
            .filter(|leaf| leaf.units >= floor)
            .map(|best| Match {
                pose: space.pose(best.scan, best.dx, best.dy),
                score: (f64::from(MIN_PROBABILITY)
                    + f64::from(MAX_PROBABILITY - MIN_PROBABILITY) * best.units as f64
                        / (UNITS_PER_PROBABILITY_RANGE * n as f64)) as f32,
            })
            .collect()
    }
}

/// Leaves of [`FastCorrelativeScanMatcher::match_full_candidates`] closer than this many cells (in x and
/// in y) …
pub const DISTINCT_TRANSLATION_CELLS: i32 = 10;
/// … and this rotation (radians, 10°) to a better leaf belong to its peak.
pub const DISTINCT_ROTATION_RAD: f64 = 0.1745;

/// Points summed between two checks of the early cut-off in [`sum_unless_below`].
const CUTOFF_CHUNK: usize = 16;

/// `Σ read(c)` over `scan`, or `None` as soon as even `max_per_point` for every remaining point could not
/// bring the sum to `need`.
#[inline]
fn sum_unless_below(
    scan: &[CellIndex],
    need: u64,
    max_per_point: u64,
    mut read: impl FnMut(&CellIndex) -> u64,
) -> Option<u64> {
    let mut sum = 0u64;
    let mut remaining = scan.len() as u64;
    for chunk in scan.chunks(CUTOFF_CHUNK) {
        sum += chunk.iter().map(&mut read).sum::<u64>();
        remaining -= chunk.len() as u64;
        if sum + remaining * max_per_point < need {
            return None;
        }
    }
    Some(sum)
}

/// State of one depth-first search.
struct Search<'a> {
    matcher: &'a FastCorrelativeScanMatcher,
    space: &'a SearchSpace,
    /// `min_score` in score units, rounded up.
    min_units: u64,
    /// How far below the best leaf so far another may score (units; `u64::MAX`: unbounded).
    window_units: u64,
    /// The best leaves of distinct peaks so far, best first (at most `count`).
    best: Vec<Candidate>,
    count: usize,
}

impl Search<'_> {
    /// The smallest score (units) that would improve on the best leaf so far and reach `min_score`.
    fn need(&self) -> u64 {
        let within = self
            .best
            .first()
            .map_or(0, |top| top.units.saturating_sub(self.window_units));
        let need = if self.best.len() < self.count {
            self.min_units
        } else {
            self.best
                .last()
                .map_or(self.min_units, |worst| self.min_units.max(worst.units + 1))
        };
        need.max(within)
    }

    /// Whether two leaves belong to the same peak.
    fn same_peak(&self, a: &Candidate, b: &Candidate) -> bool {
        (a.dx - b.dx).abs() <= DISTINCT_TRANSLATION_CELLS
            && (a.dy - b.dy).abs() <= DISTINCT_TRANSLATION_CELLS
            && crate::geometry::normalize_angle(self.space.angle(a.scan) - self.space.angle(b.scan))
                .abs()
                <= DISTINCT_ROTATION_RAD
    }

    /// Keeps `leaf` among the best distinct leaves (it scores at least [`Self::need`]).
    fn offer(&mut self, leaf: Candidate) {
        if self.count == 1 {
            self.best.clear();
            self.best.push(leaf);
            return;
        }
        if let Some(k) = self.best.iter().position(|b| self.same_peak(b, &leaf)) {
            if self.best[k].units >= leaf.units {
                return;
            }
            self.best.remove(k);
        }
        let at = self.best.partition_point(|b| b.units >= leaf.units);
        self.best.insert(at, leaf);
        self.best.truncate(self.count);
    }

    /// Score units of the node at `depth` for rotated scan `k` and offset `(dx, dy)` — exact at depth 0, an
    /// upper bound above — or `None` if it is certainly below [`Self::need`] (then the summation stops early).
    #[inline]
    fn score(&self, depth: u32, k: usize, dx: i32, dy: i32) -> Option<u64> {
        let need = self.need();
        let scan = self.space.scan(k);
        let (lo, hi) = self.space.scan_box(k);
        let offset = CellIndex::new(dx, dy);
        let m = self.matcher;
        if depth == 0 {
            let (width, height) = (m.limits.width, m.limits.height);
            let max_per_point = u64::from(MAX_GRID_VALUE - 1);
            let need_raw = need.div_ceil(LEAF_SCALE);
            let (dx64, dy64) = (i64::from(dx), i64::from(dy));
            let inside = i64::from(lo.x) + dx64 >= 0
                && i64::from(lo.y) + dy64 >= 0
                && i64::from(hi.x) + dx64 < i64::from(width)
                && i64::from(hi.y) + dy64 < i64::from(height);
            let sum = if inside {
                let base = dy as isize * width as isize + dx as isize;
                let stride = width as isize;
                sum_unless_below(scan, need_raw, max_per_point, |c| {
                    let i = (base + c.y as isize * stride + c.x as isize) as usize;
                    u64::from(m.values[i].saturating_sub(1))
                })
            } else {
                sum_unless_below(scan, need_raw, max_per_point, |c| {
                    let (x, y) = (c.x.wrapping_add(dx), c.y.wrapping_add(dy));
                    if x >= 0 && y >= 0 && x < width && y < height {
                        u64::from(
                            m.values[y as usize * width as usize + x as usize].saturating_sub(1),
                        )
                    } else {
                        0
                    }
                })
            };
            sum.map(|s| s * LEAF_SCALE)
        } else {
            let level = &m.levels[depth as usize - 1];
            let max_per_point = u64::from(MAX_QUANTIZED);
            let need_raw = need.div_ceil(BOUND_SCALE);
            let sum = if let Some((base, stride)) = level.window(lo, hi, offset) {
                let cells = level.cells();
                sum_unless_below(scan, need_raw, max_per_point, |c| {
                    u64::from(cells[(base + c.y as isize * stride + c.x as isize) as usize])
                })
            } else {
                sum_unless_below(scan, need_raw, max_per_point, |c| {
                    u64::from(level.get(c.x.wrapping_add(dx), c.y.wrapping_add(dy)))
                })
            };
            sum.map(|s| s * BOUND_SCALE)
        }
    }

    fn can_improve(&self, units: u64) -> bool {
        units >= self.need()
    }

    /// Visits `candidates` (all at `depth`, sorted by decreasing score) best first.
    fn descend(&mut self, candidates: &[Candidate], depth: u32) {
        for candidate in candidates {
            if !self.can_improve(candidate.units) {
                // Sorted: no later sibling can improve either.
                break;
            }
            if depth == 0 {
                self.offer(*candidate);
                continue;
            }
            let child_depth = depth - 1;
            let half = 1 << child_depth;
            let bounds = self.space.bounds(candidate.scan);
            let mut children = [Candidate::default(); 4];
            let mut count = 0;
            for (ox, oy) in [(0, 0), (half, 0), (0, half), (half, half)] {
                let (dx, dy) = (candidate.dx + ox, candidate.dy + oy);
                if dx > bounds.max_x || dy > bounds.max_y {
                    continue;
                }
                if let Some(units) = self.score(child_depth, candidate.scan, dx, dy) {
                    children[count] = Candidate {
                        scan: candidate.scan,
                        dx,
                        dy,
                        units,
                    };
                    count += 1;
                }
            }
            let children = &mut children[..count];
            children.sort_unstable_by_key(|c| std::cmp::Reverse(c.units));
            self.descend(children, child_depth);
        }
    }
}

#[cfg(test)]
mod tests;
