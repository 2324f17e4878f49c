//! The simulated supermarket: fixed structure, movable items with a per-session schedule, walkers, routes.

use nalgebra::{Point2, Vector2};
use rand::{Rng as _, SeedableRng as _};
use rand_pcg::Pcg64;

use super::ray_caster::Aabb;
use super::{SessionOptions, SimulatedSession, SimulationError, StoreOptions, simulated_session};
use crate::grid::{
    CellIndex, MAX_PROBABILITY, MIN_PROBABILITY, MapLimits, ProbabilityGrid, UNKNOWN_VALUE,
    probability_to_value,
};

/// What a movable item is (for pictures and statistics).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ItemKind {
    /// Goods on one shelf module, protruding by a varying depth.
    Goods,
    /// A pallet standing in an aisle against a shelf.
    Pallet,
    /// A display or promotion stand.
    Display,
    /// A door in the outer wall (present = closed).
    Door,
}

/// A movable item: the shapes it can take (`None` = absent) and its schedule.
#[derive(Clone, Debug)]
struct MovableItem {
    kind: ItemKind,
    variants: Vec<Option<Aabb>>,
    initial: usize,
}

/// A person or cart moving back and forth along a line during a session.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Walker {
    pub start: Point2<f64>,
    pub end: Point2<f64>,
    pub speed: f64,
    pub phase: f64,
    /// Disc radius for a person; `None` for a cart.
    pub radius: Option<f64>,
}

impl Walker {
    /// Where the walker is `t` seconds into the session.
    pub fn position(&self, t: f64) -> Point2<f64> {
        let length = (self.end - self.start).norm().max(1e-6);
        let s = (self.phase + self.speed * t).rem_euclid(2.0 * length);
        let s = if s > length { 2.0 * length - s } else { s };
        self.start + (self.end - self.start) * (s / length)
    }

    /// The walker's shape at `t`.
    pub fn shape(&self, t: f64) -> WalkerShape {
        let p = self.position(t);
        if let Some(r) = self.radius {
            WalkerShape::Disc(p, r)
        } else {
            let along_x = (self.end.x - self.start.x).abs() > (self.end.y - self.start.y).abs();
            let (hx, hy) = if along_x { (0.45, 0.25) } else { (0.25, 0.45) };
            WalkerShape::Box(Aabb::new(p.x - hx, p.y - hy, p.x + hx, p.y + hy))
        }
    }
}

/// The shape of a walker at one instant.
#[derive(Clone, Copy, Debug)]
pub(crate) enum WalkerShape {
    Disc(Point2<f64>, f64),
    Box(Aabb),
}

/// The rasterized layout of one session (no walkers): `occupied[y * width + x]`.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthOccupancy {
    /// Cell geometry.
    pub limits: MapLimits,
    /// Whether each cell is inside an obstacle.
    pub occupied: Vec<bool>,
}

impl TruthOccupancy {
    /// Occupied cells with a free 4-neighbour: the surfaces a LiDAR can see (interiors of shelves and
    /// walls are never observed, so they are not part of a map).
    pub fn surface(&self) -> Vec<bool> {
        let (w, h) = (self.limits.width as usize, self.limits.height as usize);
        let mut surface = vec![false; self.occupied.len()];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if !self.occupied[i] {
                    continue;
                }
                let free = |xx: usize, yy: usize| !self.occupied[yy * w + xx];
                surface[i] = (x > 0 && free(x - 1, y))
                    || (x + 1 < w && free(x + 1, y))
                    || (y > 0 && free(x, y - 1))
                    || (y + 1 < h && free(x, y + 1));
            }
        }
        surface
    }

    /// The layout as a map would see it: surface cells occupied ([`MAX_PROBABILITY`]), free cells free
    /// ([`MIN_PROBABILITY`]), the interiors of obstacles unknown (a LiDAR never sees them). Compared with
    /// [`map_change_rate`](crate::lifelong::map_change_rate), two layouts give the simulator's own change
    /// rate, measured exactly as the map change rate (MCR) of the maps is.
    pub fn surface_grid(&self) -> ProbabilityGrid {
        let surface = self.surface();
        let mut grid = ProbabilityGrid::new(self.limits.clone());
        for (i, value) in grid.values_mut().iter_mut().enumerate() {
            *value = if surface[i] {
                probability_to_value(MAX_PROBABILITY)
            } else if self.occupied[i] {
                UNKNOWN_VALUE
            } else {
                probability_to_value(MIN_PROBABILITY)
            };
        }
        grid
    }
}

/// A seeded supermarket: see the module documentation of [`crate::simulation`].
#[derive(Clone, Debug)]
pub struct Store {
    options: StoreOptions,
    seed: u64,
    fixed: Vec<Aabb>,
    items: Vec<MovableItem>,
    /// y of every aisle centre line, bottom to top (the first and last are the perimeter aisles).
    aisle_ys: Vec<f64>,
    /// x of every cross-aisle centre line, left to right (the first and last are the perimeter aisles).
    cross_xs: Vec<f64>,
}

fn seeded(seed: u64, stream: u64) -> Pcg64 {
    Pcg64::seed_from_u64(seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

impl Store {
    /// Lays out a store from `options` and `seed`.
    pub fn generate(options: &StoreOptions, seed: u64) -> Result<Self, SimulationError> {
        options.validate()?;
        let o = options;
        let mut rng = seeded(seed, 1);
        let (w, d, t) = (o.width, o.depth, o.wall_thickness);
        let mut fixed = Vec::new();
        let mut items = Vec::new();

        // Outer walls with door gaps.
        let door_width = 2.0;
        let mut door_gaps: Vec<(usize, f64)> = Vec::new(); // (wall 0..4, centre along the wall)
        for k in 0..o.doors {
            let wall = k % 4;
            let length = if wall < 2 { w } else { d };
            let slot = (k / 4 + 1) as f64 / ((o.doors / 4 + 1) as f64 + 1.0);
            door_gaps.push((wall, (slot * length).clamp(door_width, length - door_width)));
        }
        for wall in 0..4 {
            let length = if wall < 2 { w } else { d };
            let mut gaps: Vec<f64> = door_gaps
                .iter()
                .filter(|g| g.0 == wall)
                .map(|g| g.1)
                .collect();
            gaps.sort_by(f64::total_cmp);
            let mut from = -t;
            let mut pieces = Vec::new();
            for c in &gaps {
                pieces.push((from, c - door_width / 2.0));
                from = c + door_width / 2.0;
            }
            pieces.push((from, length + t));
            let rect = |a: f64, b: f64| match wall {
                0 => Aabb::new(a, -t, b, 0.0),
                1 => Aabb::new(a, d, b, d + t),
                2 => Aabb::new(-t, a, 0.0, b),
                _ => Aabb::new(w, a, w + t, b),
            };
            for (a, b) in pieces {
                if b > a {
                    fixed.push(rect(a, b));
                }
            }
            for c in gaps {
                items.push(MovableItem {
                    kind: ItemKind::Door,
                    variants: vec![None, Some(rect(c - door_width / 2.0, c + door_width / 2.0))],
                    initial: rng.random_range(0..2),
                });
            }
        }

        // Blocks, shelf rows, goods modules, pillars.
        let c = o.cross_aisle_width;
        let block_width = (w - (o.blocks + 1) as f64 * c) / o.blocks as f64;
        let shelf = o.frame_depth + 2.0 * o.goods_depth;
        let pitch = o.row_pitch();
        let mut rows = Vec::new(); // y of each row's lower edge
        let mut y = c;
        while y + shelf <= d - c + 1e-9 {
            rows.push(y);
            y += pitch;
        }
        let mut aisle_ys = vec![c / 2.0];
        for pair in rows.windows(2) {
            aisle_ys.push(0.5 * (pair[0] + shelf + pair[1]));
        }
        let last_end = rows.last().map_or(c, |r| r + shelf);
        aisle_ys.push(last_end + 0.5 * (d - last_end).min(c));
        let mut cross_xs = vec![c / 2.0];
        let mut block_xs = Vec::new();
        for b in 0..o.blocks {
            let x0 = c + b as f64 * (block_width + c);
            block_xs.push((x0, x0 + block_width));
            cross_xs.push(x0 + block_width + c / 2.0);
        }
        for &(x0, x1) in &block_xs {
            for &row in &rows {
                let frame_lo = row + o.goods_depth;
                let frame_hi = frame_lo + o.frame_depth;
                fixed.push(Aabb::new(x0, frame_lo, x1, frame_hi));
                if rng.random::<f64>() < o.pillar_fraction {
                    let yc = 0.5 * (frame_lo + frame_hi);
                    fixed.push(Aabb::new(x0 - 0.6, yc - 0.3, x0, yc + 0.3));
                    fixed.push(Aabb::new(x1, yc - 0.3, x1 + 0.6, yc + 0.3));
                }
                let modules = (block_width / o.module_length).floor().max(1.0) as usize;
                let module = block_width / modules as f64;
                for m in 0..modules {
                    let (a, b) = (x0 + m as f64 * module, x0 + (m + 1) as f64 * module);
                    for (face, sign) in [(frame_lo, -1.0), (frame_hi, 1.0)] {
                        let variants = std::iter::once(None)
                            .chain((1..=3).map(|k| {
                                let depth = o.goods_depth * f64::from(k) / 3.0;
                                Some(Aabb::new(a, face, b, face + sign * depth))
                            }))
                            .collect();
                        items.push(MovableItem {
                            kind: ItemKind::Goods,
                            variants,
                            initial: rng.random_range(0..4),
                        });
                    }
                }
            }
        }

        // Pallets against shelf faces, in aisles.
        for _ in 0..o.pallet_slots {
            let (x0, x1) = block_xs[rng.random_range(0..block_xs.len())];
            let row = rows[rng.random_range(0..rows.len())];
            let x = rng.random_range(x0..(x1 - 1.2).max(x0 + 0.01));
            let (face, sign) = if rng.random::<bool>() {
                (row + o.goods_depth, -1.0)
            } else {
                (row + o.goods_depth + o.frame_depth, 1.0)
            };
            items.push(MovableItem {
                kind: ItemKind::Pallet,
                variants: vec![None, Some(Aabb::new(x, face, x + 1.2, face + sign * 0.8))],
                initial: usize::from(rng.random::<f64>() < 0.3),
            });
        }
        // Displays: against the side walls (in the perimeter aisle) and at shelf ends (in cross aisles).
        for k in 0..o.display_slots {
            let shape = if k % 2 == 0 {
                let y = rng.random_range(c..(d - c - 1.0));
                if rng.random::<bool>() {
                    Aabb::new(0.0, y, 0.8, y + 1.0)
                } else {
                    Aabb::new(w - 0.8, y, w, y + 1.0)
                }
            } else {
                let (x0, x1) = block_xs[rng.random_range(0..block_xs.len())];
                let row = rows[rng.random_range(0..rows.len())];
                if rng.random::<bool>() {
                    Aabb::new(x0 - 0.7, row, x0, row + shelf)
                } else {
                    Aabb::new(x1, row, x1 + 0.7, row + shelf)
                }
            };
            items.push(MovableItem {
                kind: ItemKind::Display,
                variants: vec![None, Some(shape)],
                initial: usize::from(rng.random::<f64>() < 0.5),
            });
        }
        Ok(Self {
            options: options.clone(),
            seed,
            fixed,
            items,
            aisle_ys,
            cross_xs,
        })
    }

    /// The options the store was generated with.
    pub fn options(&self) -> &StoreOptions {
        &self.options
    }

    /// Floor area inside the outer walls, m².
    pub fn area_m2(&self) -> f64 {
        self.options.width * self.options.depth
    }

    /// The variant each movable item shows in session `session` (a Markov chain per item: each session
    /// an item changes to a different variant with probability `change_probability`).
    fn states(&self, session: u32) -> Vec<usize> {
        let p = self.options.change_probability;
        self.items
            .iter()
            .enumerate()
            .map(|(i, item)| {
                let mut rng = seeded(self.seed, 1000 + i as u64);
                let mut state = item.initial;
                for _ in 0..session {
                    if rng.random::<f64>() < p && item.variants.len() > 1 {
                        let shift = rng.random_range(1..item.variants.len());
                        state = (state + shift) % item.variants.len();
                    }
                }
                state
            })
            .collect()
    }

    /// Every obstacle box of session `session` (fixed structure plus the movable items present).
    pub fn obstacles(&self, session: u32) -> Vec<Aabb> {
        let mut boxes = self.fixed.clone();
        for (item, state) in self.items.iter().zip(self.states(session)) {
            if let Some(b) = item.variants[state] {
                boxes.push(b);
            }
        }
        boxes
    }

    /// How many movable items of each kind are present in session `session`: (goods, pallets, displays,
    /// closed doors).
    pub fn items_present(&self, session: u32) -> [usize; 4] {
        let mut counts = [0; 4];
        for (item, state) in self.items.iter().zip(self.states(session)) {
            if item.variants[state].is_some() {
                counts[item.kind as usize] += 1;
            }
        }
        counts
    }

    /// The layout of session `session` rasterized at `resolution` metres (a cell is occupied when its
    /// centre is inside an obstacle).
    pub fn occupancy(&self, session: u32, resolution: f64) -> TruthOccupancy {
        let t = self.options.wall_thickness + resolution;
        let width = ((self.options.width + 2.0 * t) / resolution).ceil() as i32;
        let height = ((self.options.depth + 2.0 * t) / resolution).ceil() as i32;
        let limits = MapLimits::new(resolution, Vector2::new(-t, -t), width, height);
        let mut occupied = vec![false; limits.num_cells()];
        for b in self.obstacles(session) {
            let lo = limits.cell_index(&b.min);
            let hi = limits.cell_index(&b.max);
            for y in lo.y.max(0)..=hi.y.min(height - 1) {
                for x in lo.x.max(0)..=hi.x.min(width - 1) {
                    let index = CellIndex::new(x, y);
                    if b.contains(&limits.cell_center(&index))
                        && let Some(i) = limits.flat_index(&index)
                    {
                        occupied[i] = true;
                    }
                }
            }
        }
        TruthOccupancy { limits, occupied }
    }

    /// The pedestrians and carts of session `session`.
    pub(crate) fn walkers(&self, session: u32) -> Vec<Walker> {
        let o = &self.options;
        let mut rng = seeded(self.seed, 500_000 + u64::from(session));
        let n = o.pedestrians + o.carts;
        (0..n)
            .map(|k| {
                let along_aisle = rng.random::<bool>();
                let offset = if rng.random::<bool>() { 0.6 } else { -0.6 };
                let (start, end) = if along_aisle {
                    let y = self.aisle_ys[rng.random_range(0..self.aisle_ys.len())] + offset;
                    let b = rng.random_range(0..self.cross_xs.len() - 1);
                    (
                        Point2::new(self.cross_xs[b], y),
                        Point2::new(self.cross_xs[b + 1], y),
                    )
                } else {
                    let x = self.cross_xs[rng.random_range(0..self.cross_xs.len())] + offset;
                    (
                        Point2::new(x, self.aisle_ys[0]),
                        Point2::new(x, self.aisle_ys[self.aisle_ys.len() - 1]),
                    )
                };
                Walker {
                    start,
                    end,
                    speed: rng.random_range(0.5..1.3),
                    phase: rng.random_range(0.0..200.0),
                    radius: (k < o.pedestrians).then_some(0.25),
                }
            })
            .collect()
    }

    /// Aisle centre lines (y) and cross-aisle centre lines (x): where the robot drives.
    pub fn driving_lines(&self) -> (&[f64], &[f64]) {
        (&self.aisle_ys, &self.cross_xs)
    }

    /// The waypoints of a session's route: session 0 sweeps every aisle of every block from the bottom-left
    /// corner; a later session starts in a random aisle of a random block (`seed`, `session`) and sweeps on
    /// from there. The route is long enough for any duration (it wraps around the store).
    pub(crate) fn route(&self, session: u32, laps: usize) -> Vec<Point2<f64>> {
        let (ys, xs) = (&self.aisle_ys, &self.cross_xs);
        let blocks = xs.len() - 1;
        let (mut block, mut aisle, mut up, mut at_left) = (0, 0, true, true);
        if session > 0 {
            let mut rng = seeded(self.seed, 900_000 + u64::from(session));
            block = rng.random_range(0..blocks);
            aisle = rng.random_range(0..ys.len());
            up = rng.random::<bool>();
            at_left = rng.random::<bool>();
        }
        let mut points = Vec::new();
        let x_of = |block: usize, left: bool| if left { xs[block] } else { xs[block + 1] };
        points.push(Point2::new(x_of(block, at_left), ys[aisle]));
        let last = ys.len() - 1;
        let mut visited_blocks = 0;
        while visited_blocks < blocks * laps {
            // Sweep the rest of this block.
            loop {
                at_left = !at_left;
                points.push(Point2::new(x_of(block, at_left), ys[aisle]));
                let next = if up {
                    aisle.checked_add(1).filter(|a| *a <= last)
                } else {
                    aisle.checked_sub(1)
                };
                let Some(next) = next else { break };
                aisle = next;
                points.push(Point2::new(x_of(block, at_left), ys[aisle]));
            }
            // On to the next block along the perimeter aisle we ended in.
            visited_blocks += 1;
            let next_block = (block + 1) % blocks;
            let target_x = xs[next_block];
            points.push(Point2::new(target_x, ys[aisle]));
            block = next_block;
            at_left = true;
            up = !up;
        }
        points.dedup_by(|a, b| (*a - *b).norm() < 1e-9);
        points
    }

    /// Simulates session `session` (see [`SimulatedSession`]).
    pub fn session(
        &self,
        session: u32,
        options: &SessionOptions,
    ) -> Result<SimulatedSession, SimulationError> {
        options.validate()?;
        simulated_session::simulate(
            self,
            session,
            options,
            seeded(self.seed, 700_000 + u64::from(session)),
        )
    }
}
