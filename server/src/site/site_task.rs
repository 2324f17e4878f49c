//! The task that owns a site map: it applies requests one at a time, persists every accepted change
//! before answering, and publishes each new version. Robots fetch what a version published
//! ([`super::PublishedSubmaps`]) without queueing behind the task's work; a fetch of an unloaded site
//! is a request to the task, which restores it first.
//!
//! Persistence is a log: change number `v` (which makes site version `v`) is stored as an encoded
//! `SiteLogEntry` under record id `v` of kind [`SITE_LOG_KIND`], in the same atomic, fsynced write that
//! bumps the store's map version (and, for uploads, records the session's sequence number). On start the
//! task replays the log in order, which rebuilds the same map (the core is deterministic), and continues
//! the version sequence. Heavy work (replay, GLM searches and optimization, rendering) and blocking
//! storage calls run on tokio's blocking pool, or on maintenance threads (a session's end, checkpoint
//! writes: below), never on the async workers.
//!
//! **Checkpoints** (issue 34; [`CheckpointOptions`]). After a change that ended a session, or
//! `every_n_versions` versions after the last checkpoint, the task writes the site's whole state
//! ([`SiteMap::checkpoint`]: only while no session is mid-start, else at a later change) as a
//! `SiteCheckpoint` covering the log up to its version, atomically with that position
//! ([`storage::MapStore::put_checkpoint`]), then compacts the log behind the older kept checkpoint
//! ([`storage::MapStore::compact`]). Both run after the change is acknowledged and published, and
//! beside the task: it waits only while the site's state is copied, then goes on with its requests
//! while the copy is encoded and written (one write at a time; a checkpoint due while another session's
//! end is already queued waits for it, so one covers both; the task's end waits for a write in
//! flight). A start
//! (and a rebuild) is the newest checkpoint that reads back, plus the log after it: one that fails its
//! CRC or does not decode is skipped for the one before it (whose log compaction kept); one of a format
//! version this build does not read (a newer build's, or one older than
//! `proto::OLDEST_CHECKPOINT_FORMAT_VERSION`) stops the site with [`SiteError::CheckpointRefused`] —
//! never rebuilt behind it. One written under other lifelong options (an older build's, or before the
//! operator changed `[map]`) is restored as it stands, under the options configured now (logged).
//!
//! **Robots' data first** (issue 34: a fleet's sessions all end in the same second). Ending a session
//! (its final optimization, trimming and sparsification) and encoding and writing checkpoints are
//! *maintenance*: they run on threads of lower CPU priority (`maintenance_thread`), and a session end
//! waits behind another
//! session's upload queued after it (at most 16 times in a row), so the submaps the fleet waits for are
//! not held up by work nobody waits for in real time.
//!
//! A session whose robot falls silent (no open, upload or close of it) for longer than
//! [`SiteTaskOptions::session_idle_timeout`] is ended by the task itself, exactly as if its robot had
//! closed it (a `SessionClosed` log entry: final optimization, trimming, dropped if never placed), so a
//! robot that never comes back does not hold its session open for ever. Silence is counted from the
//! last request or, after a restart, from the task's start (the server's own downtime is not the
//! robot's silence). A robot that comes back later finds its session closed: its remaining batches are
//! refused (`SessionClosed`), so the timeout must be longer than the link outages robots are expected
//! to ride out with their outbox.
//!
//! **Idle sites leave memory** (issue 34, item 4; [`SiteTaskOptions::unload_after`]). A site with no
//! open session that has had no request (of any kind: a robot's, a map query, the console's) for that
//! long is *unloaded*: the task makes sure a checkpoint covering its current version is durable
//! (writing one if the last does not cover it; with checkpoints disabled, or when one cannot be
//! written or the store may differ from the map, the site stays loaded and tries again after another
//! idle period), then drops its [`SiteMap`] — graph, grids, branch-and-bound precomputations, history —
//! and hands the freed pages back to the system ([`proto::memory_release`]). What stays answers
//! without the map: the published [`VersionInfo`] (version and counts: `Watch`, metrics, the console's
//! site list) and the view's session list without trajectories ([`SiteView::unloaded`]). The next
//! request of any kind first restores the site from its checkpoint plus the log after it (the same
//! [`load`] a start runs; nothing is left to replay unless the store moved) and is then handled as if
//! the site had never left: the caller only waits. The restored map equals the dropped one bit for
//! bit (checkpoint restore does, see [`SiteMap::checkpoint`]), except its console history, which
//! starts again at the restored version as after a restart. A restore that fails answers that request
//! with the error and is tried again at the next.
//!
//! **Sites start unloaded** (issue 34: one instance holds hundreds of sites). With unloading and
//! checkpoints on, a site whose newest checkpoint covers its whole log and that has no open session
//! starts unloaded, exactly as if it had gone idle: from its stored [`SiteSummary`] (what an unloaded
//! site publishes, stored beside each checkpoint taken with no session open and at each unload), so a
//! start reads a few kB per site and no checkpoint. A site with such a checkpoint but no usable
//! summary (a store written before summaries, a log after its checkpoint) is loaded, then unloaded at
//! once (which checkpoints it if needed and stores its summary). Every other site — no checkpoint, a
//! session open, unloading or checkpoints off — loads as before. The first command restores it, as
//! any unloaded site's.
//!
//! A full disk (or any storage failure) is a refusal, never a half-applied change: a write that fails
//! stores nothing and leaves the map as it was. A write the store applied but could not flush (a
//! log-structured store whose flush hits the full disk) is applied to the map too — the map always
//! equals the stored log — but neither acknowledged nor published until a later flush succeeds: the
//! robot's retry is then a duplicate, acknowledged once the task has flushed.
//!
//! A store that a failed write left refusing writes (sled after a full disk) reopens itself in place
//! (see [`storage::MapStore::generation`]); changes applied but never flushed may be gone after that, or
//! may have survived. The task notes the store's generation its map was built under; when it has
//! changed and the map may differ from the store (a change stored but not proven durable under that
//! generation, or another version), the task rebuilds its map by replaying the store's log — so the map
//! again equals the stored log — before it takes any other change, and answers the pending request
//! with a retryable refusal: the robot's retry is applied once, or acknowledged as a duplicate. The
//! rebuilt version is never below the published one (what was published was durable).

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use mapping::lifelong::{LifelongOptions, render_submaps_log_odds};
use storage::{MapStore, RecordKind};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tracing::Instrument as _;

use super::request_clock::RequestClock;
use super::site_handle::Command;
use super::site_summary::SiteSummary;
use super::{
    CheckpointOptions, RenderedMap, SiteError, SiteHandle, SiteMap, SiteView, VersionInfo,
};
use crate::ServerMetrics;

mod checkpointing;
mod data_before_session_end;
mod loading;
mod map_work;
mod persistence;
mod publishing;
mod session_changes;
mod silent_sessions;
mod unload_restore;

use checkpointing::{CheckpointWriting, CheckpointWritten, written};
#[cfg(test)]
pub(crate) use loading::{LoadTimes, restore_checkpoint};
pub(crate) use loading::{Loaded, load};

/// Record kind of the site log. (The storage crate has no dedicated kind yet; a site's log is the chain
/// of its sessions' trajectories, so it lives under `Trajectory`.)
pub const SITE_LOG_KIND: RecordKind = RecordKind::Trajectory;

/// How a [`SiteTask`] runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SiteTaskOptions {
    /// Commands queued before callers wait (backpressure), count; at least 1 is used.
    pub queue_depth: usize,
    /// End a session whose robot has been silent this long; `None`: never.
    pub session_idle_timeout: Option<Duration>,
    /// When to checkpoint the site, and what compaction keeps.
    pub checkpoints: CheckpointOptions,
    /// Unload the site (drop its map from memory until the next request) once it has had no open
    /// session and no request this long; `None`: never. Needs checkpoints (see the module docs).
    pub unload_after: Option<Duration>,
}

/// [`SiteTaskOptions::unload_after`]'s default: 10 minutes.
pub const DEFAULT_SITE_UNLOAD_AFTER: Duration = Duration::from_secs(600);

impl Default for SiteTaskOptions {
    /// 64 queued commands; sessions ended after one hour of silence; checkpoints as
    /// [`CheckpointOptions::DEFAULT`]; unloaded after [`DEFAULT_SITE_UNLOAD_AFTER`] idle.
    fn default() -> Self {
        Self {
            queue_depth: 64,
            session_idle_timeout: Some(Duration::from_secs(3600)),
            checkpoints: CheckpointOptions::DEFAULT,
            unload_after: Some(DEFAULT_SITE_UNLOAD_AFTER),
        }
    }
}

/// How often, at most, silent sessions and an idle site are looked for (and at least 4 times per
/// timeout).
const IDLE_CHECK_INTERVAL: Duration = Duration::from_secs(1);

/// What the task's loop wakes up for.
enum Wake {
    Command(Command),
    CheckpointWritten(Result<Result<CheckpointWritten, SiteError>, tokio::task::JoinError>),
    IdleCheck,
}

/// Owns one site's [`SiteMap`]; see the module docs.
pub struct SiteTask {
    site: Arc<str>,
    /// `None` while unloaded (or if a failed worker lost it).
    map: Option<Box<SiteMap>>,
    /// The map is out of memory because the site was idle (see the module docs).
    unloaded: bool,
    unload_after: Option<Duration>,
    /// When the last request (any command but an unload) arrived, or the task started.
    last_request: Arc<RequestClock>,
    /// The map's options (a rebuild replays with them).
    options: LifelongOptions,
    /// The store's generation the map is known to agree with (see the module docs).
    generation: u64,
    store: Arc<dyn MapStore>,
    versions: watch::Sender<VersionInfo>,
    views: watch::Sender<Arc<SiteView>>,
    metrics: Arc<ServerMetrics>,
    session_idle_timeout: Option<Duration>,
    /// When each open session was last heard of.
    last_heard: BTreeMap<String, tokio::time::Instant>,
    /// A stored change could not be flushed yet: nothing is acknowledged or published until one is.
    unflushed: bool,
    checkpoints: CheckpointOptions,
    /// A session ended since the last checkpoint.
    checkpoint_due: bool,
    /// The version of the last checkpoint written or loaded (0: none).
    checkpointed_version: u64,
    /// The version of the last summary stored or read (0: none; see [`SiteSummary`]).
    summary_version: u64,
    /// The checkpoint being encoded and written beside the task, if any.
    checkpoint_writing: Option<CheckpointWriting>,
    /// Commands taken off the queue ahead of their turn, handled before the queue.
    backlog: VecDeque<Command>,
    /// Times in a row the session end at the head of the backlog was put behind robots' data.
    session_end_deferrals: u32,
}

/// How [`SiteTask::spawn`] starts a site.
enum Start {
    /// Its map, loaded (boxed: a `SiteMap` is kilobytes on the stack).
    Loaded(Box<Loaded>),
    /// Unloaded, publishing its stored summary.
    Unloaded(SiteSummary),
}

/// The span a site's task runs in, `site{site}`: every line the task (and the zenoh front end's tasks
/// of the site) logs names the site through it. At ERROR level so that it is on whenever any event is: a
/// filter at WARN still shows which site a warning is about.
pub(crate) fn site_span(site: &str) -> tracing::Span {
    tracing::error_span!("site", site = %site)
}

/// The span a site task handles one session's request in, `session{robot, session}` (inside the
/// site's span).
fn session_span(robot_id: &str, session_uuid: &str) -> tracing::Span {
    tracing::error_span!("session", robot = %robot_id, session = %session_uuid)
}

impl SiteTask {
    /// Rebuilds `site` from `store` (its newest checkpoint and the log after it), then starts its task.
    /// Returns the handle and the task's join handle (the task ends on [`SiteHandle::shutdown`] or when
    /// every handle is dropped).
    ///
    /// With unloading and checkpoints on, a site whose newest checkpoint covers its whole log starts
    /// unloaded instead (see the module docs): from its stored summary when there is one, without
    /// reading the checkpoint; else it is loaded and then unloaded at once (no session open), which
    /// stores the summary for the next start.
    pub async fn spawn(
        site: &str,
        options: LifelongOptions,
        store: Arc<dyn MapStore>,
        metrics: Arc<ServerMetrics>,
        task_options: SiteTaskOptions,
    ) -> Result<(SiteHandle, JoinHandle<()>), SiteError> {
        let span = site_span(site);
        let started = Instant::now();
        let generation = store.generation();
        let may_unload = task_options.unload_after.is_some() && task_options.checkpoints.enabled;
        let start = {
            let (site, store, options) = (site.to_owned(), Arc::clone(&store), options.clone());
            let use_checkpoints = task_options.checkpoints.enabled;
            let span = span.clone();
            tokio::task::spawn_blocking(move || {
                span.in_scope(|| {
                    if may_unload
                        && let Some(summary) = SiteSummary::usable_at_start(store.as_ref(), &site)?
                    {
                        return Ok(Start::Unloaded(summary));
                    }
                    load(&site, options, store.as_ref(), use_checkpoints)
                        .map(|loaded| Start::Loaded(Box::new(loaded)))
                })
            })
            .await
            .map_err(SiteError::Worker)??
        };
        let mut task = Self {
            site: site.into(),
            map: None,
            unloaded: false,
            unload_after: task_options.unload_after,
            last_request: Arc::new(RequestClock::new()),
            options,
            generation,
            store,
            versions: watch::channel(VersionInfo::default()).0,
            views: watch::channel(Arc::new(SiteView::default())).0,
            metrics,
            session_idle_timeout: task_options.session_idle_timeout,
            last_heard: BTreeMap::new(),
            unflushed: false,
            checkpoints: task_options.checkpoints,
            checkpoint_due: false,
            checkpointed_version: 0,
            summary_version: 0,
            checkpoint_writing: None,
            backlog: VecDeque::new(),
            session_end_deferrals: 0,
        };
        let mut unload_now = false;
        match start {
            Start::Unloaded(summary) => {
                let version = summary.info.version;
                span.in_scope(|| {
                    tracing::info!(
                        version,
                        seconds = started.elapsed().as_secs_f64(),
                        "site starts unloaded: its newest checkpoint covers its whole log"
                    );
                });
                task.versions.send_replace(summary.info);
                task.views.send_replace(Arc::new(summary.unloaded_view()));
                task.unloaded = true;
                task.checkpointed_version = version;
                task.summary_version = version;
            }
            Start::Loaded(loaded) => {
                span.in_scope(|| {
                    tracing::info!(
                        version = loaded.map.version(),
                        checkpoint = loaded.checkpoint,
                        replayed = loaded.replayed,
                        seconds = started.elapsed().as_secs_f64(),
                        read_s = loaded.times.read.as_secs_f64(),
                        decode_s = loaded.times.decode.as_secs_f64(),
                        rebuild_s = loaded.times.rebuild.as_secs_f64(),
                        replay_s = loaded.times.replay.as_secs_f64(),
                        "site log replayed"
                    );
                });
                unload_now = may_unload
                    && loaded.checkpoint.is_some()
                    && loaded.map.open_sessions().is_empty();
                task.install(*loaded, generation);
                task.publish();
            }
        }
        let (commands, commands_rx) = mpsc::channel(task_options.queue_depth.max(1));
        let handle = SiteHandle::new(
            site,
            commands,
            task.versions.subscribe(),
            task.views.subscribe(),
            Arc::clone(&task.last_request),
        );
        if unload_now {
            // A site a checkpoint covers starts unloaded; this one had no summary yet (or a log after
            // its checkpoint): unloading now stores both.
            task.unload().instrument(span.clone()).await;
        }
        let join = tokio::spawn(task.run(commands_rx).instrument(span));
        Ok((handle, join))
    }

    async fn run(mut self, mut commands: mpsc::Receiver<Command>) {
        let check_every = [self.session_idle_timeout, self.unload_after]
            .into_iter()
            .flatten()
            .map(|t| (t / 4).min(IDLE_CHECK_INTERVAL))
            .min()
            .unwrap_or(IDLE_CHECK_INTERVAL)
            .max(Duration::from_millis(1));
        let timers = self.session_idle_timeout.is_some() || self.unload_after.is_some();
        let mut idle_check = tokio::time::interval(check_every);
        idle_check.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            let wake = if let Some(command) = self.backlog.pop_front() {
                Wake::Command(command)
            } else {
                tokio::select! {
                    command = commands.recv() => match command {
                        Some(command) => Wake::Command(command),
                        None => break,
                    },
                    outcome = written(&mut self.checkpoint_writing) => Wake::CheckpointWritten(outcome),
                    _ = idle_check.tick(), if timers => Wake::IdleCheck,
                }
            };
            let command = match wake {
                Wake::Command(command) => command,
                Wake::CheckpointWritten(outcome) => {
                    self.checkpoint_writing = None;
                    self.checkpoint_written(outcome);
                    self.checkpoint_if_due().await;
                    continue;
                }
                Wake::IdleCheck => {
                    if !self.unloaded {
                        self.end_silent_sessions().await;
                        self.checkpoint_if_due().await;
                        self.unload_if_idle().await;
                    }
                    continue;
                }
            };
            let command = self.data_before_session_end(command, &mut commands);
            if command.needs_map() {
                self.last_request.touch();
                if self.unloaded
                    && let Err(e) = self.restore().await
                {
                    tracing::warn!("cannot restore the unloaded site: {e}");
                    command.fail(e);
                    continue;
                }
            }
            match command {
                Command::OpenSession {
                    robot_id,
                    session_uuid,
                    reply,
                } => {
                    let opened = self
                        .open_session(&robot_id, &session_uuid)
                        .instrument(session_span(&robot_id, &session_uuid))
                        .await;
                    let _ = reply.send(opened);
                    self.heard(&session_uuid);
                }
                Command::Upload { batch, sent, reply } => {
                    let session = batch.session_uuid.clone();
                    let span = session_span(&batch.robot_id, &session);
                    let _ = reply.send(self.upload(*batch, sent).instrument(span).await);
                    self.heard(&session);
                }
                Command::CloseSession {
                    robot_id,
                    session_uuid,
                    reply,
                } => {
                    let closed = self
                        .close_session(&robot_id, &session_uuid)
                        .instrument(session_span(&robot_id, &session_uuid))
                        .await;
                    let _ = reply.send(closed);
                }
                Command::Delta { since, reply } => {
                    let _ = reply.send(self.map().and_then(|m| m.delta_since(since)));
                }
                Command::Submap {
                    id,
                    revision,
                    reply,
                } => {
                    let _ = reply.send(self.map().and_then(|m| m.submap(id, revision)));
                }
                Command::Render { resolution, reply } => match self.map() {
                    Ok(map) => {
                        let (version, grids) = (map.version(), map.grids_for_render());
                        // Rendering can take a while: do it beside the task, not in it.
                        tokio::spawn(
                            async move {
                                let grid = tokio::task::spawn_blocking(move || {
                                    render_submaps_log_odds(&grids, resolution)
                                })
                                .await
                                .map_err(SiteError::Worker);
                                let _ = reply.send(grid.map(|grid| RenderedMap { version, grid }));
                            }
                            .in_current_span(),
                        );
                    }
                    Err(e) => {
                        let _ = reply.send(Err(e));
                    }
                },
                Command::NodePoses { reply } => {
                    let _ = reply.send(self.map().map(SiteMap::node_poses).unwrap_or_default());
                }
                Command::Load { reply } => {
                    let _ = reply.send(self.map().map(|_| self.views.borrow().clone()));
                }
                Command::Unload { reply } => {
                    let _ = reply.send(Ok(self.unload().await));
                }
                Command::Shutdown => break,
            }
            // A session end already queued (taken into the backlog by `data_before_session_end`) comes
            // first: one checkpoint then covers both ends.
            if !self.backlog.iter().any(Command::ends_session) {
                self.checkpoint_if_due().await;
            }
        }
        // A checkpoint write in flight finishes before the task ends.
        self.finish_checkpoint().await;
    }

    fn map(&self) -> Result<&SiteMap, SiteError> {
        self.map.as_deref().ok_or_else(|| {
            SiteError::Internal(if self.unloaded {
                "the site is unloaded".into()
            } else {
                "the site map was lost by a failed worker".into()
            })
        })
    }

    fn site(&self) -> String {
        self.site.to_string()
    }
}

#[cfg(test)]
mod tests;
