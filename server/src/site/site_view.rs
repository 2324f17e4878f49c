//! What read-only front ends (the web console) see of a site, published by its task with every
//! version so they read it without queueing behind the site's work.

use std::sync::Arc;

use super::{HistoryEntry, SessionView};

/// A site as of one version: its sessions and its map history.
#[derive(Clone, Debug, Default)]
pub struct SiteView {
    /// The version.
    pub version: u64,
    /// Every session, in the order they were opened ([`super::SiteMap::session_views`]).
    pub sessions: Arc<Vec<SessionView>>,
    /// The published map at past versions, oldest first ([`super::MapHistory`]).
    pub history: Arc<Vec<HistoryEntry>>,
}

impl SiteView {
    /// The published map at `version`: the newest history entry at or before it (`None` before the
    /// site's first map).
    pub fn map_at(&self, version: u64) -> Option<&HistoryEntry> {
        let after = self.history.partition_point(|e| e.version <= version);
        after.checked_sub(1).and_then(|i| self.history.get(i))
    }
}
