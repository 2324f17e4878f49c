//! A smooth view of a [`ProbabilityGrid`]: bicubic (Catmull–Rom) interpolation of the cell probabilities
//! over the cell centres, with its analytic gradient.
//!
//! Along each axis the interpolant through samples `p₀..p₃` at `−1, 0, 1, 2` is the cubic Hermite spline
//! with central-difference tangents, `f(t) = p₁ + t·(p₂−p₀)/2 + t²·(p₀ − 5p₁/2 + 2p₂ − p₃/2)
//! + t³·(3(p₁−p₂)/2 + (p₃−p₀)/2)` for `t ∈ [0, 1]`; the 2D value is that spline applied to four row splines
//! (as in Ceres' `BiCubicInterpolator`). The result passes through every cell value at the cell's centre and
//! is C¹, which is what a gradient-based matcher needs; the price is 16 cell reads per evaluation and small
//! overshoots next to sharp edges. Unknown and out-of-grid cells read as
//! [`MIN_PROBABILITY`](crate::grid::MIN_PROBABILITY), so far outside the grid the value is constant.

use nalgebra::{Point2, Vector2};

use crate::grid::{ProbabilityGrid, value_to_probability};

/// Bicubic interpolation of a borrowed grid. Building one is free (no precomputation).
#[derive(Clone, Copy, Debug)]
pub struct InterpolatedGrid<'a> {
    values: &'a [u16],
    width: i32,
    height: i32,
    origin: Vector2<f64>,
    inv_resolution: f64,
}

/// One axis of the Catmull–Rom spline: value and derivative with respect to `t` at `t ∈ [0, 1]`.
#[inline]
fn cubic(p: [f64; 4], t: f64) -> (f64, f64) {
    let b = 0.5 * (p[2] - p[0]);
    let c = p[0] - 2.5 * p[1] + 2.0 * p[2] - 0.5 * p[3];
    let d = 1.5 * (p[1] - p[2]) + 0.5 * (p[3] - p[0]);
    (
        p[1] + t * (b + t * (c + t * d)),
        b + t * (2.0 * c + 3.0 * t * d),
    )
}

impl<'a> InterpolatedGrid<'a> {
    /// A view of `grid`.
    pub fn new(grid: &'a ProbabilityGrid) -> Self {
        let limits = grid.limits();
        Self {
            values: grid.values(),
            width: limits.width,
            height: limits.height,
            origin: limits.origin,
            inv_resolution: 1.0 / limits.resolution,
        }
    }

    #[inline]
    fn cell(&self, x: i32, y: i32) -> f64 {
        let value = if x >= 0 && y >= 0 && x < self.width && y < self.height {
            self.values[y as usize * self.width as usize + x as usize]
        } else {
            0
        };
        f64::from(value_to_probability(value))
    }

    /// The interpolated probability at world point `p` and its gradient with respect to `p` (per metre).
    #[inline]
    pub fn evaluate(&self, p: &Point2<f64>) -> (f64, Vector2<f64>) {
        // Continuous cell coordinates in which cell centres sit at integers.
        let u = (p.x - self.origin.x) * self.inv_resolution - 0.5;
        let v = (p.y - self.origin.y) * self.inv_resolution - 0.5;
        // Beyond two cells outside the grid every sample is the minimum: constant value, zero gradient.
        // (Also catches NaN.)
        let in_reach = u > -3.0
            && v > -3.0
            && u < f64::from(self.width) + 2.0
            && v < f64::from(self.height) + 2.0;
        if !in_reach {
            return (self.cell(-1, -1), Vector2::zeros());
        }
        let (fu, fv) = (u.floor(), v.floor());
        let (tx, ty) = (u - fu, v - fv);
        let (i, j) = (fu as i32 - 1, fv as i32 - 1);
        let mut rows = [0.0; 4];
        let mut row_slopes = [0.0; 4];
        if i >= 0 && j >= 0 && i + 3 < self.width && j + 3 < self.height {
            let w = self.width as usize;
            for (r, (row, slope)) in rows.iter_mut().zip(&mut row_slopes).enumerate() {
                let start = (j as usize + r) * w + i as usize;
                let s = &self.values[start..start + 4];
                let samples = [
                    f64::from(value_to_probability(s[0])),
                    f64::from(value_to_probability(s[1])),
                    f64::from(value_to_probability(s[2])),
                    f64::from(value_to_probability(s[3])),
                ];
                (*row, *slope) = cubic(samples, tx);
            }
        } else {
            for (r, (row, slope)) in rows.iter_mut().zip(&mut row_slopes).enumerate() {
                let y = j + r as i32;
                let samples = [
                    self.cell(i, y),
                    self.cell(i + 1, y),
                    self.cell(i + 2, y),
                    self.cell(i + 3, y),
                ];
                (*row, *slope) = cubic(samples, tx);
            }
        }
        let (value, d_dv) = cubic(rows, ty);
        let (d_du, _) = cubic(row_slopes, ty);
        (value, Vector2::new(d_du, d_dv) * self.inv_resolution)
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng as _, SeedableRng as _};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::grid::{CellIndex, MIN_PROBABILITY, MapLimits};

    fn random_grid(seed: u64) -> ProbabilityGrid {
        let mut rng = Pcg64::seed_from_u64(seed);
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::new(-0.3, 0.2), 12, 9));
        for v in grid.values_mut() {
            if rng.random_bool(0.8) {
                *v = rng.random_range(1..=32767);
            }
        }
        grid
    }

    #[test]
    fn equals_cell_value_at_cell_centres() {
        let grid = random_grid(1);
        let interpolated = InterpolatedGrid::new(&grid);
        for iy in -2..11 {
            for ix in -2..14 {
                let index = CellIndex::new(ix, iy);
                let (value, _) = interpolated.evaluate(&grid.limits().cell_center(&index));
                assert!(
                    (value - f64::from(grid.probability(&index))).abs() < 1e-9,
                    "cell {ix},{iy}"
                );
            }
        }
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let grid = random_grid(2);
        let interpolated = InterpolatedGrid::new(&grid);
        let mut rng = Pcg64::seed_from_u64(3);
        let h = 1e-6;
        for _ in 0..500 {
            // Includes points near and beyond the border.
            let p = Point2::new(rng.random_range(-0.5..0.5), rng.random_range(0.0..0.7));
            let (_, gradient) = interpolated.evaluate(&p);
            let dx = (interpolated.evaluate(&Point2::new(p.x + h, p.y)).0
                - interpolated.evaluate(&Point2::new(p.x - h, p.y)).0)
                / (2.0 * h);
            let dy = (interpolated.evaluate(&Point2::new(p.x, p.y + h)).0
                - interpolated.evaluate(&Point2::new(p.x, p.y - h)).0)
                / (2.0 * h);
            assert!(
                (gradient.x - dx).abs() < 1e-4 * (1.0 + dx.abs()),
                "{p:?}: {gradient:?} vs {dx}"
            );
            assert!(
                (gradient.y - dy).abs() < 1e-4 * (1.0 + dy.abs()),
                "{p:?}: {gradient:?} vs {dy}"
            );
        }
    }

    #[test]
    fn is_continuous_across_cell_borders() {
        let grid = random_grid(4);
        let interpolated = InterpolatedGrid::new(&grid);
        // Cell-centre lines (integer u) are where the spline pieces join.
        let y = 0.2 + 0.05 * 4.3;
        for ix in 0..12 {
            let x = -0.3 + 0.05 * (f64::from(ix) + 0.5);
            let (a, ga) = interpolated.evaluate(&Point2::new(x - 1e-9, y));
            let (b, gb) = interpolated.evaluate(&Point2::new(x + 1e-9, y));
            assert!(
                (a - b).abs() < 1e-6 && (ga - gb).norm() < 1e-4,
                "{ix}: {a} {b} {ga} {gb}"
            );
        }
    }

    #[test]
    fn far_outside_reads_min_probability_with_zero_gradient() {
        let grid = random_grid(5);
        let interpolated = InterpolatedGrid::new(&grid);
        for p in [
            Point2::new(100.0, 0.3),
            Point2::new(-1e30, 1e30),
            Point2::new(f64::NAN, 0.0),
        ] {
            let (value, gradient) = interpolated.evaluate(&p);
            assert!((value - f64::from(MIN_PROBABILITY)).abs() < 1e-12);
            assert_eq!(gradient, Vector2::zeros());
        }
    }
}
