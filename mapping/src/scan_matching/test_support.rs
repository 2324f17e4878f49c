//! Synthetic worlds shared by the scan matcher tests.

use nalgebra::{Point2, Vector2};

use crate::geometry::Rigid2;
use crate::grid::{MAX_PROBABILITY, MIN_PROBABILITY, MapLimits, ProbabilityGrid};

/// Walls of an asymmetric 6 m × 5 m room with a few obstacles, world frame, metres.
pub(crate) const ROOM_WALLS: [([f64; 2], [f64; 2]); 8] = [
    ([0.0, 0.0], [6.0, 0.0]),
    ([6.0, 0.0], [6.0, 5.0]),
    ([6.0, 5.0], [0.0, 5.0]),
    ([0.0, 5.0], [0.0, 0.0]),
    ([2.0, 0.0], [2.0, 1.5]),
    ([4.0, 3.5], [5.0, 3.5]),
    ([1.0, 3.0], [1.8, 3.8]),
    ([3.2, 2.0], [3.6, 2.2]),
];

fn distance_to_segment(p: &Vector2<f64>, a: &Vector2<f64>, b: &Vector2<f64>) -> f64 {
    let ab = b - a;
    let t = ((p - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0);
    (p - (a + ab * t)).norm()
}

/// `walls` (segments, world frame) drawn into a grid over `limits`: each cell's probability falls off from
/// [`MAX_PROBABILITY`] with a Gaussian (σ = 5 cm) of its centre's distance to the nearest wall; cells whose
/// centre `known` rejects stay unknown.
pub(crate) fn walls_grid(
    walls: &[([f64; 2], [f64; 2])],
    limits: &MapLimits,
    known: impl Fn(&Vector2<f64>) -> bool,
) -> ProbabilityGrid {
    let mut grid = ProbabilityGrid::new(limits.clone());
    let sigma = 0.05;
    for iy in 0..limits.height {
        for ix in 0..limits.width {
            let index = crate::grid::CellIndex::new(ix, iy);
            let c = limits.cell_center(&index).coords;
            if !known(&c) {
                continue;
            }
            let d = walls
                .iter()
                .map(|(a, b)| distance_to_segment(&c, &Vector2::from(*a), &Vector2::from(*b)))
                .fold(f64::INFINITY, f64::min);
            let p = f64::from(MIN_PROBABILITY)
                + f64::from(MAX_PROBABILITY - MIN_PROBABILITY)
                    * (-d * d / (2.0 * sigma * sigma)).exp();
            grid.set_probability(&index, p as f32);
        }
    }
    grid
}

/// Points every `spacing` metres along each of `walls` (the first `first` metres in), those within
/// `max_range` of a robot at `world_from_robot`, in the robot's frame.
pub(crate) fn wall_points(
    walls: &[([f64; 2], [f64; 2])],
    world_from_robot: &Rigid2,
    first: f64,
    spacing: f64,
    max_range: f64,
) -> Vec<Point2<f32>> {
    let robot_from_world = world_from_robot.inverse();
    let mut points = Vec::new();
    for (a, b) in walls {
        let (a, b) = (Vector2::from(*a), Vector2::from(*b));
        let length = (b - a).norm();
        let mut s = first;
        while s < length {
            let w = a + (b - a) * (s / length);
            if (w - world_from_robot.translation.vector).norm() <= max_range {
                let p = robot_from_world * Point2::from(w);
                points.push(Point2::new(p.x as f32, p.y as f32));
            }
            s += spacing;
        }
    }
    points
}

/// The room drawn in a 5 cm grid with origin (−1, −1), 8 m × 7 m (see [`walls_grid`]). Cells more than
/// 0.6 m outside the room stay unknown.
pub(crate) fn room_grid() -> ProbabilityGrid {
    let limits = MapLimits::new(0.05, Vector2::new(-1.0, -1.0), 160, 140);
    walls_grid(&ROOM_WALLS, &limits, |c| {
        !(c.x < -0.6 || c.y < -0.6 || c.x > 6.6 || c.y > 5.6)
    })
}

/// Points every 15 cm along every wall of [`ROOM_WALLS`], expressed in the frame of a robot at
/// `world_from_robot` (about 190 points).
pub(crate) fn room_scan(world_from_robot: &Rigid2) -> Vec<Point2<f32>> {
    wall_points(&ROOM_WALLS, world_from_robot, 0.037, 0.15, f64::INFINITY)
}
