//! In-memory PNG and Nav2 (pgm + yaml) encodings of a grid, for `GetMapImage`: the pixels, PGM and YAML
//! of `mapping::map_image` (free white, occupied black, unknown gray 205, top row first) and the PNG of
//! `proto::encode_png`, as the agent writes them to files.

use mapping::grid::ProbabilityGrid;
use mapping::map_image::{gray_to_pgm, grid_to_gray, nav2_map_yaml};
use proto::{PngCompression, PngPixels, encode_png};

/// The encoded images of one grid.
#[derive(Clone, Debug, PartialEq)]
pub struct EncodedMap {
    /// Width in pixels (cells).
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// 8-bit gray PNG.
    pub png: Vec<u8>,
    /// Binary PGM (P5).
    pub pgm: Vec<u8>,
    /// Nav2 `map_server` yaml naming `map.pgm`.
    pub yaml: String,
}

/// Encodes `grid`; `None` for an empty grid or a PNG encoder failure.
pub fn encode_map(grid: &ProbabilityGrid) -> Option<EncodedMap> {
    let (width, height, pixels) = grid_to_gray(grid);
    let png = encode_png(
        width,
        height,
        PngPixels::Gray,
        &pixels,
        PngCompression::Balanced,
    )
    .ok()?;
    Some(EncodedMap {
        width,
        height,
        png,
        pgm: gray_to_pgm(width, height, &pixels),
        yaml: nav2_map_yaml("map.pgm", grid.limits()),
    })
}

#[cfg(test)]
mod tests {
    use mapping::grid::{CellIndex, MapLimits};
    use nalgebra::Vector2;

    use super::*;

    #[test]
    fn encodes_png_pgm_and_yaml() {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::new(-2.0, 1.5), 3, 2));
        grid.set_probability(&CellIndex::new(0, 0), 0.9);
        let map = encode_map(&grid).unwrap();
        assert_eq!(&map.png[1..4], b"PNG");
        assert_eq!(map.pgm.len(), b"P5\n3 2\n255\n".len() + 6);
        assert!(map.yaml.contains("origin: [-2, 1.5, 0.0]"), "{}", map.yaml);
        let empty = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::zeros(), 0, 0));
        assert!(encode_map(&empty).is_none());
    }
}
