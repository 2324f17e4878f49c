//! The robot's copy of its site's finished submaps (what global matching runs against), kept current by
//! applying the server's deltas.

use std::collections::BTreeMap;

use mapping::pose_graph::SubmapId;
use proto::{MapDelta, SubmapSnapshot};

/// A delta that does not follow the cache's version.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("delta from version {from} does not apply to a cache at version {cached}")]
pub struct CacheError {
    /// The delta's base version.
    pub from: u64,
    /// The cache's version.
    pub cached: u64,
}

/// Global submaps at one site version.
#[derive(Clone, Debug, Default)]
pub struct GlobalSubmapCache {
    version: u64,
    submaps: BTreeMap<SubmapId, SubmapSnapshot>,
}

impl GlobalSubmapCache {
    /// The version the cache reflects (0: empty).
    pub fn version(&self) -> u64 {
        self.version
    }

    /// The cached submaps with their current global poses.
    pub fn submaps(&self) -> &BTreeMap<SubmapId, SubmapSnapshot> {
        &self.submaps
    }

    /// Applies a delta computed since a version at or before the cache's (older bases re-send what the
    /// cache has, which is harmless). Fresh submaps in, moved poses updated, trimmed submaps out.
    pub fn apply(&mut self, delta: MapDelta) -> Result<(), CacheError> {
        if delta.from_version > self.version {
            return Err(CacheError {
                from: delta.from_version,
                cached: self.version,
            });
        }
        if delta.to_version <= self.version {
            return Ok(());
        }
        for submap in delta.submaps_added {
            self.submaps.insert(submap.id, submap);
        }
        for (id, pose) in delta.pose_updates {
            if let Some(submap) = self.submaps.get_mut(&id) {
                submap.global_pose = pose;
            }
        }
        for id in delta.trimmed {
            self.submaps.remove(&id);
        }
        self.version = delta.to_version;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use mapping::geometry::rigid2;
    use mapping::grid::{MapLimits, ProbabilityGrid};
    use nalgebra::Vector2;

    use super::*;

    fn submap(index: u32) -> SubmapSnapshot {
        SubmapSnapshot {
            id: SubmapId {
                trajectory: 0,
                index,
            },
            revision: 1,
            global_pose: rigid2(0.0, 0.0, 0.0),
            local_pose: rigid2(0.0, 0.0, 0.0),
            grid: Arc::new(ProbabilityGrid::new(MapLimits::new(
                0.05,
                Vector2::zeros(),
                2,
                2,
            ))),
        }
    }

    fn delta(from: u64, to: u64) -> MapDelta {
        MapDelta {
            site: "s".into(),
            from_version: from,
            to_version: to,
            submaps_added: vec![],
            pose_updates: vec![],
            trimmed: vec![],
        }
    }

    #[test]
    fn deltas_add_move_and_trim_in_version_order() {
        let mut cache = GlobalSubmapCache::default();
        let mut d = delta(0, 3);
        d.submaps_added = vec![submap(0), submap(1)];
        cache.apply(d).unwrap();
        let mut d = delta(3, 5);
        d.pose_updates = vec![(submap(1).id, rigid2(2.0, 0.0, 0.0))];
        d.trimmed = vec![submap(0).id];
        cache.apply(d).unwrap();
        assert_eq!(cache.version(), 5);
        assert_eq!(cache.submaps().len(), 1);
        assert!((cache.submaps()[&submap(1).id].global_pose.translation.x - 2.0).abs() < 1e-12);
        assert_eq!(
            cache.apply(delta(7, 9)),
            Err(CacheError { from: 7, cached: 5 })
        );
        // A stale delta changes nothing.
        let mut stale = delta(0, 4);
        stale.submaps_added = vec![submap(0)];
        cache.apply(stale).unwrap();
        assert_eq!(cache.submaps().len(), 1);
    }
}
