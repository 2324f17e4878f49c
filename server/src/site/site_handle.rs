//! The cloneable, transport-agnostic handle on a site task.

use std::collections::BTreeMap;
use std::sync::Arc;

use mapping::geometry::Rigid2;
use mapping::grid::ProbabilityGrid;
use mapping::pose_graph::{NodeId, SubmapId};
use proto::{MapDelta, SubmapSnapshot, UploadBatch};
use tokio::sync::{mpsc, oneshot, watch};

use super::request_clock::RequestClock;
use super::{
    HistoryEntry, MapCounts, PublishedSubmaps, SessionOpened, SessionView, SiteError, SiteView,
};

/// A published version of a site map.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct VersionInfo {
    /// The version (monotonic per site).
    pub version: u64,
    /// The map's sizes at that version.
    pub counts: MapCounts,
}

/// The answer to an upload, sent once the batch is durably stored and applied.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UploadAck {
    /// The batch's sequence number.
    pub seq: u64,
    /// The site version after the batch (the current one for a duplicate).
    pub map_version: u64,
    /// The batch had already been applied and was not applied again.
    pub duplicate: bool,
    /// For a batch that ended its session: the session's last node in the site map, if the session is
    /// placed ([`super::SiteMap::session_end_pose`]).
    pub session_end_pose: Option<Rigid2>,
}

/// A rendered site map.
#[derive(Clone, Debug)]
pub struct RenderedMap {
    /// The version rendered.
    pub version: u64,
    /// The grid in the site frame; `None` when the site has no finished submap yet.
    pub grid: Option<ProbabilityGrid>,
}

/// What a site task can be asked. Every request carries the channel its answer goes to.
pub(crate) enum Command {
    OpenSession {
        robot_id: String,
        session_uuid: String,
        reply: oneshot::Sender<Result<(SessionOpened, u64), SiteError>>,
    },
    Upload {
        batch: Box<UploadBatch>,
        /// When the request reached the site (the task's queue wait is logged).
        sent: std::time::Instant,
        reply: oneshot::Sender<Result<UploadAck, SiteError>>,
    },
    CloseSession {
        robot_id: String,
        session_uuid: String,
        reply: oneshot::Sender<Result<u64, SiteError>>,
    },
    Delta {
        since: u64,
        reply: oneshot::Sender<Result<MapDelta, SiteError>>,
    },
    Submap {
        id: SubmapId,
        revision: u64,
        reply: oneshot::Sender<Result<SubmapSnapshot, SiteError>>,
    },
    Render {
        resolution: f64,
        reply: oneshot::Sender<Result<RenderedMap, SiteError>>,
    },
    NodePoses {
        reply: oneshot::Sender<BTreeMap<NodeId, Rigid2>>,
    },
    /// Restores the site if it is unloaded; answers with its view.
    Load {
        reply: oneshot::Sender<Result<Arc<SiteView>, SiteError>>,
    },
    /// Unloads the site now if it can be (not a request: the idle timer does not restart).
    Unload {
        reply: oneshot::Sender<Result<bool, SiteError>>,
    },
    Shutdown,
}

impl Command {
    /// Whether the command needs the site's map in memory (everything but unloading and stopping).
    pub(crate) fn needs_map(&self) -> bool {
        !matches!(self, Self::Unload { .. } | Self::Shutdown)
    }

    /// Whether handling the command ends a session (a close, or an upload whose batch ends it): the
    /// session-end maintenance it sets off may wait behind other robots' data (see `SiteTask`).
    pub(crate) fn ends_session(&self) -> bool {
        match self {
            Self::CloseSession { .. } => true,
            Self::Upload { batch, .. } => batch.ends_session(),
            _ => false,
        }
    }

    /// Whether the command is an upload of another session than `session` that does not end its own:
    /// robots' data, which goes before a session end (see [`Command::ends_session`]).
    pub(crate) fn is_data_of_another_session(&self, session: &str) -> bool {
        matches!(self, Self::Upload { batch, .. } if batch.session_uuid != session)
            && !self.ends_session()
    }

    /// The session the command is about, if any.
    pub(crate) fn session(&self) -> Option<&str> {
        match self {
            Self::OpenSession { session_uuid, .. } | Self::CloseSession { session_uuid, .. } => {
                Some(session_uuid)
            }
            Self::Upload { batch, .. } => Some(&batch.session_uuid),
            _ => None,
        }
    }

    /// Answers the command with `error` (a map of no nodes for `NodePoses`, which cannot fail).
    pub(crate) fn fail(self, error: SiteError) {
        match self {
            Self::OpenSession { reply, .. } => {
                let _ = reply.send(Err(error));
            }
            Self::Upload { reply, .. } => {
                let _ = reply.send(Err(error));
            }
            Self::CloseSession { reply, .. } => {
                let _ = reply.send(Err(error));
            }
            Self::Delta { reply, .. } => {
                let _ = reply.send(Err(error));
            }
            Self::Submap { reply, .. } => {
                let _ = reply.send(Err(error));
            }
            Self::Render { reply, .. } => {
                let _ = reply.send(Err(error));
            }
            Self::NodePoses { reply } => {
                let _ = reply.send(BTreeMap::new());
            }
            Self::Load { reply } => {
                let _ = reply.send(Err(error));
            }
            Self::Unload { reply } => {
                let _ = reply.send(Err(error));
            }
            Self::Shutdown => {}
        }
    }
}

/// Talks to one site's task: every request is queued (bounded: callers wait when the site is busy) and
/// applied in order. Cheap to clone.
#[derive(Clone)]
pub struct SiteHandle {
    site: Arc<str>,
    commands: mpsc::Sender<Command>,
    versions: watch::Receiver<VersionInfo>,
    views: watch::Receiver<Arc<SiteView>>,
    requests: Arc<RequestClock>,
}

impl SiteHandle {
    pub(crate) fn new(
        site: &str,
        commands: mpsc::Sender<Command>,
        versions: watch::Receiver<VersionInfo>,
        views: watch::Receiver<Arc<SiteView>>,
        requests: Arc<RequestClock>,
    ) -> Self {
        Self {
            site: site.into(),
            commands,
            versions,
            views,
            requests,
        }
    }

    /// The published version's submaps, if the site is loaded (a request: the site's idle time restarts).
    fn published_submaps(&self) -> Option<Arc<PublishedSubmaps>> {
        let submaps = self.views.borrow().submaps.clone()?;
        self.requests.touch();
        Some(submaps)
    }

    /// The site id.
    pub fn site(&self) -> &str {
        &self.site
    }

    async fn ask<T>(
        &self,
        make: impl FnOnce(oneshot::Sender<T>) -> Command,
    ) -> Result<T, SiteError> {
        let (reply, answer) = oneshot::channel();
        let stopped = || SiteError::Stopped(self.site.to_string());
        self.commands
            .send(make(reply))
            .await
            .map_err(|_| stopped())?;
        answer.await.map_err(|_| stopped())
    }

    /// Opens (or re-opens) a session; returns the session and the current version.
    pub async fn open_session(
        &self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<(SessionOpened, u64), SiteError> {
        self.ask(|reply| Command::OpenSession {
            robot_id: robot_id.to_owned(),
            session_uuid: session_uuid.to_owned(),
            reply,
        })
        .await?
    }

    /// Uploads a batch; answers once it is durably stored and applied.
    pub async fn upload(&self, batch: UploadBatch) -> Result<UploadAck, SiteError> {
        self.ask(|reply| Command::Upload {
            batch: Box::new(batch),
            sent: std::time::Instant::now(),
            reply,
        })
        .await?
    }

    /// Closes a session (idempotent); returns the version after it.
    pub async fn close_session(
        &self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<u64, SiteError> {
        self.ask(|reply| Command::CloseSession {
            robot_id: robot_id.to_owned(),
            session_uuid: session_uuid.to_owned(),
            reply,
        })
        .await?
    }

    /// What changed after version `since`: from the published version, beside the site task's queue,
    /// while the site is loaded; else the task restores it first.
    pub async fn delta_since(&self, since: u64) -> Result<MapDelta, SiteError> {
        if let Some(submaps) = self.published_submaps() {
            return submaps.delta_since(since);
        }
        self.ask(|reply| Command::Delta { since, reply }).await?
    }

    /// One finished submap (`revision` 0: the current one), answered as [`Self::delta_since`] is.
    pub async fn submap(&self, id: SubmapId, revision: u64) -> Result<SubmapSnapshot, SiteError> {
        if let Some(submaps) = self.published_submaps() {
            return submaps.submap(id, revision);
        }
        self.ask(|reply| Command::Submap {
            id,
            revision,
            reply,
        })
        .await?
    }

    /// The map rendered at `resolution` (m; 0: the submaps' own).
    pub async fn render(&self, resolution: f64) -> Result<RenderedMap, SiteError> {
        self.ask(|reply| Command::Render { resolution, reply })
            .await?
    }

    /// Current global pose of every node (diagnostics and tests).
    pub async fn node_poses(&self) -> Result<BTreeMap<NodeId, Rigid2>, SiteError> {
        self.ask(|reply| Command::NodePoses { reply }).await
    }

    /// The site as read-only front ends see it, as of the latest published version (read without
    /// queueing behind the site's work). While the site is unloaded this holds no history and no
    /// trajectories ([`SiteView::unloaded`]); [`Self::loaded_view`] waits for them.
    pub fn view(&self) -> Arc<SiteView> {
        Arc::clone(&self.views.borrow())
    }

    /// Whether the site's map is in memory (`false`: unloaded while idle; the next request restores it).
    pub fn is_loaded(&self) -> bool {
        !self.views.borrow().unloaded
    }

    /// The site's view with its history and trajectories: [`Self::view`] if the site is loaded, else
    /// after the site task restored it from its checkpoint (a request like any other: it restarts the
    /// site's idle time).
    pub async fn loaded_view(&self) -> Result<Arc<SiteView>, SiteError> {
        let view = self.view();
        if !view.unloaded {
            return Ok(view);
        }
        self.ask(|reply| Command::Load { reply }).await?
    }

    /// Drops the site's map from memory now, as its idle timer would, if it can: no session open and
    /// a checkpoint covering its version durable (one is written if needed). `Ok(true)` if the site is
    /// unloaded now (or already was). Queued like any request, but not one: the idle time goes on.
    pub async fn unload(&self) -> Result<bool, SiteError> {
        self.ask(|reply| Command::Unload { reply }).await?
    }

    /// Every session with its placement state and trajectory (the console); without trajectories while
    /// the site is unloaded.
    pub fn sessions(&self) -> Arc<Vec<SessionView>> {
        Arc::clone(&self.view().sessions)
    }

    /// The versions of the map's history (each with its counts), oldest first (see
    /// [`super::MapHistory`]); none while the site is unloaded.
    pub fn history(&self) -> Vec<(u64, MapCounts)> {
        self.view()
            .history
            .iter()
            .map(|e| (e.version, e.counts))
            .collect()
    }

    /// The published map at `version` (`u64::MAX`: the newest): the newest history entry at or before
    /// it, `None` before the site's first map (and while the site is unloaded: see
    /// [`Self::loaded_view`]).
    pub fn map_at(&self, version: u64) -> Option<HistoryEntry> {
        self.view().map_at(version).cloned()
    }

    /// The latest published version.
    pub fn current(&self) -> VersionInfo {
        *self.versions.borrow()
    }

    /// A receiver that sees every newly published version (and the site stopping, as a closed channel).
    pub fn subscribe(&self) -> watch::Receiver<VersionInfo> {
        self.versions.clone()
    }

    /// A receiver that sees every newly published view (a version, the site unloaded or restored).
    pub fn subscribe_views(&self) -> watch::Receiver<Arc<SiteView>> {
        self.views.clone()
    }

    /// Requests queued and not yet taken by the task.
    pub fn queue_depth(&self) -> usize {
        self.commands.max_capacity() - self.commands.capacity()
    }

    /// Asks the task to stop after the requests queued before this one.
    pub async fn shutdown(&self) {
        let _ = self.commands.send(Command::Shutdown).await;
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use mapping::lifelong::LifelongOptions;

    use super::*;
    use crate::site::SiteMap;

    /// A handle whose site task never reads its queue, publishing `view`.
    fn handle_without_a_task(view: SiteView) -> (SiteHandle, mpsc::Receiver<Command>) {
        let (commands, queue) = mpsc::channel(1);
        let (_, versions) = watch::channel(VersionInfo::default());
        let (_, views) = watch::channel(Arc::new(view));
        let handle = SiteHandle::new(
            "s",
            commands,
            versions,
            views,
            Arc::new(RequestClock::new()),
        );
        (handle, queue)
    }

    #[tokio::test(start_paused = true)]
    async fn a_loaded_site_answers_fetches_without_its_task_and_an_unloaded_one_waits_for_it() {
        let map = SiteMap::new("s", LifelongOptions::default()).unwrap();
        let (loaded, _queue) = handle_without_a_task(map.view());
        let wait = Duration::from_secs(1);
        let delta = tokio::time::timeout(wait, loaded.delta_since(0))
            .await
            .expect("answered from the published version, not the task's queue")
            .unwrap();
        assert_eq!(delta, map.delta_since(0).unwrap());
        assert!(loaded.delta_since(1).await.is_err(), "a version ahead");
        let missing = SubmapId {
            trajectory: 0,
            index: 0,
        };
        assert!(matches!(
            loaded.submap(missing, 0).await,
            Err(SiteError::NotFound(_))
        ));
        // Unloaded, the same fetch is the task's: it waits in the queue.
        let (unloaded, _queue) = handle_without_a_task(map.view().unloaded());
        assert!(
            tokio::time::timeout(wait, unloaded.delta_since(0))
                .await
                .is_err()
        );
    }
}
