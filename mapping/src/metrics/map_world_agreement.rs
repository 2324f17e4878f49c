//! How well a site map shows the world of one day: the simulated store's truth against the map.
//!
//! Both grids hold occupied surfaces (probability above [`OCCUPIED_PROBABILITY`]) and free space; the
//! truth's obstacle interiors are unknown, as a LiDAR never sees them. Over an *area* (the cells a set of
//! sessions observed, in the map frame):
//!
//! ```text
//! shown = world's occupied cells with a map occupied cell within the tolerance / world's occupied cells
//! gone  = map's occupied cells where the world is free, with no world occupied cell within the tolerance
//!         / map's occupied cells the world knows
//! ```
//!
//! `shown` is what a robot localizing on the map finds of today's structure; `gone` is what the map
//! still holds that today's world no longer has (goods sold, a shelf moved), where scan matching finds
//! walls that are not there. Both read the map as it is, beside MCR (the map against its own first
//! session) and the world's change rate (the truth against its own first day).

use nalgebra::Point2;
use serde::Serialize;

use crate::geometry::Rigid2;
use crate::grid::{CellIndex, ProbabilityGrid};
use crate::lifelong::OCCUPIED_PROBABILITY;
use crate::lifelong::map_change::{neighbourhood, occupied_near, state as occupied};

/// Registration tolerance of [`map_world_agreement`], metres: 0.1 m, two cells of the 0.05 m submap
/// grid. A map is registered to the truth through its first session's trajectory (a few centimetres of
/// error), so a wall one or two cells over is the same wall; the smallest change the simulator makes
/// (goods moved 0.1 m) sits at the bound.
pub const MAP_WORLD_TOLERANCE_M: f64 = 0.1;

/// The result of [`map_world_agreement`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct MapWorldAgreement {
    /// Occupied cells of the world within the area.
    pub world_occupied: usize,
    /// Of those, the ones the map shows (an occupied map cell within the tolerance).
    pub world_shown: usize,
    /// Occupied cells of the map within the area where the world is known (surface or free).
    pub map_occupied: usize,
    /// Of those, the ones the world no longer has (free there, no occupied world cell within the
    /// tolerance).
    pub map_gone: usize,
}

impl MapWorldAgreement {
    /// Share of the world's occupied structure the map shows (`None` with no such structure).
    pub fn shown(&self) -> Option<f64> {
        (self.world_occupied > 0).then(|| self.world_shown as f64 / self.world_occupied as f64)
    }

    /// Share of the map's occupied cells the world no longer has (`None` with no such cells).
    pub fn gone(&self) -> Option<f64> {
        (self.map_occupied > 0).then(|| self.map_gone as f64 / self.map_occupied as f64)
    }
}

/// Compares `map` (map frame) with `world` (the day's truth, world frame; `world_from_map` registers
/// the two) over the cells `area` knows (map frame), with a registration tolerance of `tolerance_m`
/// ([`MAP_WORLD_TOLERANCE_M`] in the reports). See the module docs.
pub fn map_world_agreement(
    map: &ProbabilityGrid,
    world: &ProbabilityGrid,
    world_from_map: &Rigid2,
    area: &ProbabilityGrid,
    tolerance_m: f64,
) -> MapWorldAgreement {
    let map_from_world = world_from_map.inverse();
    let in_area = |p_map: &Point2<f64>| area.is_known(&area.limits().cell_index(p_map));
    let mut agreement = MapWorldAgreement::default();
    let world_offsets = neighbourhood(world.limits().resolution, tolerance_m.max(0.0));
    let map_offsets = neighbourhood(map.limits().resolution, tolerance_m.max(0.0));
    let world_limits = world.limits();
    for iy in 0..world_limits.height {
        for ix in 0..world_limits.width {
            let index = CellIndex::new(ix, iy);
            if !(world.is_known(&index) && world.probability(&index) > OCCUPIED_PROBABILITY) {
                continue;
            }
            let p_map = map_from_world * world_limits.cell_center(&index);
            if !in_area(&p_map) {
                continue;
            }
            agreement.world_occupied += 1;
            // The map's lattice is rotated against the world's: look around the transformed point on
            // the map's own lattice.
            if occupied_near(map, &p_map, &map_offsets) {
                agreement.world_shown += 1;
            }
        }
    }
    let map_limits = map.limits();
    for iy in 0..map_limits.height {
        for ix in 0..map_limits.width {
            let index = CellIndex::new(ix, iy);
            if !(map.is_known(&index) && map.probability(&index) > OCCUPIED_PROBABILITY) {
                continue;
            }
            let p_map = map_limits.cell_center(&index);
            if !in_area(&p_map) {
                continue;
            }
            let p_world = world_from_map * p_map;
            let Some(world_occupied) = occupied(world, &p_world) else {
                continue; // inside an obstacle or outside the world: nothing to compare with
            };
            agreement.map_occupied += 1;
            if !world_occupied && !occupied_near(world, &p_world, &world_offsets) {
                agreement.map_gone += 1;
            }
        }
    }
    agreement
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector2;

    use super::*;
    use crate::grid::{MAX_PROBABILITY, MIN_PROBABILITY, MapLimits};

    /// A 4 m × 4 m free room at 0.05 m with the given occupied cells (x, y indices), origin at `origin`.
    fn room(origin: Vector2<f64>, walls: &[(i32, i32)]) -> ProbabilityGrid {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, origin, 80, 80));
        for iy in 0..80 {
            for ix in 0..80 {
                grid.set_probability(&CellIndex::new(ix, iy), MIN_PROBABILITY);
            }
        }
        for &(ix, iy) in walls {
            grid.set_probability(&CellIndex::new(ix, iy), MAX_PROBABILITY);
        }
        grid
    }

    fn wall(x: i32) -> Vec<(i32, i32)> {
        (10..70).map(|y| (x, y)).collect()
    }

    #[test]
    fn a_map_of_todays_world_shows_all_of_it_and_holds_nothing_gone() {
        let world = room(Vector2::zeros(), &wall(40));
        let agreement = map_world_agreement(
            &world,
            &world,
            &Rigid2::identity(),
            &world,
            MAP_WORLD_TOLERANCE_M,
        );
        assert_eq!(agreement.world_occupied, 60);
        assert_eq!(agreement.shown(), Some(1.0));
        assert_eq!(agreement.gone(), Some(0.0));
    }

    #[test]
    fn a_wall_one_cell_over_in_a_shifted_frame_is_the_same_wall() {
        let world = room(Vector2::zeros(), &wall(40));
        // The map's frame is 1 m to the left of the world's, and its wall lands one cell (0.05 m) over.
        let map = room(Vector2::new(-1.0, 0.0), &wall(41));
        let world_from_map = Rigid2::new(Vector2::new(1.0, 0.0), 0.0);
        let agreement =
            map_world_agreement(&map, &world, &world_from_map, &map, MAP_WORLD_TOLERANCE_M);
        assert_eq!(agreement.shown(), Some(1.0));
        assert_eq!(agreement.gone(), Some(0.0));
    }

    #[test]
    fn a_shelf_moved_away_is_gone_from_the_map_and_its_new_place_is_not_shown() {
        // Today the shelf face stands at x = 3 m; the map still holds it at x = 1 m.
        let world = room(Vector2::zeros(), &wall(60));
        let map = room(Vector2::zeros(), &wall(20));
        let agreement = map_world_agreement(
            &map,
            &world,
            &Rigid2::identity(),
            &map,
            MAP_WORLD_TOLERANCE_M,
        );
        assert_eq!(agreement.shown(), Some(0.0));
        assert_eq!(agreement.gone(), Some(1.0));
        // Outside the area nothing counts.
        let mut area = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::new(10.0, 10.0), 4, 4));
        area.set_probability(&CellIndex::new(0, 0), MIN_PROBABILITY);
        let none = map_world_agreement(&map, &world, &Rigid2::identity(), &area, 0.1);
        assert_eq!((none.shown(), none.gone()), (None, None));
    }
}
