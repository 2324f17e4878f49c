//! The published map at past versions: what the console's version slider and change overlay show.
//!
//! A site's map is its finished, committed submaps at their global poses. Every change that alters that
//! (a submap published, one trimmed, an optimization moving one) records an entry: the version, the map's
//! counts, and the placed grids (`global_from_grid`, shared `Arc`s, so an entry costs a few dozen bytes
//! per submap, not a copy of the grids). The map at any version `v` is the newest entry at or before `v`.
//!
//! The history is rebuilt with the map (replay records the same entries), so it spans the site's whole
//! life after a restart too. It is bounded: entries are kept every `stride` map changes (1 at first),
//! plus always the newest; once [`MapHistory::capacity`] entries are held, every second kept entry is
//! dropped (the first one always stays) and the stride doubles. So the slider always reaches from the
//! site's first map to its newest, in roughly even steps.
//!
//! It is bounded in bytes too. Trimmed submaps' grids stay in memory as long as an entry refers to them,
//! and a lifelong map replaces its submaps session after session: with a count bound only, the history
//! of a site kept nearly every grid the site ever published (the soak's memory growth, issue 16 §5).
//! So the cells of the grids the entries hold that the newest map does not (the past's own cost,
//! counted once per grid however many entries share it) are kept under
//! [`MapHistory::past_grid_budget_bytes`]: past it, the history thins the same way until it fits,
//! keeping the first and the newest entry (the newest map's grids are the map's, not the history's).
//! A long-lived site's slider then has fewer, wider steps.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;

use mapping::geometry::Rigid2;
use mapping::grid::ProbabilityGrid;

use super::MapCounts;

/// Entries kept per site before thinning (count). 256 entries of a 500-submap map are ~5 MB of poses
/// and pointers.
pub const DEFAULT_HISTORY_CAPACITY: usize = 256;

/// Cells of grids the history may hold beyond the newest map's, per site (bytes): 32 MiB, about one
/// more map of the demo's 48 × 30 m store at 5 cm in submaps that were trimmed or replaced since.
pub const DEFAULT_HISTORY_PAST_GRID_BUDGET_BYTES: usize = 32 << 20;

/// The placed grids of one version: `global_from_grid` (the grid's frame is its session's local frame)
/// and the grid, oldest submap first.
pub type PlacedGrids = Arc<Vec<(Rigid2, Arc<ProbabilityGrid>)>>;

/// The published map at one version.
#[derive(Clone, Debug)]
pub struct HistoryEntry {
    /// The version that made this map.
    pub version: u64,
    /// The map's counts at that version.
    pub counts: MapCounts,
    /// Its placed grids.
    pub grids: PlacedGrids,
}

/// A bounded history of a site's published maps; see the module docs.
#[derive(Clone, Debug)]
pub struct MapHistory {
    entries: VecDeque<HistoryEntry>,
    capacity: usize,
    /// Most cells' bytes of grids held beyond the newest entry's.
    past_grid_budget_bytes: usize,
    /// Every grid the entries hold, by address: (entries holding it, its cells' bytes). An address is
    /// unique while an entry holds the grid, so it stays unique as long as it is a key here.
    held: BTreeMap<usize, (usize, usize)>,
    /// Sum of the cells' bytes of `held`.
    held_bytes: usize,
    /// Map changes between kept entries.
    stride: u64,
    /// Map changes recorded since the last kept entry.
    since_kept: u64,
    /// The last entry is the newest map only, not a kept step (the next change replaces it).
    newest_only: bool,
}

impl Default for MapHistory {
    fn default() -> Self {
        Self::new(
            DEFAULT_HISTORY_CAPACITY,
            DEFAULT_HISTORY_PAST_GRID_BUDGET_BYTES,
        )
    }
}

impl MapHistory {
    /// An empty history keeping up to `capacity` entries (at least 4 are kept) and at most
    /// `past_grid_budget_bytes` of grid cells beyond the newest map's (see the module docs).
    pub fn new(capacity: usize, past_grid_budget_bytes: usize) -> Self {
        Self {
            entries: VecDeque::new(),
            capacity: capacity.max(4),
            past_grid_budget_bytes,
            held: BTreeMap::new(),
            held_bytes: 0,
            stride: 1,
            since_kept: 0,
            newest_only: false,
        }
    }

    /// Most entries kept.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Most cells' bytes of grids kept beyond the newest map's.
    pub fn past_grid_budget_bytes(&self) -> usize {
        self.past_grid_budget_bytes
    }

    /// Cells' bytes of the distinct grids the entries hold, the newest map's among them.
    pub fn grid_bytes(&self) -> usize {
        self.held_bytes
    }

    /// Cells' bytes of the distinct grids the entries hold that the newest map does not.
    pub fn past_grid_bytes(&self) -> usize {
        let newest: usize = self.entries.back().map_or(0, |e| {
            let mut seen: Vec<usize> = e.grids.iter().map(|(_, g)| grid_key(g)).collect();
            seen.sort_unstable();
            seen.dedup();
            seen.iter()
                .filter_map(|key| self.held.get(key).map(|(_, bytes)| bytes))
                .sum()
        });
        self.held_bytes.saturating_sub(newest)
    }

    /// Records the map of `version` (versions must grow; an older or equal one is ignored).
    pub fn record(&mut self, entry: HistoryEntry) {
        if self
            .entries
            .back()
            .is_some_and(|last| last.version >= entry.version)
        {
            return;
        }
        if self.newest_only
            && let Some(replaced) = self.entries.pop_back()
        {
            self.release(&replaced);
        }
        self.since_kept += 1;
        self.newest_only = self.since_kept < self.stride;
        if !self.newest_only {
            self.since_kept = 0;
            // One place stays free for the newest map between kept steps.
            if self.entries.len() + 1 >= self.capacity {
                self.thin();
            }
        }
        self.hold(&entry);
        self.entries.push_back(entry);
        // Bounded: each round halves the entries before the newest.
        while self.entries.len() > 2 && self.past_grid_bytes() > self.past_grid_budget_bytes {
            let newest = self.entries.pop_back();
            self.thin();
            if let Some(newest) = newest {
                self.entries.push_back(newest);
            }
        }
    }

    /// Drops every second kept entry, keeping the first, and doubles the stride.
    fn thin(&mut self) {
        let mut dropped = Vec::new();
        for (index, entry) in std::mem::take(&mut self.entries).into_iter().enumerate() {
            if index % 2 == 0 {
                self.entries.push_back(entry);
            } else {
                dropped.push(entry);
            }
        }
        for entry in &dropped {
            self.release(entry);
        }
        self.stride = self.stride.saturating_mul(2);
    }

    /// Counts the grids of an entry coming in.
    fn hold(&mut self, entry: &HistoryEntry) {
        for (_, grid) in entry.grids.iter() {
            let held = self
                .held
                .entry(grid_key(grid))
                .or_insert((0, std::mem::size_of_val(grid.values())));
            if held.0 == 0 {
                self.held_bytes += held.1;
            }
            held.0 += 1;
        }
    }

    /// Counts the grids of an entry going out.
    fn release(&mut self, entry: &HistoryEntry) {
        for (_, grid) in entry.grids.iter() {
            let key = grid_key(grid);
            if let Some(held) = self.held.get_mut(&key) {
                held.0 -= 1;
                if held.0 == 0 {
                    self.held_bytes -= held.1;
                    self.held.remove(&key);
                }
            }
        }
    }

    /// Every entry, oldest first.
    pub fn entries(&self) -> impl ExactSizeIterator<Item = &HistoryEntry> + '_ {
        self.entries.iter()
    }

    /// The map at `version`: the newest entry at or before it (`None` before the first map).
    pub fn at(&self, version: u64) -> Option<&HistoryEntry> {
        let after = self.entries.partition_point(|e| e.version <= version);
        after.checked_sub(1).and_then(|i| self.entries.get(i))
    }

    /// The newest entry.
    pub fn latest(&self) -> Option<&HistoryEntry> {
        self.entries.back()
    }
}

/// A grid's identity while it is held: its address.
fn grid_key(grid: &Arc<ProbabilityGrid>) -> usize {
    Arc::as_ptr(grid) as usize
}

#[cfg(test)]
mod tests {
    use std::sync::Weak;

    use mapping::grid::MapLimits;

    use super::*;

    fn entry(version: u64) -> HistoryEntry {
        HistoryEntry {
            version,
            counts: MapCounts::default(),
            grids: Arc::new(Vec::new()),
        }
    }

    fn versions(h: &MapHistory) -> Vec<u64> {
        h.entries().map(|e| e.version).collect()
    }

    #[test]
    fn the_map_at_a_version_is_the_newest_entry_not_after_it() {
        let mut h = MapHistory::new(10, usize::MAX);
        for v in [3, 5, 9] {
            h.record(entry(v));
        }
        h.record(entry(9));
        h.record(entry(4));
        assert_eq!(versions(&h), [3, 5, 9], "versions only grow");
        assert!(h.at(2).is_none());
        assert_eq!(h.at(3).unwrap().version, 3);
        assert_eq!(h.at(4).unwrap().version, 3);
        assert_eq!(h.at(8).unwrap().version, 5);
        assert_eq!(h.at(100).unwrap().version, 9);
        assert_eq!(h.latest().unwrap().version, 9);
    }

    #[test]
    fn a_full_history_thins_its_past_and_keeps_both_ends() {
        let mut h = MapHistory::new(8, usize::MAX);
        for v in 1..=1000 {
            h.record(entry(v));
            assert!(h.entries().len() <= 8, "bounded at version {v}");
        }
        let kept = versions(&h);
        assert_eq!(kept.first(), Some(&1), "the first map stays: {kept:?}");
        assert_eq!(kept.last(), Some(&1000), "{kept:?}");
        assert!(kept.windows(2).all(|w| w[0] < w[1]), "{kept:?}");
        assert!(kept.len() >= 4, "{kept:?}");
        // Steps over the whole life, no hole of more than a third of it.
        let largest = kept.windows(2).map(|w| w[1] - w[0]).max().unwrap();
        assert!(largest <= 1000 / 3, "{kept:?}");
    }

    /// A map whose submaps turn over: two 100 × 100 grids that stay (session 0's) and four more of
    /// which every version replaces two.
    fn turnover(h: &mut MapHistory, versions: u64, made: &mut Vec<Weak<ProbabilityGrid>>) {
        let limits = MapLimits::new(0.05, Rigid2::identity().translation.vector, 100, 100);
        let mut grid = || {
            let grid = Arc::new(ProbabilityGrid::new(limits.clone()));
            made.push(Arc::downgrade(&grid));
            grid
        };
        let base = [grid(), grid()];
        let mut fresh: Vec<Arc<ProbabilityGrid>> = Vec::new();
        for v in 1..=versions {
            if fresh.len() >= 4 {
                fresh.drain(..2);
            }
            while fresh.len() < 4 {
                fresh.push(grid());
            }
            h.record(HistoryEntry {
                version: v,
                counts: MapCounts::default(),
                grids: Arc::new(
                    base.iter()
                        .chain(&fresh)
                        .map(|g| (Rigid2::identity(), Arc::clone(g)))
                        .collect(),
                ),
            });
        }
    }

    #[test]
    fn the_grids_of_a_map_that_turns_over_are_kept_within_the_budget() {
        // 20 kB a grid; 240 kB of past grids may stay (12 grids), the count alone would keep 64 entries.
        let grid_bytes = 100 * 100 * 2;
        let mut h = MapHistory::new(64, 12 * grid_bytes);
        let mut made = Vec::new();
        turnover(&mut h, 500, &mut made);
        // What is still alive is the newest map's 6 grids and what the history keeps.
        let alive = made.iter().filter(|g| g.upgrade().is_some()).count();
        assert!(alive <= 6 + 12, "{alive} grids alive");
        assert_eq!(h.grid_bytes(), alive * grid_bytes);
        assert!(
            h.past_grid_bytes() <= 12 * grid_bytes,
            "{}",
            h.past_grid_bytes()
        );
        // The slider still reaches from the first map to the newest, in a few steps.
        let kept = versions(&h);
        assert_eq!(kept.first(), Some(&1), "{kept:?}");
        assert_eq!(kept.last(), Some(&500), "{kept:?}");
        assert!(kept.len() >= 3, "{kept:?}");
    }

    #[test]
    fn without_a_budget_the_count_bound_keeps_the_grids_of_every_entry() {
        let mut h = MapHistory::new(64, usize::MAX);
        let mut made = Vec::new();
        turnover(&mut h, 500, &mut made);
        let alive = made.iter().filter(|g| g.upgrade().is_some()).count();
        assert!(alive > 60, "{alive} grids alive");
        assert_eq!(h.grid_bytes(), alive * 100 * 100 * 2);
    }
}
