//! What an unloaded site publishes — its [`VersionInfo`] and its [`SiteView::unloaded`] — stored beside
//! the checkpoint that covers the same version (`site_summary.proto`), so that a server start can serve
//! the site unloaded without reading its checkpoint (issue 34: sites start unloaded).
//!
//! The summary is a cache of what the map at its version publishes (the map at a version is a function
//! of the log up to it, so a summary written at version `v` is right for every later start at `v`). It
//! is stored as one record (kind [`SUMMARY_KIND`], id [`SUMMARY_ID`], overwritten), after the checkpoint
//! at its version is durable and only while no session is open. A start uses it only if it decodes,
//! its version is the store's map version, the newest checkpoint covers exactly that version and no
//! session is open: any other summary (older, damaged, lost in a crash before it reached the disk) is
//! ignored and the site loads as it always did.

use std::sync::Arc;

use mapping::geometry::Rigid2;
use prost::Message as _;
use proto::{ConversionError, FORMAT_VERSION, pb};
use storage::{MapStore, RecordId, RecordKind};

use super::{
    MapCounts, PlacementState, SessionView, SiteError, SiteView, VersionInfo, copy_counts,
};

/// The record kind a site's summary is stored under.
pub(crate) const SUMMARY_KIND: RecordKind = RecordKind::SiteMeta;

/// The record id a site's summary is stored under (one per site, overwritten).
pub(crate) const SUMMARY_ID: &str = "unloaded-summary";

/// What a site publishes while unloaded, at one version.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct SiteSummary {
    /// The version and counts (`Watch`, metrics, the console's site list).
    pub(crate) info: VersionInfo,
    /// The sessions, without their trajectories.
    pub(crate) sessions: Vec<SessionView>,
}

impl SiteSummary {
    /// The summary of a site publishing `info` and `view` (the view's trajectories are left out).
    pub(crate) fn of(info: VersionInfo, view: &SiteView) -> Self {
        Self {
            info,
            sessions: view.unloaded().sessions.to_vec(),
        }
    }

    /// The view an unloaded site with this summary publishes.
    pub(crate) fn unloaded_view(&self) -> SiteView {
        SiteView {
            version: self.info.version,
            sessions: Arc::new(self.sessions.clone()),
            history: Arc::new(Vec::new()),
            submaps: None,
            unloaded: true,
        }
    }

    /// Stores the summary as the site's (a plain write: a summary lost in a crash only makes the next
    /// start load the site).
    pub(crate) fn store(&self, store: &dyn MapStore, site: &str) -> Result<(), SiteError> {
        store.put(
            site,
            SUMMARY_KIND,
            &RecordId::from(SUMMARY_ID),
            &self.to_bytes(),
        )?;
        Ok(())
    }

    /// The site's stored summary if a start may serve the site unloaded with it (see the module
    /// docs); `Ok(None)` if not. A summary that does not decode is logged and not used.
    pub(crate) fn usable_at_start(
        store: &dyn MapStore,
        site: &str,
    ) -> Result<Option<Self>, SiteError> {
        let Some(bytes) = store.get(site, SUMMARY_KIND, &RecordId::from(SUMMARY_ID))? else {
            return Ok(None);
        };
        let summary = match Self::from_bytes(&bytes) {
            Ok(summary) => summary,
            Err(e) => {
                tracing::warn!("the site's stored summary does not decode, the site loads: {e}");
                return Ok(None);
            }
        };
        let version = summary.info.version;
        let usable = summary.info.counts.open_sessions == 0
            && store.map_version(site)? == version
            && store.checkpoint_indexes(site)?.first() == Some(&version);
        Ok(usable.then_some(summary))
    }

    fn to_bytes(&self) -> Vec<u8> {
        let c = &self.info.counts;
        pb::SiteSummary {
            format_version: FORMAT_VERSION,
            version: self.info.version,
            counts: Some(copy_counts!(c => pb::SiteCounts {
                loop_closure_searches: c.loop_closure_searches,
                loop_closures_outvoted: c.loop_closures_outvoted,
                loop_closures_beyond_drift: c.loop_closures_beyond_drift,
                loop_closures_retracted: c.loop_closures_retracted,
                session_starts: Some(c.session_starts),
            })),
            sessions: self.sessions.iter().map(session_to_pb).collect(),
        }
        .encode_to_vec()
    }

    fn from_bytes(bytes: &[u8]) -> Result<Self, ConversionError> {
        let message = pb::SiteSummary::decode(bytes).map_err(|e| ConversionError::Decode {
            message: "SiteSummary",
            source: proto::ErrorSource::new(e),
        })?;
        proto::check_format_version("SiteSummary", message.format_version)?;
        let c = message.counts.ok_or(ConversionError::MissingField {
            message: "SiteSummary",
            field: "counts",
        })?;
        let session_starts = c
            .session_starts
            .as_ref()
            .ok_or(ConversionError::MissingField {
                message: "SiteCounts",
                field: "session_starts",
            })?;
        let counts = copy_counts!(c => MapCounts {
            loop_closure_searches: c.loop_closure_searches,
            loop_closures_outvoted: c.loop_closures_outvoted,
            loop_closures_beyond_drift: c.loop_closures_beyond_drift,
            loop_closures_retracted: c.loop_closures_retracted,
            session_starts: *session_starts,
        });
        let sessions = message
            .sessions
            .iter()
            .map(session_from_pb)
            .collect::<Result<_, _>>()?;
        Ok(Self {
            info: VersionInfo {
                version: message.version,
                counts,
            },
            sessions,
        })
    }
}

fn session_to_pb(s: &SessionView) -> pb::SessionSummary {
    let state = match s.state {
        PlacementState::Waiting => pb::PlacementStateKind::Waiting,
        PlacementState::Base => pb::PlacementStateKind::Base,
        PlacementState::Searching => pb::PlacementStateKind::Searching,
        PlacementState::Probation => pb::PlacementStateKind::Probation,
        PlacementState::Committed => pb::PlacementStateKind::Committed,
        PlacementState::Dropped => pb::PlacementStateKind::Dropped,
    };
    pb::SessionSummary {
        session_uuid: s.session.clone(),
        robot_id: s.robot_id.clone(),
        trajectory: s.trajectory,
        closed: s.closed,
        nodes: s.nodes,
        state: state.into(),
        prior_from_robot: s.prior_from_robot,
        robot_prior_revoked: s.robot_prior_revoked,
        global_from_local: s.global_from_local.as_ref().map(proto::pose_to_exact),
        latest_pose: s.latest_pose.as_ref().map(proto::pose_to_exact),
    }
}

fn session_from_pb(s: &pb::SessionSummary) -> Result<SessionView, ConversionError> {
    const MESSAGE: &str = "SessionSummary";
    let state = match pb::PlacementStateKind::try_from(s.state) {
        Ok(pb::PlacementStateKind::Waiting) => PlacementState::Waiting,
        Ok(pb::PlacementStateKind::Base) => PlacementState::Base,
        Ok(pb::PlacementStateKind::Searching) => PlacementState::Searching,
        Ok(pb::PlacementStateKind::Probation) => PlacementState::Probation,
        Ok(pb::PlacementStateKind::Committed) => PlacementState::Committed,
        Ok(pb::PlacementStateKind::Dropped) => PlacementState::Dropped,
        Ok(pb::PlacementStateKind::Unspecified) | Err(_) => {
            return Err(ConversionError::OutOfRange {
                message: MESSAGE,
                field: "state",
                value: s.state.into(),
                expected: "a known PlacementStateKind other than UNSPECIFIED",
            });
        }
    };
    let pose = |pose: Option<&pb::ExactPose2>, field| -> Result<Option<Rigid2>, ConversionError> {
        pose.map(|p| proto::pose_from_exact(Some(p), MESSAGE, field))
            .transpose()
    };
    Ok(SessionView {
        session: s.session_uuid.clone(),
        robot_id: s.robot_id.clone(),
        trajectory: s.trajectory,
        closed: s.closed,
        nodes: s.nodes,
        state,
        prior_from_robot: s.prior_from_robot,
        robot_prior_revoked: s.robot_prior_revoked,
        global_from_local: pose(s.global_from_local.as_ref(), "global_from_local")?,
        trajectory_poses: Vec::new(),
        latest_pose: pose(s.latest_pose.as_ref(), "latest_pose")?,
    })
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;
    use storage::{MemStore, WriteBatch};

    use super::*;

    fn summary(version: u64, open_sessions: u64) -> SiteSummary {
        let session = |n: u32, state, placed: Option<Rigid2>| SessionView {
            session: format!("s{n}"),
            robot_id: format!("r{n}"),
            trajectory: n,
            closed: true,
            nodes: 17 + u64::from(n),
            state,
            prior_from_robot: n % 2 == 1,
            robot_prior_revoked: n == 2,
            global_from_local: placed,
            trajectory_poses: vec![rigid2(1.0, 2.0, 3.0)],
            latest_pose: placed.map(|p| p * rigid2(0.5, 0.0, 0.1)),
        };
        let view = SiteView {
            version,
            sessions: Arc::new(vec![
                session(0, PlacementState::Base, Some(rigid2(0.0, -0.0, 0.0))),
                session(1, PlacementState::Committed, Some(rigid2(3.5, -1.25, 2.9))),
                session(2, PlacementState::Dropped, None),
            ]),
            history: Arc::new(Vec::new()),
            submaps: None,
            unloaded: false,
        };
        let counts = MapCounts {
            sessions: 3,
            nodes: 1234,
            submaps: 40,
            finished_submaps: 38,
            constraints: 9876,
            trimmed_submaps: 5,
            dropped_sessions: 1,
            loop_closures: 321,
            loop_closure_searches: 4321,
            loop_closures_outvoted: 7,
            loop_closures_beyond_drift: 2,
            loop_closures_retracted: 3,
            session_starts: proto::testing::distinct_session_start_counts(),
            open_sessions,
        };
        SiteSummary::of(VersionInfo { version, counts }, &view)
    }

    #[test]
    fn a_summary_comes_back_bit_for_bit_without_trajectories() {
        let summary = summary(42, 0);
        assert!(
            summary
                .sessions
                .iter()
                .all(|s| s.trajectory_poses.is_empty())
        );
        let back = SiteSummary::from_bytes(&summary.to_bytes()).unwrap();
        assert_eq!(back, summary);
        // −0.0 keeps its sign (an `ExactPose2`), so the console shows what the loaded site showed.
        let base = back.sessions[0].global_from_local.unwrap();
        assert!(base.translation.vector.y.is_sign_negative());
        let view = back.unloaded_view();
        assert!(view.unloaded && view.history.is_empty());
        assert_eq!(view.version, 42);
        assert_eq!(view.sessions.len(), 3);
    }

    #[test]
    fn a_summary_of_another_format_or_damaged_is_refused() {
        let mut message = pb::SiteSummary::decode(summary(1, 0).to_bytes().as_slice()).unwrap();
        message.format_version = FORMAT_VERSION + 1;
        let error = SiteSummary::from_bytes(&message.encode_to_vec()).unwrap_err();
        assert!(error.to_string().contains("SiteSummary"), "{error}");
        assert!(SiteSummary::from_bytes(b"\xff\xff\xff").is_err());
        message.format_version = FORMAT_VERSION;
        message.sessions[1].state = 99;
        assert!(SiteSummary::from_bytes(&message.encode_to_vec()).is_err());
    }

    /// A store whose site is at `version` with a checkpoint at each of `checkpoints`.
    fn store_at(version: u64, checkpoints: &[u64]) -> MemStore {
        let store = MemStore::new();
        for v in 1..=version {
            let mut batch = WriteBatch::new("s");
            batch
                .put(super::super::SITE_LOG_KIND, v, b"entry".to_vec())
                .bump_map_version();
            store.apply(&batch).unwrap();
            if checkpoints.contains(&v) {
                store.put_checkpoint("s", v, b"checkpoint").unwrap();
            }
        }
        store
    }

    // Reference: issue 34 — a start serves a site unloaded only where its newest checkpoint covers
    // its whole log (nothing to replay) and no session is open; otherwise it loads as before.
    #[test]
    fn a_start_uses_a_summary_only_at_the_sites_version_and_newest_checkpoint() {
        let store = store_at(5, &[3, 5]);
        assert_eq!(SiteSummary::usable_at_start(&store, "s").unwrap(), None);
        summary(5, 0).store(&store, "s").unwrap();
        assert_eq!(
            SiteSummary::usable_at_start(&store, "s").unwrap(),
            Some(summary(5, 0))
        );
        // A session open at that version: the site loads (its idle timeout runs from the start).
        summary(5, 1).store(&store, "s").unwrap();
        assert_eq!(SiteSummary::usable_at_start(&store, "s").unwrap(), None);
        // A summary of an older version (the log went on since), or a version no checkpoint covers.
        summary(3, 0).store(&store, "s").unwrap();
        assert_eq!(SiteSummary::usable_at_start(&store, "s").unwrap(), None);
        let store = store_at(6, &[3, 5]);
        summary(6, 0).store(&store, "s").unwrap();
        assert_eq!(SiteSummary::usable_at_start(&store, "s").unwrap(), None);
        // A damaged summary is not used.
        store
            .put(
                "s",
                SUMMARY_KIND,
                &RecordId::from(SUMMARY_ID),
                b"\x08\x01\xff",
            )
            .unwrap();
        assert_eq!(SiteSummary::usable_at_start(&store, "s").unwrap(), None);
    }
}
