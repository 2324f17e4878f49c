//! Exact 2D ray casting against axis-aligned boxes and discs, accelerated by a uniform bucket grid.

use nalgebra::{Point2, Vector2};

/// An axis-aligned box obstacle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Lowest corner (metres).
    pub min: Point2<f64>,
    /// Highest corner (metres).
    pub max: Point2<f64>,
}

impl Aabb {
    /// The box with corners `(x0, y0)` and `(x1, y1)` in any order.
    pub fn new(x0: f64, y0: f64, x1: f64, y1: f64) -> Self {
        Self {
            min: Point2::new(x0.min(x1), y0.min(y1)),
            max: Point2::new(x0.max(x1), y0.max(y1)),
        }
    }

    /// Whether `p` is inside or on the box.
    pub fn contains(&self, p: &Point2<f64>) -> bool {
        p.x >= self.min.x && p.x <= self.max.x && p.y >= self.min.y && p.y <= self.max.y
    }

    /// Distance along the unit ray `origin + t·direction` (`t ≥ 0`) to the box's boundary, if it is hit
    /// (slab method; a ray starting inside the box hits it at 0).
    pub fn intersect(&self, origin: &Point2<f64>, direction: &Vector2<f64>) -> Option<f64> {
        let mut t_near = 0.0f64;
        let mut t_far = f64::INFINITY;
        for axis in 0..2 {
            let (o, d) = (origin[axis], direction[axis]);
            let (lo, hi) = (self.min[axis], self.max[axis]);
            if d.abs() < 1e-12 {
                if o < lo || o > hi {
                    return None;
                }
            } else {
                let (mut t0, mut t1) = ((lo - o) / d, (hi - o) / d);
                if t0 > t1 {
                    std::mem::swap(&mut t0, &mut t1);
                }
                t_near = t_near.max(t0);
                t_far = t_far.min(t1);
                if t_near > t_far {
                    return None;
                }
            }
        }
        Some(t_near)
    }
}

/// Distance along the unit ray to a disc of `radius` around `center`, if hit.
pub fn intersect_disc(
    center: &Point2<f64>,
    radius: f64,
    origin: &Point2<f64>,
    direction: &Vector2<f64>,
) -> Option<f64> {
    let oc = origin - center;
    let b = oc.dot(direction);
    let c = oc.norm_squared() - radius * radius;
    if c <= 0.0 {
        return Some(0.0);
    }
    let disc = b * b - c;
    if disc < 0.0 {
        return None;
    }
    let t = -b - disc.sqrt();
    (t >= 0.0).then_some(t)
}

/// Static boxes bucketed on a uniform grid for fast ray casting.
#[derive(Clone, Debug)]
pub struct RayCaster {
    boxes: Vec<Aabb>,
    origin: Point2<f64>,
    cell: f64,
    width: usize,
    height: usize,
    /// Box indices per bucket, row-major.
    buckets: Vec<Vec<u32>>,
}

impl RayCaster {
    /// Buckets `boxes` on cells of `cell` metres covering their bounding box.
    pub fn new(boxes: Vec<Aabb>, cell: f64) -> Self {
        let cell = cell.max(0.05);
        let (mut lo, mut hi) = (Point2::new(0.0, 0.0), Point2::new(1.0, 1.0));
        if let Some(first) = boxes.first() {
            (lo, hi) = (first.min, first.max);
        }
        for b in &boxes {
            lo = lo.inf(&b.min);
            hi = hi.sup(&b.max);
        }
        let origin = lo - Vector2::new(cell, cell);
        let width = (((hi.x - origin.x) / cell).ceil() as usize + 2).max(1);
        let height = (((hi.y - origin.y) / cell).ceil() as usize + 2).max(1);
        let mut buckets = vec![Vec::new(); width * height];
        for (i, b) in boxes.iter().enumerate() {
            let (x0, y0) = Self::cell_of(origin, cell, &b.min);
            let (x1, y1) = Self::cell_of(origin, cell, &b.max);
            for y in y0..=y1.min(height - 1) {
                for x in x0..=x1.min(width - 1) {
                    buckets[y * width + x].push(i as u32);
                }
            }
        }
        Self {
            boxes,
            origin,
            cell,
            width,
            height,
            buckets,
        }
    }

    fn cell_of(origin: Point2<f64>, cell: f64, p: &Point2<f64>) -> (usize, usize) {
        (
            ((p.x - origin.x) / cell).floor().max(0.0) as usize,
            ((p.y - origin.y) / cell).floor().max(0.0) as usize,
        )
    }

    /// The boxes.
    pub fn boxes(&self) -> &[Aabb] {
        &self.boxes
    }

    /// Distance to the nearest box along the unit ray, up to `max_range` (Amanatides–Woo walk over the
    /// buckets; stops at the first bucket holding a hit closer than the bucket's exit).
    pub fn cast(
        &self,
        origin: &Point2<f64>,
        direction: &Vector2<f64>,
        max_range: f64,
    ) -> Option<f64> {
        let local = (origin - self.origin) / self.cell;
        let (mut x, mut y) = (local.x.floor() as i64, local.y.floor() as i64);
        let step_x: i64 = if direction.x >= 0.0 { 1 } else { -1 };
        let step_y: i64 = if direction.y >= 0.0 { 1 } else { -1 };
        let next = |coord: f64, cell: i64, step: i64| {
            if step > 0 {
                (cell + 1) as f64 - coord
            } else {
                coord - cell as f64
            }
        };
        let inv = |d: f64| {
            if d.abs() < 1e-12 {
                f64::INFINITY
            } else {
                self.cell / d.abs()
            }
        };
        let (delta_x, delta_y) = (inv(direction.x), inv(direction.y));
        let mut t_max_x = next(local.x, x, step_x) * delta_x;
        let mut t_max_y = next(local.y, y, step_y) * delta_y;
        let mut best = f64::INFINITY;
        loop {
            if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
                for &i in &self.buckets[y as usize * self.width + x as usize] {
                    if let Some(t) = self.boxes[i as usize].intersect(origin, direction) {
                        best = best.min(t);
                    }
                }
            } else if (step_x > 0 && x >= self.width as i64)
                || (step_x < 0 && x < 0)
                || (step_y > 0 && y >= self.height as i64)
                || (step_y < 0 && y < 0)
            {
                break;
            }
            let t_exit = t_max_x.min(t_max_y);
            if best <= t_exit || t_exit > max_range {
                break;
            }
            if t_max_x < t_max_y {
                x += step_x;
                t_max_x += delta_x;
            } else {
                y += step_y;
                t_max_y += delta_y;
            }
        }
        (best <= max_range).then_some(best)
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng as _, SeedableRng as _};
    use rand_pcg::Pcg64;

    use super::*;

    #[test]
    fn bucketed_cast_equals_brute_force() {
        let mut rng = Pcg64::seed_from_u64(3);
        let boxes: Vec<Aabb> = (0..300)
            .map(|_| {
                let (x, y) = (rng.random_range(0.0..40.0), rng.random_range(0.0..30.0));
                Aabb::new(
                    x,
                    y,
                    x + rng.random_range(0.1..3.0),
                    y + rng.random_range(0.1..3.0),
                )
            })
            .collect();
        let caster = RayCaster::new(boxes.clone(), 1.0);
        for _ in 0..3000 {
            let origin = Point2::new(rng.random_range(-5.0..45.0), rng.random_range(-5.0..35.0));
            let a: f64 = rng.random_range(-3.2..3.2);
            let direction = Vector2::new(a.cos(), a.sin());
            let brute = boxes
                .iter()
                .filter_map(|b| b.intersect(&origin, &direction))
                .fold(f64::INFINITY, f64::min);
            let expected = (brute <= 25.0).then_some(brute);
            let got = caster.cast(&origin, &direction, 25.0);
            match (expected, got) {
                (None, None) => {}
                (Some(e), Some(g)) => assert!((e - g).abs() < 1e-9, "{e} vs {g}"),
                _ => panic!("{expected:?} vs {got:?} from {origin:?} at {a}"),
            }
        }
    }

    #[test]
    fn disc_and_box_hits() {
        let o = Point2::new(0.0, 0.0);
        let d = Vector2::new(1.0, 0.0);
        assert!(
            (intersect_disc(&Point2::new(5.0, 0.0), 1.0, &o, &d).expect("hit") - 4.0).abs() < 1e-12
        );
        assert!(intersect_disc(&Point2::new(5.0, 2.0), 1.0, &o, &d).is_none());
        assert!(intersect_disc(&Point2::new(-5.0, 0.0), 1.0, &o, &d).is_none());
        let b = Aabb::new(2.0, -1.0, 3.0, 1.0);
        assert!((b.intersect(&o, &d).expect("hit") - 2.0).abs() < 1e-12);
        assert!(b.intersect(&o, &Vector2::new(-1.0, 0.0)).is_none());
    }
}
