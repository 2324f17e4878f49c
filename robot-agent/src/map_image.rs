//! Writing occupancy grids as pictures: PNG for people, PGM + YAML for Nav2's `map_server`. The pixels
//! come from [`mapping::map_image`] (shared with the server); this module encodes and writes them.

use std::io::Write;
use std::path::Path;

use mapping::grid::ProbabilityGrid;
pub use mapping::map_image::{grid_to_gray, layout_to_rgb, map_change_to_rgb};

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
