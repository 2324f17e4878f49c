//! [`LifelongMap`] as plain data, and back: the mapping core's part of a site checkpoint.
//!
//! A checkpoint restores a site without replaying its log, so the restored map must behave exactly as
//! the one a replay would rebuild: the same outputs, bit for bit, for every later session. The state is
//! what the map holds beyond its options, [`GlobalSlamState`] included (see its module docs and
//! ARCHITECTURE.md, "Checkpoints: what a site's state is"). Encoding it (the `proto` crate) and
//! storing it are the shell's business; nothing here does I/O.

use std::collections::{BTreeMap, BTreeSet};

use super::{LifelongError, LifelongMap, Session};
use crate::global_slam::{GlobalSlam, GlobalSlamError, GlobalSlamState};
use crate::lifelong::LifelongOptions;

/// Where a started session stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SessionProgress {
    /// Position in start order (0 for the first session); the trimmer's "fresher" is by this order.
    pub order: usize,
    /// Whether the session has ended.
    pub finished: bool,
}

/// Everything a [`LifelongMap`] holds beyond its options. Take it with [`LifelongMap::to_state`], restore
/// it with [`LifelongMap::from_state`].
#[derive(Clone, Debug, PartialEq)]
pub struct LifelongMapState {
    /// Global SLAM: graph, records, grids, matches and their bookkeeping.
    pub global: GlobalSlamState,
    /// Every started session, by id.
    pub sessions: BTreeMap<u32, SessionProgress>,
    /// The first session started (never trimmed).
    pub base: Option<u32>,
    /// Sessions placed tentatively.
    pub probation: BTreeSet<u32>,
    /// Stale submaps trimmed so far.
    pub trimmed_total: usize,
    /// Submaps of sessions that did not update the map, dropped so far.
    pub dropped_total: usize,
    /// Sparsifications since the last capped optimization after trims.
    pub sparsifications_since_optimization: usize,
}

impl LifelongMap {
    /// Everything needed to rebuild this map exactly with [`Self::from_state`] (grids and scan points are
    /// shared, not copied).
    pub fn to_state(&self) -> LifelongMapState {
        LifelongMapState {
            global: self.global.to_state(),
            sessions: self
                .sessions
                .iter()
                .map(|(id, s)| {
                    (
                        *id,
                        SessionProgress {
                            order: s.order,
                            finished: s.finished,
                        },
                    )
                })
                .collect(),
            base: self.base,
            probation: self.probation.clone(),
            trimmed_total: self.trimmed_total,
            dropped_total: self.dropped_total,
            sparsifications_since_optimization: self.sparsifications_since_optimization,
        }
    }

    /// The map `state` was taken from. `options` must be the ones it ran with: the state does not carry
    /// them, and a map restored with others behaves like neither map. Fails on invalid options and on a
    /// state that contradicts itself.
    pub fn from_state(
        options: LifelongOptions,
        state: LifelongMapState,
    ) -> Result<Self, LifelongError> {
        options.validate()?;
        let LifelongMapState {
            global,
            sessions,
            base,
            probation,
            trimmed_total,
            dropped_total,
            sparsifications_since_optimization,
        } = state;
        let inconsistent = |what: String| -> Result<Self, LifelongError> {
            Err(GlobalSlamError::InconsistentState(what).into())
        };
        if let Some(session) = base.filter(|b| !sessions.contains_key(b)) {
            return inconsistent(format!("base session {session} was never started"));
        }
        if let Some(session) = probation.iter().find(|s| !sessions.contains_key(s)) {
            return inconsistent(format!("session {session} on probation was never started"));
        }
        Ok(Self {
            global: GlobalSlam::from_state(options.global.clone(), global)?,
            options,
            sessions: sessions
                .into_iter()
                .map(|(id, s)| {
                    (
                        id,
                        Session {
                            order: s.order,
                            finished: s.finished,
                        },
                    )
                })
                .collect(),
            base,
            probation,
            trimmed_total,
            dropped_total,
            sparsifications_since_optimization,
        })
    }
}
