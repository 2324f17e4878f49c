//! Streaming a prepared session to the server on its recording's clock (phases 2b and 3 of `load`),
//! timing each finished submap from when the robot finished it to the server's acknowledgement.

use std::time::{Duration, Instant};

use proto::UploadItem;
use robot_agent::outbox::Outbox;
use robot_agent::uplink::{GrpcUplink, Uploader};
use tracing::Instrument as _;

use crate::load_fleet::site_id;
use crate::prepared_session::PreparedSession;

/// Nodes per upload batch (a batch holding a finished submap goes at once).
const NODES_PER_BATCH: usize = 10;

/// A finished submap on its way to the fleet.
pub(crate) struct SubmapTiming {
    pub site: usize,
    /// When the robot finished it (on the session's real-time schedule).
    pub finished: Instant,
    /// When the server acknowledged the batch holding it.
    pub acked: Instant,
    /// The site version that batch made.
    pub version: u64,
}

/// What one robot's streaming did.
#[derive(Default)]
pub(crate) struct StreamOutcome {
    pub submaps: Vec<SubmapTiming>,
    pub batches: u64,
    pub failed_flushes: u64,
    pub left_in_outbox: usize,
    /// Largest lag behind the recording's clock when a batch was sent, seconds.
    pub max_lag_s: f64,
    /// When the server acknowledged each batch.
    pub acks: Vec<Instant>,
}

impl StreamOutcome {
    /// Adds the outcome of the robot's next session.
    pub fn add(&mut self, other: Self) {
        self.submaps.extend(other.submaps);
        self.batches += other.batches;
        self.failed_flushes += other.failed_flushes;
        self.left_in_outbox += other.left_in_outbox;
        self.max_lag_s = self.max_lag_s.max(other.max_lag_s);
        self.acks.extend(other.acks);
    }
}

/// The uploader of robot `id`'s session `name` on site number `site`, with an outbox in memory.
pub(crate) fn session_uploader(
    uplink: &GrpcUplink,
    site: usize,
    id: &str,
    name: &str,
) -> anyhow::Result<Uploader<GrpcUplink>> {
    Ok(Uploader::new(
        uplink.clone(),
        Outbox::in_memory(&site_id(site)),
        &site_id(site),
        id,
        &format!("load-{id}-{name}"),
    )?)
}

/// A non-negative, finite number of seconds as a duration (anything else: zero).
pub(crate) fn seconds(s: f64) -> Duration {
    Duration::try_from_secs_f64(s).unwrap_or(Duration::ZERO)
}

/// Streams a prepared session on its recording's clock divided by `speed`, starting at `start`, in
/// the robot session's span.
pub(crate) async fn stream_prepared(
    mut uploader: Uploader<GrpcUplink>,
    session: &PreparedSession,
    site: usize,
    glm_on_server: bool,
    start: Instant,
    speed: f64,
) -> anyhow::Result<StreamOutcome> {
    let span = uploader.session_span();
    async move {
        let mut outcome = StreamOutcome::default();
        tokio::time::sleep_until(start.into()).await;
        let first_time = session.steps.iter().flatten().find_map(|item| match item {
            UploadItem::NodeAdded(node) => Some(node.time),
            _ => None,
        });
        let mut batch: Vec<UploadItem> = Vec::new();
        if let Some(prior) = session.prior {
            batch.push(UploadItem::SessionStartPrior {
                global_from_local: prior,
                glm_on_robot: !glm_on_server,
                at_dock: false,
                fitted: None,
            });
        }
        let mut nodes_in_batch = 0;
        // Finish times of the submaps in the batch being filled.
        let mut finished: Vec<Instant> = Vec::new();
        let send = async |uploader: &mut Uploader<GrpcUplink>,
                          batch: &mut Vec<UploadItem>,
                          finished: &mut Vec<Instant>,
                          outcome: &mut StreamOutcome|
               -> anyhow::Result<()> {
            uploader.enqueue(batch)?;
            outcome.batches += 1;
            batch.clear();
            match uploader.flush().await {
                Ok(stats) => {
                    let acked = Instant::now();
                    outcome.acks.push(acked);
                    for at in finished.drain(..) {
                        outcome.submaps.push(SubmapTiming {
                            site,
                            finished: at,
                            acked,
                            version: stats.map_version,
                        });
                    }
                }
                // Left in the outbox; the next flush sends it (its submaps then go untimed).
                Err(e) if e.is_transient() => {
                    outcome.failed_flushes += 1;
                    finished.clear();
                }
                Err(e) => return Err(e.into()),
            }
            Ok(())
        };
        for step in &session.steps {
            let time = step.iter().find_map(|item| match item {
                UploadItem::NodeAdded(node) => Some(node.time),
                _ => None,
            });
            let due = match (time, first_time) {
                (Some(t), Some(t0)) => start + seconds(t.seconds_since(t0) / speed),
                _ => Instant::now(),
            };
            tokio::time::sleep_until(due.into()).await;
            outcome.max_lag_s = outcome
                .max_lag_s
                .max(Instant::now().saturating_duration_since(due).as_secs_f64());
            let finishes = step
                .iter()
                .filter(|item| matches!(item, UploadItem::SubmapFinished { .. }))
                .count();
            finished.extend(std::iter::repeat_n(due, finishes));
            batch.extend(step.iter().cloned());
            nodes_in_batch += 1;
            if nodes_in_batch >= NODES_PER_BATCH || finishes > 0 {
                send(&mut uploader, &mut batch, &mut finished, &mut outcome).await?;
                nodes_in_batch = 0;
            }
        }
        // Until the recording's end, then the session ends.
        tokio::time::sleep_until((start + seconds(session.duration_s / speed)).into()).await;
        batch.push(UploadItem::SessionEnd);
        send(&mut uploader, &mut batch, &mut finished, &mut outcome).await?;
        let deadline = Instant::now() + Duration::from_secs(120);
        while !uploader.outbox().is_empty()? && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(500)).await;
            if let Err(e) = uploader.flush().await
                && !e.is_transient()
            {
                return Err(e.into());
            }
        }
        outcome.left_in_outbox = uploader.outbox().len()?;
        Ok(outcome)
    }
    .instrument(span)
    .await
}
