//! Times the relocalization map's render (`mapping::lifelong::render_relocalization_map`) on a
//! store-sized stack of submaps: `cargo run --release --example render_map [-- SUBMAPS]`.
//!
//! The submaps are synthetic (random cells, seeded): 20 m × 20 m at 5 cm, placed at random poses over a
//! 100 m × 60 m floor, four per session — about what a store's map holds after a few sessions (session 0
//! of the simulated store alone has 209 submaps).

use std::time::Instant;

use mapping::geometry::rigid2;
use mapping::grid::{CellIndex, MapLimits, ProbabilityGrid};
use mapping::lifelong::{MapCells, PlacedGrid, render_relocalization_map};
use nalgebra::Vector2;
use rand::{Rng as _, SeedableRng as _};
use rand_pcg::Pcg64;

fn main() {
    let submaps: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(240);
    let mut rng = Pcg64::seed_from_u64(1);
    let limits = MapLimits::new(0.05, Vector2::new(-10.0, -10.0), 400, 400);
    let grids: Vec<ProbabilityGrid> = (0..submaps)
        .map(|_| {
            let mut grid = ProbabilityGrid::new(limits.clone());
            for iy in 0..limits.height {
                for ix in 0..limits.width {
                    // A disc of known cells, as a submap's scans leave them.
                    let (dx, dy) = (ix - 200, iy - 200);
                    if dx * dx + dy * dy < 190 * 190 {
                        let p = if rng.random_bool(0.1) { 0.85 } else { 0.2 };
                        grid.set_probability(&CellIndex::new(ix, iy), p);
                    }
                }
            }
            grid
        })
        .collect();
    let poses: Vec<_> = (0..submaps)
        .map(|_| {
            rigid2(
                rng.random_range(0.0..100.0),
                rng.random_range(0.0..60.0),
                rng.random_range(-std::f64::consts::PI..std::f64::consts::PI),
            )
        })
        .collect();
    let placed = || {
        grids
            .iter()
            .zip(&poses)
            .enumerate()
            .map(|(i, (grid, pose))| {
                (
                    (i / 4) as u32,
                    PlacedGrid {
                        global_from_grid: *pose,
                        grid,
                    },
                )
            })
    };
    for cells in MapCells::ALL {
        let mut times = Vec::new();
        let mut known = 0;
        for _ in 0..3 {
            let start = Instant::now();
            let map = render_relocalization_map(placed(), 0.05, cells).expect("cells are known");
            times.push(start.elapsed().as_secs_f64() * 1e3);
            known = map.values().iter().filter(|v| **v != 0).count();
        }
        times.sort_by(f64::total_cmp);
        println!(
            "{cells:?}: {submaps} submaps, {known} known cells, median {:.0} ms (of {:.0}, {:.0}, {:.0})",
            times[1], times[0], times[1], times[2]
        );
    }
}
