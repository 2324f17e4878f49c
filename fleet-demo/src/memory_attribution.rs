//! Where the load benchmark's memory is, sampled every minute of a soak: the allocator's live heap
//! beside the process's resident set (resident memory the heap does not explain is the allocator's
//! free-but-kept pages: fragmentation), and the sizes of every structure that could grow with time —
//! each site's graph (nodes, submaps, constraints), the grids its map and its console history hold,
//! the server's sled store on disk and what it holds in memory, and the robots' submap caches.
//!
//! Grid sizes are the cells' bytes (2 per cell) of distinct grids, each counted once however many
//! history entries or snapshots share it: the figure that grows if trimmed submaps stay referenced.

use std::collections::BTreeSet;
use std::path::Path;
use std::sync::{Arc, Mutex};

use mapping::grid::ProbabilityGrid;
use robot_agent::uplink::GlobalSubmapCache;
use serde_json::json;
use server::site::SiteHandle;
use storage::SledStore;

/// Bytes per MiB.
const MIB: f64 = 1024.0 * 1024.0;

/// The allocator's live heap now, bytes: the binary's global allocator counts every allocation
/// (`peak_alloc`); `None` when it is not the global allocator (nothing counted).
pub fn live_heap_bytes() -> Option<usize> {
    let bytes = peak_alloc::PeakAlloc.current_usage();
    (bytes > 0).then_some(bytes)
}

/// One site's share of the server's memory.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SiteMemory {
    /// Nodes in the site's graph.
    pub nodes: u64,
    /// Submaps in the site's graph.
    pub submaps: u64,
    /// Pose-graph constraints.
    pub constraints: u64,
    /// Entries of the console's map history.
    pub history_entries: usize,
    /// Cells of the distinct grids the published map holds now, MiB.
    pub map_grids_mb: f64,
    /// Cells of the distinct grids the whole history holds (the current map's among them), MiB.
    pub history_grids_mb: f64,
}

/// What one sample attributes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MemoryAttribution {
    /// The allocator's live heap, MiB (`None`: not measured).
    pub live_heap_mb: Option<f64>,
    /// Every site, in the order given.
    pub sites: Vec<SiteMemory>,
    /// The server's sled store on disk, MiB.
    pub store_disk_mb: f64,
    /// Bytes of values the sled store has written or read since it last reopened, MiB: what sled holds
    /// in memory (`storage::SledStore::held_bytes`).
    pub store_held_mb: f64,
    /// Reopens of the sled store that freed that memory so far.
    pub store_memory_reopens: u64,
    /// Submaps in all robots' caches.
    pub robot_cache_submaps: usize,
    /// Cells of the distinct grids in all robots' caches, MiB.
    pub robot_cache_grids_mb: f64,
}

impl MemoryAttribution {
    /// Measures now: the live heap, every site (by its handle), the store (its folder and what it holds
    /// in memory) and the caches.
    pub fn measure(
        sites: &[SiteHandle],
        store: &SledStore,
        caches: &[Arc<Mutex<GlobalSubmapCache>>],
    ) -> Self {
        let sites = sites
            .iter()
            .map(|handle| {
                let counts = handle.current().counts;
                let view = handle.view();
                let map_grids = view
                    .history
                    .last()
                    .map_or(0.0, |entry| grid_mb(entry.grids.iter().map(|(_, g)| g)));
                SiteMemory {
                    nodes: counts.nodes,
                    submaps: counts.submaps,
                    constraints: counts.constraints,
                    history_entries: view.history.len(),
                    map_grids_mb: map_grids,
                    history_grids_mb: grid_mb(
                        view.history
                            .iter()
                            .flat_map(|entry| entry.grids.iter().map(|(_, g)| g)),
                    ),
                }
            })
            .collect();
        let mut robot_cache_submaps = 0;
        let mut cached = Vec::new();
        for cache in caches {
            if let Ok(cache) = cache.lock() {
                robot_cache_submaps += cache.submaps().len();
                cached.extend(cache.submaps().values().map(|s| Arc::clone(&s.grid)));
            }
        }
        Self {
            live_heap_mb: live_heap_bytes().map(|b| b as f64 / MIB),
            sites,
            store_disk_mb: folder_bytes(store.path(), 4) as f64 / MIB,
            store_held_mb: store.held_bytes() as f64 / MIB,
            store_memory_reopens: store.memory_reopens(),
            robot_cache_submaps,
            robot_cache_grids_mb: grid_mb(cached.iter()),
        }
    }

    /// The sample as the report's JSON.
    pub fn to_json(&self) -> serde_json::Value {
        json!({
            "live_heap_mb": self.live_heap_mb,
            "store_disk_mb": self.store_disk_mb,
            "store_held_mb": self.store_held_mb,
            "store_memory_reopens": self.store_memory_reopens,
            "robot_cache_submaps": self.robot_cache_submaps,
            "robot_cache_grids_mb": self.robot_cache_grids_mb,
            "sites": self.sites.iter().map(|s| json!({
                "nodes": s.nodes,
                "submaps": s.submaps,
                "constraints": s.constraints,
                "history_entries": s.history_entries,
                "map_grids_mb": s.map_grids_mb,
                "history_grids_mb": s.history_grids_mb,
            })).collect::<Vec<_>>(),
        })
    }

    /// Sum over the sites of the history's grids, MiB.
    pub fn history_grids_mb(&self) -> f64 {
        self.sites.iter().map(|s| s.history_grids_mb).sum()
    }
}

/// Cells' bytes of the distinct grids among `grids` (by address), MiB.
fn grid_mb<'a>(grids: impl Iterator<Item = &'a Arc<ProbabilityGrid>>) -> f64 {
    let mut seen = BTreeSet::new();
    let mut bytes = 0usize;
    for grid in grids {
        if seen.insert(Arc::as_ptr(grid) as usize) {
            bytes += std::mem::size_of_val(grid.values());
        }
    }
    bytes as f64 / MIB
}

/// Bytes of the files under `dir`, `depth` folders deep at most (0 when unreadable).
pub(crate) fn folder_bytes(dir: &Path, depth: usize) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .filter_map(Result::ok)
        .filter_map(|e| Some((e.path(), e.metadata().ok()?)))
        .map(|(path, meta)| {
            if meta.is_dir() {
                if depth > 0 {
                    folder_bytes(&path, depth - 1)
                } else {
                    0
                }
            } else {
                meta.len()
            }
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use mapping::geometry::Rigid2;
    use mapping::grid::MapLimits;

    use super::*;

    #[test]
    fn shared_grids_count_once() {
        let limits = MapLimits::new(0.05, Rigid2::identity().translation.vector, 100, 50);
        let a = Arc::new(ProbabilityGrid::new(limits.clone()));
        let b = Arc::new(ProbabilityGrid::new(limits));
        let one = 100.0 * 50.0 * 2.0 / MIB;
        assert!((grid_mb([&a, &a, &a].into_iter()) - one).abs() < 1e-12);
        assert!((grid_mb([&a, &b, &a].into_iter()) - 2.0 * one).abs() < 1e-12);
    }

    #[test]
    fn a_folder_sums_its_files() {
        let dir = tempfile::tempdir().expect("tempdir");
        std::fs::write(dir.path().join("a"), [0u8; 100]).expect("write");
        std::fs::create_dir(dir.path().join("sub")).expect("mkdir");
        std::fs::write(dir.path().join("sub").join("b"), [0u8; 50]).expect("write");
        assert_eq!(folder_bytes(dir.path(), 4), 150);
        assert_eq!(folder_bytes(dir.path(), 0), 100);
        assert_eq!(folder_bytes(&dir.path().join("missing"), 4), 0);
    }
}
