//! Precomputation grids for branch-and-bound scan matching (Hess et al., "Real-Time Loop Closure in 2D LIDAR
//! SLAM", ICRA 2016, §V-C): at depth `d`, cell `k` holds the maximum of the original grid over the
//! `2^d × 2^d` block of cells `[k, k + 2^d)`, so the sum over a scan's points is an upper bound of the score
//! of every translation in that block.
//!
//! Each depth is built from the previous one with the doubling identity
//! `max[k, k+2w) = max(max[k, k+w), max[k+w, k+2w))`, separably along x then y: one pass per depth, O(cells),
//! equivalent to a sliding-window maximum of width `2^d` over the original grid. The grid at depth `d` is
//! padded by `2^d − 1` cells below and left, where a block still overlaps the map; farther out (and above,
//! right) every block is unknown and reads 0 without being stored.
//!
//! Values are quantized to `u8` and rounded **up** (`q = ⌈(v−1)·255/32766⌉` for a stored value `v`), so the
//! bounds stay valid upper bounds of the exact score and a depth costs one byte per cell; the exact score of
//! a leaf is read from the original grid.

use crate::grid::{CellIndex, ProbabilityGrid, UNKNOWN_VALUE};

/// Largest stored grid value (probability [`MAX_PROBABILITY`](crate::grid::MAX_PROBABILITY)).
pub(crate) const MAX_GRID_VALUE: u16 = 32767;
/// Largest quantized value.
pub(crate) const MAX_QUANTIZED: u8 = u8::MAX;

/// Quantizes a stored grid value to `0..=255`, rounding up; unknown reads as 0 like the minimum.
pub(crate) fn quantize(value: u16) -> u8 {
    if value == UNKNOWN_VALUE {
        return 0;
    }
    let above_min = u32::from(value.min(MAX_GRID_VALUE) - 1);
    let range = u32::from(MAX_GRID_VALUE - 1);
    above_min
        .saturating_mul(u32::from(MAX_QUANTIZED))
        .div_ceil(range) as u8
}

/// Windowed maxima of a grid at one depth.
#[derive(Clone, Debug)]
pub(crate) struct PrecomputationGrid {
    /// `2^depth − 1`: stored cell `(0, 0)` is original cell `(−pad, −pad)`.
    pad: i32,
    width: i32,
    height: i32,
    cells: Vec<u8>,
}

impl PrecomputationGrid {
    /// Depth 0: the quantized grid itself.
    fn base(grid: &ProbabilityGrid) -> Self {
        let limits = grid.limits();
        Self {
            pad: 0,
            width: limits.width.max(0),
            height: limits.height.max(0),
            cells: grid.values().iter().map(|&v| quantize(v)).collect(),
        }
    }

    /// The next depth: blocks twice as wide.
    fn doubled(&self) -> Self {
        let half = self.pad + 1;
        let pad = 2 * half - 1;
        let (width, height) = (self.width + half, self.height + half);
        // Maximum along x into a buffer with the new width and the old height.
        let mut along_x = vec![0u8; width as usize * self.height as usize];
        let (old_width, shift) = (self.width as usize, half as usize);
        for y in 0..self.height {
            let src = &self.cells[(y * self.width) as usize..((y + 1) * self.width) as usize];
            let dst = &mut along_x[(y * width) as usize..((y + 1) * width) as usize];
            // New stored column i is original cell i − pad, i.e. the maximum of old stored columns i
            // and i − half (0 where either is outside: the minimum of a quantized value). Two passes
            // over whole slices, which the compiler vectorizes: column i first, then i − half.
            dst[..old_width].copy_from_slice(src);
            for (d, a) in dst[shift..shift + old_width].iter_mut().zip(src) {
                *d = (*d).max(*a);
            }
        }
        let mut cells = vec![0u8; width as usize * height as usize];
        for y in 0..height {
            let dst = &mut cells[(y * width) as usize..((y + 1) * width) as usize];
            let row = |r: i32| {
                (0..self.height)
                    .contains(&r)
                    .then(|| &along_x[(r * width) as usize..((r + 1) * width) as usize])
            };
            match (row(y - half), row(y)) {
                (Some(a), Some(b)) => {
                    for ((d, a), b) in dst.iter_mut().zip(a).zip(b) {
                        *d = (*a).max(*b);
                    }
                }
                (Some(r), None) | (None, Some(r)) => dst.copy_from_slice(r),
                (None, None) => {}
            }
        }
        Self {
            pad,
            width,
            height,
            cells,
        }
    }

    /// The quantized maximum over original cells `[x, x+2^d) × [y, y+2^d)`; 0 where that block misses the
    /// grid.
    #[inline]
    pub fn get(&self, x: i32, y: i32) -> u8 {
        let (x, y) = (x.wrapping_add(self.pad), y.wrapping_add(self.pad));
        if x >= 0 && y >= 0 && x < self.width && y < self.height {
            self.cells[y as usize * self.width as usize + x as usize]
        } else {
            0
        }
    }

    /// If every original cell of the box `[lo + offset, hi + offset]` is stored, the flat index of original
    /// cell `offset` (which may itself lie outside) and the row stride: cell `offset + c` for `c` in
    /// `[lo, hi]` is then at `base + c.y·stride + c.x`, with no bounds to check but the slice's own.
    #[inline]
    pub fn window(
        &self,
        lo: CellIndex,
        hi: CellIndex,
        offset: CellIndex,
    ) -> Option<(isize, isize)> {
        let pad = i64::from(self.pad);
        let (ox, oy) = (i64::from(offset.x) + pad, i64::from(offset.y) + pad);
        let inside = i64::from(lo.x) + ox >= 0
            && i64::from(lo.y) + oy >= 0
            && i64::from(hi.x) + ox < i64::from(self.width)
            && i64::from(hi.y) + oy < i64::from(self.height);
        inside.then(|| {
            (
                (oy * i64::from(self.width) + ox) as isize,
                self.width as isize,
            )
        })
    }

    /// Stored cells, row-major; see [`Self::window`].
    #[inline]
    pub fn cells(&self) -> &[u8] {
        &self.cells
    }

    /// Bytes of cell storage.
    pub fn memory_bytes(&self) -> usize {
        self.cells.len()
    }
}

/// Precomputation grids for depths `1..=max_depth` (depth 0 is the original grid).
pub(crate) fn build_stack(grid: &ProbabilityGrid, max_depth: u32) -> Vec<PrecomputationGrid> {
    let base = PrecomputationGrid::base(grid);
    let mut levels: Vec<PrecomputationGrid> = Vec::with_capacity(max_depth as usize);
    for _ in 0..max_depth {
        // Each depth from the one before, kept as built (no copy).
        let next = levels.last().unwrap_or(&base).doubled();
        levels.push(next);
    }
    levels
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector2;
    use rand::{Rng as _, SeedableRng as _};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::grid::{CellIndex, MapLimits};

    #[test]
    fn quantization_rounds_up_and_is_monotone() {
        assert_eq!(quantize(UNKNOWN_VALUE), 0);
        assert_eq!(quantize(1), 0);
        assert_eq!(quantize(2), 1);
        assert_eq!(quantize(MAX_GRID_VALUE), MAX_QUANTIZED);
        let mut previous = 0;
        for v in 1..=MAX_GRID_VALUE {
            let q = quantize(v);
            assert!(q >= previous);
            previous = q;
            let exact = f64::from(v - 1) / f64::from(MAX_GRID_VALUE - 1);
            let bound = f64::from(q) / f64::from(MAX_QUANTIZED);
            assert!(bound >= exact && bound - exact < 1.0 / 255.0, "{v}");
        }
    }

    #[test]
    fn equals_brute_force_window_maximum() {
        let mut rng = Pcg64::seed_from_u64(7);
        let (w, h) = (13, 9);
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::zeros(), w, h));
        for v in grid.values_mut() {
            if rng.random_bool(0.6) {
                *v = rng.random_range(1..=MAX_GRID_VALUE);
            }
        }
        let levels = build_stack(&grid, 4);
        assert_eq!(levels.len(), 4);
        for (d, level) in levels.iter().enumerate() {
            let width = 1 << (d + 1);
            assert_eq!(
                level.memory_bytes(),
                ((w + width - 1) * (h + width - 1)) as usize
            );
            for y in -20..20 {
                for x in -20..25 {
                    let mut expected = 0;
                    for yy in y..y + width {
                        for xx in x..x + width {
                            if (0..w).contains(&xx) && (0..h).contains(&yy) {
                                let v = grid.values()[(yy * w + xx) as usize];
                                expected = expected.max(quantize(v));
                            }
                        }
                    }
                    assert_eq!(level.get(x, y), expected, "depth {} cell {x},{y}", d + 1);
                }
            }
        }
    }

    #[test]
    fn window_addresses_the_same_cells_as_get() {
        let mut rng = Pcg64::seed_from_u64(8);
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::zeros(), 11, 7));
        for v in grid.values_mut() {
            *v = rng.random_range(0..=MAX_GRID_VALUE);
        }
        let levels = build_stack(&grid, 2);
        let level = &levels[1];
        let (mut some, mut none) = (0, 0);
        for _ in 0..2000 {
            let lo = CellIndex::new(rng.random_range(-8..8), rng.random_range(-8..8));
            let hi = lo + CellIndex::new(rng.random_range(0..6), rng.random_range(0..6));
            let offset = CellIndex::new(rng.random_range(-6..6), rng.random_range(-6..6));
            let stored = |c: CellIndex| {
                let p = c + offset + CellIndex::repeat(3);
                p.x >= 0 && p.y >= 0 && p.x < 11 + 3 && p.y < 7 + 3
            };
            if let Some((base, stride)) = level.window(lo, hi, offset) {
                some += 1;
                assert!(stored(lo) && stored(hi));
                for y in lo.y..=hi.y {
                    for x in lo.x..=hi.x {
                        let i = (base + y as isize * stride + x as isize) as usize;
                        assert_eq!(level.cells()[i], level.get(x + offset.x, y + offset.y));
                    }
                }
            } else {
                none += 1;
                assert!(!(stored(lo) && stored(hi)));
            }
        }
        assert!(some > 100 && none > 100, "{some} {none}");
    }
}
