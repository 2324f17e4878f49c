//! The one grid a session starts against: the site's placed submaps rendered into the map frame.
//!
//! Every submap that knows a map cell has an opinion of it, and the submaps of a changing store
//! disagree: the shelf a session saw stocked, a later one saw empty. [`MapCells`] says how the opinions
//! become one value: the highest (every wall and every goods arrangement any session saw, merged), the
//! newest (what the store looks like now), or the newest weighted by how persistently the sessions that
//! know the cell saw it occupied (walls, pillars and shelf frames count fully; goods that came with the
//! last session count half). The session start ([`super::StartSearch`]) searches this grid
//! ([`super::LifelongMap::relocalization_map`]; the agent renders its cache of the site's submaps the
//! same way).

use nalgebra::{Point2, Vector2};
use serde::Deserialize;

use super::PlacedGrid;
use crate::grid::{
    CellIndex, MapLimits, ProbabilityGrid, UNKNOWN_VALUE, probability_to_value,
    value_to_probability,
};

/// How the relocalization map gives a cell one value from the submaps that know it (see the module
/// docs). Submaps are taken oldest first: by session, then by index within it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MapCells {
    /// The highest probability any submap gives the cell: every goods arrangement ever seen, merged.
    Highest,
    /// The newest submap's value: what the site looks like now (issue 14 §3). The default.
    #[default]
    Newest,
    /// The newest submap's value, its occupancy (the part above 0.5) scaled by the fraction of the
    /// sessions knowing the cell that saw it occupied (each session by its newest submap): a cell
    /// occupied in every session that saw it keeps its value; goods that appeared since the last
    /// session count half (issue 14 §3's per-cell persistence, over the sessions the map still holds —
    /// a trimmed session's evidence goes with its submaps). Not the default: it lowers the fit of right
    /// answers too. Why: `docs/TUNING.md#reloc-map-cells`.
    Persistent,
}

impl MapCells {
    /// Every choice, for help texts and tests.
    pub const ALL: [Self; 3] = [Self::Highest, Self::Newest, Self::Persistent];
}

/// A probability above this counts as occupied for [`MapCells::Persistent`] (the map change rate's).
const OCCUPIED: f32 = super::OCCUPIED_PROBABILITY;

/// Renders `grids` (each with its session, oldest first) into one map-frame grid of cell size
/// `resolution`, each cell valued as `cells` says. `None` when no grid knows anything.
pub fn render_relocalization_map<'a>(
    grids: impl IntoIterator<Item = (u32, PlacedGrid<'a>)>,
    resolution: f64,
    cells: MapCells,
) -> Option<ProbabilityGrid> {
    let grids: Vec<(u32, PlacedGrid<'a>)> = grids.into_iter().collect();
    let limits = covering_limits(grids.iter().map(|(_, g)| g), resolution)?;
    let mut out = ProbabilityGrid::new(limits.clone());
    match cells {
        MapCells::Highest | MapCells::Newest => {
            let values = out.values_mut();
            for (_, g) in &grids {
                for_each_known_cell(g, &limits, |to, value| {
                    let cell = &mut values[to];
                    *cell = if cells == MapCells::Newest {
                        value
                    } else {
                        (*cell).max(value)
                    };
                });
            }
        }
        MapCells::Persistent => {
            let mut history = vec![CellHistory::default(); limits.num_cells()];
            for (session, g) in &grids {
                for_each_known_cell(g, &limits, |to, value| history[to].see(*session, value));
            }
            for (cell, h) in out.values_mut().iter_mut().zip(history) {
                *cell = h.value();
            }
        }
    }
    let known = out.values().iter().any(|&v| v != UNKNOWN_VALUE);
    known.then(|| out.cropped_to_known())
}

/// What the sessions that know one cell saw: the current session's newest value (`UNKNOWN_VALUE`, 0,
/// before any), and how many earlier sessions knew it and saw it occupied.
#[derive(Clone, Copy, Debug, Default)]
struct CellHistory {
    session: Option<u32>,
    value: u16,
    known: u16,
    occupied: u16,
}

impl CellHistory {
    fn see(&mut self, session: u32, value: u16) {
        if self.session.is_some_and(|s| s != session) {
            self.close_session();
        }
        self.session = Some(session);
        self.value = value;
    }

    /// Counts the current session's view (its newest value) into the history.
    fn close_session(&mut self) {
        self.known = self.known.saturating_add(1);
        if value_to_probability(self.value) > OCCUPIED {
            self.occupied = self.occupied.saturating_add(1);
        }
    }

    /// [`MapCells::Persistent`]'s value of the cell.
    fn value(mut self) -> u16 {
        if self.session.is_none() {
            return UNKNOWN_VALUE;
        }
        let newest = self.value;
        self.close_session();
        let p = value_to_probability(newest);
        if p <= OCCUPIED {
            return newest;
        }
        let persistence = f32::from(self.occupied) / f32::from(self.known);
        probability_to_value(OCCUPIED + (p - OCCUPIED) * persistence)
    }
}

/// Map-frame limits at `resolution` covering every grid's bounds; `None` without grids.
fn covering_limits<'a>(
    grids: impl IntoIterator<Item = &'a PlacedGrid<'a>>,
    resolution: f64,
) -> Option<MapLimits> {
    let mut min = Vector2::repeat(f64::INFINITY);
    let mut max = Vector2::repeat(f64::NEG_INFINITY);
    for g in grids {
        let (a, b) = g.global_bounds();
        min = min.inf(&a);
        max = max.sup(&b);
    }
    if !(min.x.is_finite() && max.x.is_finite()) {
        return None;
    }
    let origin = min.map(|v| (v / resolution).floor() * resolution);
    let width = ((max.x - origin.x) / resolution).ceil() as i32 + 1;
    let height = ((max.y - origin.y) / resolution).ceil() as i32 + 1;
    Some(MapLimits::new(resolution, origin, width, height))
}

/// Calls `f(flat index in limits, value)` for every cell of `limits` whose centre `g` knows.
///
/// A map-sized render visits tens of millions of cells per session start, so each row is walked
/// incrementally: the cell centres of a row are evenly spaced, and so are their coordinates in the
/// source grid (in cells), which are truncated instead of floored once known non-negative (where the
/// two agree, and without a libm call per cell; a NaN is no cell).
fn for_each_known_cell(g: &PlacedGrid<'_>, limits: &MapLimits, mut f: impl FnMut(usize, u16)) {
    let (a, b) = g.global_bounds();
    let lo = limits.cell_index(&Point2::from(a));
    let hi = limits.cell_index(&Point2::from(b));
    let (x0, x1) = (lo.x.max(0), hi.x.min(limits.width - 1));
    if x0 > x1 {
        return;
    }
    let grid_from_global = g.global_from_grid.inverse();
    let source = g.grid.limits();
    let values = g.grid.values();
    let (source_width, source_height) = (source.width, source.height);
    // Where a map-frame point falls in the source grid, in (fractional) cells from its origin: what
    // `MapLimits::cell_index` floors.
    let in_source_cells = |p: Point2<f64>| (grid_from_global * p).coords - source.origin;
    let step = grid_from_global.rotation * Vector2::new(limits.resolution, 0.0);
    for iy in lo.y.max(0)..=hi.y.min(limits.height - 1) {
        let row_start = in_source_cells(limits.cell_center(&CellIndex::new(x0, iy)));
        let row_offset = iy as usize * limits.width as usize;
        for (k, ix) in (x0..=x1).enumerate() {
            let v = (row_start + step * k as f64) / source.resolution;
            if !(v.x >= 0.0 && v.y >= 0.0) {
                continue;
            }
            let (sx, sy) = (v.x as i32, v.y as i32);
            if sx >= source_width || sy >= source_height {
                continue;
            }
            let value = values[sy as usize * source_width as usize + sx as usize];
            if value != UNKNOWN_VALUE {
                f(row_offset + ix as usize, value);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng as _, SeedableRng as _};
    use rand_pcg::Pcg64;

    use super::*;
    use crate::geometry::{Rigid2, rigid2};

    fn random_grid(rng: &mut Pcg64) -> ProbabilityGrid {
        let limits = MapLimits::new(
            0.1,
            Vector2::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)),
            rng.random_range(8..30),
            rng.random_range(8..30),
        );
        let mut grid = ProbabilityGrid::new(limits.clone());
        for iy in 0..limits.height {
            for ix in 0..limits.width {
                if rng.random_bool(0.7) {
                    let p = if rng.random_bool(0.4) { 0.85 } else { 0.2 };
                    grid.set_probability(&CellIndex::new(ix, iy), p);
                }
            }
        }
        grid
    }

    /// The oracle: for every output cell, every session's newest value by a plain scan of all grids.
    fn brute_force(
        grids: &[(u32, PlacedGrid<'_>)],
        limits: &MapLimits,
        cells: MapCells,
    ) -> Vec<u16> {
        (0..limits.height)
            .flat_map(|iy| (0..limits.width).map(move |ix| CellIndex::new(ix, iy)))
            .map(|index| {
                let centre = limits.cell_center(&index);
                // Each knowing grid's value, oldest first.
                let seen: Vec<(u32, u16)> = grids
                    .iter()
                    .filter_map(|(session, g)| {
                        let local = g.global_from_grid.inverse() * centre;
                        let flat = g
                            .grid
                            .limits()
                            .flat_index(&g.grid.limits().cell_index(&local))?;
                        let v = g.grid.values()[flat];
                        (v != UNKNOWN_VALUE).then_some((*session, v))
                    })
                    .collect();
                let Some(&(_, newest)) = seen.last() else {
                    return UNKNOWN_VALUE;
                };
                match cells {
                    MapCells::Highest => seen.iter().map(|(_, v)| *v).max().unwrap(),
                    MapCells::Newest => newest,
                    MapCells::Persistent => {
                        let mut sessions: Vec<u32> = seen.iter().map(|(s, _)| *s).collect();
                        sessions.dedup();
                        let occupied = sessions
                            .iter()
                            .filter(|s| {
                                let last = seen.iter().rev().find(|(t, _)| t == *s).unwrap().1;
                                value_to_probability(last) > OCCUPIED
                            })
                            .count();
                        let p = value_to_probability(newest);
                        if p <= OCCUPIED {
                            newest
                        } else {
                            let w = occupied as f32 / sessions.len() as f32;
                            probability_to_value(OCCUPIED + (p - OCCUPIED) * w)
                        }
                    }
                }
            })
            .collect()
    }

    #[test]
    fn every_kind_of_cell_matches_a_brute_force_render() {
        let mut rng = Pcg64::seed_from_u64(11);
        let mut weighted = 0;
        for case in 0..12 {
            let owned: Vec<(u32, ProbabilityGrid, Rigid2)> = (0..6)
                .map(|i| {
                    let pose = rigid2(
                        rng.random_range(-0.5..0.5),
                        rng.random_range(-0.5..0.5),
                        rng.random_range(-0.3..0.3),
                    );
                    (i / 2, random_grid(&mut rng), pose)
                })
                .collect();
            let grids: Vec<(u32, PlacedGrid<'_>)> = owned
                .iter()
                .map(|(s, grid, pose)| {
                    (
                        *s,
                        PlacedGrid {
                            global_from_grid: *pose,
                            grid,
                        },
                    )
                })
                .collect();
            let limits = covering_limits(grids.iter().map(|(_, g)| g), 0.1).unwrap();
            let newest = brute_force(&grids, &limits, MapCells::Newest);
            for cells in MapCells::ALL {
                let rendered =
                    render_relocalization_map(grids.iter().copied(), 0.1, cells).unwrap();
                let expected = brute_force(&grids, &limits, cells);
                // The render is cropped to its known cells: compare through map-frame centres.
                for iy in 0..limits.height {
                    for ix in 0..limits.width {
                        let index = CellIndex::new(ix, iy);
                        let flat = limits.flat_index(&index).unwrap();
                        let at = rendered.limits().cell_index(&limits.cell_center(&index));
                        let got = rendered
                            .limits()
                            .flat_index(&at)
                            .map_or(UNKNOWN_VALUE, |i| rendered.values()[i]);
                        assert_eq!(
                            got, expected[flat],
                            "case {case}, {cells:?}, cell ({ix}, {iy})"
                        );
                        if cells == MapCells::Persistent && expected[flat] != newest[flat] {
                            weighted += 1;
                        }
                    }
                }
            }
        }
        assert!(weighted > 100, "too few cells weighted down: {weighted}");
    }

    /// One cell seen by three sessions of one submap each, the same pose.
    fn one_cell(probabilities: &[f32], cells: MapCells) -> f32 {
        let limits = MapLimits::new(0.1, Vector2::zeros(), 1, 1);
        let owned: Vec<ProbabilityGrid> = probabilities
            .iter()
            .map(|&p| {
                let mut g = ProbabilityGrid::new(limits.clone());
                g.set_probability(&CellIndex::new(0, 0), p);
                g
            })
            .collect();
        let grids = owned.iter().enumerate().map(|(s, grid)| {
            (
                s as u32,
                PlacedGrid {
                    global_from_grid: Rigid2::identity(),
                    grid,
                },
            )
        });
        let map = render_relocalization_map(grids, 0.1, cells).unwrap();
        map.probability(&CellIndex::new(0, 0))
    }

    #[test]
    fn goods_gone_since_are_gone_and_goods_new_since_count_by_persistence() {
        // Occupied in session 0, free in the last: the highest keeps it, the newest and persistent do not.
        assert!(one_cell(&[0.9, 0.2], MapCells::Highest) > 0.85);
        assert!(one_cell(&[0.9, 0.2], MapCells::Newest) < 0.25);
        assert!(one_cell(&[0.9, 0.2], MapCells::Persistent) < 0.25);
        // A wall every session saw keeps its value.
        assert!((one_cell(&[0.9, 0.9, 0.9], MapCells::Persistent) - 0.9).abs() < 1e-3);
        // Goods new in the last of two sessions count half their occupancy; in one of three, a third.
        assert!((one_cell(&[0.2, 0.9], MapCells::Persistent) - 0.7).abs() < 1e-3);
        assert!((one_cell(&[0.2, 0.2, 0.8], MapCells::Persistent) - 0.6).abs() < 1e-3);
        assert!((one_cell(&[0.2, 0.2, 0.8], MapCells::Newest) - 0.8).abs() < 1e-3);
    }
}
