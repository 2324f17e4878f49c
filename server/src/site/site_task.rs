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
//! and hands the freed pages back to the system ([`crate::memory_release`]). What stays answers
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
use prost::Message as _;
use proto::{FORMAT_VERSION, SiteCheckpoint, UploadBatch, UploadItem, pb};
use storage::{BatchOutcome, MapStore, RecordKind, WriteBatch};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tracing::Instrument as _;

use super::maintenance_thread::run_as_maintenance;
use super::request_clock::RequestClock;
use super::site_handle::Command;
use super::site_summary::SiteSummary;
use super::{
    CheckpointOptions, RenderedMap, SiteError, SiteHandle, SiteMap, SiteView, UploadAck,
    UploadCheck, VersionInfo,
};
use crate::ServerMetrics;

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

/// Most times in a row a session end is put behind another robot's upload (see
/// [`SiteTask::data_before_session_end`]).
const MAX_SESSION_END_DEFERRALS: u32 = 16;

/// Most commands taken off the queue into the backlog (the queue's own capacity).
const MAX_BACKLOG: usize = 64;

/// A checkpoint written beside the task (see [`SiteTask::checkpoint_if_due`]).
struct CheckpointWritten {
    version: u64,
    bytes: usize,
    compaction: storage::Compaction,
    /// The summary's write, if one was stored with it.
    summary: Option<Result<(), SiteError>>,
    /// From the start of the checkpoint to its durability.
    seconds: f64,
    /// The part the task waited for: the copy of the site's state.
    copy_s: f64,
}

/// The checkpoint write in flight.
type CheckpointWriting = JoinHandle<Result<CheckpointWritten, SiteError>>;

/// What the task's loop wakes up for.
enum Wake {
    Command(Command),
    CheckpointWritten(Result<Result<CheckpointWritten, SiteError>, tokio::task::JoinError>),
    IdleCheck,
}

/// The in-flight checkpoint write's outcome (never, if there is none).
async fn written(
    writing: &mut Option<CheckpointWriting>,
) -> Result<Result<CheckpointWritten, SiteError>, tokio::task::JoinError> {
    match writing {
        Some(handle) => handle.await,
        None => std::future::pending().await,
    }
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

    /// Robots' data before session-end maintenance: if `command` ends a session and another session's
    /// upload that does not is queued, that upload is handled now and `command` waits at the head of
    /// the backlog — at most [`MAX_SESSION_END_DEFERRALS`] times in a row, so a busy site still ends its
    /// sessions. Ending a session (the final optimization, trimming, sparsification: seconds of CPU when
    /// a fleet's sessions end together) answers nobody in real time; another robot's upload carries
    /// submaps the fleet waits for. The log records the order the changes were applied in, so a replay
    /// rebuilds the same map.
    fn data_before_session_end(
        &mut self,
        command: Command,
        commands: &mut mpsc::Receiver<Command>,
    ) -> Command {
        let Some(session) = command.session().filter(|_| command.ends_session()) else {
            return command;
        };
        if self.session_end_deferrals >= MAX_SESSION_END_DEFERRALS {
            self.session_end_deferrals = 0;
            return command;
        }
        while self.backlog.len() < MAX_BACKLOG {
            match commands.try_recv() {
                Ok(queued) => self.backlog.push_back(queued),
                Err(_) => break,
            }
        }
        let Some(data) = self
            .backlog
            .iter()
            .position(|queued| queued.is_data_of_another_session(session))
            .and_then(|i| self.backlog.remove(i))
        else {
            self.session_end_deferrals = 0;
            return command;
        };
        self.session_end_deferrals += 1;
        self.backlog.push_front(command);
        data
    }

    /// Notes a request of `session`'s robot (only sessions the map knows and has not closed are kept).
    fn heard(&mut self, session: &str) {
        let open = self
            .map
            .as_ref()
            .is_some_and(|m| m.session_robot(session).is_some() && !m.is_closed(session));
        if open {
            self.last_heard
                .insert(session.to_owned(), tokio::time::Instant::now());
        }
    }

    /// Ends every open session silent for longer than the idle timeout.
    async fn end_silent_sessions(&mut self) {
        let Some(timeout) = self.session_idle_timeout else {
            return;
        };
        let Ok(open) = self.map().map(SiteMap::open_sessions) else {
            return;
        };
        let now = tokio::time::Instant::now();
        // Every open session is heard of at the task's start and at its open; one that somehow was
        // not counts as silent from now on.
        let silent: Vec<(String, String)> = open
            .into_iter()
            .filter(|(session, _)| {
                let heard = *self.last_heard.entry(session.clone()).or_insert(now);
                now.duration_since(heard) > timeout
            })
            .collect();
        for (session, robot) in silent {
            let span = session_span(&robot, &session);
            match self
                .close_session(&robot, &session)
                .instrument(span.clone())
                .await
            {
                Ok(version) => {
                    self.metrics.session_timed_out();
                    span.in_scope(|| {
                        tracing::info!(
                            version,
                            silent_s = timeout.as_secs_f64(),
                            "session ended: its robot was silent past the idle timeout"
                        );
                    });
                }
                Err(e) => span.in_scope(|| tracing::warn!("cannot end a silent session: {e}")),
            }
        }
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

    /// Unloads the site if it has been idle long enough (see the module docs).
    async fn unload_if_idle(&mut self) {
        let Some(after) = self.unload_after else {
            return;
        };
        if self.unloaded || self.last_request.idle() < after {
            return;
        }
        if !self.unload().await {
            // Not now (a session open, no checkpoint possible): look again after another idle period.
            self.last_request.touch();
        }
    }

    /// Drops the map from memory if no session is open and a durable checkpoint covers its version
    /// (written now if needed); `true` if the site is unloaded now.
    async fn unload(&mut self) -> bool {
        if self.unloaded {
            return true;
        }
        let Ok(map) = self.map() else {
            return false;
        };
        let version = map.version();
        if !self.checkpoints.enabled || !map.open_sessions().is_empty() {
            return false;
        }
        self.finish_checkpoint().await;
        if self.checkpointed_version != version {
            self.checkpoint_due = true;
            self.checkpoint_if_due().await;
            self.finish_checkpoint().await;
        }
        if self.checkpointed_version != version
            || self.unflushed
            || self.store.generation() != self.generation
        {
            tracing::debug!(
                version,
                checkpointed = self.checkpointed_version,
                "site idle but not unloaded: no durable checkpoint covers its version"
            );
            return false;
        }
        if self.summary_version != version {
            // Checkpointed while a session was open, or the summary's write failed: without one
            // the next start loads the site.
            if let Some(summary) = self.summary() {
                let (store, site) = (Arc::clone(&self.store), self.site());
                match tokio::task::spawn_blocking(move || summary.store(store.as_ref(), &site))
                    .await
                {
                    Ok(Ok(())) => self.summary_version = version,
                    Ok(Err(e)) => tracing::warn!(version, "cannot store the site's summary: {e}"),
                    Err(e) => tracing::warn!(version, "cannot store the site's summary: {e}"),
                }
            }
        }
        let Some(map) = self.map.take() else {
            return false;
        };
        self.unloaded = true;
        self.last_heard.clear();
        let view = self.views.borrow().unloaded();
        self.views.send_replace(Arc::new(view));
        self.metrics.site_unloaded();
        tracing::info!(
            version,
            idle_s = self.last_request.idle().as_secs_f64(),
            "site unloaded: its map dropped from memory until the next request"
        );
        // Freeing a big map takes a while: beside the task, then the pages go back to the system.
        drop(tokio::task::spawn_blocking(move || {
            drop(map);
            crate::memory_release::release_all_freed_memory_in_background();
        }));
        true
    }

    /// Restores an unloaded site from its store (its checkpoint and the log after it) and publishes
    /// its view again; `Err` leaves it unloaded.
    async fn restore(&mut self) -> Result<(), SiteError> {
        let started = Instant::now();
        let generation = self.store.generation();
        let loaded = self.load_from_store("the unloaded site's store").await?;
        let seconds = started.elapsed();
        self.metrics.site_restored(seconds);
        tracing::info!(
            version = loaded.map.version(),
            checkpoint = loaded.checkpoint,
            replayed = loaded.replayed,
            seconds = seconds.as_secs_f64(),
            read_s = loaded.times.read.as_secs_f64(),
            decode_s = loaded.times.decode.as_secs_f64(),
            rebuild_s = loaded.times.rebuild.as_secs_f64(),
            replay_s = loaded.times.replay.as_secs_f64(),
            "unloaded site restored"
        );
        self.install(loaded, generation);
        self.unloaded = false;
        // The view comes back with the map; the version is only announced if it moved.
        if let Ok(map) = self.map() {
            let info = VersionInfo {
                version: map.version(),
                counts: map.counts(),
            };
            self.views.send_replace(Arc::new(map.view()));
            self.versions.send_if_modified(|current| {
                let moved = *current != info;
                *current = info;
                moved
            });
        }
        Ok(())
    }

    /// [`load`] on the blocking pool. A map below the published version is refused as a corrupt log
    /// (what was published was durable); `what` names the store in that error.
    async fn load_from_store(&self, what: &str) -> Result<Loaded, SiteError> {
        let (site, store, options) = (self.site(), Arc::clone(&self.store), self.options.clone());
        let use_checkpoints = self.checkpoints.enabled;
        let loaded = tokio::task::spawn_blocking(move || {
            load(&site, options, store.as_ref(), use_checkpoints)
        })
        .await
        .map_err(SiteError::Worker)??;
        let (version, published) = (loaded.map.version(), self.versions.borrow().version);
        if version < published {
            return Err(SiteError::CorruptLog {
                index: version + 1,
                reason: format!(
                    "{what} ends at version {version}, below the published {published}"
                ),
            });
        }
        Ok(loaded)
    }

    /// Makes `loaded` the task's map, built under the store's `generation`.
    fn install(&mut self, loaded: Loaded, generation: u64) {
        let map = loaded.map;
        self.checkpointed_version = loaded.checkpoint.unwrap_or(0);
        let now = tokio::time::Instant::now();
        let open: Vec<String> = map.open_sessions().into_iter().map(|(s, _)| s).collect();
        self.last_heard.retain(|session, _| open.contains(session));
        for session in open {
            self.last_heard.entry(session).or_insert(now);
        }
        self.map = Some(Box::new(map));
        self.generation = generation;
        self.unflushed = false;
    }

    /// Writes log entry `version` with the version bump and the session's sequence number, and flushes
    /// it. A failed write stores nothing (`Err`); a write applied but not flushed is `Ok` with
    /// [`Self::unflushed`] set: the caller applies it to the map, and [`Self::durable`] refuses to
    /// acknowledge it until a flush succeeds.
    async fn persist(
        &mut self,
        version: u64,
        entry: pb::site_log_entry::Entry,
        session_seq: Option<(String, u64)>,
    ) -> Result<(), SiteError> {
        let bytes = pb::SiteLogEntry {
            format_version: FORMAT_VERSION,
            map_version: version,
            entry: Some(entry),
        }
        .encode_to_vec();
        let mut batch = WriteBatch::new(self.site());
        batch.put(SITE_LOG_KIND, version, bytes).bump_map_version();
        if let Some((session, seq)) = session_seq {
            batch.for_session(session, seq);
        }
        let store = Arc::clone(&self.store);
        let (outcome, flushed) =
            tokio::task::spawn_blocking(move || store.apply(&batch).map(|o| (o, store.flush())))
                .await
                .map_err(SiteError::Worker)??;
        match outcome {
            BatchOutcome::Applied { map_version } if map_version == version => {}
            other => {
                return Err(SiteError::Internal(format!(
                    "store disagrees on the site version: expected to write {version}, got {other:?}"
                )));
            }
        }
        if let Err(e) = flushed {
            tracing::warn!(
                version,
                "change stored but not durable ({e}): not acknowledged until a flush succeeds"
            );
            self.unflushed = true;
        } else if self.store.generation() != self.generation {
            // Reopened between the write and the flush: the flush may not have covered the write.
            self.unflushed = true;
        }
        Ok(())
    }

    /// Before any change: if the store was reopened since the map was built and the map may differ
    /// from it, rebuilds the map from the store (see the module docs). `Err` while that fails (nothing
    /// may be changed on a map that may not equal the store).
    async fn check_store(&mut self) -> Result<(), SiteError> {
        let generation = self.store.generation();
        if generation == self.generation {
            return Ok(());
        }
        let stored = {
            let (store, site) = (Arc::clone(&self.store), self.site());
            tokio::task::spawn_blocking(move || store.map_version(&site))
                .await
                .map_err(SiteError::Worker)??
        };
        if !self.unflushed && stored == self.map()?.version() {
            self.generation = generation;
            return Ok(());
        }
        self.rebuild(generation).await
    }

    /// Replays the store's log into a new map, which replaces the current one.
    async fn rebuild(&mut self, generation: u64) -> Result<(), SiteError> {
        let before = self.map()?.version();
        let started = Instant::now();
        let loaded = self
            .load_from_store("after the store was reopened its log")
            .await?;
        let version = loaded.map.version();
        tracing::warn!(
            from_version = before,
            to_version = version,
            seconds = started.elapsed().as_secs_f64(),
            "the store was reopened after a failed write: site map rebuilt from its log"
        );
        self.install(loaded, generation);
        self.publish();
        Ok(())
    }

    /// Flushes a change [`Self::persist`] could not; `Err` while the store still cannot (nothing may
    /// be acknowledged or published before), and publishes the version once it can.
    async fn durable(&mut self) -> Result<(), SiteError> {
        if !self.unflushed {
            return Ok(());
        }
        let store = Arc::clone(&self.store);
        tokio::task::spawn_blocking(move || store.flush())
            .await
            .map_err(SiteError::Worker)??;
        if self.store.generation() != self.generation {
            // The store was reopened: the unflushed change may be gone. Rebuild, and let the robot
            // retry (its batch is then applied once, or acknowledged as a duplicate).
            let generation = self.store.generation();
            self.rebuild(generation).await?;
            return Err(SiteError::Storage(storage::StorageError::Wedged {
                cause: "the store was reopened before the change was durable".into(),
                out_of_space: false,
            }));
        }
        self.unflushed = false;
        tracing::info!("stored changes are durable again");
        self.publish();
        Ok(())
    }

    /// Runs `f` on the map on the blocking pool and puts the map back.
    async fn with_map_blocking<T: Send + 'static>(
        &mut self,
        f: impl FnOnce(&mut SiteMap) -> T + Send + 'static,
    ) -> Result<T, SiteError> {
        let mut map = self.map.take().ok_or_else(|| {
            SiteError::Internal("the site map was lost by a failed worker".into())
        })?;
        let (map, result) = tokio::task::spawn_blocking(move || {
            let result = f(&mut map);
            (map, result)
        })
        .await
        .map_err(SiteError::Worker)?;
        self.map = Some(map);
        Ok(result)
    }

    /// [`Self::with_map_blocking`] on a maintenance thread (see `maintenance_thread`): a session's end,
    /// which yields the CPU to robots' data. `what` names the work in errors.
    async fn with_map_in_maintenance<T: Send + 'static>(
        &mut self,
        what: &'static str,
        f: impl FnOnce(&mut SiteMap) -> T + Send + 'static,
    ) -> Result<T, SiteError> {
        let mut map = self.map.take().ok_or_else(|| {
            SiteError::Internal("the site map was lost by a failed worker".into())
        })?;
        let (map, result) = run_as_maintenance(what, move || {
            let result = f(&mut map);
            (map, result)
        })
        .await?;
        self.map = Some(map);
        Ok(result)
    }

    /// What the site publishes now, as its [`SiteSummary`] (`None` while unloaded).
    fn summary(&self) -> Option<SiteSummary> {
        if self.unloaded || self.map.is_none() {
            return None;
        }
        Some(SiteSummary::of(
            *self.versions.borrow(),
            &self.views.borrow(),
        ))
    }

    fn publish(&self) {
        if let Ok(map) = self.map() {
            let info = VersionInfo {
                version: map.version(),
                counts: map.counts(),
            };
            // The view first: whoever hears of the version finds it.
            self.views.send_replace(Arc::new(map.view()));
            self.versions.send_replace(info);
        }
    }

    /// Starts a checkpoint of the site when one is due and can be taken (see the module docs): the
    /// site's state is copied ([`SiteMap::checkpoint`]) while the task waits, then encoded, written and
    /// the log compacted on a maintenance thread beside the task, which goes on with its
    /// requests ([`Self::checkpoint_written`] records the outcome). One write at a time: a checkpoint
    /// due meanwhile starts when the write ends. A failure is logged and retried after a later change:
    /// the log stays whole until a checkpoint is durable, so nothing depends on it.
    async fn checkpoint_if_due(&mut self) {
        if self.checkpoint_writing.is_some() {
            return;
        }
        let Ok(version) = self.map().map(SiteMap::version) else {
            return;
        };
        let options = self.checkpoints;
        let by_versions =
            version.saturating_sub(self.checkpointed_version) >= options.every_n_versions;
        if !options.enabled
            || !(self.checkpoint_due || by_versions)
            || version <= self.checkpointed_version
            || self.unflushed
            || self.store.generation() != self.generation
        {
            return;
        }
        let started = Instant::now();
        // The task waits for the copy (at the priority of the requests behind it), not for the rest.
        let copied = self.with_map_blocking(|map| map.checkpoint()).await;
        let checkpoint = match copied {
            Ok(Some(checkpoint)) => checkpoint,
            Ok(None) => return, // a session is mid-start: at a later change
            Err(e) => {
                tracing::warn!(version, "cannot checkpoint the site: {e}");
                return;
            }
        };
        let copy_s = started.elapsed().as_secs_f64();
        // Due again only if a later change makes it so (or this write fails).
        self.checkpoint_due = false;
        let (store, site) = (Arc::clone(&self.store), self.site());
        let retention = options.retention();
        // Stored only once the checkpoint at its version is durable, and only if a start could use it.
        let summary = self
            .summary()
            .filter(|s| s.info.version == version && s.info.counts.open_sessions == 0);
        let span = tracing::Span::current();
        let write = move || {
            let _entered = span.enter();
            let bytes = pb::SiteCheckpoint::from(&checkpoint).encode_to_vec();
            drop(checkpoint);
            // What the kill -9 chaos test times its kills by (`fleet-demo/tests/kill_nine_fleet.rs`).
            tracing::debug!(
                version,
                bytes = bytes.len(),
                "writing the site's checkpoint"
            );
            store.put_checkpoint(&site, version, &bytes)?;
            let compaction = store.compact(&site, SITE_LOG_KIND, &retention)?;
            let summary = summary.map(|s| s.store(store.as_ref(), &site));
            Ok(CheckpointWritten {
                version,
                bytes: bytes.len(),
                compaction,
                summary,
                seconds: started.elapsed().as_secs_f64(),
                copy_s,
            })
        };
        self.checkpoint_writing = Some(tokio::spawn(async move {
            run_as_maintenance("checkpoint", write).await?
        }));
    }

    /// Records the outcome of the checkpoint write [`Self::checkpoint_if_due`] started.
    fn checkpoint_written(
        &mut self,
        outcome: Result<Result<CheckpointWritten, SiteError>, tokio::task::JoinError>,
    ) {
        let written = match outcome.map_err(SiteError::Worker).and_then(|w| w) {
            Ok(written) => written,
            Err(e) => {
                self.checkpoint_due = true;
                tracing::warn!("cannot store the site's checkpoint: {e}");
                return;
            }
        };
        let version = written.version;
        self.checkpointed_version = self.checkpointed_version.max(version);
        let summarized = written.summary.is_some();
        match written.summary {
            Some(Ok(())) => self.summary_version = self.summary_version.max(version),
            Some(Err(e)) => tracing::warn!(version, "cannot store the site's summary: {e}"),
            None => {}
        }
        tracing::info!(
            version,
            bytes = written.bytes,
            seconds = written.seconds,
            copy_s = written.copy_s,
            log_compacted_through = written.compaction.log_compacted_through,
            log_entries_removed = written.compaction.log_entries_removed,
            summarized,
            "site checkpointed"
        );
    }

    /// Waits for the checkpoint write in flight, if any, and records it.
    async fn finish_checkpoint(&mut self) {
        if let Some(writing) = self.checkpoint_writing.take() {
            let outcome = writing.await;
            self.checkpoint_written(outcome);
        }
    }

    async fn open_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<(super::SessionOpened, u64), SiteError> {
        storage::validate_session_id(session_uuid)?;
        self.check_store().await?;
        let opened = self.map()?.check_open(robot_id, session_uuid)?;
        if !opened.created {
            self.durable().await?;
            return Ok((opened, self.map()?.version()));
        }
        let version = self.map()?.version() + 1;
        self.persist(
            version,
            pb::site_log_entry::Entry::SessionOpened(pb::SessionOpened {
                robot_id: robot_id.to_owned(),
                session_uuid: session_uuid.to_owned(),
                trajectory: opened.trajectory,
            }),
            None,
        )
        .await?;
        if let Some(map) = self.map.as_mut() {
            map.open_session(robot_id, session_uuid, opened.trajectory, version)?;
        }
        self.metrics.session_opened();
        self.durable().await?;
        self.publish();
        Ok((opened, version))
    }

    async fn upload(&mut self, batch: UploadBatch, sent: Instant) -> Result<UploadAck, SiteError> {
        self.check_store().await?;
        let map = self.map()?;
        if let UploadCheck::Duplicate { .. } = map.check_upload(&batch)? {
            self.durable().await?;
            self.metrics.upload_duplicate();
            let map = self.map()?;
            return Ok(UploadAck {
                seq: batch.seq,
                map_version: map.version(),
                duplicate: true,
                session_end_pose: batch
                    .ends_session()
                    .then(|| map.session_end_pose(&batch.session_uuid))
                    .flatten(),
            });
        }
        let version = map.version() + 1;
        let received = Instant::now();
        // The map applies exactly what replay will: the batch decoded from its stored form (a pose's
        // angle goes through `atan2` and `sin`/`cos` once more, which can move its last bit), so a
        // restart rebuilds this map bit for bit. A batch whose stored form does not decode is refused
        // before anything is stored.
        let entry = pb::UploadBatch::from(&batch);
        let batch = UploadBatch::try_from(&entry).map_err(SiteError::Unstorable)?;
        self.persist(
            version,
            pb::site_log_entry::Entry::Upload(entry),
            Some((batch.session_uuid.clone(), batch.seq)),
        )
        .await?;
        let (seq, session) = (batch.seq, batch.session_uuid.clone());
        let (nodes, submaps_finished) =
            batch.items.iter().fold((0, 0), |(n, s), item| match item {
                UploadItem::NodeAdded(_) => (n + 1, s),
                UploadItem::SubmapFinished { .. } => (n, s + 1),
                _ => (n, s),
            });
        let started = Instant::now();
        let ends_session = batch.ends_session();
        let apply = move |map: &mut SiteMap| map.apply_upload(&batch, version);
        let applied = if ends_session {
            self.with_map_in_maintenance("session end", apply).await?
        } else {
            self.with_map_blocking(apply).await?
        };
        let applying = started.elapsed();
        self.metrics.record_pgr(applying);
        tracing::debug!(
            version,
            nodes,
            submaps_finished,
            ends_session,
            optimizations = applied.as_ref().ok(),
            queue_seconds = (received - sent).as_secs_f64(),
            store_seconds = (started - received).as_secs_f64(),
            apply_seconds = applying.as_secs_f64(),
            "upload applied"
        );
        if let Err(e) = applied {
            // Stored but not fully applied: a bug (check_upload accepted it). Replay will hit it again.
            tracing::error!(version, "stored upload failed to apply: {e}");
            return Err(e);
        }
        self.metrics.upload_applied();
        if self.map()?.is_closed(&session) {
            self.last_heard.remove(&session);
            self.checkpoint_due = true;
        }
        self.durable().await?;
        self.publish();
        let session_end_pose = ends_session
            .then(|| self.map().ok()?.session_end_pose(&session))
            .flatten();
        Ok(UploadAck {
            seq,
            map_version: version,
            duplicate: false,
            session_end_pose,
        })
    }

    async fn close_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> Result<u64, SiteError> {
        self.check_store().await?;
        let map = self.map()?;
        map.check_open(robot_id, session_uuid)?;
        if map.is_closed(session_uuid) {
            self.durable().await?;
            return Ok(self.map()?.version());
        }
        if map.check_open(robot_id, session_uuid)?.created {
            return Err(SiteError::UnknownSession(session_uuid.to_owned()));
        }
        let version = map.version() + 1;
        self.persist(
            version,
            pb::site_log_entry::Entry::SessionClosed(pb::SessionClosed {
                session_uuid: session_uuid.to_owned(),
            }),
            None,
        )
        .await?;
        let (robot, session) = (robot_id.to_owned(), session_uuid.to_owned());
        let started = Instant::now();
        self.with_map_in_maintenance("session end", move |map| {
            map.close_session(&robot, &session, version)
        })
        .await??;
        self.last_heard.remove(session_uuid);
        self.checkpoint_due = true;
        let closing = started.elapsed();
        self.metrics.record_pgr(closing);
        tracing::info!(
            version,
            seconds = closing.as_secs_f64(),
            "session closed: trimmed, sparsified and optimized"
        );
        self.durable().await?;
        self.publish();
        Ok(version)
    }
}

/// What [`load`] rebuilt a site from.
pub(crate) struct Loaded {
    pub(crate) map: SiteMap,
    /// The log index of the checkpoint it started from (`None`: the whole log).
    pub(crate) checkpoint: Option<u64>,
    /// Log entries replayed after it.
    pub(crate) replayed: u64,
    /// Where the time went.
    pub(crate) times: LoadTimes,
}

/// Where a [`load`]'s time went, wall-clock time of each step (logged with every load and restore).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct LoadTimes {
    /// Reading the checkpoints' bytes (index, file, CRC), every one tried.
    pub(crate) read: Duration,
    /// Decoding them (protobuf, then the checks of `SiteCheckpoint`'s conversion).
    pub(crate) decode: Duration,
    /// Building the site map from the decoded state (`SiteMap::restore`: what the checkpoint does not
    /// store, such as the branch-and-bound precomputation grids).
    pub(crate) rebuild: Duration,
    /// Reading the log and replaying the entries after the checkpoint.
    pub(crate) replay: Duration,
}

/// Rebuilds a site map from its store: the newest checkpoint that reads back (when `use_checkpoints`)
/// and the log after it, or the whole log (see the module docs for which checkpoints are skipped and
/// which stop the site).
pub(crate) fn load(
    site: &str,
    options: LifelongOptions,
    store: &dyn MapStore,
    use_checkpoints: bool,
) -> Result<Loaded, SiteError> {
    let mut from = None;
    let mut times = LoadTimes::default();
    if use_checkpoints {
        for index in store.checkpoint_indexes(site)? {
            match restore_checkpoint(site, options.clone(), store, index, &mut times) {
                Ok(Some(map)) => {
                    from = Some((index, map));
                    break;
                }
                Ok(None) => {}
                Err(
                    e @ (SiteError::CorruptCheckpoint { .. }
                    | SiteError::Storage(storage::StorageError::Corrupt { .. })),
                ) => {
                    tracing::warn!(
                        index,
                        "site checkpoint unreadable, falling back to the one before it: {e}"
                    );
                }
                Err(e) => return Err(e),
            }
        }
    }
    let checkpoint = from.as_ref().map(|(index, _)| *index);
    let mut map = match from {
        Some((_, map)) => map,
        None => SiteMap::new(site, options).map_err(SiteError::Map)?,
    };
    let started = Instant::now();
    let replayed = replay_after(&mut map, store)?;
    times.replay = started.elapsed();
    Ok(Loaded {
        map,
        checkpoint,
        replayed,
        times,
    })
}

/// The site the checkpoint at `index` holds; `Ok(None)` if it is gone (compacted since it was listed).
pub(crate) fn restore_checkpoint(
    site: &str,
    options: LifelongOptions,
    store: &dyn MapStore,
    index: u64,
    times: &mut LoadTimes,
) -> Result<Option<SiteMap>, SiteError> {
    let corrupt = |reason: String| SiteError::CorruptCheckpoint {
        index,
        reason,
        source: None,
    };
    let started = Instant::now();
    let bytes = store.checkpoint(site, index);
    times.read += started.elapsed();
    let Some(bytes) = bytes? else {
        return Ok(None);
    };
    let started = Instant::now();
    let message =
        pb::SiteCheckpoint::decode(bytes.as_slice()).map_err(|e| SiteError::CorruptCheckpoint {
            index,
            reason: format!("it does not decode: {e}"),
            source: Some(e.into()),
        })?;
    // A version this build does not read is never guessed at, never rebuilt behind: the log it covers
    // may be compacted away.
    proto::check_checkpoint_format_version(message.format_version).map_err(|e| {
        SiteError::CheckpointRefused {
            index,
            source: e.into(),
        }
    })?;
    let checkpoint = SiteCheckpoint::try_from(&message).map_err(|e| SiteError::CorruptCheckpoint {
        index,
        reason: e.to_string(),
        source: Some(e.into()),
    });
    drop(message);
    times.decode += started.elapsed();
    let checkpoint = checkpoint?;
    if checkpoint.log_index != index {
        return Err(corrupt(format!(
            "it is stored under log index {index} but says it covers {}",
            checkpoint.log_index
        )));
    }
    let started = Instant::now();
    let map = SiteMap::restore(site, options, checkpoint);
    times.rebuild += started.elapsed();
    map.map(Some)
}

/// Replays the log entries after `map`'s version (entries at or before it, kept for a fallback or for
/// audit, are skipped undecoded); the log must continue the map without a gap and end at the store's
/// version. Returns the number of entries replayed.
fn replay_after(map: &mut SiteMap, store: &dyn MapStore) -> Result<u64, SiteError> {
    let site = map.site().to_owned();
    let stored_version = store.map_version(&site)?;
    let mut replayed = 0;
    for record in store.scan(&site, SITE_LOG_KIND)? {
        let (id, bytes) = record?;
        let index = id.as_u64().ok_or_else(|| SiteError::CorruptLog {
            index: 0,
            reason: format!("log record id {id} is not a number"),
        })?;
        if index <= map.version() {
            continue;
        }
        let corrupt = |reason: String| SiteError::CorruptLog { index, reason };
        let undecodable = |source: Box<dyn std::error::Error + Send + Sync>| {
            SiteError::CorruptEntry { index, source }
        };
        if index != map.version() + 1 {
            return Err(corrupt(if map.version() == 0 {
                "the log before it is compacted away and no readable checkpoint covers it".into()
            } else {
                format!("expected entry {}", map.version() + 1)
            }));
        }
        let entry =
            pb::SiteLogEntry::decode(bytes.as_slice()).map_err(|e| undecodable(e.into()))?;
        proto::check_format_version("SiteLogEntry", entry.format_version)
            .map_err(|e| undecodable(e.into()))?;
        match entry.entry {
            Some(pb::site_log_entry::Entry::SessionOpened(open)) => {
                map.open_session(&open.robot_id, &open.session_uuid, open.trajectory, index)?;
            }
            Some(pb::site_log_entry::Entry::Upload(upload)) => {
                let batch = UploadBatch::try_from(&upload).map_err(|e| undecodable(e.into()))?;
                map.apply_upload(&batch, index)?;
            }
            Some(pb::site_log_entry::Entry::SessionClosed(close)) => {
                let robot = map
                    .session_robot(&close.session_uuid)
                    .ok_or_else(|| corrupt("closes an unknown session".into()))?
                    .to_owned();
                map.close_session(&robot, &close.session_uuid, index)?;
            }
            None => return Err(corrupt("empty entry".into())),
        }
        replayed += 1;
    }
    if map.version() != stored_version {
        return Err(SiteError::CorruptLog {
            index: map.version() + 1,
            reason: format!(
                "the log ends at version {} but the store is at {stored_version}",
                map.version()
            ),
        });
    }
    Ok(replayed)
}

#[cfg(test)]
mod tests {
    use storage::MemStore;

    use super::super::site_summary::{SUMMARY_ID, SUMMARY_KIND};
    use super::*;

    async fn spawn(store: &Arc<dyn MapStore>) -> Result<(SiteHandle, JoinHandle<()>), SiteError> {
        spawn_with(store, None).await
    }

    async fn spawn_with(
        store: &Arc<dyn MapStore>,
        session_idle_timeout: Option<Duration>,
    ) -> Result<(SiteHandle, JoinHandle<()>), SiteError> {
        SiteTask::spawn(
            "s",
            LifelongOptions::default(),
            Arc::clone(store),
            Arc::new(ServerMetrics::default()),
            SiteTaskOptions {
                queue_depth: 4,
                session_idle_timeout,
                checkpoints: CheckpointOptions::DEFAULT,
                unload_after: None,
            },
        )
        .await
    }

    /// A batch of one node.
    fn node_batch(session: &str, seq: u64) -> UploadBatch {
        UploadBatch {
            site: "s".into(),
            robot_id: "r".into(),
            session_uuid: session.into(),
            seq,
            items: vec![proto::UploadItem::NodeAdded(proto::NodeAdded {
                time: mapping::sensor::Timestamp(seq as i64 * 1_000_000_000),
                local_pose: mapping::geometry::rigid2(0.1 * seq as f64, 0.0, 0.0),
                points: vec![
                    nalgebra::Point2::new(1.0, 0.5),
                    nalgebra::Point2::new(2.0, 0.0),
                ],
                insertion_submaps: vec![(0, mapping::geometry::rigid2(0.0, 0.0, 0.0))],
                recovered: false,
            })],
        }
    }

    #[tokio::test]
    async fn another_sessions_data_goes_before_a_session_end_queued_ahead_of_it() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let (site, task) = spawn_with(&store, None).await.unwrap();
        for session in ["ending", "mapping"] {
            site.open_session("r", session).await.unwrap();
            site.upload(node_batch(session, 1)).await.unwrap();
        }
        let mut end = node_batch("ending", 2);
        end.items.push(proto::UploadItem::SessionEnd);
        // Both are queued before the task takes either (the test's runtime has one thread).
        let (ended, data) = tokio::join!(site.upload(end), site.upload(node_batch("mapping", 2)));
        let (ended, data) = (ended.unwrap(), data.unwrap());
        assert!(
            data.map_version < ended.map_version,
            "the other robot's data ({}) before the session end ({})",
            data.map_version,
            ended.map_version
        );
        // Applied in that order, logged in that order: a restart rebuilds the same map.
        let poses = site.node_poses().await.unwrap();
        site.shutdown().await;
        task.await.unwrap();
        let (site, task) = spawn_with(&store, None).await.unwrap();
        assert_eq!(site.current().version, ended.map_version);
        assert_eq!(site.node_poses().await.unwrap(), poses);
        site.shutdown().await;
        task.await.unwrap();
    }

    /// Sleeps `seconds` of (paused, virtual) time in steps, letting the site task run between them.
    async fn let_time_pass(seconds: u64) {
        for _ in 0..seconds {
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
    }

    #[tokio::test(start_paused = true)]
    async fn a_session_whose_robot_falls_silent_is_ended_by_the_server() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let (site, task) = spawn_with(&store, Some(Duration::from_secs(60)))
            .await
            .unwrap();
        site.open_session("r", "silent").await.unwrap();
        site.open_session("r", "talking").await.unwrap();
        site.upload(node_batch("silent", 1)).await.unwrap();
        assert_eq!(site.current().counts.open_sessions, 2);
        let mut empty = node_batch("silent", 2);
        empty.items.clear();
        assert!(
            matches!(site.upload(empty).await, Err(SiteError::InvalidBatch(_))),
            "an empty batch could not be replayed: it is refused"
        );
        for seq in 1..=4 {
            let_time_pass(20).await;
            site.upload(node_batch("talking", seq)).await.unwrap();
        }
        // 80 s after its last upload "silent" is ended; "talking" spoke 0 s ago.
        assert_eq!(site.current().counts.open_sessions, 1);
        assert!(matches!(
            site.upload(node_batch("silent", 2)).await,
            Err(SiteError::SessionClosed(_))
        ));
        let closed_at = site.current().version;
        // Ending it was logged like a robot's close: a restart replays it.
        site.shutdown().await;
        task.await.unwrap();
        let (site, task) = spawn_with(&store, Some(Duration::from_secs(60)))
            .await
            .unwrap();
        assert_eq!(site.current().version, closed_at);
        assert_eq!(site.current().counts.open_sessions, 1);
        // After a restart silence counts from the start: 40 s is not enough, 70 s is.
        let_time_pass(40).await;
        assert_eq!(site.current().counts.open_sessions, 1);
        let_time_pass(30).await;
        assert_eq!(site.current().counts.open_sessions, 0);
        assert_eq!(site.current().version, closed_at + 1);
        site.shutdown().await;
        task.await.unwrap();
    }

    async fn spawn_unloading(
        store: &Arc<dyn MapStore>,
        metrics: &Arc<ServerMetrics>,
        checkpoints: CheckpointOptions,
    ) -> (SiteHandle, JoinHandle<()>) {
        SiteTask::spawn(
            "s",
            LifelongOptions::default(),
            Arc::clone(store),
            Arc::clone(metrics),
            SiteTaskOptions {
                queue_depth: 4,
                session_idle_timeout: None,
                checkpoints,
                unload_after: Some(Duration::from_secs(60)),
            },
        )
        .await
        .unwrap()
    }

    // Reference: issue 34 item 4 — "a site with no open session for a configurable time is dropped
    // from memory and restored from its checkpoint on the next robot or query; the answer waits for
    // the restore".
    #[tokio::test(start_paused = true)]
    async fn an_idle_site_is_unloaded_and_its_next_request_restores_it() {
        // A site mapped without checkpoints: the first unload has to write one.
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let metrics = Arc::new(ServerMetrics::default());
        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DISABLED).await;
        site.open_session("r", "a").await.unwrap();
        site.upload(node_batch("a", 1)).await.unwrap();
        let closed = site.close_session("r", "a").await.unwrap();
        let_time_pass(200).await;
        assert!(site.is_loaded(), "no checkpoints: never unloaded");
        assert!(!site.unload().await.unwrap());
        assert!(store.checkpoint_indexes("s").unwrap().is_empty());
        site.shutdown().await;
        task.await.unwrap();

        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DEFAULT).await;
        let counts = site.current().counts;
        let poses = site.node_poses().await.unwrap();
        assert_eq!(poses.len(), 1);
        assert!(
            site.unload().await.unwrap(),
            "a checkpoint written, then unloaded"
        );
        assert_eq!(store.checkpoint_indexes("s").unwrap(), vec![closed]);
        assert!(!site.is_loaded());
        assert_eq!(site.node_poses().await.unwrap(), poses);
        assert!(site.is_loaded());
        assert_eq!(metrics.site_unloads_and_restores(), (1, 1));
        // An open session keeps the site loaded however long it is silent.
        site.open_session("r", "b").await.unwrap();
        assert!(!site.unload().await.unwrap());
        let_time_pass(200).await;
        assert!(site.is_loaded());
        let closed_b = site.close_session("r", "b").await.unwrap();
        assert_eq!(closed_b, closed + 2);
        let_time_pass(50).await;
        assert!(site.is_loaded(), "idle for 50 s of 60");
        let_time_pass(20).await;
        assert!(!site.is_loaded(), "idle for 70 s of 60");
        assert_eq!(metrics.site_unloads_and_restores(), (2, 1));
        // A checkpoint covering the version is durable, and what lists the site still answers.
        assert_eq!(store.checkpoint_indexes("s").unwrap()[0], closed_b);
        assert_eq!(site.current().version, closed_b);
        let view = site.view();
        assert!(view.unloaded && view.history.is_empty());
        assert_eq!(view.sessions.len(), 2);
        assert_eq!(view.sessions[0].nodes, 1);

        // A read-only query restores it and is answered as before.
        assert_eq!(site.node_poses().await.unwrap(), poses);
        assert!(site.is_loaded());
        assert_eq!(metrics.site_unloads_and_restores(), (2, 2));
        assert_eq!(site.current().version, closed_b);
        assert_eq!(site.current().counts.nodes, counts.nodes);
        assert_eq!(site.current().counts.sessions, 2);
        // Its idle time began again at that query.
        let_time_pass(50).await;
        assert!(site.is_loaded());
        let_time_pass(20).await;
        assert!(!site.is_loaded());
        // A robot's request restores it too, and the versions go on.
        assert!(site.unload().await.unwrap(), "already unloaded");
        let (opened, version) = site.open_session("r", "c").await.unwrap();
        assert!(opened.created);
        assert_eq!(version, closed_b + 1);
        assert!(site.is_loaded());
        assert_eq!(metrics.site_unloads_and_restores(), (3, 3));
        let text = metrics.render(std::slice::from_ref(&site));
        for line in [
            "evermap_sites_loaded 1",
            "evermap_sites_unloaded 0",
            "evermap_site_unloads_total 3",
            "evermap_site_restore_seconds_count 3",
            "evermap_site_loaded{site=\"s\"} 1",
        ] {
            assert!(text.lines().any(|l| l == line), "{line:?} in\n{text}");
        }
        site.shutdown().await;
        task.await.unwrap();
    }

    // Reference: issue 34 — "from a submap finished on a robot to its version in every cache of its
    // site": robots fetch the published version beside the task's queue, and their fetches keep the
    // site as busy as any request.
    #[tokio::test(start_paused = true)]
    async fn robots_fetch_the_published_version_and_their_fetches_keep_the_site_loaded() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let metrics = Arc::new(ServerMetrics::default());
        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DEFAULT).await;
        site.open_session("r", "a").await.unwrap();
        site.upload(node_batch("a", 1)).await.unwrap();
        let closed = site.close_session("r", "a").await.unwrap();
        let published = site
            .view()
            .submaps
            .clone()
            .expect("a loaded site publishes its submaps");
        let delta = site.delta_since(0).await.unwrap();
        assert_eq!(delta.to_version, closed);
        assert_eq!(delta, published.delta_since(0).unwrap());
        assert!(
            site.delta_since(closed + 1).await.is_err(),
            "a version ahead"
        );
        // Fetching every 20 s for 100 s: never idle for the 60 s it takes to unload.
        for _ in 0..5 {
            let_time_pass(20).await;
            assert_eq!(site.delta_since(0).await.unwrap(), delta);
        }
        assert!(site.is_loaded());
        let_time_pass(70).await;
        assert!(!site.is_loaded(), "no fetch for 70 s");
        assert!(
            site.view().submaps.is_none(),
            "an unloaded site publishes no grids"
        );
        // A fetch of an unloaded site waits for its restore, and answers the same.
        assert_eq!(site.delta_since(0).await.unwrap(), delta);
        assert!(site.is_loaded());
        assert_eq!(metrics.site_unloads_and_restores(), (1, 1));
        site.shutdown().await;
        task.await.unwrap();
    }

    // Reference: issue 34 — "one instance holds 500 sites": a site its newest checkpoint covers
    // starts unloaded and publishes what it published when it stopped; its first request restores it.
    #[tokio::test(start_paused = true)]
    async fn a_site_its_checkpoint_covers_starts_unloaded_and_its_first_request_restores_it() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let metrics = Arc::new(ServerMetrics::default());
        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DEFAULT).await;
        assert!(site.is_loaded(), "a new site (no checkpoint) loads");
        site.open_session("r", "a").await.unwrap();
        site.upload(node_batch("a", 1)).await.unwrap();
        let closed = site.close_session("r", "a").await.unwrap();
        let (info, view) = (site.current(), site.view());
        let poses = site.node_poses().await.unwrap();
        // The close's checkpoint is written beside the task; the task's end waits for it.
        site.shutdown().await;
        task.await.unwrap();
        assert_eq!(store.checkpoint_indexes("s").unwrap(), vec![closed]);

        let metrics = Arc::new(ServerMetrics::default());
        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DEFAULT).await;
        assert!(
            !site.is_loaded(),
            "the checkpoint at the session's end covers the log"
        );
        assert_eq!(site.current(), info, "the same version and counts");
        let (started, expected) = (site.view(), view.unloaded());
        assert_eq!(
            started.sessions, expected.sessions,
            "the same sessions, no trajectories"
        );
        assert_eq!(started.version, expected.version);
        assert!(started.unloaded && started.history.is_empty());
        assert_eq!(metrics.site_unloads_and_restores(), (0, 0));
        let text = metrics.render(std::slice::from_ref(&site));
        for line in ["evermap_sites_loaded 0", "evermap_sites_unloaded 1"] {
            assert!(text.lines().any(|l| l == line), "{line:?} in\n{text}");
        }
        assert_eq!(site.node_poses().await.unwrap(), poses);
        assert!(site.is_loaded());
        assert_eq!(metrics.site_unloads_and_restores(), (0, 1));
        assert_eq!(site.current(), info);
        assert_eq!(site.view().sessions, view.sessions, "trajectories back");
        // A robot's request goes on from the restored version; an open session keeps the site loaded
        // at the next start.
        let (_, opened) = site.open_session("r", "b").await.unwrap();
        assert_eq!(opened, closed + 1);
        site.shutdown().await;
        task.await.unwrap();
        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DEFAULT).await;
        assert!(site.is_loaded(), "a session open at the start: loaded");
        let closed_b = site.close_session("r", "b").await.unwrap();
        let info = site.current();
        site.shutdown().await;
        task.await.unwrap();

        // Without unloading every site loads.
        let (site, task) = spawn_with(&store, None).await.unwrap();
        assert!(site.is_loaded());
        assert_eq!(site.current(), info);
        site.shutdown().await;
        task.await.unwrap();

        // No summary (a store from before them): loaded, then unloaded at once, which stores one.
        store
            .delete("s", SUMMARY_KIND, &storage::RecordId::from(SUMMARY_ID))
            .unwrap();
        let metrics = Arc::new(ServerMetrics::default());
        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DEFAULT).await;
        assert!(!site.is_loaded());
        assert_eq!(metrics.site_unloads_and_restores(), (1, 0));
        assert_eq!(site.current(), info);
        assert_eq!(site.current().version, closed_b);
        assert!(
            SiteSummary::usable_at_start(store.as_ref(), "s")
                .unwrap()
                .is_some()
        );
        site.shutdown().await;
        task.await.unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn a_site_with_a_log_after_its_checkpoint_is_loaded_checkpointed_and_unloaded_at_the_start()
     {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let metrics = Arc::new(ServerMetrics::default());
        let (site, task) = spawn_with(&store, None).await.unwrap();
        site.open_session("r", "a").await.unwrap();
        site.upload(node_batch("a", 1)).await.unwrap();
        let closed = site.close_session("r", "a").await.unwrap();
        site.shutdown().await;
        task.await.unwrap();
        // Changes made with checkpoints off (one checkpoint: compaction kept the whole log).
        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DISABLED).await;
        site.open_session("r", "b").await.unwrap();
        let closed_b = site.close_session("r", "b").await.unwrap();
        assert_eq!(closed_b, closed + 2);
        site.shutdown().await;
        task.await.unwrap();
        assert_eq!(store.checkpoint_indexes("s").unwrap(), vec![closed]);

        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DEFAULT).await;
        assert!(!site.is_loaded());
        assert_eq!(store.checkpoint_indexes("s").unwrap()[0], closed_b);
        assert_eq!(site.current().version, closed_b);
        assert_eq!(site.current().counts.sessions, 2);
        let counts = site.current().counts;
        site.shutdown().await;
        task.await.unwrap();
        // And the next start serves it unloaded from its summary.
        let (site, task) = spawn_unloading(&store, &metrics, CheckpointOptions::DEFAULT).await;
        assert!(!site.is_loaded());
        assert_eq!(site.current().counts, counts);
        assert_eq!(site.node_poses().await.unwrap().len(), 1);
        site.shutdown().await;
        task.await.unwrap();
    }

    /// Log lines written by a test's subscriber.
    #[derive(Clone, Default)]
    struct Captured(Arc<std::sync::Mutex<Vec<u8>>>);

    impl std::io::Write for Captured {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            if let Ok(mut captured) = self.0.lock() {
                captured.extend_from_slice(bytes);
            }
            Ok(bytes.len())
        }

        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    // Reference: issue 35 item 6 — a span per site task and per session, not fields on every line.
    #[tokio::test(start_paused = true)]
    async fn the_tasks_lines_run_in_the_sites_span_and_the_sessions_span() {
        let captured = Captured::default();
        let writer = captured.clone();
        // A current-thread runtime: the site task runs on this thread, under this subscriber.
        let _default = tracing::subscriber::set_default(
            tracing_subscriber::fmt()
                .with_env_filter(proto::logging::fallback_filter(
                    tracing_subscriber::filter::LevelFilter::INFO,
                ))
                .with_ansi(false)
                .with_writer(move || writer.clone())
                .finish(),
        );
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let (site, _task) = spawn_with(&store, Some(Duration::from_secs(60)))
            .await
            .unwrap();
        site.open_session("r", "also-silent").await.unwrap();
        let_time_pass(70).await;
        let text = String::from_utf8(captured.0.lock().unwrap().clone()).unwrap();
        let line = |needle: &str| {
            text.lines()
                .find(|l| l.contains(needle))
                .unwrap_or_else(|| panic!("no {needle:?} in\n{text}"))
                .to_owned()
        };
        assert!(
            line("site log replayed").contains("site{site=s}: "),
            "{text}"
        );
        let ended = line("its robot was silent past the idle timeout");
        assert!(
            ended.contains("site{site=s}:session{robot=r session=also-silent}: "),
            "{ended}"
        );
        assert!(
            !ended.contains(" site=s"),
            "no site field repeated: {ended}"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn without_a_timeout_sessions_stay_open() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let (site, _task) = spawn(&store).await.unwrap();
        site.open_session("r", "a").await.unwrap();
        let_time_pass(100).await;
        tokio::time::sleep(Duration::from_secs(1_000_000)).await;
        assert_eq!(site.current().counts.open_sessions, 1);
    }

    #[tokio::test]
    async fn changes_are_logged_and_replayed_with_the_same_versions() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let (site, task) = spawn(&store).await.unwrap();
        let (opened, v1) = site.open_session("r", "a").await.unwrap();
        assert!(opened.created);
        assert_eq!(v1, 1);
        assert_eq!(
            site.open_session("r", "a").await.unwrap().1,
            1,
            "a re-open logs nothing"
        );
        assert_eq!(site.close_session("r", "a").await.unwrap(), 2);
        assert_eq!(site.close_session("r", "a").await.unwrap(), 2, "idempotent");
        site.shutdown().await;
        task.await.unwrap();
        assert_eq!(store.map_version("s").unwrap(), 2);
        assert_eq!(store.scan("s", SITE_LOG_KIND).unwrap().count(), 2);

        let (site, _task) = spawn(&store).await.unwrap();
        assert_eq!(site.current().version, 2);
        assert_eq!(site.current().counts.sessions, 1);
        assert!(matches!(
            site.open_session("intruder", "a").await,
            Err(SiteError::WrongRobot { .. })
        ));
    }

    #[tokio::test]
    async fn a_damaged_log_is_reported_not_used() {
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let mut batch = WriteBatch::new("s");
        batch
            .put(SITE_LOG_KIND, 1_u64, b"not a log entry".to_vec())
            .bump_map_version();
        store.apply(&batch).unwrap();
        let error = spawn(&store).await.err().unwrap();
        assert!(
            matches!(error, SiteError::CorruptEntry { index: 1, .. }),
            "{error}"
        );
        // The decoder's own error stays the source (issue 35 item 6), and in the message as before.
        let source = std::error::Error::source(&error).unwrap();
        assert!(source.is::<prost::DecodeError>(), "{source:?}");
        assert!(error.to_string().ends_with(&source.to_string()), "{error}");

        // A version bumped without its log entry (a lost entry) is caught too.
        let store: Arc<dyn MapStore> = Arc::new(MemStore::new());
        let mut batch = WriteBatch::new("s");
        batch.bump_map_version();
        store.apply(&batch).unwrap();
        assert!(matches!(
            spawn(&store).await,
            Err(SiteError::CorruptLog { .. })
        ));
    }
}
