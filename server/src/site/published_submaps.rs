//! The finished submaps of one published site version, as robots fetch them: what [`super::SiteView`]
//! carries so that a robot's `Delta` or `Submap` request is answered from the published version beside the
//! site task, not in its queue behind a session's end (trimming, sparsification, optimization and a
//! checkpoint can keep the task busy for seconds).

use std::collections::BTreeMap;
use std::sync::Arc;

use mapping::pose_graph::SubmapId;
use proto::{MapDelta, SubmapSnapshot};

use super::SiteError;

/// One finished submap of a published version.
#[derive(Clone, Debug)]
pub(crate) struct PublishedSubmap {
    /// Version at which its grid was stored.
    pub revision: u64,
    /// Version at which its global pose last changed.
    pub pose_version: u64,
    /// The submap with its grid and its global pose at the version.
    pub snapshot: SubmapSnapshot,
}

/// The finished submaps of one site version and the submaps trimmed before it.
#[derive(Clone, Debug)]
pub struct PublishedSubmaps {
    site: String,
    version: u64,
    submaps: Arc<BTreeMap<SubmapId, PublishedSubmap>>,
    /// Every submap trimmed so far and the version that trimmed it.
    trimmed: Arc<BTreeMap<SubmapId, u64>>,
}

impl PublishedSubmaps {
    pub(crate) fn new(
        site: &str,
        version: u64,
        submaps: BTreeMap<SubmapId, PublishedSubmap>,
        trimmed: Arc<BTreeMap<SubmapId, u64>>,
    ) -> Self {
        Self {
            site: site.to_owned(),
            version,
            submaps: Arc::new(submaps),
            trimmed,
        }
    }

    /// What changed after version `since` (0: the whole map): finished submaps stored after it (with
    /// grids and poses), poses of older finished submaps that moved after it, and the submaps trimmed
    /// after it.
    pub fn delta_since(&self, since: u64) -> Result<MapDelta, SiteError> {
        if since > self.version {
            return Err(SiteError::NotFound(format!(
                "version {since} is ahead of site {:?} (at {})",
                self.site, self.version
            )));
        }
        let mut delta = MapDelta {
            site: self.site.clone(),
            from_version: since,
            to_version: self.version,
            submaps_added: Vec::new(),
            pose_updates: Vec::new(),
            trimmed: Vec::new(),
        };
        for (id, submap) in self.submaps.iter() {
            if submap.revision > since {
                delta.submaps_added.push(submap.snapshot.clone());
            } else if submap.pose_version > since {
                delta.pose_updates.push((*id, submap.snapshot.global_pose));
            }
        }
        delta.trimmed = self
            .trimmed
            .iter()
            .filter(|(_, v)| **v > since)
            .map(|(id, _)| *id)
            .collect();
        Ok(delta)
    }

    /// One finished submap; `revision` 0 means the current one.
    pub fn submap(&self, id: SubmapId, revision: u64) -> Result<SubmapSnapshot, SiteError> {
        self.submaps
            .get(&id)
            .filter(|s| revision == 0 || revision == s.revision)
            .map(|s| s.snapshot.clone())
            .ok_or_else(|| {
                SiteError::NotFound(format!(
                    "submap ({}, {}) revision {revision} is not in site {:?}",
                    id.trajectory, id.index, self.site
                ))
            })
    }
}
