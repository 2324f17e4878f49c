//! One mapping session of a robot: LLO on a recording, batched into the durable uploader; and following
//! the site's versions into the global submap cache.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mapping::local_slam::LocalTrajectoryBuilderOptions;
use proto::UploadItem;
use tokio::sync::{mpsc, watch};
use tokio_stream::StreamExt as _;

use super::{GlobalSubmapCache, LloStats, MapUplink, UplinkError, Uploader, run_llo};
use crate::source::Recording;

/// How a session streams.
#[derive(Clone, Debug)]
pub struct SessionOptions {
    /// Nodes per upload batch (at least 1).
    pub nodes_per_batch: usize,
    /// Recording pace: multiple of real time; 0 = as fast as possible.
    pub replay_speed: f64,
    /// Stop after this many scans (all when `None`).
    pub max_scans: Option<usize>,
    /// Pause between flush attempts while the server is unreachable.
    pub retry_interval: Duration,
    /// After the recording ends, how long to keep retrying until everything is acknowledged.
    pub final_flush_timeout: Duration,
    /// LLO settings.
    pub local: LocalTrajectoryBuilderOptions,
}

impl Default for SessionOptions {
    fn default() -> Self {
        Self {
            nodes_per_batch: 10,
            replay_speed: 1.0,
            max_scans: None,
            retry_interval: Duration::from_millis(500),
            final_flush_timeout: Duration::from_secs(60),
            local: LocalTrajectoryBuilderOptions::default(),
        }
    }
}

/// What a session did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SessionReport {
    /// LLO's figures.
    pub llo: LloStats,
    /// Batches made.
    pub batches: u64,
    /// Flushes that failed transiently (link or server down) and were retried.
    pub failed_flushes: u64,
    /// Batches applied by the server.
    pub applied: usize,
    /// Site version after the last acknowledgement.
    pub map_version: u64,
    /// Batches still in the outbox at the end (0 unless the final flush timed out).
    pub left_in_outbox: usize,
}

/// Why a session stopped early.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The server refused something for good.
    #[error(transparent)]
    Uplink(#[from] UplinkError),
    /// The LLO thread could not be started or panicked.
    #[error("LLO thread: {0}")]
    Llo(String),
}

/// Runs LLO over `recording` on a named thread and streams its output through `uploader` in batches of
/// `nodes_per_batch` nodes, ending with `SessionEnd`. Transient failures are retried while LLO goes on
/// (the outbox keeps everything); after the recording, flushing is retried for up to
/// `final_flush_timeout`. A permanent refusal stops the session with an error.
pub async fn stream_recording<U: MapUplink>(
    recording: Arc<Recording>,
    options: &SessionOptions,
    uploader: &mut Uploader<U>,
) -> Result<SessionReport, SessionError> {
    let (sender, mut receiver) = mpsc::channel::<Vec<UploadItem>>(64);
    let llo_options = options.local.clone();
    let (speed, max_scans) = (options.replay_speed, options.max_scans);
    let llo = std::thread::Builder::new()
        .name("llo".into())
        .spawn(move || {
            run_llo(&recording, &llo_options, speed, max_scans, &mut |items| {
                sender.blocking_send(items).is_ok()
            })
        })
        .map_err(|e| SessionError::Llo(e.to_string()))?;

    let mut report = SessionReport::default();
    let mut batch: Vec<UploadItem> = Vec::new();
    let mut nodes_in_batch = 0;
    let mut retry = tokio::time::interval(options.retry_interval);
    retry.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut backlog = false;
    let flush = async |uploader: &mut Uploader<U>,
                       report: &mut SessionReport|
           -> Result<bool, UplinkError> {
        match uploader.flush().await {
            Ok(stats) => {
                report.applied += stats.applied;
                report.map_version = stats.map_version;
                Ok(false)
            }
            Err(e) if e.is_transient() => {
                report.failed_flushes += 1;
                Ok(true)
            }
            Err(e) => Err(e),
        }
    };
    loop {
        tokio::select! {
            items = receiver.recv() => {
                let Some(items) = items else { break };
                nodes_in_batch += 1;
                batch.extend(items);
                if nodes_in_batch >= options.nodes_per_batch.max(1) {
                    uploader.enqueue(&batch)?;
                    report.batches += 1;
                    batch.clear();
                    nodes_in_batch = 0;
                    backlog = flush(uploader, &mut report).await?;
                }
            }
            _ = retry.tick(), if backlog => {
                backlog = flush(uploader, &mut report).await?;
            }
        }
    }
    report.llo = llo
        .join()
        .map_err(|_| SessionError::Llo("the LLO thread panicked".into()))?;
    batch.push(UploadItem::SessionEnd);
    uploader.enqueue(&batch)?;
    report.batches += 1;
    let deadline = Instant::now() + options.final_flush_timeout;
    while flush(uploader, &mut report).await? {
        if Instant::now() >= deadline {
            break;
        }
        tokio::time::sleep(options.retry_interval).await;
    }
    report.left_in_outbox = uploader.outbox().len().map_err(UplinkError::from)?;
    Ok(report)
}

/// Keeps `cache` at the site's latest version until `stop` turns true: watches versions and, for each
/// one newer than the cache, fetches the delta since the cache's version. After a broken link it
/// reconnects every `retry_interval` and catches up by delta (not by re-reading the whole map).
pub async fn follow_site<U: MapUplink>(
    mut uplink: U,
    cache: Arc<Mutex<GlobalSubmapCache>>,
    mut stop: watch::Receiver<bool>,
    retry_interval: Duration,
) {
    let cached = |cache: &Arc<Mutex<GlobalSubmapCache>>| cache.lock().map_or(0, |c| c.version());
    while !*stop.borrow() {
        let Ok(mut versions) = uplink.watch_versions().await else {
            tokio::select! {
                () = tokio::time::sleep(retry_interval) => continue,
                _ = stop.changed() => return,
            }
        };
        loop {
            let next = tokio::select! {
                next = versions.next() => next,
                _ = stop.changed() => return,
            };
            let Some(Ok(version)) = next else { break };
            if version <= cached(&cache) {
                continue;
            }
            match uplink.delta_since(cached(&cache)).await {
                Ok(delta) => {
                    if let Ok(mut cache) = cache.lock() {
                        // A delta from an older base is harmless; one from a newer base cannot happen.
                        let _ = cache.apply(delta);
                    }
                }
                Err(_) => break,
            }
        }
    }
}
