//! What an occupancy grid looks like as a picture: pixel buffers (8-bit gray or RGB, one pixel per cell,
//! top row first) for the site map and the map-change overlay, and the grid in the format of Nav2's
//! `map_server` (binary PGM and the YAML naming it). A simulated store's layout picture is the
//! `simulator` crate's (`layout_to_rgb`), so the server links no simulator.
//!
//! The pixels live here, beside the grid, so that the robot agent (PNG and Nav2 files), the server
//! (PNG, PGM and YAML for `GetMapImage` and the web console) and the fleet simulations draw maps the
//! same way without one linking the other. This crate stays free of I/O and of image-format
//! dependencies: it returns bytes and text, the shells write them, and PNG encoding is
//! `proto::encode_png`'s.

use crate::grid::{CellIndex, MapLimits, ProbabilityGrid};

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

/// 8-bit gray pixels (`width` × `height`, top row first, as [`grid_to_gray`] gives them) as a binary
/// PGM (P5), the image format of Nav2's `map_server`.
pub fn gray_to_pgm(width: u32, height: u32, pixels: &[u8]) -> Vec<u8> {
    let mut pgm = format!("P5\n{width} {height}\n255\n").into_bytes();
    pgm.extend_from_slice(pixels);
    pgm
}

/// The YAML Nav2's `map_server` reads beside the image `image` (a file name, e.g. `map.pgm`) of a grid
/// with `limits`: trinary mode with ROS's default thresholds, which read [`grid_to_gray`]'s pixels back
/// as free, occupied and unknown.
pub fn nav2_map_yaml(image: &str, limits: &MapLimits) -> String {
    format!(
        "image: {image}\nmode: trinary\nresolution: {}\norigin: [{}, {}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
        limits.resolution, limits.origin.x, limits.origin.y
    )
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

    #[test]
    fn nav2_map_is_a_p5_pgm_and_a_yaml_naming_it() {
        let pgm = gray_to_pgm(3, 2, &[0, 1, 2, 3, 4, 5]);
        assert_eq!(&pgm[..], b"P5\n3 2\n255\n\x00\x01\x02\x03\x04\x05");
        let limits = MapLimits::new(0.05, Vector2::new(-2.0, 1.5), 3, 2);
        assert_eq!(
            nav2_map_yaml("site.pgm", &limits),
            "image: site.pgm\nmode: trinary\nresolution: 0.05\norigin: [-2, 1.5, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
        );
    }
}
