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
//! site's first map to its newest, in roughly even steps. Trimmed submaps' grids stay in memory as long as an
//! entry refers to them.

use std::collections::VecDeque;
use std::sync::Arc;

use mapping::geometry::Rigid2;
use mapping::grid::ProbabilityGrid;

use super::MapCounts;

/// Entries kept per site before thinning (count). 256 entries of a 500-submap map are ~5 MB of poses
/// and pointers.
pub const DEFAULT_HISTORY_CAPACITY: usize = 256;

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
    /// Map changes between kept entries.
    stride: u64,
    /// Map changes recorded since the last kept entry.
    since_kept: u64,
    /// The last entry is the newest map only, not a kept step (the next change replaces it).
    newest_only: bool,
}

impl Default for MapHistory {
    fn default() -> Self {
        Self::new(DEFAULT_HISTORY_CAPACITY)
    }
}

impl MapHistory {
    /// An empty history keeping up to `capacity` entries (at least 4 are kept).
    pub fn new(capacity: usize) -> Self {
        Self {
            entries: VecDeque::new(),
            capacity: capacity.max(4),
            stride: 1,
            since_kept: 0,
            newest_only: false,
        }
    }

    /// Most entries kept.
    pub fn capacity(&self) -> usize {
        self.capacity
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
        if self.newest_only {
            self.entries.pop_back();
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
        self.entries.push_back(entry);
    }

    /// Drops every second kept entry, keeping the first, and doubles the stride.
    fn thin(&mut self) {
        let mut index = 0;
        self.entries.retain(|_| {
            let keep = index % 2 == 0;
            index += 1;
            keep
        });
        self.stride = self.stride.saturating_mul(2);
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

#[cfg(test)]
mod tests {
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
        let mut h = MapHistory::new(10);
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
        let mut h = MapHistory::new(8);
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
}
