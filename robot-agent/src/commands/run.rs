//! `evermap-agent run --config agent.toml`: replays a recording through LLO and streams the result to the
//! fleet map server, following the site's versions into the global submap cache. The session's start is
//! relocalized against that cache and, once placed, the robot runs GLM against it and sends its matches.
//!
//! A run killed mid-session (kill -9, power loss) leaves its session unfinished in the outbox. The next
//! run ends it — delivers what the outbox still holds of it and closes it on the server — before its own
//! session starts relocalizing, so the interrupted trip is in the map it relocalizes against; then it
//! maps a new session. It does not resume the old one: the LLO state that session's nodes and active
//! submaps live in died with the process (see `robot_agent::uplink::Uploader`).
//!
//! The configuration file: [`robot_agent::agent_config::AgentConfig`] (its module docs show one).

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context as _;
use clap::Args;
use mapping::lifelong::RelocalizationOptions;
use rand::RngCore as _;
use robot_agent::agent_config::AgentConfig;
use robot_agent::config_file::load_toml;
use robot_agent::outbox::Outbox;
use robot_agent::ros2_publisher::{PublishStats, Ros2Publisher, odom_from_base_at};
use robot_agent::source::{self, LiveRos2Source, OdometryHistory, Ros2LiveOptions};
use robot_agent::uplink::{
    ClientTls, FleetUplink, GlobalSubmapCache, GrpcUplink, MapUplink as _, SessionInput,
    SessionOptions, SessionStart, Uploader, ZenohUplink, follow_site, session_span,
    stream_session_from,
};
use tracing::Instrument as _;

/// Arguments of `run`.
#[derive(Args)]
pub struct RunArgs {
    /// The agent's TOML configuration (see `robot_agent::agent_config::AgentConfig`).
    #[arg(long)]
    config: PathBuf,
}

/// A random (version 4) UUID.
fn random_uuid() -> String {
    let mut bytes = [0_u8; 16];
    rand::rng().fill_bytes(&mut bytes);
    bytes[6] = (bytes[6] & 0x0f) | 0x40;
    bytes[8] = (bytes[8] & 0x3f) | 0x80;
    let hex = bytes.iter().fold(String::with_capacity(32), |mut hex, b| {
        let _ = write!(hex, "{b:02x}");
        hex
    });
    format!(
        "{}-{}-{}-{}-{}",
        &hex[0..8],
        &hex[8..12],
        &hex[12..16],
        &hex[16..20],
        &hex[20..32]
    )
}

/// Runs the command (the caller has set up logging: `proto::logging::init_logging`).
pub fn run(args: &RunArgs) -> anyhow::Result<()> {
    let config: AgentConfig = load_toml(&args.config)?;
    config
        .validate()
        .with_context(|| format!("invalid configuration {}", args.config.display()))?;
    let (input, live_session) = match &config.ros2 {
        Some(ros2) => {
            let live = LiveRos2Source::open(ros2, ros2.stream_end())?;
            let session = live.session().clone();
            let odometry = live.odometry_history();
            let input = SessionInput::Live(Box::new(live));
            (input, Some((session, ros2.clone(), odometry)))
        }
        None => (
            SessionInput::Recording(Arc::new(
                source::read_recording(&config.source)
                    .with_context(|| format!("cannot read {}", config.source.display()))?,
            )),
            None,
        ),
    };
    let outbox = Outbox::open(&config.outbox_dir, &config.site)
        .with_context(|| format!("cannot open the outbox at {}", config.outbox_dir.display()))?;
    let session_uuid = config.session_uuid.clone().unwrap_or_else(random_uuid);
    let interrupted = outbox.unfinished_sessions()?;
    anyhow::ensure!(
        !interrupted.iter().any(|(s, _)| *s == session_uuid),
        "session {session_uuid:?} was interrupted and cannot be resumed (its LLO state is gone): remove \
         session_uuid from {} (or choose a new one); the next run ends the interrupted session",
        args.config.display()
    );
    // The robot's dock: where its last session in the site ended. It is forgotten while this session
    // runs (the robot is moving; a session that dies leaves no stale dock) and stored again at its end.
    let dock = if config.dock_starts {
        outbox.dock().with_context(|| {
            format!(
                "cannot read the robot's dock from {} (remove its outbox to forget it)",
                config.outbox_dir.display()
            )
        })?
    } else {
        None
    };
    outbox.set_dock(None)?;
    let dock_store = outbox.clone();
    let call_timeout = config.call_timeout()?;
    let retry_interval = config.retry_interval()?;
    let (node_poses, node_pose_receiver) = tokio::sync::mpsc::channel(64);
    let options = SessionOptions {
        node_poses: live_session
            .as_ref()
            .filter(|(_, ros2, _)| ros2.publish.enabled)
            .map(|_| node_poses),
        nodes_per_batch: config.nodes_per_batch,
        replay_speed: config.replay_speed,
        max_scans: config.max_scans,
        retry_interval,
        final_flush_timeout: config.final_flush_timeout()?,
        local: config.local.clone(),
        ..SessionOptions::default()
    };
    // Everything from here on is this robot session's: its lines name it through the span (entered
    // on this thread, which polls the session's future in `block_on`; the tasks it spawns carry it).
    let span = session_span(&config.site, &config.robot_id, &session_uuid);
    let _in_session = span.enter();
    tracing::info!(
        pending = outbox.len()?,
        interrupted = interrupted.len(),
        "starting session"
    );
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .thread_name("evermap-agent")
        .build()?;
    runtime.block_on(async {
        let uplink = if let Some(zenoh) = &config.zenoh {
            FleetUplink::Zenoh(
                ZenohUplink::connect(zenoh, &config.site, &config.token, call_timeout).await?,
            )
        } else {
            let tls = match &config.tls_ca_pem {
                Some(path) => Some(ClientTls {
                    ca_pem: std::fs::read(path)
                        .with_context(|| format!("cannot read {}", path.display()))?,
                    domain: config.tls_domain.clone(),
                }),
                None => None,
            };
            FleetUplink::Grpc(Box::new(GrpcUplink::with_tls(
                &config.server_url,
                &config.site,
                &config.token,
                config.max_message_bytes,
                call_timeout,
                tls.as_ref(),
            )?))
        };
        tracing::info!(transport = uplink.transport(), "uplink ready");
        let cache = Arc::new(Mutex::new(GlobalSubmapCache::default()));
        let (stop, stopped) = tokio::sync::watch::channel(false);
        let follower = tokio::spawn(
            follow_site(uplink.clone(), Arc::clone(&cache), stopped, retry_interval)
                .in_current_span(),
        );
        let mut uploader = Uploader::new(
            uplink,
            outbox,
            &config.site,
            &config.robot_id,
            &session_uuid,
        )?;
        end_interrupted(&mut uploader, call_timeout, retry_interval).await?;
        // Relocalize the session's start against the site map (and run GLM on the robot from there), once
        // the cache has caught up with the server; with no server or an empty site, map without a prior.
        let mut probe = uploader.uplink_mut().clone();
        if let Ok(Ok(version)) = tokio::time::timeout(call_timeout, probe.map_version()).await {
            let deadline = tokio::time::Instant::now() + call_timeout;
            while cache.lock().map_or(0, |c| c.version()) < version
                && tokio::time::Instant::now() < deadline
            {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }
        let start = SessionStart {
            cache: &cache,
            relocalization: RelocalizationOptions::default(),
            session_start: mapping::lifelong::SessionStartOptions::default(),
            dock,
        };
        let map_publisher = match live_session {
            Some((session, ros2, odometry)) if ros2.publish.enabled => Some(tokio::spawn(
                publish_to_ros2(
                    session,
                    ros2,
                    Arc::clone(&cache),
                    (node_pose_receiver, odometry),
                    stop.subscribe(),
                )
                .in_current_span(),
            )),
            _ => None,
        };
        let (report, trace) =
            stream_session_from(input, &options, &mut uploader, Some(start)).await?;
        // The dock is where the server put the session's end (the base session's too, which the robot
        // never had to place); the robot's own estimate only if the end was not acknowledged.
        let end = uploader
            .session_end()
            .map_or_else(|| trace.end_pose(), |ended| ended.pose);
        dock_store.set_dock(end)?;
        tracing::info!(
            relocalized = trace.prior.is_some(),
            from_dock = dock.is_some(),
            dock_outcome = ?trace.dock,
            score = trace.score,
            glm_on_robot = trace.glm_on_robot,
            glm_matches = trace.glm_matches,
            "session start relocalization and GLM on the robot"
        );
        let _ = stop.send(true);
        let _ = follower.await;
        if let Some(task) = map_publisher {
            match task.await {
                Ok(Ok(stats)) => tracing::info!(
                    maps = stats.map_versions,
                    poses = stats.poses,
                    failed = stats.failed,
                    "published on ROS 2"
                ),
                Ok(Err(e)) => tracing::warn!("ROS 2 map publisher: {e:#}"),
                Err(e) => tracing::warn!("ROS 2 map publisher task: {e}"),
            }
        }
        let (version, submaps) = cache
            .lock()
            .map(|c| (c.version(), c.submaps().len()))
            .unwrap_or_default();
        tracing::info!(
            scans = report.llo.scans,
            nodes = report.llo.nodes,
            submaps_finished = report.llo.submaps_finished,
            batches = report.batches,
            applied = report.applied,
            failed_flushes = report.failed_flushes,
            map_version = report.map_version,
            left_in_outbox = report.left_in_outbox,
            cache_version = version,
            cached_submaps = submaps,
            "session done"
        );
        anyhow::ensure!(
            report.left_in_outbox == 0,
            "{} batches are still in the outbox: run again to deliver them",
            report.left_in_outbox
        );
        anyhow::Ok(())
    })
}

/// With `[ros2]`: publishes on ROS 2 (see `robot_agent::ros2_publisher`) the site map
/// (`nav_msgs/msg/OccupancyGrid`) each time the cache reaches a new version, and each node's global pose
/// as the robot estimates it (`PoseWithCovarianceStamped`, and `map -> odom` on `/tf` from the odometry
/// at the node's stamp), until `stop`.
async fn publish_to_ros2(
    session: zenoh::Session,
    ros2: Ros2LiveOptions,
    cache: Arc<Mutex<GlobalSubmapCache>>,
    (mut poses, odometry): (
        tokio::sync::mpsc::Receiver<(mapping::sensor::Timestamp, mapping::geometry::Rigid2)>,
        OdometryHistory,
    ),
    mut stop: tokio::sync::watch::Receiver<bool>,
) -> anyhow::Result<PublishStats> {
    let publisher = {
        let (session, ros2) = (session.clone(), ros2.clone());
        tokio::task::spawn_blocking(move || {
            Ros2Publisher::open(&session, ros2.domain_id, &ros2.publish)
        })
        .await??
    };
    let publisher = Arc::new(Mutex::new(publisher));
    let mut published_version = 0;
    let mut tick = tokio::time::interval(Duration::from_millis(500));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let stats = |publisher: &Arc<Mutex<Ros2Publisher>>| {
        publisher.lock().map(|p| p.stats()).unwrap_or_default()
    };
    loop {
        let pose = tokio::select! {
            _ = tick.tick() => None,
            Some(pose) = poses.recv() => Some(pose),
            _ = stop.changed() => return Ok(stats(&publisher)),
        };
        let (cache, publisher) = (Arc::clone(&cache), Arc::clone(&publisher));
        if let Some((stamp, map_from_base)) = pose {
            let odometry = Arc::clone(&odometry);
            tokio::task::spawn_blocking(move || {
                let map_from_odom = odometry
                    .lock()
                    .ok()
                    .and_then(|h| odom_from_base_at(&h, stamp))
                    .map(|odom_from_base| map_from_base * odom_from_base.inverse());
                if let Ok(mut publisher) = publisher.lock() {
                    publisher.publish_pose(stamp, &map_from_base, map_from_odom.as_ref());
                }
            })
            .await?;
            continue;
        }
        let version = cache.lock().map_or(0, |c| c.version());
        let resolution = ros2.publish.map_resolution_m;
        let stamp = mapping::sensor::Timestamp(
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX)),
        );
        let fresh = version > published_version;
        tokio::task::spawn_blocking(move || {
            let Ok(mut publisher) = publisher.lock() else {
                return;
            };
            if fresh {
                let grids: Vec<_> = cache
                    .lock()
                    .map(|c| {
                        c.submaps()
                            .values()
                            .map(|s| (s.global_pose * s.local_pose.inverse(), Arc::clone(&s.grid)))
                            .collect()
                    })
                    .unwrap_or_default();
                let map = mapping::lifelong::render_submaps_max(
                    grids
                        .iter()
                        .map(|(global_from_grid, grid)| mapping::lifelong::PlacedGrid {
                            global_from_grid: *global_from_grid,
                            grid,
                        }),
                    resolution,
                );
                if let Some(map) = map {
                    publisher.publish_map(&map, stamp);
                }
            } else {
                publisher.republish_map_if_due();
            }
        })
        .await?;
        if fresh {
            published_version = version;
        }
    }
}

/// Ends the sessions an earlier run left unfinished (see the module docs), retrying for up to `patience`
/// while the server is unreachable; after that the session's own flushes keep trying.
async fn end_interrupted<U: robot_agent::uplink::MapUplink>(
    uploader: &mut Uploader<U>,
    patience: Duration,
    retry_interval: Duration,
) -> anyhow::Result<()> {
    let deadline = tokio::time::Instant::now() + patience;
    loop {
        let interrupted = uploader.interrupted_sessions()?;
        if interrupted.is_empty() {
            return Ok(());
        }
        match uploader.flush().await {
            Ok(stats) => {
                // A successful flush ends every interrupted session.
                tracing::info!(
                    ended = stats.interrupted_ended,
                    delivered = stats.applied,
                    dropped = stats.dropped_after_server_end,
                    "interrupted sessions of an earlier run ended"
                );
                return Ok(());
            }
            Err(e) if e.is_transient() => {
                if tokio::time::Instant::now() >= deadline {
                    tracing::warn!(
                        sessions = interrupted.len(),
                        "cannot end the interrupted sessions yet ({e}): retrying while mapping"
                    );
                    return Ok(());
                }
                tokio::time::sleep(retry_interval).await;
            }
            Err(e) => return Err(e.into()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_uuids_are_version_4_and_differ() {
        let uuid = random_uuid();
        assert_eq!(uuid.len(), 36);
        assert_eq!(&uuid[14..15], "4");
        assert_ne!(uuid, random_uuid());
    }
}
