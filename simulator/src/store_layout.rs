//! The floor plan of the `store` world: a supermarket laid out the way published store-planning guidance
//! describes typical ones, so that places in it can be told apart the way they can in a real store.
//!
//! # What it is based on
//!
//! Typical published supermarket layout guidance (store-planning and fixture-vendor design guides, and
//! the usual descriptions of grid and racetrack layouts):
//!
//! * **Fresh departments on the perimeter, dry goods in the centre.** Refrigerated and frozen multideck
//!   cases ([`CASE_DEPTH_M`], 1.0–1.2 m deep) line the side and back walls in line-ups of different
//!   lengths with breaks between them; the back wall has service counters (deli, butcher, bakery,
//!   seafood: a counter [`SERVICE_COUNTER_DEPTH_M`] deep standing [`SERVICE_ZONE_DEPTH_M`] from the wall,
//!   staff space and a prep counter behind, side panels at each end).
//! * **Produce at the entrance side**, here the right: wall cases plus two columns of produce islands
//!   (tables at least [`ISLAND_WIDTH_M`] wide — wider where the gondola grid leaves room — 2.4–4.8 m
//!   long, with gaps of 1.5–3.5 m between them).
//! * **Centre store as a grid of gondola runs** perpendicular to the front, in `banks` banks separated
//!   by cross aisles ([`MAIN_AISLE_WIDTH_M`]); gondolas are double-sided, [`GONDOLA_DEPTH_M`] deep
//!   (1.2–1.4 m) including a [`GOODS_DEPTH_M`] goods zone on each face, in [`MODULE_LENGTH_M`] sections
//!   (4 ft); aisles are `aisle_width` (1.8–2.4 m; default 2.0 m). Runs have different lengths (each end
//!   is shortened by 0–3 sections, some runs are split by a cross-over), and every run end carries an
//!   end cap ([`END_CAP_DEPTH_M`]) with a promotion space ([`PROMO_DEPTH_M`]) in front of it.
//! * **Checkouts and the entrance at the front**: a front corridor ([`FRONT_CORRIDOR_WIDTH_M`]) along the
//!   front wall with the entrance and exit doors and cart rows, a bank of checkstands
//!   ([`CHECKSTAND_LENGTH_M`] × [`CHECKSTAND_WIDTH_M`] at a [`CHECKOUT_PITCH_M`] pitch), an L-shaped
//!   customer-service desk, then the power aisle ([`POWER_AISLE_WIDTH_M`]) along the gondola ends.
//! * **Structural columns on a grid** ([`COLUMN_SIZE_M`] square, every [`COLUMN_SPACING_PITCHES`]
//!   gondola pitches = 9.9 m with the default aisles; typical grids are 8–10 m) aligned with the gondola
//!   lines, as planners align fixtures to columns: most stand inside gondola runs, the rest stand free in
//!   the front end, the produce department, cross-overs and the service zone. A column that would stand
//!   in a driving lane is left out (planners move the aisle, not the robot).
//!
//! What changes from day to day (see [`Store::obstacles`](super::Store::obstacles)): goods on every
//! gondola section, end cap and island protrude in [`GOODS_STEP_M`] steps or are absent; half pallets in
//! aisles, impulse displays in the power aisle, promotions in front of end caps and cart rows at the
//! front appear and vanish; doors open and close. The structure — walls, columns, cases, counters,
//! checkstands, gondola frames, end-cap frames, island tables — never moves.
//!
//! The robot's cleaning route covers the store like a cleaning robot's: the front corridor and the power
//! aisle end to end, every aisle of every bank (a serpentine over the left perimeter aisle, every aisle
//! between gondolas, the aisles of the produce department and the right perimeter aisle), every cross
//! aisle and the back aisle end to end, and back along the left perimeter to where it started.

use nalgebra::{Point2, Vector2};
use rand::Rng as _;
use rand_pcg::Pcg64;

use super::StoreOptions;
use super::ray_caster::Aabb;
use super::store::{ItemKind, Layout, MovableItem, Plan, Walker, seeded};

/// Depth of a double-sided gondola, goods zones included, m (typical 1.2–1.4 m).
pub const GONDOLA_DEPTH_M: f64 = 1.3;
/// Depth of the goods zone on each face of a gondola, end cap or island, m.
pub const GOODS_DEPTH_M: f64 = 0.3;
/// Goods protrude in steps of this, m (0 = the section is empty).
pub const GOODS_STEP_M: f64 = 0.1;
/// Length of one gondola section, m (a 4 ft section is 1.22 m).
pub const MODULE_LENGTH_M: f64 = 1.25;
/// Depth of an end-cap fixture at a gondola run's end, m.
pub const END_CAP_DEPTH_M: f64 = 0.5;
/// Depth of the promotion space in front of an end cap (dump bins, shipper displays), m.
pub const PROMO_DEPTH_M: f64 = 0.6;
/// Width of the perimeter (racetrack), cross and back aisles, m (typical 2.4–3.6 m).
pub const MAIN_AISLE_WIDTH_M: f64 = 3.0;
/// Width of the power aisle between the checkouts and the gondola ends, m.
pub const POWER_AISLE_WIDTH_M: f64 = 4.0;
/// Depth of the refrigerated and frozen multideck cases along the walls, m (typical 1.0–1.2 m).
pub const CASE_DEPTH_M: f64 = 1.1;
/// Width of the corridor between the front wall and the checkstands, m.
pub const FRONT_CORRIDOR_WIDTH_M: f64 = 3.0;
/// Length of a checkstand (belt, register, bagging), m (typical 3.5–4.5 m).
pub const CHECKSTAND_LENGTH_M: f64 = 4.0;
/// Width of a checkstand, m.
pub const CHECKSTAND_WIDTH_M: f64 = 0.9;
/// Distance between neighbouring checkstands (a checkstand and its ~1 m customer lane and bagging
/// space), m.
pub const CHECKOUT_PITCH_M: f64 = 3.0;
/// Depth of a service counter, m.
pub const SERVICE_COUNTER_DEPTH_M: f64 = 1.0;
/// Depth of the service zone along the back wall (staff space and prep counter behind a service
/// counter), m: the back aisle starts this far from the back wall.
pub const SERVICE_ZONE_DEPTH_M: f64 = 3.2;
/// Side of a square structural column, m.
pub const COLUMN_SIZE_M: f64 = 0.6;
/// Column grid spacing in gondola pitches (3 × 3.3 m = 9.9 m with the default aisles).
pub const COLUMN_SPACING_PITCHES: usize = 3;
/// Narrowest produce island (a 1.0 m table and a 0.2 m produce zone on each side), m.
pub const ISLAND_WIDTH_M: f64 = 1.4;
/// Width of the aisle between the two columns of produce islands, m.
pub const PRODUCE_LANE_WIDTH_M: f64 = 2.6;
/// Width of a door in the outer wall, m.
pub const DOOR_WIDTH_M: f64 = 2.4;

/// A column is left out when it comes closer than this to a driving lane's centre line, m.
const LANE_CLEARANCE_M: f64 = 0.9;
/// Goods zone on each side of an island table, m.
const ISLAND_GOODS_M: f64 = 0.2;

/// Where the robot and the walkers drive in the `store` world.
#[derive(Clone, Debug)]
pub(crate) struct StorePlan {
    /// The cleaning tour: a closed polyline (last point = first point) along lane centre lines.
    tour: Vec<Point2<f64>>,
    /// The aisles between gondolas, bank by bank, as centre-line segments.
    aisles: Vec<(Point2<f64>, Point2<f64>)>,
}

/// Lane centre lines and fixture lines of the floor plan (everything the layout derives from the
/// options before drawing anything).
struct Grid {
    /// x of the driving columns of the serpentine: left perimeter aisle, aisles between gondolas, the
    /// lane right of the last gondola, the produce lane, the right perimeter aisle.
    columns: Vec<f64>,
    /// y of the horizontal lanes: power aisle, cross aisles, back aisle.
    lanes: Vec<f64>,
    /// y extent of every bank.
    banks: Vec<(f64, f64)>,
    /// Left edge of every gondola.
    gondolas: Vec<f64>,
    /// Left edge of the two columns of produce islands.
    islands: [f64; 2],
    /// Width of the produce islands: at least [`ISLAND_WIDTH_M`], wider to take up what the gondola
    /// pitch leaves of the floor's width (so that every lane keeps its width).
    island_width: f64,
    /// y of the front corridor's centre line.
    front_corridor: f64,
}

impl Grid {
    fn new(o: &StoreOptions) -> Self {
        let (w, d) = (o.width, o.depth);
        let front_corridor = FRONT_CORRIDOR_WIDTH_M / 2.0;
        let checkouts_top = FRONT_CORRIDOR_WIDTH_M + CHECKSTAND_LENGTH_M;
        let power_aisle = checkouts_top + POWER_AISLE_WIDTH_M / 2.0;
        let floor_lo = checkouts_top + POWER_AISLE_WIDTH_M;
        let back_edge = d - SERVICE_ZONE_DEPTH_M;
        let floor_hi = back_edge - MAIN_AISLE_WIDTH_M;
        let banks_n = o.banks as f64;
        let bank_length = (floor_hi - floor_lo - (banks_n - 1.0) * MAIN_AISLE_WIDTH_M) / banks_n;
        let banks: Vec<(f64, f64)> = (0..o.banks)
            .map(|b| {
                let lo = floor_lo + b as f64 * (bank_length + MAIN_AISLE_WIDTH_M);
                (lo, lo + bank_length)
            })
            .collect();
        let mut lanes = vec![power_aisle];
        lanes.extend(banks.iter().skip(1).map(|b| b.0 - MAIN_AISLE_WIDTH_M / 2.0));
        lanes.push(back_edge - MAIN_AISLE_WIDTH_M / 2.0);

        let left_lane = CASE_DEPTH_M + MAIN_AISLE_WIDTH_M / 2.0;
        let first_gondola = CASE_DEPTH_M + MAIN_AISLE_WIDTH_M;
        let right_lane = w - CASE_DEPTH_M - MAIN_AISLE_WIDTH_M / 2.0;
        let islands_end = w - CASE_DEPTH_M - MAIN_AISLE_WIDTH_M;
        let centre_end =
            islands_end - 2.0 * ISLAND_WIDTH_M - PRODUCE_LANE_WIDTH_M - MAIN_AISLE_WIDTH_M;
        let pitch = o.gondola_pitch();
        let count = ((centre_end - first_gondola - GONDOLA_DEPTH_M) / pitch).floor() as usize + 1;
        let gondolas: Vec<f64> = (0..count)
            .map(|i| first_gondola + i as f64 * pitch)
            .collect();
        let last_right = gondolas
            .last()
            .map_or(first_gondola, |g| g + GONDOLA_DEPTH_M);
        let island_a = last_right + MAIN_AISLE_WIDTH_M;
        let island_width = 0.5 * (islands_end - island_a - PRODUCE_LANE_WIDTH_M);
        let island_b = islands_end - island_width;
        let mut columns = vec![left_lane];
        columns.extend(
            gondolas
                .iter()
                .take(count - 1)
                .map(|g| g + GONDOLA_DEPTH_M + o.aisle_width / 2.0),
        );
        columns.push(0.5 * (last_right + island_a));
        columns.push(island_a + island_width + PRODUCE_LANE_WIDTH_M / 2.0);
        columns.push(right_lane);
        Self {
            columns,
            lanes,
            banks,
            gondolas,
            islands: [island_a, island_b],
            island_width,
            front_corridor,
        }
    }

    /// The cleaning tour (see the module documentation), closed.
    fn tour(&self) -> Vec<Point2<f64>> {
        let (Some(&left), Some(&right)) = (self.columns.first(), self.columns.last()) else {
            return Vec::new();
        };
        let p = Point2::new;
        let mut tour = vec![
            p(left, self.front_corridor),
            p(right, self.front_corridor),
            p(right, self.lanes[0]),
            p(left, self.lanes[0]),
        ];
        for pair in self.lanes.windows(2) {
            let (from, to) = (pair[0], pair[1]);
            let mut at_to = false;
            for (j, &x) in self.columns.iter().enumerate() {
                if j > 0 {
                    tour.push(p(x, if at_to { to } else { from }));
                }
                at_to = !at_to;
                tour.push(p(x, if at_to { to } else { from }));
            }
            if !at_to {
                tour.push(p(right, to));
            }
            tour.push(p(left, to));
        }
        tour.push(p(left, self.front_corridor));
        tour.dedup_by(|a, b| (*a - *b).norm() < 1e-9);
        tour
    }
}

/// Goods on one face: `None`, then protruding 1..=`steps` × [`GOODS_STEP_M`] from `face` towards
/// `sign` along `axis` (0 = x, 1 = y), spanning `[a, b]` along the other axis.
fn goods_item(rng: &mut Pcg64, face: f64, sign: f64, a: f64, b: f64, axis: usize) -> MovableItem {
    let steps = (GOODS_DEPTH_M / GOODS_STEP_M).round() as u32;
    let variants: Vec<Option<Aabb>> = std::iter::once(None)
        .chain((1..=steps).map(|k| {
            let depth = GOODS_STEP_M * f64::from(k);
            Some(if axis == 0 {
                Aabb::new(face, a, face + sign * depth, b)
            } else {
                Aabb::new(a, face, b, face + sign * depth)
            })
        }))
        .collect();
    let initial = rng.random_range(0..variants.len());
    MovableItem {
        kind: ItemKind::Goods,
        variants,
        initial,
    }
}

/// An item that is either absent or one of `shapes`.
fn optional_item(rng: &mut Pcg64, kind: ItemKind, shapes: &[Aabb], present: f64) -> MovableItem {
    let variants: Vec<Option<Aabb>> = std::iter::once(None)
        .chain(shapes.iter().copied().map(Some))
        .collect();
    let initial = if rng.random::<f64>() < present {
        rng.random_range(1..variants.len())
    } else {
        0
    };
    MovableItem {
        kind,
        variants,
        initial,
    }
}

/// Pieces of `[from, to]` left after cutting out the `gaps` (centre, width), in order.
fn cut(from: f64, to: f64, gaps: &[(f64, f64)]) -> Vec<(f64, f64)> {
    let mut gaps = gaps.to_vec();
    gaps.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut pieces = Vec::new();
    let mut start = from;
    for (c, width) in gaps {
        let (a, b) = (c - width / 2.0, c + width / 2.0);
        if a > start {
            pieces.push((start, a.min(to)));
        }
        start = start.max(b);
    }
    if to > start {
        pieces.push((start, to));
    }
    pieces
}

/// Case line-ups of different lengths along `[from, to]`, with breaks between them, avoiding `doors`.
fn line_ups(rng: &mut Pcg64, from: f64, to: f64, doors: &[f64]) -> Vec<(f64, f64)> {
    const LENGTHS: [f64; 5] = [3.75, 5.0, 6.25, 7.5, 10.0];
    const BREAKS: [f64; 4] = [0.8, 1.5, 2.5, 4.0];
    let gaps: Vec<(f64, f64)> = doors.iter().map(|&c| (c, DOOR_WIDTH_M + 1.0)).collect();
    let mut out = Vec::new();
    for (a, b) in cut(from, to, &gaps) {
        let mut x = a;
        while x < b - 1.0 {
            let length = LENGTHS[rng.random_range(0..LENGTHS.len())].min(b - x);
            out.push((x, x + length));
            x += length + BREAKS[rng.random_range(0..BREAKS.len())];
        }
    }
    out
}

/// Lays out the `store` world from `options` and `seed`.
#[expect(
    clippy::too_many_lines,
    reason = "one floor plan drawn department by department"
)]
pub(crate) fn lay_out(o: &StoreOptions, seed: u64) -> Layout {
    let mut rng = seeded(seed, 1);
    let (w, d, t) = (o.width, o.depth, o.wall_thickness);
    let grid = Grid::new(o);
    let tour = grid.tour();
    let mut fixed = Vec::new();
    let mut items = Vec::new();
    let checkouts_top = FRONT_CORRIDOR_WIDTH_M + CHECKSTAND_LENGTH_M;

    // Checkstands and the service desk, left of the produce department.
    let first_gondola = grid.gondolas.first().copied().unwrap_or(0.0);
    let centre_end = grid.islands[0] - MAIN_AISLE_WIDTH_M;
    let checkouts_from = first_gondola + 4.0;
    let checkouts_to = first_gondola + 0.55 * (centre_end - first_gondola);
    let mut x = checkouts_from;
    while x + CHECKSTAND_WIDTH_M <= checkouts_to {
        fixed.push(Aabb::new(
            x,
            FRONT_CORRIDOR_WIDTH_M,
            x + CHECKSTAND_WIDTH_M,
            checkouts_top,
        ));
        x += CHECKOUT_PITCH_M;
    }
    let desk = x + 2.0;
    fixed.push(Aabb::new(
        desk,
        FRONT_CORRIDOR_WIDTH_M,
        desk + 5.0,
        FRONT_CORRIDOR_WIDTH_M + 1.0,
    ));
    fixed.push(Aabb::new(
        desk + 4.0,
        FRONT_CORRIDOR_WIDTH_M + 1.0,
        desk + 5.0,
        FRONT_CORRIDOR_WIDTH_M + 3.0,
    ));

    // Doors: exit beside the service desk, entrance at the produce side (front wall); a backroom door in
    // the left wall, a fire exit in the right wall, two in the back wall.
    let exit = desk + 8.0;
    let entrance = grid.islands[0] - 2.0;
    let (_, floor_hi) = grid.banks.last().copied().unwrap_or((0.0, d));
    let (floor_lo, _) = grid.banks.first().copied().unwrap_or((0.0, d));
    let side_door_left = rng.random_range(floor_lo + 3.0..floor_hi - 3.0);
    let side_door_right = rng.random_range(floor_lo + 3.0..floor_hi - 3.0);
    let back_doors = [
        rng.random_range(0.15 * w..0.4 * w),
        rng.random_range(0.6 * w..0.85 * w),
    ];
    let walls: [(Vec<f64>, f64); 4] = [
        (vec![exit, entrance], w),
        (back_doors.to_vec(), w),
        (vec![side_door_left], d),
        (vec![side_door_right], d),
    ];
    for (wall, (doors, length)) in walls.iter().enumerate() {
        let rect = |a: f64, b: f64| match wall {
            0 => Aabb::new(a, -t, b, 0.0),
            1 => Aabb::new(a, d, b, d + t),
            2 => Aabb::new(-t, a, 0.0, b),
            _ => Aabb::new(w, a, w + t, b),
        };
        let gaps: Vec<(f64, f64)> = doors.iter().map(|&c| (c, DOOR_WIDTH_M)).collect();
        for (a, b) in cut(-t, length + t, &gaps) {
            fixed.push(rect(a, b));
        }
        for &c in doors {
            items.push(MovableItem {
                kind: ItemKind::Door,
                variants: vec![
                    None,
                    Some(rect(c - DOOR_WIDTH_M / 2.0, c + DOOR_WIDTH_M / 2.0)),
                ],
                initial: rng.random_range(0..2),
            });
        }
    }

    // Cart rows along the front wall beside the doors.
    for start in [
        entrance + DOOR_WIDTH_M / 2.0 + 0.5,
        exit - DOOR_WIDTH_M / 2.0 - 0.5,
    ] {
        let sign = if start > entrance { 1.0 } else { -1.0 };
        let shapes: Vec<Aabb> = [2.0, 4.0, 6.0]
            .iter()
            .map(|l| Aabb::new(start, 0.0, (start + sign * l).clamp(0.2, w - 0.2), 0.7))
            .collect();
        items.push(optional_item(&mut rng, ItemKind::CartRow, &shapes, 0.7));
    }

    // Wall cases: dairy and frozen along the left wall, produce cases along the right wall, chillers and
    // service counters along the back wall.
    let case_top = d - CASE_DEPTH_M;
    for (a, b) in line_ups(
        &mut rng,
        FRONT_CORRIDOR_WIDTH_M + 1.0,
        case_top,
        &[side_door_left],
    ) {
        fixed.push(Aabb::new(0.0, a, CASE_DEPTH_M, b));
    }
    for (a, b) in line_ups(&mut rng, floor_lo, case_top, &[side_door_right]) {
        fixed.push(Aabb::new(w - CASE_DEPTH_M, a, w, b));
    }
    let back = line_ups(&mut rng, CASE_DEPTH_M, w - CASE_DEPTH_M, &back_doors);
    let counters = 2 + rng.random_range(0..3usize);
    let mut candidates: Vec<usize> = (0..back.len())
        .filter(|&i| back[i].1 - back[i].0 >= 5.0)
        .collect();
    let mut service = Vec::new();
    while service.len() < counters && !candidates.is_empty() {
        service.push(candidates.swap_remove(rng.random_range(0..candidates.len())));
    }
    for (i, &(a, b)) in back.iter().enumerate() {
        if service.contains(&i) {
            let front = d - SERVICE_ZONE_DEPTH_M;
            fixed.push(Aabb::new(a, front, b, front + SERVICE_COUNTER_DEPTH_M));
            fixed.push(Aabb::new(a, d - 0.7, b, d));
            fixed.push(Aabb::new(a - 0.15, front, a, d));
            fixed.push(Aabb::new(b, front, b + 0.15, d));
        } else {
            fixed.push(Aabb::new(a, case_top, b, d));
        }
    }

    // Gondola runs with end caps and promotions, bank by bank.
    let pitch = o.gondola_pitch();
    let end = END_CAP_DEPTH_M + GOODS_DEPTH_M + PROMO_DEPTH_M;
    let mut runs: Vec<(f64, f64, f64)> = Vec::new(); // (gondola left edge, run lo, run hi)
    for &(lo, hi) in &grid.banks {
        for &g in &grid.gondolas {
            const SHORTEN: [f64; 6] = [0.0, 0.0, 0.0, 1.0, 2.0, 3.0];
            let mut a = lo + end;
            let mut b = hi - end;
            let (s_lo, s_hi) = (
                SHORTEN[rng.random_range(0..SHORTEN.len())],
                SHORTEN[rng.random_range(0..SHORTEN.len())],
            );
            if b - a - (s_lo + s_hi) * MODULE_LENGTH_M >= 4.0 * MODULE_LENGTH_M {
                a += s_lo * MODULE_LENGTH_M;
                b -= s_hi * MODULE_LENGTH_M;
            }
            let modules = ((b - a) / MODULE_LENGTH_M).floor() as usize;
            let split = rng.random::<f64>() < 0.2 && modules >= 10;
            if split {
                let at = a + rng.random_range(4..modules - 5) as f64 * MODULE_LENGTH_M;
                let gap = 2.0 * (END_CAP_DEPTH_M + GOODS_DEPTH_M) + 1.6;
                runs.push((g, a, at));
                runs.push((g, at + gap, b));
            } else {
                runs.push((g, a, b));
            }
        }
    }
    for &(g, a, b) in &runs {
        let (frame_lo, frame_hi) = (g + GOODS_DEPTH_M, g + GONDOLA_DEPTH_M - GOODS_DEPTH_M);
        fixed.push(Aabb::new(frame_lo, a, frame_hi, b));
        let modules = ((b - a) / MODULE_LENGTH_M).round().max(1.0);
        let module = (b - a) / modules;
        for m in 0..modules as usize {
            let (y0, y1) = (a + m as f64 * module, a + (m + 1) as f64 * module);
            items.push(goods_item(&mut rng, frame_lo, -1.0, y0, y1, 0));
            items.push(goods_item(&mut rng, frame_hi, 1.0, y0, y1, 0));
        }
        // A promotion space in front of the end caps near a bank's edge (where a run ends at a lane; the
        // inner ends of a split run face a cross-over, which only sometimes falls in this band).
        let near_bank_edge = |y: f64| {
            let band = end + 4.0 * MODULE_LENGTH_M;
            grid.banks
                .iter()
                .any(|&(lo, hi)| (y - lo).abs() < band || (hi - y).abs() < band)
        };
        for (y, sign) in [(a, -1.0), (b, 1.0)] {
            let cap = y + sign * END_CAP_DEPTH_M;
            fixed.push(Aabb::new(g, y, g + GONDOLA_DEPTH_M, cap));
            items.push(goods_item(&mut rng, cap, sign, g, g + GONDOLA_DEPTH_M, 1));
            let promo = cap + sign * GOODS_DEPTH_M;
            if near_bank_edge(y) {
                let shapes = [
                    Aabb::new(g, promo, g + GONDOLA_DEPTH_M, promo + sign * PROMO_DEPTH_M),
                    Aabb::new(g + 0.2, promo, g + 1.1, promo + sign * 0.4),
                ];
                items.push(optional_item(&mut rng, ItemKind::Display, &shapes, 0.6));
            }
        }
    }

    // Produce islands: two columns of tables of different lengths in every bank.
    for &(lo, hi) in &grid.banks {
        for &x0 in &grid.islands {
            const LENGTHS: [f64; 3] = [2.4, 3.6, 4.8];
            const GAPS: [f64; 3] = [1.5, 2.5, 3.5];
            let mut y = lo + 0.5 + GAPS[rng.random_range(0..GAPS.len())] / 2.0;
            loop {
                let length = LENGTHS[rng.random_range(0..LENGTHS.len())];
                if y + length > hi - 0.5 {
                    break;
                }
                let (t0, t1) = (x0 + ISLAND_GOODS_M, x0 + grid.island_width - ISLAND_GOODS_M);
                fixed.push(Aabb::new(t0, y, t1, y + length));
                for (face, sign) in [(t0, -1.0), (t1, 1.0)] {
                    let variants = vec![
                        None,
                        Some(Aabb::new(face, y, face + sign * GOODS_STEP_M, y + length)),
                        Some(Aabb::new(face, y, face + sign * ISLAND_GOODS_M, y + length)),
                    ];
                    let initial = rng.random_range(0..variants.len());
                    items.push(MovableItem {
                        kind: ItemKind::Goods,
                        variants,
                        initial,
                    });
                }
                y += length + GAPS[rng.random_range(0..GAPS.len())];
            }
        }
    }

    // Half pallets against gondola faces in the aisles.
    for _ in 0..o.pallet_slots {
        let Some(&(g, a, b)) = runs.get(rng.random_range(0..runs.len().max(1))) else {
            break;
        };
        let y = rng.random_range(a..(b - 0.8).max(a + 0.01));
        let shape = if rng.random::<bool>() {
            Aabb::new(g - 0.6, y, g, y + 0.8)
        } else {
            Aabb::new(g + GONDOLA_DEPTH_M, y, g + GONDOLA_DEPTH_M + 0.6, y + 0.8)
        };
        items.push(optional_item(&mut rng, ItemKind::Pallet, &[shape], 0.3));
    }
    // Impulse displays along the power aisle, in front of the checkouts and the service desk.
    for _ in 0..o.display_slots {
        let x = rng.random_range(checkouts_from..desk + 4.0);
        let shape = Aabb::new(x, checkouts_top, x + 1.0, checkouts_top + 0.8);
        items.push(optional_item(&mut rng, ItemKind::Display, &[shape], 0.5));
    }

    // Structural columns on a grid aligned with the gondola lines, except in driving lanes.
    let spacing = COLUMN_SPACING_PITCHES as f64 * pitch;
    let half = COLUMN_SIZE_M / 2.0;
    let mut cx = first_gondola + GONDOLA_DEPTH_M / 2.0;
    while cx < w - CASE_DEPTH_M - half {
        let mut cy = FRONT_CORRIDOR_WIDTH_M + CHECKSTAND_LENGTH_M / 2.0;
        while cy < d - CASE_DEPTH_M - half {
            let column = Aabb::new(cx - half, cy - half, cx + half, cy + half);
            let clear = tour
                .windows(2)
                .all(|s| box_distance_to_segment(&column, &s[0], &s[1]) >= LANE_CLEARANCE_M);
            if clear {
                fixed.push(column);
            }
            cy += spacing;
        }
        cx += spacing;
    }

    let aisles = grid
        .banks
        .iter()
        .flat_map(|&(lo, hi)| {
            grid.columns[1..grid.columns.len() - 3]
                .iter()
                .map(move |&x| (Point2::new(x, lo), Point2::new(x, hi)))
        })
        .collect();
    Layout {
        fixed,
        items,
        plan: Plan::Store(StorePlan { tour, aisles }),
    }
}

/// Distance from an axis-aligned segment's points to a box (0 when they touch), m.
fn box_distance_to_segment(b: &Aabb, p: &Point2<f64>, q: &Point2<f64>) -> f64 {
    // Sample the segment finely enough for a lane-clearance test (segments are axis-aligned).
    let length = (q - p).norm();
    let steps = (length / 0.1).ceil().max(1.0) as usize;
    (0..=steps)
        .map(|k| {
            let s = p + (q - p) * (k as f64 / steps as f64);
            let dx = (b.min.x - s.x).max(s.x - b.max.x).max(0.0);
            let dy = (b.min.y - s.y).max(s.y - b.max.y).max(0.0);
            dx.hypot(dy)
        })
        .fold(f64::INFINITY, f64::min)
}

impl StorePlan {
    /// The aisles between gondolas (see [`Store::aisles`](super::Store::aisles)).
    pub(crate) fn aisles(&self) -> Vec<(Point2<f64>, Point2<f64>)> {
        self.aisles.clone()
    }

    /// Session 0 drives the tour `laps` times from its start; a later session starts at a seeded random
    /// place on the tour (`seed`, `session`), in a random direction, and drives on around it.
    pub(crate) fn route(&self, seed: u64, session: u32, laps: usize) -> Vec<Point2<f64>> {
        let mut cycle: Vec<Point2<f64>> = self.tour[..self.tour.len().saturating_sub(1)].to_vec();
        if cycle.len() < 2 {
            return cycle;
        }
        let mut points = Vec::new();
        let mut index = 0;
        if session == 0 {
            points.push(cycle[0]);
        } else {
            let mut rng = seeded(seed, 900_000 + u64::from(session));
            if rng.random::<bool>() {
                cycle.reverse();
            }
            index = rng.random_range(0..cycle.len());
            let next = cycle[(index + 1) % cycle.len()];
            let fraction: f64 = rng.random_range(0.0..0.9);
            points.push(cycle[index] + (next - cycle[index]) * fraction);
        }
        for k in 1..=laps * cycle.len() {
            points.push(cycle[(index + k) % cycle.len()]);
        }
        points.dedup_by(|a, b| (*a - *b).norm() < 1e-9);
        points
    }

    /// Pedestrians and carts walk back and forth along tour segments at least 4 m long, 0.6 m left or
    /// right of the centre line.
    pub(crate) fn walkers(
        &self,
        seed: u64,
        session: u32,
        pedestrians: usize,
        carts: usize,
    ) -> Vec<Walker> {
        let mut rng = seeded(seed, 500_000 + u64::from(session));
        let segments: Vec<(Point2<f64>, Point2<f64>)> = self
            .tour
            .windows(2)
            .filter(|s| (s[1] - s[0]).norm() >= 4.0)
            .map(|s| (s[0], s[1]))
            .collect();
        if segments.is_empty() {
            return Vec::new();
        }
        (0..pedestrians + carts)
            .map(|k| {
                let (a, b) = segments[rng.random_range(0..segments.len())];
                let along = (b - a).normalize();
                let side = if rng.random::<bool>() { 0.6 } else { -0.6 };
                let offset = Vector2::new(-along.y, along.x) * side;
                Walker {
                    start: a + offset,
                    end: b + offset,
                    speed: rng.random_range(0.5..1.3),
                    phase: rng.random_range(0.0..200.0),
                    radius: (k < pedestrians).then_some(0.25),
                }
            })
            .collect()
    }
}
