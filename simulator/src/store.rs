//! The simulated world: fixed structure, movable items with a per-session schedule, walkers, routes. The
//! floor plans themselves are laid out by [`store_layout`](super::store_layout) (`--world store`) and
//! [`aisles`](super::aisles) (`--world aisles`).

use mapping::grid::{
    CellIndex, MAX_PROBABILITY, MIN_PROBABILITY, MapLimits, ProbabilityGrid, UNKNOWN_VALUE,
    probability_to_value,
};
use nalgebra::{Point2, Vector2};
use rand::{Rng as _, SeedableRng as _};
use rand_pcg::Pcg64;

use super::aisles::{self, AislesPlan};
use super::ray_caster::Aabb;
use super::store_layout::{self, StorePlan};
use super::{SessionOptions, SimulatedSession, SimulationError, WorldOptions, simulated_session};

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
    /// A row of nested shopping carts parked at the front (`store` world only).
    CartRow,
}

impl ItemKind {
    /// How many kinds there are (the length of [`Store::items_present`]).
    pub const COUNT: usize = 5;
}

/// A movable item: the shapes it can take (`None` = absent) and its schedule.
#[derive(Clone, Debug)]
pub(crate) struct MovableItem {
    pub kind: ItemKind,
    pub variants: Vec<Option<Aabb>>,
    pub initial: usize,
}

/// A floor plan as a layout module produces it: fixed structure, movable items, where to drive.
#[derive(Clone, Debug)]
pub(crate) struct Layout {
    /// Structure that never moves (walls, columns, shelf frames, cases, checkouts, counters).
    pub fixed: Vec<Aabb>,
    /// Everything that changes from day to day.
    pub items: Vec<MovableItem>,
    /// Routes and walker lanes.
    pub plan: Plan,
}

/// Where the robot and the walkers drive, per world.
#[derive(Clone, Debug)]
pub(crate) enum Plan {
    /// The `aisles` world's grid of aisles and cross aisles.
    Aisles(AislesPlan),
    /// The `store` world's cleaning tour.
    Store(StorePlan),
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
    /// [`map_change_rate`](mapping::lifelong::map_change_rate), two layouts give the simulator's own change
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

/// A seeded supermarket: see the module documentation of [`crate`].
#[derive(Clone, Debug)]
pub struct Store {
    options: WorldOptions,
    seed: u64,
    fixed: Vec<Aabb>,
    items: Vec<MovableItem>,
    plan: Plan,
}

/// A random stream of `seed`, one per purpose (`stream`), so adding draws to one purpose leaves the others
/// unchanged.
pub(crate) fn seeded(seed: u64, stream: u64) -> Pcg64 {
    Pcg64::seed_from_u64(seed ^ stream.wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

impl Store {
    /// Lays out the world `options` names (a [`StoreOptions`](super::StoreOptions) or an
    /// [`AislesOptions`](super::AislesOptions) converts into one) from `seed`.
    pub fn generate(options: impl Into<WorldOptions>, seed: u64) -> Result<Self, SimulationError> {
        let options = options.into();
        options.validate()?;
        let Layout { fixed, items, plan } = match &options {
            WorldOptions::Store(o) => store_layout::lay_out(o, seed),
            WorldOptions::Aisles(o) => aisles::lay_out(o, seed),
        };
        Ok(Self {
            options,
            seed,
            fixed,
            items,
            plan,
        })
    }

    /// The seed the store was generated with.
    pub(crate) fn seed(&self) -> u64 {
        self.seed
    }

    /// The options the store was generated with.
    pub fn options(&self) -> &WorldOptions {
        &self.options
    }

    /// Floor area inside the outer walls, m².
    pub fn area_m2(&self) -> f64 {
        self.options.width() * self.options.depth()
    }

    /// The static structure: walls, columns, shelf frames, cases, checkouts, counters. It is part of
    /// [`obstacles`](Self::obstacles) on every day.
    pub fn structure(&self) -> &[Aabb] {
        &self.fixed
    }

    /// The movable items, in the order of [`states`](Self::states).
    #[cfg(test)]
    pub(crate) fn movable_items(&self) -> &[MovableItem] {
        &self.items
    }

    /// The centre lines of the aisles between shelf rows (perimeter and cross aisles excluded), as
    /// `(from, to)` segments.
    pub fn aisles(&self) -> Vec<(Point2<f64>, Point2<f64>)> {
        match &self.plan {
            Plan::Aisles(plan) => plan.aisles(),
            Plan::Store(plan) => plan.aisles(),
        }
    }

    /// The variant each movable item shows in session `session` (a Markov chain per item: each session
    /// an item changes to a different variant with probability `change_probability`).
    pub(crate) fn states(&self, session: u32) -> Vec<usize> {
        let p = self.options.change_probability();
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

    /// How many movable items of each kind are present in session `session`, indexed by
    /// `ItemKind as usize` (goods, pallets, displays, closed doors, cart rows).
    pub fn items_present(&self, session: u32) -> [usize; ItemKind::COUNT] {
        let mut counts = [0; ItemKind::COUNT];
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
        let t = self.options.wall_thickness() + resolution;
        let width = ((self.options.width() + 2.0 * t) / resolution).ceil() as i32;
        let height = ((self.options.depth() + 2.0 * t) / resolution).ceil() as i32;
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
        let (pedestrians, carts) = self.options.walkers();
        match &self.plan {
            Plan::Aisles(plan) => plan.walkers(self.seed, session, pedestrians, carts),
            Plan::Store(plan) => plan.walkers(self.seed, session, pedestrians, carts),
        }
    }

    /// The waypoints of a session's route, `laps` times around the world's cleaning route (session 0
    /// from the route's start, later sessions from a seeded random place on it).
    pub(crate) fn route(&self, session: u32, laps: usize) -> Vec<Point2<f64>> {
        match &self.plan {
            Plan::Aisles(plan) => plan.route(self.seed, session, laps),
            Plan::Store(plan) => plan.route(self.seed, session, laps),
        }
    }

    /// One lap of session `session`'s cleaning route: the waypoints the robot drives through, turning in
    /// place at each (session 0: the whole mapping run).
    pub fn cleaning_route(&self, session: u32) -> Vec<Point2<f64>> {
        self.route(session, 1)
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
