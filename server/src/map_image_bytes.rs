//! In-memory PNG and Nav2 (pgm + yaml) encodings of a grid, for `GetMapImage`. Pixels follow
//! `mapping::map_image` (free white, occupied black, unknown gray 205, top row first).

use mapping::grid::ProbabilityGrid;
use mapping::map_image::grid_to_gray;

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
    if width == 0 || height == 0 {
        return None;
    }
    let mut png = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut png, width, height);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().ok()?;
        writer.write_image_data(&pixels).ok()?;
        writer.finish().ok()?;
    }
    let mut pgm = format!("P5\n{width} {height}\n255\n").into_bytes();
    pgm.extend_from_slice(&pixels);
    let limits = grid.limits();
    let yaml = format!(
        "image: map.pgm\nmode: trinary\nresolution: {}\norigin: [{}, {}, 0.0]\nnegate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n",
        limits.resolution, limits.origin.x, limits.origin.y
    );
    Some(EncodedMap {
        width,
        height,
        png,
        pgm,
        yaml,
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
