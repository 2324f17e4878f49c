use proto::UploadBatch;
use storage::{MemStore, WriteBatch};

use super::*;
use crate::site::site_summary::{SUMMARY_ID, SUMMARY_KIND};

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
async fn a_site_with_a_log_after_its_checkpoint_is_loaded_checkpointed_and_unloaded_at_the_start() {
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
