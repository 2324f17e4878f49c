//! The console's images: a site's map at one version, and the map change between two versions.
//!
//! The map is rendered as `GetMapImage` renders it (`mapping::lifelong::render_submaps_log_odds`, gray
//! pixels by `mapping::map_image::grid_to_gray`), encoded by `proto::encode_png` with its fast setting
//! (fdeflate: a few milliseconds for the README demo's 1000 × 700 map, about as small as the default's).
//! The change compares the two versions' maps as the lifelong
//! reports do: each rendered newest-observation-wins (`mapping::lifelong::render_submaps_newest`, the
//! site as its latest sessions saw it), classified cell by cell by `mapping::lifelong::map_change_rate`
//! with the reports' 0.05 m registration tolerance, coloured like `map_change.png` (blue unchanged, green
//! removed, red added, white elsewhere). Both are CPU work: call them on the blocking pool.

use mapping::grid::{MapLimits, ProbabilityGrid};
use mapping::lifelong::{
    MAP_CHANGE_TOLERANCE_M, PlacedGrid, map_change_rate, render_submaps_log_odds,
    render_submaps_newest,
};
use proto::{PngCompression, PngPixels};
use serde::Serialize;

use crate::site::HistoryEntry;

/// Where an image lies in the site frame: its bottom-left corner, cell size and size in cells (the
/// image's top row is the row of largest y).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ImagePlacement {
    /// Cell size, m.
    pub resolution: f64,
    /// Site-frame coordinates of the bottom-left corner of the bottom-left cell, m.
    pub origin: [f64; 2],
    /// Width, cells (pixels).
    pub width: u32,
    /// Height, cells (pixels).
    pub height: u32,
}

impl ImagePlacement {
    fn of(limits: &MapLimits) -> Self {
        Self {
            resolution: limits.resolution,
            origin: [limits.origin.x, limits.origin.y],
            width: limits.width.max(0) as u32,
            height: limits.height.max(0) as u32,
        }
    }
}

/// A site's map at one version.
#[derive(Clone, Debug)]
pub struct MapImage {
    /// The version whose map this is (the newest map-changing version at or before the one asked).
    pub map_version: u64,
    /// Where it lies.
    pub placement: ImagePlacement,
    /// Gray PNG: free white, occupied black, unknown gray.
    pub png: Vec<u8>,
}

/// The map change between two versions.
#[derive(Clone, Debug)]
pub struct ChangeImage {
    /// The earlier map's version.
    pub from_map_version: u64,
    /// The later map's version.
    pub to_map_version: u64,
    /// Changed share of the occupied structure both maps saw (MCR).
    pub rate: f64,
    /// Occupied cells in both maps.
    pub unchanged: usize,
    /// Occupied before, free after.
    pub removed: usize,
    /// Free before, occupied after.
    pub added: usize,
    /// Where it lies.
    pub placement: ImagePlacement,
    /// RGB PNG.
    pub png: Vec<u8>,
}

/// Renders the map of `entry` at `resolution` (m). `None` when it has nothing to draw.
pub fn render_map_image(entry: &HistoryEntry, resolution: f64) -> Option<MapImage> {
    let grid = render_submaps_log_odds(&entry.grids, resolution)?;
    let (width, height, pixels) = mapping::map_image::grid_to_gray(&grid);
    Some(MapImage {
        map_version: entry.version,
        placement: ImagePlacement::of(grid.limits()),
        png: encode_png(width, height, PngPixels::Gray, &pixels)?,
    })
}

/// `pixels` (8 bits per channel, top row first) as a fast PNG; `None` when empty or on an encoder
/// error.
fn encode_png(width: u32, height: u32, layout: PngPixels, pixels: &[u8]) -> Option<Vec<u8>> {
    proto::encode_png(width, height, layout, pixels, PngCompression::Fast).ok()
}

fn render_newest(entry: &HistoryEntry, resolution: f64) -> Option<ProbabilityGrid> {
    render_submaps_newest(
        entry
            .grids
            .iter()
            .map(|(global_from_grid, grid)| PlacedGrid {
                global_from_grid: *global_from_grid,
                grid,
            }),
        resolution,
    )
}

/// Renders the change from `before` to `after` at `resolution` (m). `None` when either map is empty
/// or the PNG cannot be encoded.
pub fn render_change_image(
    before: &HistoryEntry,
    after: &HistoryEntry,
    resolution: f64,
) -> Option<ChangeImage> {
    let (old, new) = (
        render_newest(before, resolution)?,
        render_newest(after, resolution)?,
    );
    let change = map_change_rate(&old, &new, MAP_CHANGE_TOLERANCE_M);
    let (width, height, pixels) = mapping::map_image::map_change_to_rgb(&change);
    let png = encode_png(width, height, PngPixels::Rgb, &pixels)?;
    Some(ChangeImage {
        from_map_version: before.version,
        to_map_version: after.version,
        rate: change.rate,
        unchanged: change.unchanged,
        removed: change.removed,
        added: change.added,
        placement: ImagePlacement::of(&change.limits),
        png,
    })
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use mapping::geometry::{Rigid2, rigid2};
    use mapping::grid::CellIndex;
    use nalgebra::Vector2;

    use super::*;
    use crate::site::MapCounts;

    /// A 2 × 2 m grid at 0.05 m, free, with an occupied row at `wall_row`.
    fn room(wall_row: i32) -> Arc<ProbabilityGrid> {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::zeros(), 40, 40));
        for iy in 0..40 {
            for ix in 0..40 {
                let p = if iy == wall_row { 0.9 } else { 0.1 };
                grid.set_probability(&CellIndex::new(ix, iy), p);
            }
        }
        Arc::new(grid)
    }

    fn entry(version: u64, grids: Vec<(Rigid2, Arc<ProbabilityGrid>)>) -> HistoryEntry {
        HistoryEntry {
            version,
            counts: MapCounts::default(),
            grids: Arc::new(grids),
        }
    }

    #[test]
    fn the_map_image_is_placed_where_its_grids_are() {
        let image =
            render_map_image(&entry(7, vec![(rigid2(3.0, -1.0, 0.0), room(10))]), 0.05).unwrap();
        assert_eq!(image.map_version, 7);
        assert_eq!(&image.png[1..4], b"PNG");
        assert_eq!((image.placement.width, image.placement.height), (40, 40));
        assert!((image.placement.origin[0] - 3.0).abs() < 1e-9);
        assert!((image.placement.origin[1] + 1.0).abs() < 1e-9);
        assert!(render_map_image(&entry(1, Vec::new()), 0.05).is_none());
    }

    #[test]
    fn the_fast_png_decodes_to_the_map_pixels() {
        let grids = vec![(rigid2(0.3, 0.2, 0.4), room(10))];
        let image = render_map_image(&entry(2, grids.clone()), 0.05).unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(&image.png));
        let mut reader = decoder.read_info().unwrap();
        let mut pixels = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut pixels).unwrap();
        let grid = render_submaps_log_odds(&grids, 0.05).unwrap();
        let (width, height, expected) = mapping::map_image::grid_to_gray(&grid);
        assert_eq!((info.width, info.height), (width, height));
        assert_eq!(info.color_type, png::ColorType::Grayscale);
        assert_eq!(&pixels[..info.buffer_size()], &expected[..]);
        // Occupied, free and unknown (205) pixels all there.
        assert!(expected.iter().any(|p| *p < 50));
        assert!(expected.iter().any(|p| *p > 220));
        assert!(expected.contains(&205));
    }

    #[test]
    fn a_moved_wall_is_removed_and_added() {
        let before = entry(3, vec![(Rigid2::identity(), room(10))]);
        let after = entry(9, vec![(Rigid2::identity(), room(30))]);
        let change = render_change_image(&before, &after, 0.05).unwrap();
        assert_eq!((change.from_map_version, change.to_map_version), (3, 9));
        assert_eq!(change.unchanged, 0);
        assert!(change.removed >= 40 && change.added >= 40, "{change:?}");
        assert!((change.rate - 1.0).abs() < 1e-9);
        let same = render_change_image(&before, &before, 0.05).unwrap();
        assert_eq!((same.removed, same.added), (0, 0));
        assert!(same.unchanged >= 40);
    }
}
