//! The server's part of a site checkpoint (`SiteServerState` in `site_checkpoint.proto`): what the
//! server keeps about a site beyond the lifelong map — sessions with their acknowledged sequence
//! numbers, published submaps' versions, trimmed submaps, counters — as plain data. The server turns
//! its `SiteMap` into this and back; here it is only encoded, decoded and checked.

use std::collections::{BTreeMap, BTreeSet};

use mapping::geometry::Rigid2;
use mapping::pose_graph::SubmapId;

use super::{pose_from_exact, pose_to_exact, required, submap_in};
use crate::upload_batch::{fitted_nodes_from_pb, fitted_nodes_to_pb};
use crate::{ConversionError, pb};

/// A robot's `SessionStartPrior` as the server keeps it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RobotPrior {
    /// Where the session's local frame sits in the site frame.
    pub global_from_local: Rigid2,
    /// It is the robot's dock placement (`SessionStartPrior.at_dock`).
    pub at_dock: bool,
    /// The nodes the robot's search fitted at it, first and last index (`SessionStartPrior.fitted`).
    pub fitted: Option<(u32, u32)>,
}

/// One session of a site as the server keeps it.
#[derive(Clone, Debug, PartialEq)]
pub struct SiteSessionState {
    /// The robot that opened it.
    pub robot_id: String,
    /// Its trajectory in the site map.
    pub trajectory: u32,
    /// The last applied upload sequence number (0: none).
    pub last_seq: u64,
    /// Whether it has ended.
    pub closed: bool,
    /// The robot's prior, if it sent one.
    pub prior: Option<RobotPrior>,
    /// The robot matches its nodes against the map itself.
    pub glm_on_robot: bool,
    /// Nodes applied.
    pub nodes: u64,
    /// It ended unplaced or on probation and was dropped.
    pub dropped: bool,
}

/// A published submap's versions.
#[derive(Clone, Debug, PartialEq)]
pub struct PublishedSubmapState {
    /// The version at which its grid was published.
    pub revision: u64,
    /// The version at which its global pose last changed.
    pub pose_version: u64,
    /// The global pose at `pose_version`.
    pub pose: Rigid2,
}

/// The decisions of a site's session starts, counted as the site acts on them (the proto message itself:
/// one set of fields, documented in `site_checkpoint.proto`).
pub type SessionStartCounts = pb::SessionStartCountsState;

/// The server's part of a site's state (see the module docs).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SiteServerState {
    /// Every session, by session uuid.
    pub sessions: BTreeMap<String, SiteSessionState>,
    /// Published submaps' versions.
    pub published: BTreeMap<SubmapId, PublishedSubmapState>,
    /// Published submaps trimmed since, with the version that trimmed each.
    pub trimmed: BTreeMap<SubmapId, u64>,
    /// Optimizations run since the site began.
    pub optimizations: u64,
    /// Sessions dropped since the site began.
    pub dropped_sessions: u64,
    /// Trajectories whose robot's placement was revoked.
    pub robot_revoked: BTreeSet<u32>,
    /// The session that started the map.
    pub base: Option<u32>,
    /// What the session starts decided.
    pub session_starts: SessionStartCounts,
}

pub(super) fn site_to_pb(s: &SiteServerState) -> pb::SiteServerState {
    let c = s.session_starts;
    pb::SiteServerState {
        sessions: s
            .sessions
            .iter()
            .map(|(uuid, session)| pb::SiteSessionState {
                session_uuid: uuid.clone(),
                robot_id: session.robot_id.clone(),
                trajectory: session.trajectory,
                last_seq: session.last_seq,
                closed: session.closed,
                prior: session
                    .prior
                    .as_ref()
                    .map(|p| pose_to_exact(&p.global_from_local)),
                glm_on_robot: session.glm_on_robot,
                nodes: session.nodes,
                dropped: session.dropped,
                prior_at_dock: session.prior.is_some_and(|p| p.at_dock),
                prior_fitted: session.prior.and_then(|p| p.fitted).map(fitted_nodes_to_pb),
            })
            .collect(),
        published: s
            .published
            .iter()
            .map(|(id, p)| pb::PublishedSubmapState {
                id: Some((*id).into()),
                revision: p.revision,
                pose_version: p.pose_version,
                pose: Some(pose_to_exact(&p.pose)),
            })
            .collect(),
        trimmed: s
            .trimmed
            .iter()
            .map(|(id, version)| pb::TrimmedSubmapState {
                id: Some((*id).into()),
                version: *version,
            })
            .collect(),
        optimizations: s.optimizations,
        dropped_sessions: s.dropped_sessions,
        robot_revoked: s.robot_revoked.iter().copied().collect(),
        base: s.base,
        session_starts: Some(c),
    }
}

/// Refuses a key seen twice: the encoder writes each once, so a repeat is damage, not data to merge.
fn unique<K: Ord, V>(
    map: &mut BTreeMap<K, V>,
    key: K,
    value: V,
    message: &'static str,
    field: &'static str,
    shown: impl FnOnce() -> String,
) -> Result<(), ConversionError> {
    if map.insert(key, value).is_some() {
        return Err(ConversionError::Duplicate {
            message,
            field,
            key: shown(),
        });
    }
    Ok(())
}

pub(super) fn site_from_pb(s: &pb::SiteServerState) -> Result<SiteServerState, ConversionError> {
    const M: &str = "SiteServerState";
    let mut sessions = BTreeMap::new();
    for session in &s.sessions {
        const S: &str = "SiteSessionState";
        let state = SiteSessionState {
            robot_id: session.robot_id.clone(),
            trajectory: session.trajectory,
            last_seq: session.last_seq,
            closed: session.closed,
            prior: session
                .prior
                .as_ref()
                .map(|p| {
                    Ok::<_, ConversionError>(RobotPrior {
                        global_from_local: pose_from_exact(Some(p), S, "prior")?,
                        at_dock: session.prior_at_dock,
                        fitted: session
                            .prior_fitted
                            .map(|f| fitted_nodes_from_pb(f, S))
                            .transpose()?,
                    })
                })
                .transpose()?,
            glm_on_robot: session.glm_on_robot,
            nodes: session.nodes,
            dropped: session.dropped,
        };
        unique(
            &mut sessions,
            session.session_uuid.clone(),
            state,
            S,
            "session_uuid",
            || format!("session {:?}", session.session_uuid),
        )?;
    }
    let mut published = BTreeMap::new();
    for p in &s.published {
        const P: &str = "PublishedSubmapState";
        let id = submap_in(p.id.as_ref(), P, "id")?;
        let state = PublishedSubmapState {
            revision: p.revision,
            pose_version: p.pose_version,
            pose: pose_from_exact(p.pose.as_ref(), P, "pose")?,
        };
        unique(&mut published, id, state, P, "id", || format!("{id:?}"))?;
    }
    let mut trimmed = BTreeMap::new();
    for t in &s.trimmed {
        let id = submap_in(t.id.as_ref(), "TrimmedSubmapState", "id")?;
        unique(
            &mut trimmed,
            id,
            t.version,
            "TrimmedSubmapState",
            "id",
            || format!("{id:?}"),
        )?;
    }
    let c = required(s.session_starts.as_ref(), M, "session_starts")?;
    Ok(SiteServerState {
        sessions,
        published,
        trimmed,
        optimizations: s.optimizations,
        dropped_sessions: s.dropped_sessions,
        robot_revoked: s.robot_revoked.iter().copied().collect(),
        base: s.base,
        session_starts: *c,
    })
}
