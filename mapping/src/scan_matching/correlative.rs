//! The discretized candidate set shared by the correlative matchers (Olson, "Real-Time Correlative Scan
//! Matching", ICRA 2009, §III).
//!
//! A search is a set of rotations around a centre pose times a box of whole-cell translations. Each rotation's
//! scan is rotated once and discretized to cell indices, so a translation candidate `(dx, dy)` (in cells) is
//! scored by adding `(dx, dy)` to integer indices — no trigonometry or rounding in the inner loop. The price
//! is that translations are restricted to multiples of the grid resolution and rotations to a step chosen so
//! that the farthest point moves by at most about one cell.

use nalgebra::{Point2, Rotation2, Vector2};

use crate::geometry::{Rigid2, Rigid2Ext as _, rigid2};
use crate::grid::{CellIndex, MapLimits};

/// Slightly shrinks the angular step so the farthest point moves by less than one cell.
const ANGULAR_STEP_SAFETY_MARGIN: f64 = 1.0 - 1e-3;

/// The rotation step (radians) at which the farthest of `points` moves by about one `resolution` (Olson §III-B):
/// the angle subtended by a chord of length `resolution` at radius `max_range`.
pub(crate) fn angular_step(points: &[Point2<f32>], resolution: f64) -> f64 {
    let max_range = points
        .iter()
        .map(|p| f64::from(p.coords.norm()))
        .fold(resolution, f64::max);
    let cos = (1.0 - resolution * resolution / (2.0 * max_range * max_range)).clamp(-1.0, 1.0);
    ANGULAR_STEP_SAFETY_MARGIN * cos.acos()
}

/// Inclusive range of translation offsets, in cells, searched for one rotation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct LinearBounds {
    pub min_x: i32,
    pub max_x: i32,
    pub min_y: i32,
    pub max_y: i32,
}

impl LinearBounds {
    pub fn is_empty(&self) -> bool {
        self.min_x > self.max_x || self.min_y > self.max_y
    }
}

/// Rotated and discretized scans plus the translation box of each, around a centre pose.
#[derive(Clone, Debug)]
pub(crate) struct SearchSpace {
    center: Rigid2,
    resolution: f64,
    num_points: usize,
    /// Rotation offset (radians) of each rotated scan, relative to `center`'s rotation.
    angles: Vec<f64>,
    /// `angles.len() × num_points` cell indices: scan `k` is `cells[k·n .. (k+1)·n]`, the cells of the points
    /// under the pose `(center.translation, center.rotation + angles[k])`.
    cells: Vec<CellIndex>,
    /// Bounding box `(lowest, highest)` of each rotated scan's cells.
    boxes: Vec<(CellIndex, CellIndex)>,
    bounds: Vec<LinearBounds>,
}

impl SearchSpace {
    /// Rotations `center.θ + k·step` for `|k| ≤ ⌈angular_window / step⌉` and translations within
    /// `linear_window` metres (rounded up to whole cells) of `center`.
    pub fn around(
        center: &Rigid2,
        points: &[Point2<f32>],
        limits: &MapLimits,
        linear_window: f64,
        angular_window: f64,
    ) -> Self {
        let step = angular_step(points, limits.resolution);
        let n = Self::rotations_reach(points, limits, angular_window);
        let angles = (-n..=n).map(|k| k as f64 * step).collect();
        Self::new(center, points, limits, linear_window, angles)
    }

    /// The `n` of [`Self::around`]: rotations `k · step` for `|k| ≤ n` cover `angular_window`.
    pub fn rotations_reach(points: &[Point2<f32>], limits: &MapLimits, angular_window: f64) -> i64 {
        let step = angular_step(points, limits.resolution);
        (angular_window / step).ceil().max(0.0) as i64
    }

    /// Rotations covering the whole circle once, `center.θ + k·2π/m` for `k < m` with the step no larger than
    /// [`angular_step`], and translations within `linear_window` metres of `center`.
    pub fn full_circle(
        center: &Rigid2,
        points: &[Point2<f32>],
        limits: &MapLimits,
        linear_window: f64,
    ) -> Self {
        let step = angular_step(points, limits.resolution);
        let m = (std::f64::consts::TAU / step).ceil().max(1.0) as usize;
        let angles = (0..m)
            .map(|k| k as f64 * std::f64::consts::TAU / m as f64)
            .collect();
        Self::new(center, points, limits, linear_window, angles)
    }

    fn new(
        center: &Rigid2,
        points: &[Point2<f32>],
        limits: &MapLimits,
        linear_window: f64,
        angles: Vec<f64>,
    ) -> Self {
        let r = (linear_window / limits.resolution).ceil().max(0.0) as i32;
        let translation = center.translation.vector;
        let mut cells = Vec::with_capacity(angles.len() * points.len());
        for &angle in &angles {
            let rotation = Rotation2::new(center.theta() + angle);
            cells.extend(points.iter().map(|p| {
                let q = rotation * Vector2::new(f64::from(p.x), f64::from(p.y)) + translation;
                limits.cell_index(&Point2::from(q))
            }));
        }
        let boxes = cells
            .chunks(points.len().max(1))
            .map(|scan| {
                scan.iter().fold(
                    (CellIndex::repeat(i32::MAX), CellIndex::repeat(i32::MIN)),
                    |(lo, hi), c| (lo.inf(c), hi.sup(c)),
                )
            })
            .collect();
        let bounds = vec![
            LinearBounds {
                min_x: -r,
                max_x: r,
                min_y: -r,
                max_y: r
            };
            angles.len()
        ];
        Self {
            center: *center,
            resolution: limits.resolution,
            num_points: points.len(),
            angles,
            cells,
            boxes,
            bounds,
        }
    }

    /// Drops translations at which the scan's bounding box (in cells) does not overlap the grid: there every
    /// point reads as unknown, the lowest possible score.
    pub fn shrink_to_fit(&mut self, limits: &MapLimits) {
        if self.num_points == 0 {
            return;
        }
        for k in 0..self.angles.len() {
            let (lo, hi) = self.boxes[k];
            let b = &mut self.bounds[k];
            b.min_x = b.min_x.max(hi.x.saturating_neg());
            b.max_x = b.max_x.min((limits.width - 1).saturating_sub(lo.x));
            b.min_y = b.min_y.max(hi.y.saturating_neg());
            b.max_y = b.max_y.min((limits.height - 1).saturating_sub(lo.y));
        }
    }

    pub fn num_scans(&self) -> usize {
        self.angles.len()
    }

    pub fn num_points(&self) -> usize {
        self.num_points
    }

    /// The discretized points of rotated scan `k` at zero translation offset.
    pub fn scan(&self, k: usize) -> &[CellIndex] {
        &self.cells[k * self.num_points..(k + 1) * self.num_points]
    }

    /// Bounding box `(lowest, highest)` of [`Self::scan`]`(k)`; inverted (empty) for a scan without points.
    pub fn scan_box(&self, k: usize) -> (CellIndex, CellIndex) {
        self.boxes[k]
    }

    pub fn bounds(&self, k: usize) -> LinearBounds {
        self.bounds[k]
    }

    /// Rotation offset (radians) of scan `k` from the centre rotation.
    pub fn angle(&self, k: usize) -> f64 {
        self.angles[k]
    }

    /// Translation offset (metres) of the cell offset `(dx, dy)`.
    pub fn offset_metres(&self, dx: i32, dy: i32) -> Vector2<f64> {
        Vector2::new(f64::from(dx), f64::from(dy)) * self.resolution
    }

    /// The `grid_from_tracking` pose of candidate (scan `k`, offset `(dx, dy)`).
    pub fn pose(&self, k: usize, dx: i32, dy: i32) -> Rigid2 {
        let t = self.center.translation.vector + self.offset_metres(dx, dy);
        rigid2(t.x, t.y, self.center.theta() + self.angles[k])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn angular_step_moves_farthest_point_by_at_most_one_cell() {
        let points = [Point2::new(10.0f32, 0.0), Point2::new(0.0, 2.0)];
        let step = angular_step(&points, 0.05);
        let moved = 2.0 * 10.0 * (step / 2.0).sin();
        assert!(moved < 0.05 && moved > 0.049, "moved {moved}");
        // Degenerate scans (all points at the origin) still get a finite step.
        assert!(angular_step(&[Point2::origin()], 0.05).is_finite());
    }

    #[test]
    fn candidates_cover_the_windows_and_match_transformed_points() {
        let limits = MapLimits::new(0.1, Vector2::new(-5.0, -5.0), 100, 100);
        let points = [Point2::new(3.0f32, 0.5), Point2::new(-1.0, 2.0)];
        let center = rigid2(0.33, -0.71, 0.4);
        let space = SearchSpace::around(&center, &points, &limits, 0.25, 0.1);
        assert_eq!(space.num_scans() % 2, 1);
        let mid = space.num_scans() / 2;
        assert!(space.angle(mid).abs() < 1e-15);
        assert!(space.angle(space.num_scans() - 1) >= 0.1);
        assert_eq!(
            space.bounds(0),
            LinearBounds {
                min_x: -3,
                max_x: 3,
                min_y: -3,
                max_y: 3
            }
        );
        for k in [0, mid, space.num_scans() - 1] {
            let pose = space.pose(k, 2, -1);
            for (p, c) in points.iter().zip(space.scan(k)) {
                let q = pose * nalgebra::convert::<_, Point2<f64>>(*p);
                assert_eq!(limits.cell_index(&q), c + CellIndex::new(2, -1));
            }
        }
        let full = SearchSpace::full_circle(&center, &points, &limits, 0.0);
        let step = full.angle(1);
        assert!(
            step <= angular_step(&points, 0.1)
                && full.angle(full.num_scans() - 1) + step > std::f64::consts::TAU - 1e-9
        );
    }

    #[test]
    fn shrink_to_fit_keeps_exactly_the_overlapping_offsets() {
        let limits = MapLimits::new(1.0, Vector2::zeros(), 10, 8);
        let points = [Point2::new(0.5f32, 0.5), Point2::new(2.5, 0.5)];
        let mut space = SearchSpace::around(&Rigid2::identity(), &points, &limits, 100.0, 0.0);
        space.shrink_to_fit(&limits);
        // Points in cells x ∈ {0, 2}, y = 0: some point inside iff dx ∈ [-2, 9] and dy ∈ [0, 7].
        assert_eq!(
            space.bounds(0),
            LinearBounds {
                min_x: -2,
                max_x: 9,
                min_y: 0,
                max_y: 7
            }
        );
    }
}
