//! A [`SiteMap`] as a checkpoint and back (issue 34): the lifelong map's state (`LifelongMap::to_state`)
//! plus the server's part ([`proto::SiteServerState`]), so that a site restored from its newest
//! checkpoint and the log after it equals, bit for bit, the site a replay of its whole log builds.
//!
//! **When a checkpoint can be taken.** Only while no session is mid-start: every running session's
//! [`mapping::lifelong::SessionStart`] has reached a final decision (committed, or gave up) and was
//! dropped then (see `SiteMap::act_on_start`). A final `SessionStart` ignores every node and match fed
//! to it and decides nothing more, so dropping it changes no output; an undecided one holds the
//! relocalization map rendered at its session's start (which later trims change: it cannot be rendered
//! again from the current map), the held-back cloud, its search schedule, agreeing and disagreeing
//! matches, rivals and revoked poses — state we would have to store field by field in a second format.
//! Instead [`SiteMap::checkpoint`] returns `None` then, and the site task tries again after a later
//! change. In a fleet a session is mid-start only for its first minutes (held-back nodes, then three
//! agreeing matches commit it), so checkpoints wait at most that long.
//!
//! Everything else is stored: sessions with their acknowledged sequence numbers, node counts, priors
//! and end states, published submaps' revisions and pose versions (the poses exactly as kept, for the
//! next delta's "moved" test), trimmed submaps' versions, the version, the counters, the revoked robot
//! placements and the base session. Not stored: the console's [`MapHistory`] of past versions (a bounded
//! view cache of grids, rebuilt from here on): a restored site's history starts at its restored version.

use std::sync::Arc;

use mapping::lifelong::LifelongOptions;
use proto::{SiteCheckpoint, SiteServerState};

use super::{MapHistory, SiteMap};
use crate::site::SiteError;
use crate::site::map_history::HistoryEntry;

impl SiteMap {
    /// Whether a checkpoint can be taken now: no session is mid-start (see the module docs).
    pub fn is_checkpointable(&self) -> bool {
        self.starts.is_empty()
    }

    /// The site's whole state at its current version (which is the log index it covers), or `None`
    /// while a session is mid-start (see the module docs).
    pub fn checkpoint(&self) -> Option<SiteCheckpoint> {
        if !self.is_checkpointable() {
            return None;
        }
        debug_assert!(self.searched.is_empty(), "searched without a running start");
        let mut checkpoint = SiteCheckpoint::of(&self.map, self.version, self.version);
        checkpoint.site = SiteServerState {
            sessions: self.sessions.clone(),
            published: self.submap_versions.clone(),
            trimmed: std::collections::BTreeMap::clone(&self.trimmed),
            optimizations: self.optimizations,
            dropped_sessions: self.dropped_sessions,
            robot_revoked: self.robot_revoked.clone(),
            base: self.base,
            session_starts: self.session_starts,
        };
        Some(checkpoint)
    }

    /// The site `checkpoint` holds, under `options`: those configured now, which govern it from here on
    /// even if the checkpoint was written under others (logged; see [`SiteCheckpoint::restore`]). A
    /// state that contradicts itself is [`SiteError::CorruptCheckpoint`].
    pub fn restore(
        site: impl Into<String>,
        options: LifelongOptions,
        checkpoint: SiteCheckpoint,
    ) -> Result<Self, SiteError> {
        let index = checkpoint.log_index;
        let corrupt = |reason: String| SiteError::CorruptCheckpoint {
            index,
            reason,
            source: None,
        };
        if checkpoint.map_version != checkpoint.log_index {
            return Err(corrupt(format!(
                "it covers log index {} but is at map version {} (the site's log index is its version)",
                checkpoint.log_index, checkpoint.map_version
            )));
        }
        let state = checkpoint.site.clone();
        let version = checkpoint.map_version;
        if checkpoint.written_under_other_options(&options) {
            tracing::warn!(
                checkpoint = index,
                written = format_args!("{:#010x}", checkpoint.options_fingerprint),
                now = format_args!("{:#010x}", proto::options_fingerprint(&options)),
                "the site's checkpoint was written under other [map] options: restored as it stands, \
                 the options configured now govern the site from here on"
            );
        }
        let map = checkpoint
            .restore(options)
            .map_err(|e| SiteError::CorruptCheckpoint {
                index,
                reason: e.to_string(),
                source: Some(e.into()),
            })?;
        let mut trajectories: Vec<u32> = state.sessions.values().map(|s| s.trajectory).collect();
        trajectories.sort_unstable();
        if trajectories
            .iter()
            .copied()
            .ne(0..trajectories.len() as u32)
        {
            return Err(corrupt(format!(
                "its sessions' trajectories are {trajectories:?}, not 0, 1, 2, ..."
            )));
        }
        let mut restored = Self {
            site: site.into(),
            map,
            sessions: state.sessions,
            submap_versions: state.published,
            trimmed: Arc::new(state.trimmed),
            version,
            optimizations: state.optimizations,
            dropped_sessions: state.dropped_sessions,
            starts: std::collections::BTreeMap::new(),
            robot_revoked: state.robot_revoked,
            history: MapHistory::default(),
            base: state.base,
            session_starts: state.session_starts,
            searched: std::collections::BTreeSet::new(),
        };
        for id in restored.submap_versions.keys() {
            let known = restored
                .map
                .global()
                .submaps()
                .get(id)
                .is_some_and(|s| s.grid.is_some());
            if !known {
                return Err(corrupt(format!(
                    "published submap {id:?} is not a finished submap of its map"
                )));
            }
        }
        if !restored.submap_versions.is_empty() {
            restored.history.record(HistoryEntry {
                version,
                counts: restored.counts(),
                grids: Arc::new(restored.grids_for_render()),
            });
        }
        Ok(restored)
    }
}

#[cfg(test)]
mod tests;
