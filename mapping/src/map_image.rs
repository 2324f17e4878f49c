//! What an occupancy grid looks like as a picture: pixel buffers (8-bit gray or RGB, one pixel per cell,
//! top row first) for the site map, the map-change overlay and a simulated store's layout.
//!
//! Only the pixels live here, beside the grid, so that the robot agent (PNG and Nav2 files), the server
//! (PNG and PGM bytes for `GetMapImage` and the web console) and the fleet simulations draw maps the
//! same way without one linking the other. Encoding them (PNG, PGM) is the shells' business: this crate
//! stays free of I/O and of image-format dependencies.

use crate::grid::{CellIndex, ProbabilityGrid};

/// Gray level of unknown cells: ROS `map_server`'s convention (reads back as "unknown" with the
/// thresholds Nav2's map YAML carries).
pub const UNKNOWN_GRAY: u8 = 205;

/// The grid as 8-bit gray, one byte per cell, top row first (the row of largest y), free white,
/// occupied black, unknown gray.
pub fn grid_to_gray(grid: &ProbabilityGrid) -> (u32, u32, Vec<u8>) {
    let limits = grid.limits();
    let (w, h) = (limits.width.max(0), limits.height.max(0));
    let mut pixels = Vec::with_capacity(w as usize * h as usize);
    for row in 0..h {
        let iy = h - 1 - row;
        for ix in 0..w {
            let cell = CellIndex::new(ix, iy);
            pixels.push(if grid.is_known(&cell) {
                (255.0 * (1.0 - grid.probability(&cell)))
                    .round()
                    .clamp(0.0, 255.0) as u8
            } else {
                UNKNOWN_GRAY
            });
        }
    }
    (w as u32, h as u32, pixels)
}

/// A simulated world's layout on day `session` at `resolution` metres per pixel, top row first: static
/// structure (walls, columns, cases, counters, checkstands, shelf frames) black, what changes from day to
/// day (goods, pallets, displays, cart rows, closed doors) gray, free floor white, and one lap of the
/// session's cleaning route red.
pub fn layout_to_rgb(
    store: &crate::simulation::Store,
    session: u32,
    resolution: f64,
) -> (u32, u32, Vec<u8>) {
    let occupancy = store.occupancy(session, resolution);
    let limits = &occupancy.limits;
    let (w, h) = (limits.width.max(0), limits.height.max(0));
    let mut kind = vec![0u8; occupancy.occupied.len()]; // 0 free, 1 movable, 2 static, 3 route
    for (k, occupied) in kind.iter_mut().zip(&occupancy.occupied) {
        if *occupied {
            *k = 1;
        }
    }
    for b in store.structure() {
        let (lo, hi) = (limits.cell_index(&b.min), limits.cell_index(&b.max));
        for y in lo.y.max(0)..=hi.y.min(h - 1) {
            for x in lo.x.max(0)..=hi.x.min(w - 1) {
                let cell = CellIndex::new(x, y);
                if b.contains(&limits.cell_center(&cell))
                    && let Some(i) = limits.flat_index(&cell)
                {
                    kind[i] = 2;
                }
            }
        }
    }
    for pair in store.cleaning_route(session).windows(2) {
        let steps = ((pair[1] - pair[0]).norm() / (0.5 * resolution))
            .ceil()
            .max(1.0);
        for k in 0..=steps as usize {
            let p = pair[0] + (pair[1] - pair[0]) * (k as f64 / steps);
            if let Some(i) = limits.flat_index(&limits.cell_index(&p)) {
                kind[i] = 3;
            }
        }
    }
    let mut pixels = Vec::with_capacity(3 * w as usize * h as usize);
    for row in 0..h {
        let iy = h - 1 - row;
        for ix in 0..w {
            let k = limits
                .flat_index(&CellIndex::new(ix, iy))
                .map_or(0, |i| kind[i]);
            pixels.extend_from_slice(match k {
                1 => &[150, 150, 150],
                2 => &[0, 0, 0],
                3 => &[220, 30, 30],
                _ => &[255, 255, 255],
            });
        }
    }
    (w as u32, h as u32, pixels)
}

/// The map-change picture as 8-bit RGB, top row first: unchanged occupied cells blue, removed green,
/// added red, everything else white (the paper's colours).
pub fn map_change_to_rgb(change: &crate::lifelong::MapChange) -> (u32, u32, Vec<u8>) {
    use crate::lifelong::CellChange;
    let (w, h) = (change.limits.width.max(0), change.limits.height.max(0));
    let mut pixels = Vec::with_capacity(3 * w as usize * h as usize);
    for row in 0..h {
        let iy = h - 1 - row;
        for ix in 0..w {
            let rgb = match change.cells[(iy * w + ix) as usize] {
                Some(CellChange::Unchanged) => [0, 0, 255],
                Some(CellChange::Removed) => [0, 170, 0],
                Some(CellChange::Added) => [230, 0, 0],
                None => [255, 255, 255],
            };
            pixels.extend_from_slice(&rgb);
        }
    }
    (w as u32, h as u32, pixels)
}

#[cfg(test)]
mod tests {
    use crate::grid::MapLimits;
    use nalgebra::Vector2;

    use super::*;

    #[test]
    fn gray_image_is_top_row_first_with_ros_conventions() {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.1, Vector2::zeros(), 2, 2));
        grid.set_probability(&CellIndex::new(0, 1), 0.9); // top-left occupied
        grid.set_probability(&CellIndex::new(1, 0), 0.1); // bottom-right free
        let (w, h, px) = grid_to_gray(&grid);
        assert_eq!((w, h), (2, 2));
        assert_eq!(px[0], 26); // 255 · (1 − 0.9), rounded
        assert_eq!(px[1], UNKNOWN_GRAY);
        assert_eq!(px[3], 230);
    }
}
