//! The `aisles` world: blocks of identical shelf rows separated by cross aisles, pillars at some row ends.
//!
//! This is the layout the simulator had before issue 14 §4, kept bit for bit (same random streams, same
//! items in the same order, same routes and walkers) as the adversarial case: from inside an aisle every
//! aisle looks alike, so the bar there is precision (never placed wrong), not recall.

use nalgebra::Point2;
use rand::Rng as _;

use super::AislesOptions;
use super::ray_caster::Aabb;
use super::store::{ItemKind, Layout, MovableItem, Plan, Walker, seeded};

/// Where the robot and the walkers drive in the `aisles` world.
#[derive(Clone, Debug)]
pub(crate) struct AislesPlan {
    /// y of every aisle centre line, bottom to top (the first and last are the perimeter aisles).
    aisle_ys: Vec<f64>,
    /// x of every cross-aisle centre line, left to right (the first and last are the perimeter aisles).
    cross_xs: Vec<f64>,
    /// x extent of every block of shelf rows.
    block_xs: Vec<(f64, f64)>,
}

/// Lays out the `aisles` world from `options` and `seed`.
pub(crate) fn lay_out(o: &AislesOptions, seed: u64) -> Layout {
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
    Layout {
        fixed,
        items,
        plan: Plan::Aisles(AislesPlan {
            aisle_ys,
            cross_xs,
            block_xs,
        }),
    }
}

impl AislesPlan {
    /// The pedestrians and carts of session `session`.
    pub(crate) fn walkers(
        &self,
        seed: u64,
        session: u32,
        pedestrians: usize,
        carts: usize,
    ) -> Vec<Walker> {
        let mut rng = seeded(seed, 500_000 + u64::from(session));
        let n = pedestrians + carts;
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
                    radius: (k < pedestrians).then_some(0.25),
                }
            })
            .collect()
    }

    /// The centre lines of the aisles between shelf rows (not the perimeter aisles), block by block.
    pub(crate) fn aisles(&self) -> Vec<(Point2<f64>, Point2<f64>)> {
        let inner = &self.aisle_ys[1..self.aisle_ys.len() - 1];
        self.block_xs
            .iter()
            .flat_map(|&(x0, x1)| {
                inner
                    .iter()
                    .map(move |&y| (Point2::new(x0, y), Point2::new(x1, y)))
            })
            .collect()
    }

    /// The waypoints of a session's route: session 0 sweeps every aisle of every block from the
    /// bottom-left corner; a later session starts in a random aisle of a random block (`seed`, `session`)
    /// and sweeps on from there. The route is long enough for any duration (it wraps around the store).
    pub(crate) fn route(&self, seed: u64, session: u32, laps: usize) -> Vec<Point2<f64>> {
        let (ys, xs) = (&self.aisle_ys, &self.cross_xs);
        let blocks = xs.len() - 1;
        let (mut block, mut aisle, mut up, mut at_left) = (0, 0, true, true);
        if session > 0 {
            let mut rng = seeded(seed, 900_000 + u64::from(session));
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
}
