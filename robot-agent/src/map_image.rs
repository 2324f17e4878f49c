//! Writing occupancy grids as pictures: PNG for people, PGM + YAML for Nav2's `map_server`. The pixels,
//! PGM and YAML come from [`mapping::map_image`] and the PNG bytes from [`proto::encode_png`] (both shared
//! with the server); this module writes them to files.

use std::path::Path;

use mapping::grid::ProbabilityGrid;
use mapping::map_image::{gray_to_pgm, nav2_map_yaml};
pub use mapping::map_image::{grid_to_gray, map_change_to_rgb};
use proto::{PngCompression, PngError, PngPixels};

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
        source: PngError,
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
    write_png(path, width, height, PngPixels::Gray, pixels)
}

/// Writes 8-bit RGB pixels as a PNG file.
pub fn write_rgb_png(
    path: &Path,
    width: u32,
    height: u32,
    pixels: &[u8],
) -> Result<(), MapImageError> {
    write_png(path, width, height, PngPixels::Rgb, pixels)
}

fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    layout: PngPixels,
    pixels: &[u8],
) -> Result<(), MapImageError> {
    let png = proto::encode_png(width, height, layout, pixels, PngCompression::Balanced).map_err(
        |source| match source {
            PngError::Empty => MapImageError::Empty,
            source @ PngError::Encoding(_) => MapImageError::Png {
                path: path.display().to_string(),
                source,
            },
        },
    )?;
    std::fs::write(path, png).map_err(io_err(path))
}

/// Writes `<stem>.pgm` and `<stem>.yaml` in `dir` in the format of Nav2's `map_server`.
pub fn write_nav2_map(dir: &Path, stem: &str, grid: &ProbabilityGrid) -> Result<(), MapImageError> {
    let (w, h, pixels) = grid_to_gray(grid);
    if w == 0 || h == 0 {
        return Err(MapImageError::Empty);
    }
    let pgm_name = format!("{stem}.pgm");
    let pgm_path = dir.join(&pgm_name);
    std::fs::write(&pgm_path, gray_to_pgm(w, h, &pixels)).map_err(io_err(&pgm_path))?;
    let yaml_path = dir.join(format!("{stem}.yaml"));
    std::fs::write(&yaml_path, nav2_map_yaml(&pgm_name, grid.limits())).map_err(io_err(&yaml_path))
}
