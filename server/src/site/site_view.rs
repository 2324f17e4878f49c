//! What read-only front ends (the web console) see of a site, published by its task with every
//! version so they read it without queueing behind the site's work.
//!
//! While the site is unloaded (idle: its map dropped from memory, see `SiteTask`), the view keeps what
//! lists the site cheaply — its version and its sessions without their trajectories — and holds no
//! history (the grids are what unloading frees). What needs the map waits for the site's restore
//! ([`super::SiteHandle::loaded_view`]).

use std::sync::Arc;

use super::{HistoryEntry, PublishedSubmaps, SessionView};

/// A site as of one version: its sessions and its map history.
#[derive(Clone, Debug, Default)]
pub struct SiteView {
    /// The version.
    pub version: u64,
    /// Every session, in the order they were opened ([`super::SiteMap::session_views`]); while the
    /// site is unloaded, without their `trajectory_poses`.
    pub sessions: Arc<Vec<SessionView>>,
    /// The published map at past versions, oldest first ([`super::MapHistory`]); empty while the site
    /// is unloaded.
    pub history: Arc<Vec<HistoryEntry>>,
    /// The finished submaps robots fetch at this version (`Delta`, `Submap`); `None` while the site is
    /// unloaded and before its first version is published (then the site task answers).
    pub submaps: Option<Arc<PublishedSubmaps>>,
    /// The site's map is out of memory (idle past `site_unload_after_s`): the next request restores it
    /// from its checkpoint first.
    pub unloaded: bool,
}

impl SiteView {
    /// What is kept of `self` while its site is unloaded: the version and the sessions without their
    /// trajectories (a mature site's can be megabytes), no history.
    #[must_use]
    pub fn unloaded(&self) -> Self {
        let sessions = self
            .sessions
            .iter()
            .map(|s| SessionView {
                trajectory_poses: Vec::new(),
                ..s.clone()
            })
            .collect();
        Self {
            version: self.version,
            sessions: Arc::new(sessions),
            history: Arc::new(Vec::new()),
            submaps: None,
            unloaded: true,
        }
    }

    /// The published map at `version`: the newest history entry at or before it (`None` before the
    /// site's first map).
    pub fn map_at(&self, version: u64) -> Option<&HistoryEntry> {
        let after = self.history.partition_point(|e| e.version <= version);
        after.checked_sub(1).and_then(|i| self.history.get(i))
    }
}
