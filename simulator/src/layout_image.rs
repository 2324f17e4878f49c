//! A simulated world's layout as a picture (the `simulate` command's `<bag>.layout.png`): RGB pixels, one
//! per cell, top row first, as `mapping::map_image` draws maps, so `proto::encode_png` encodes them.

use mapping::grid::CellIndex;

use crate::Store;

/// A simulated world's layout on day `session` at `resolution` metres per pixel, top row first: static
/// structure (walls, columns, cases, counters, checkstands, shelf frames) black, what changes from day to
/// day (goods, pallets, displays, cart rows, closed doors) gray, free floor white, and one lap of the
/// session's cleaning route red.
pub fn layout_to_rgb(store: &Store, session: u32, resolution: f64) -> (u32, u32, Vec<u8>) {
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
