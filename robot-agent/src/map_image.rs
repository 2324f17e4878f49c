//! Writing occupancy grids as pictures: PNG for people, PGM + YAML for Nav2's `map_server`.

use std::io::Write;
use std::path::Path;

use mapping::grid::{CellIndex, ProbabilityGrid};

/// Gray level of unknown cells: ROS `map_server`'s convention (reads back as "unknown" with the
/// thresholds written by [`write_nav2_map`]).
const UNKNOWN_GRAY: u8 = 205;

/// Errors while writing map images.
#[derive(Debug, thiserror::Error)]
pub enum MapImageError {
    /// A file could not be written.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// PNG encoding failed.
    #[error("cannot encode PNG {path}: {source}")]
    Png {
        /// The file.
        path: String,
        /// Why.
        source: png::EncodingError,
    },
    /// The grid is empty.
    #[error("the map is empty: nothing to draw")]
    Empty,
}

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
    store: &mapping::simulation::Store,
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

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> MapImageError + '_ {
    move |source| MapImageError::Io {
        path: path.display().to_string(),
        source,
    }
}

/// Writes 8-bit gray pixels as a PNG file.
pub fn write_gray_png(
    path: &Path,
    width: u32,
    height: u32,
    pixels: &[u8],
) -> Result<(), MapImageError> {
    write_png(path, width, height, png::ColorType::Grayscale, pixels)
}

/// Writes 8-bit RGB pixels as a PNG file.
pub fn write_rgb_png(
    path: &Path,
    width: u32,
    height: u32,
    pixels: &[u8],
) -> Result<(), MapImageError> {
    write_png(path, width, height, png::ColorType::Rgb, pixels)
}

fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    color: png::ColorType,
    pixels: &[u8],
) -> Result<(), MapImageError> {
    if width == 0 || height == 0 {
        return Err(MapImageError::Empty);
    }
    let file = std::fs::File::create(path).map_err(io_err(path))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    encoder.set_color(color);
    encoder.set_depth(png::BitDepth::Eight);
    let png_err = |source| MapImageError::Png {
        path: path.display().to_string(),
        source,
    };
    let mut writer = encoder.write_header().map_err(png_err)?;
    writer.write_image_data(pixels).map_err(png_err)?;
    writer.finish().map_err(png_err)
}

/// Writes `<stem>.pgm` and `<stem>.yaml` in `dir` in the format of Nav2's `map_server`.
pub fn write_nav2_map(dir: &Path, stem: &str, grid: &ProbabilityGrid) -> Result<(), MapImageError> {
    let (w, h, pixels) = grid_to_gray(grid);
    if w == 0 || h == 0 {
        return Err(MapImageError::Empty);
    }
    let pgm_name = format!("{stem}.pgm");
    let pgm_path = dir.join(&pgm_name);
    let mut pgm = Vec::with_capacity(pixels.len() + 32);
    write!(pgm, "P5\n{w} {h}\n255\n").map_err(io_err(&pgm_path))?;
    pgm.extend_from_slice(&pixels);
    std::fs::write(&pgm_path, pgm).map_err(io_err(&pgm_path))?;

    let limits = grid.limits();
    let yaml_path = dir.join(format!("{stem}.yaml"));
    let yaml = format!(
        "image: {pgm_name}\nmode: trinary\nresolution: {}\norigin: [{}, {}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
        limits.resolution, limits.origin.x, limits.origin.y
    );
    std::fs::write(&yaml_path, yaml).map_err(io_err(&yaml_path))
}

/// The map-change picture as 8-bit RGB, top row first: unchanged occupied cells blue, removed green,
/// added red, everything else white (the paper's colours).
pub fn map_change_to_rgb(change: &mapping::lifelong::MapChange) -> (u32, u32, Vec<u8>) {
    use mapping::lifelong::CellChange;
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
    use mapping::grid::MapLimits;
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
