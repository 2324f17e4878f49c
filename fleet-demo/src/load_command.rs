//! `evermap-demo load`: the fleet load benchmark. N simulated robots stream cleaning sessions at real
//! time (or `--speed` times faster) into one map server (sled, loopback gRPC) spread over several sites,
//! while every robot follows its site's versions; measures what the fleet issue asks for: server CPU and
//! memory, uplink bytes per robot-second, the latency from a submap being finished on a robot to its
//! version reaching every robot of the site, and the catch-up (time and bytes) of a robot that was
//! offline for the whole run. A soak (`--duration-s 1800 --session-s 300`): each robot streams sessions
//! back to back, and the report gets the figures of every minute of robot time ([`crate::minute_figures`]:
//! memory, median and p95 latency, throughput; the slopes after the warm-up) and `minutes.png`.
//!
//! Phases:
//! 1. *Mapping* (not measured): robot 0 of every site maps its store (session 0: the whole sweep of the
//!    demo's 48 × 30 m store unless capped by `--mapping-duration-s`), streamed as fast as the server
//!    takes it.
//! 2. *Preparation* (not measured): every robot's cleaning sessions (one, or `--duration-s` over
//!    `--session-s` of them, each on a later simulated day) are simulated and run through LLO ahead of
//!    time, and the robot's session start (`SessionStart`, as in `demo`) places each against the robot's
//!    cache of the site map from its first nodes; the placement goes with the session's first batch, as
//!    if decided at once (a streaming robot holds its nodes back until it is). Robots run LLO on their
//!    own CPUs; doing it ahead keeps the 50 robots' LLO off the server's two cores, so the figures are
//!    the server's. The prepared sessions stay
//!    in memory until the end, so memory growth during the measured phase is the server's (and its
//!    clients').
//!    With `--mature-sessions K`, K more sessions per robot are prepared, on earlier days, and streamed
//!    as fast as the server takes them before the measured window (not measured): the soak then starts
//!    from sites that have had K sessions per robot, as a server in production holds them, instead of
//!    fresh maps still filling their one layer of later submaps.
//! 3. *Streaming* (measured): every robot replays its LLO output on the recording's clock, divided by
//!    `--speed` (10 nodes per batch, and a batch is sent at once when it holds a finished submap), its
//!    sessions back to back, starts staggered over 2 s. If the server falls behind, uploads wait and the
//!    delay shows up in the latency.
//!
//! The robots' outboxes are in memory here (one sled per robot would put 50 databases' I/O on the
//! server's disk, which a real robot keeps on its own); the server's store is sled, as deployed.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use clap::Args;
use robot_agent::map_image;
use robot_agent::process_stats::{cpu_seconds, current_rss_mb, peak_rss_mb};
use serde_json::json;
use simulator::{Store, World};

use crate::catch_up::catch_up_since;
use crate::command_runtime::{block_on, recreate_dir};
use crate::idle_sites::{self, IdleProbe};
use crate::load_fleet::{Fleet, site_id};
use crate::memory_attribution::MemoryAttribution;
use crate::minute_figures::{self, MinuteInputs, MinuteSample};
use crate::prepared_session::{Prepared, PreparedSession, prepare_sessions, session_lengths};
use crate::prepared_stream::{StreamOutcome, seconds, session_uploader, stream_prepared};
use crate::site_growth::{half_life_version, site_growth_until, site_sizes};
use crate::submap_latency::SubmapLatencies;

/// Robot time per wall-clock time of the unmeasured maturing sessions: as fast as the server takes them.
const MATURING_SPEED: f64 = 1e4;

/// Arguments of `load`.
#[derive(Args)]
pub struct LoadArgs {
    /// Output folder (deleted and recreated): `data/` (the server's sled), `report.json` and
    /// `submap_latencies.csv` (one line per finished submap: when, its site and version, its latencies).
    #[arg(long, default_value = "out/load")]
    pub(crate) out: PathBuf,
    /// Robots streaming at once, spread evenly over the sites.
    #[arg(long, default_value_t = 50)]
    pub(crate) agents: usize,
    /// Sites (stores), each with its own simulated store and map.
    #[arg(long, default_value_t = 10)]
    pub(crate) sites: usize,
    /// Seconds of robot time each robot streams (the measured window), 10..=3600.
    #[arg(long, default_value_t = 120.0)]
    pub(crate) duration_s: f64,
    /// Length of each cleaning session, seconds of robot time (30..=300): a robot streams
    /// ceil(duration / session) sessions back to back, each on a later simulated day. Default: one
    /// session of `--duration-s` (at most 300 s).
    #[arg(long)]
    pub(crate) session_s: Option<f64>,
    /// Robot time per wall-clock time (0.1..=20): 1 streams at real time, 10 replays ten minutes of robot
    /// time in one minute (the server then gets ten times the load of the same fleet).
    #[arg(long, default_value_t = 1.0)]
    pub(crate) speed: f64,
    /// Cap on each site's mapping session 0, seconds of simulated time (default: the whole sweep of the
    /// store, as in `demo`).
    #[arg(long)]
    pub(crate) mapping_duration_s: Option<f64>,
    /// Seed of the stores and routes (site `s` uses `seed + s`).
    #[arg(long, default_value_t = 1)]
    pub(crate) seed: u64,
    /// Which simulated world each site is, at the demo's 48 × 30 m: `store` (a realistic supermarket)
    /// or `aisles` (identical shelf rows, adversarial).
    #[arg(long, value_enum, default_value_t = World::Store)]
    pub(crate) world: World,
    /// The server's sled page cache, MiB, 1..=65536 (the server's `[storage] cache_capacity_bytes`;
    /// default its default, 256 MiB).
    #[arg(long, default_value_t = 256)]
    pub(crate) store_cache_mib: u64,
    /// Let the server run GLM for every node (the design before GLM moved onto the robots) instead of
    /// the robots sending their own matches.
    #[arg(long)]
    pub(crate) glm_on_server: bool,
    /// Sessions each robot streams before the measured window, as fast as the server takes them (not
    /// measured; default 0): the sites start the soak with the map a store has after that many
    /// cleaning days instead of a fresh one. A fresh site's map grows until the fresh submaps over its
    /// routes form one layer (here about 4 sessions of 300 s per site; about a dozen of 120 s in the
    /// lifelong experiment); a server in production mostly holds sites past that. At most 100 (issue 34's
    /// site age).
    #[arg(long, default_value_t = 0)]
    pub(crate) mature_sessions: usize,
    /// Run the server without site checkpoints (`[checkpoints] enabled = false`): the store keeps its
    /// whole log and a restart replays it (the figure checkpoints are compared with).
    #[arg(long)]
    pub(crate) no_checkpoints: bool,
    /// Wall-clock seconds over which the robots start their first session, evenly spread (0..=3600).
    /// At the default every robot's sessions start and end within 2 s of each other's — the worst case:
    /// every site ends its sessions, and LLO finishes every robot's last submaps, in the same second. A
    /// fleet whose robots start cleaning at different times is a spread of a session's length or more.
    #[arg(long, default_value_t = 2.0)]
    pub(crate) start_spread_s: f64,
    /// A sled store of other sites (hundreds of copies of mapped ones: `scripts/clone_sites.sh`) that the
    /// server opens instead of a fresh `data/` and serves beside the load's sites: they start unloaded
    /// and stay idle but for `--idle-probes` requests (issue 34: 500 sites on one instance, 40 active).
    /// The load's sites are written into it: give a copy. Default none.
    #[arg(long)]
    pub(crate) idle_store: Option<PathBuf>,
    /// With `--idle-store`: requests to idle sites during the measured phase, one at a time, spread
    /// evenly over it, each to another site and timed (how long an unloaded site takes to answer while
    /// the active ones stream). 0..=1000.
    #[arg(long, default_value_t = 10)]
    pub(crate) idle_probes: usize,
}

/// Runs the command.
pub fn run(args: &LoadArgs) -> anyhow::Result<()> {
    anyhow::ensure!(args.sites >= 1, "--sites must be at least 1");
    anyhow::ensure!(
        (1..=65_536).contains(&args.store_cache_mib),
        "--store-cache-mib must be in 1..=65536"
    );
    anyhow::ensure!(
        args.agents >= args.sites && args.agents <= 500,
        "--agents must be between --sites and 500"
    );
    anyhow::ensure!(
        args.duration_s.is_finite() && (10.0..=3600.0).contains(&args.duration_s),
        "--duration-s must be in 10..=3600"
    );
    anyhow::ensure!(
        args.session_s
            .is_none_or(|s| s.is_finite() && (30.0..=300.0).contains(&s)),
        "--session-s must be in 30..=300"
    );
    anyhow::ensure!(
        args.speed.is_finite() && (0.1..=20.0).contains(&args.speed),
        "--speed must be in 0.1..=20"
    );
    anyhow::ensure!(
        args.mapping_duration_s
            .is_none_or(|d| d.is_finite() && d >= 30.0),
        "--mapping-duration-s must be at least 30"
    );
    anyhow::ensure!(
        args.mature_sessions <= 100,
        "--mature-sessions must be at most 100"
    );
    anyhow::ensure!(
        args.start_spread_s.is_finite() && (0.0..=3600.0).contains(&args.start_spread_s),
        "--start-spread-s must be in 0..=3600"
    );
    anyhow::ensure!(
        args.idle_probes <= 1000,
        "--idle-probes must be at most 1000"
    );
    if let Some(store) = &args.idle_store {
        anyhow::ensure!(
            store.is_dir(),
            "--idle-store {}: no store there (make one with scripts/clone_sites.sh)",
            store.display()
        );
    }
    block_on(load(args))
}

async fn load(args: &LoadArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    recreate_dir(&args.out)?;
    let mut fleet = Fleet::start(args).await?;
    let worlds: Vec<Store> = (0..args.sites)
        .map(|s| Store::generate(args.world.demo_options(), args.seed + s as u64))
        .collect::<Result<_, _>>()?;

    // 1. Every site's robot 0 maps its store.
    eprintln!("phase 1/3: mapping {} stores", args.sites);
    fleet
        .map_stores(&worlds, args.mapping_duration_s.unwrap_or(0.0))
        .await?;
    eprintln!(
        "  mapped in {:.0} s; site versions {:?}",
        started.elapsed().as_secs_f64(),
        fleet.site_versions(args.sites)
    );

    // 2. LLO and the session start of every cleaning session, ahead of time.
    let session_plan = session_lengths(args.duration_s, args.session_s);
    let CleaningSessions {
        measured: prepared,
        maturing,
        glm_matches,
        placed,
        data_seconds,
    } = prepare_cleaning_sessions(args, &fleet, &worlds, &session_plan).await?;

    // 2b. Not measured: the sites mature.
    let maturing_growth = if args.mature_sessions > 0 {
        mature_sites(args, &fleet, maturing).await?
    } else {
        Vec::new()
    };

    // 3. Measured: everyone streams at real time.
    eprintln!(
        "phase 3/3: {} robots stream {} s of robot time each ({} session(s)) at {}x real time",
        fleet.robots.len(),
        args.duration_s,
        session_plan.len(),
        args.speed
    );
    // Validated in `run`: 10..=3600 s of robot time at 0.1..=20× real time.
    let measured_wall =
        Duration::try_from_secs_f64(args.duration_s / args.speed).unwrap_or(Duration::ZERO);
    let idle_probes = spawn_idle_probes(args, &fleet, measured_wall);
    let window = stream_measured(args, &mut fleet, prepared).await?;
    let idle_probes = match idle_probes {
        Some(task) => task.await.context("idle probes task")??,
        None => Vec::new(),
    };
    let metrics = Arc::clone(fleet.server.metrics());

    let catch_up = catch_up_after_half_life(&fleet, &metrics, &maturing_growth).await?;
    let resync = resync_after_offline(&fleet, &metrics, &window).await?;

    let latencies = SubmapLatencies::measure(&window.outcomes, &fleet.robots, window.started);
    let per_minute = minute_report(args, &window, &latencies)?;
    let sites = final_site_counts(&fleet, args.sites);
    let outcomes = &window.outcomes;
    let report = json!({
        "world": args.world.name(),
        "agents": args.agents,
        "glm": if args.glm_on_server { "server" } else { "robot" },
        "robot_glm_matches": glm_matches,
        "sites": args.sites,
        "duration_s": args.duration_s,
        "session_s": session_plan.first(),
        "sessions_per_robot": session_plan.len(),
        "mature_sessions_per_robot": args.mature_sessions,
        "start_spread_s": args.start_spread_s,
        "speed": args.speed,
        "streaming_wall_s": window.streaming_s,
        "measured_wall_s": window.measured_s,
        "sessions_placed": placed,
        "server_process": {
            "cpu_s": window.cpu_s,
            "cores_busy": window.cpu_s.map(|c| c / window.measured_s),
            "peak_rss_mb": peak_rss_mb(),
            "final_rss_mb": current_rss_mb(),
            "note": "one process: server, the robots' replay and gRPC clients, the followers, and the prepared sessions (allocated before the measured phase)",
        },
        "uplink_bytes": window.bytes_in,
        "uplink_bytes_per_robot_second": window.bytes_in as f64 / data_seconds.max(1e-9),
        "downlink_bytes": window.bytes_out,
        "downlink_bytes_per_robot_second": window.bytes_out as f64 / data_seconds.max(1e-9),
        "backend_runs": window.pgr_runs,
        "backend_mean_ms": window.pgr_mean_ms,
        "deepest_site_queue": window.deepest_site_queue,
        "batches": outcomes.iter().map(|o| o.batches).sum::<u64>(),
        "failed_flushes": outcomes.iter().map(|o| o.failed_flushes).sum::<u64>(),
        "left_in_outboxes": outcomes.iter().map(|o| o.left_in_outbox).sum::<usize>(),
        "max_lag_behind_real_time_s": outcomes.iter().map(|o| o.max_lag_s).fold(0.0, f64::max),
        "submap_latency_s": latencies.report(),
        "resync_after_offline": resync,
        "catch_up_after_half_the_sites_life": catch_up,
        "idle_sites": idle_report(&fleet, &idle_probes),
        "per_minute_of_robot_time": per_minute,
        "sites_final": sites,
        "maturing_growth": maturing_growth,
        "robot_data_s": data_seconds,
        "wall_time_s": started.elapsed().as_secs_f64(),
    });
    std::fs::write(
        args.out.join("submap_latencies.csv"),
        latencies.csv_lines.join("\n") + "\n",
    )
    .context("writing submap_latencies.csv")?;
    let path = args.out.join("report.json");
    std::fs::write(&path, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", path.display()))?;
    fleet.server.shutdown().await?;
    print_summary(args, &report, &path);
    Ok(())
}

/// The cleaning sessions of every robot, simulated with LLO and their session start ahead of time.
struct CleaningSessions {
    /// Per robot, the sessions streamed in the measured phase.
    measured: Vec<Vec<PreparedSession>>,
    /// Per robot, the maturing sessions streamed before it (not measured).
    maturing: Vec<Vec<PreparedSession>>,
    /// GLM matches the robots found ahead of time.
    glm_matches: u64,
    /// Measured sessions placed at their start.
    placed: usize,
    /// Robot time of the measured sessions, seconds.
    data_seconds: f64,
}

/// Phase 2: LLO and the session start of every robot's sessions (`--mature-sessions` maturing ones on
/// the robots' earlier days, as long as the measured ones, then `session_plan`), ahead of time.
async fn prepare_cleaning_sessions(
    args: &LoadArgs,
    fleet: &Fleet,
    worlds: &[Store],
    session_plan: &[f64],
) -> anyhow::Result<CleaningSessions> {
    eprintln!(
        "phase 2/3: LLO of the cleaning sessions of {} robots ahead of time",
        fleet.robots.len()
    );
    let prepare_started = Instant::now();
    let lengths: Vec<f64> = std::iter::repeat_n(session_plan[0], args.mature_sessions)
        .chain(session_plan.iter().copied())
        .collect();
    let Prepared {
        sessions: mut prepared,
        glm_matches,
    } = prepare_sessions(
        &fleet.robots,
        worlds,
        &lengths,
        args.agents.div_ceil(args.sites),
        args.glm_on_server,
    )
    .await?;
    let maturing: Vec<Vec<PreparedSession>> = prepared
        .iter_mut()
        .map(|sessions| sessions.drain(..args.mature_sessions).collect())
        .collect();
    let sessions = || prepared.iter().flatten();
    let placed = sessions().filter(|p| p.prior.is_some()).count();
    let data_seconds: f64 = sessions().map(|p| p.duration_s).sum();
    eprintln!(
        "  prepared in {:.0} s: {} nodes, {placed}/{} sessions placed at their start, {}",
        prepare_started.elapsed().as_secs_f64(),
        sessions().map(|p| p.steps.len()).sum::<usize>(),
        sessions().count(),
        if args.glm_on_server {
            "GLM on the server".to_owned()
        } else {
            format!("{glm_matches} GLM matches found on the robots")
        }
    );
    Ok(CleaningSessions {
        measured: prepared,
        maturing,
        glm_matches,
        placed,
        data_seconds,
    })
}

/// With `--idle-store` and `--idle-probes`, the task that probes the idle sites over the measured
/// phase (`measured_wall` of wall time), each probe noting whether its site was unloaded.
fn spawn_idle_probes(
    args: &LoadArgs,
    fleet: &Fleet,
    measured_wall: Duration,
) -> Option<tokio::task::JoinHandle<anyhow::Result<Vec<IdleProbe>>>> {
    (!fleet.idle_sites.is_empty() && args.idle_probes > 0).then(|| {
        let handles: BTreeMap<String, server::site::SiteHandle> = fleet
            .idle_sites
            .iter()
            .filter_map(|s| Some((s.id.clone(), fleet.server.site(&s.id)?.clone())))
            .collect();
        tokio::spawn(idle_sites::probe_idle_sites(
            fleet.url.clone(),
            fleet.idle_sites.clone(),
            args.idle_probes,
            measured_wall / u32::try_from(args.idle_probes + 1).unwrap_or(u32::MAX),
            move |site| handles.get(site).is_some_and(|h| !h.is_loaded()),
        ))
    })
}

/// Site 0's robot last seen halfway through the site's life (its session count then half of what it is
/// now, from the maturing samples) catches up: one delta holding every submap changed since (`null`
/// without maturing sessions).
async fn catch_up_after_half_life(
    fleet: &Fleet,
    metrics: &server::ServerMetrics,
    maturing_growth: &[serde_json::Value],
) -> anyhow::Result<serde_json::Value> {
    let Some((sessions_then, from_version)) = half_life_version(maturing_growth) else {
        return Ok(serde_json::Value::Null);
    };
    let caught = catch_up_since(fleet.robots[0].uplink.clone(), metrics, from_version).await?;
    let sessions_now = fleet
        .server
        .site(&site_id(0))
        .map_or(0, |h| h.current().counts.sessions);
    Ok(json!({
        "site": site_id(0),
        "sessions_missed": sessions_now.saturating_sub(sessions_then),
        "from_version": from_version,
        "to_version": caught.delta.to_version,
        "submaps_added": caught.delta.submaps_added.len(),
        "trimmed": caught.delta.trimmed.len(),
        "ms": caught.ms,
        "bytes": caught.bytes,
        "whole_map_bytes": caught.whole_map_bytes,
        "bytes_per_whole_map": caught.bytes as f64 / caught.whole_map_bytes.max(1) as f64,
    }))
}

/// The robot of site 0 that was offline through the measured window catches up by delta.
async fn resync_after_offline(
    fleet: &Fleet,
    metrics: &server::ServerMetrics,
    window: &MeasuredWindow,
) -> anyhow::Result<serde_json::Value> {
    let caught = catch_up_since(
        fleet.robots[0].uplink.clone(),
        metrics,
        window.offline_version,
    )
    .await?;
    Ok(json!({
        "site": site_id(0),
        "offline_s": window.measured_s,
        "from_version": window.offline_version,
        "to_version": caught.delta.to_version,
        "submaps_added": caught.delta.submaps_added.len(),
        "ms": caught.ms,
        "bytes": caught.bytes,
        "whole_map_ms": caught.whole_map_ms,
        "whole_map_bytes": caught.whole_map_bytes,
    }))
}

/// The measured window's figures per minute of robot time (the report's `per_minute_of_robot_time`),
/// charted in `minutes.png` when there are at least two minutes.
fn minute_report(
    args: &LoadArgs,
    window: &MeasuredWindow,
    latencies: &SubmapLatencies,
) -> anyhow::Result<serde_json::Value> {
    let robot_minute = |at: Instant| {
        at.saturating_duration_since(window.started).as_secs_f64() * args.speed / 60.0
    };
    let minute_inputs = MinuteInputs {
        samples: window.minute_samples.clone(),
        submap_latencies: latencies
            .by_finish
            .iter()
            .map(|&(finished, latency)| (robot_minute(finished), latency))
            .collect(),
        batch_acks: window
            .outcomes
            .iter()
            .flat_map(|o| &o.acks)
            .map(|&at| robot_minute(at))
            .collect(),
    };
    let minutes = (args.duration_s / 60.0).floor() as usize;
    let figures = minute_figures::minute_figures(&minute_inputs, minutes);
    // Sessions end (and trims free memory) every `--session-s` of robot time; the figures are per
    // minute, so per-period figures need a whole number of minutes.
    let session_period_minutes = args
        .session_s
        .filter(|s| *s >= 60.0 && s % 60.0 == 0.0)
        .map(|s| (s / 60.0) as usize);
    let per_minute = minute_figures::report(&figures, session_period_minutes);
    if figures.len() >= 2 {
        let (w, h, pixels) = minute_figures::chart(
            &figures,
            &format!(
                "{} robots, {} sites, {}x{}",
                args.agents,
                args.sites,
                args.speed,
                if args.mature_sessions > 0 {
                    format!(", after {} maturing sessions each", args.mature_sessions)
                } else {
                    String::new()
                }
            ),
            720,
        );
        map_image::write_rgb_png(&args.out.join("minutes.png"), w, h, &pixels)?;
    }
    Ok(per_minute)
}

/// Each measured site's version and graph counts at the end.
fn final_site_counts(fleet: &Fleet, sites: usize) -> BTreeMap<String, serde_json::Value> {
    (0..sites)
        .filter_map(|s| {
            let info = fleet.server.site(&site_id(s))?.current();
            Some((
                site_id(s),
                json!({
                    "version": info.version,
                    "sessions": info.counts.sessions,
                    "nodes": info.counts.nodes,
                    "submaps": info.counts.submaps,
                    "constraints": info.counts.constraints,
                    "loop_closures": info.counts.loop_closures,
                }),
            ))
        })
        .collect()
}

/// The idle sites (`--idle-store`): how many, how many the server held unloaded at the end, and the
/// timed requests to them.
fn idle_report(fleet: &Fleet, probes: &[IdleProbe]) -> serde_json::Value {
    if fleet.idle_sites.is_empty() {
        return serde_json::Value::Null;
    }
    let unloaded = fleet
        .idle_sites
        .iter()
        .filter(|s| fleet.server.site(&s.id).is_some_and(|h| !h.is_loaded()))
        .count();
    let mut answered: Vec<f64> = probes
        .iter()
        .filter(|p| p.was_unloaded)
        .map(|p| p.answered_s)
        .collect();
    answered.sort_by(f64::total_cmp);
    json!({
        "sites": fleet.idle_sites.len(),
        "unloaded_at_the_end": unloaded,
        "probes": probes,
        "unloaded_answered_s": {
            "count": answered.len(),
            "p50": answered.get(answered.len() / 2),
            "max": answered.last(),
        },
    })
}

/// Phase 2b (not measured): every robot streams its `maturing` sessions as fast as the server takes
/// them. Returns the sites' growth, sampled while they mature and once at the end.
async fn mature_sites(
    args: &LoadArgs,
    fleet: &Fleet,
    maturing: Vec<Vec<PreparedSession>>,
) -> anyhow::Result<Vec<serde_json::Value>> {
    let maturing_started = Instant::now();
    eprintln!(
        "phase 2b: every robot streams {} maturing session(s) as fast as the server takes them (not measured)",
        args.mature_sessions
    );
    let mut streams = Vec::new();
    let maturing_done = AtomicBool::new(false);
    for (robot, sessions) in fleet.robots.iter().zip(maturing) {
        let (uplink, site, id) = (robot.uplink.clone(), robot.site, robot.id.clone());
        let glm_on_server = args.glm_on_server;
        streams.push(tokio::spawn(async move {
            let mut left = 0;
            for (j, session) in sessions.iter().enumerate() {
                let uploader = session_uploader(&uplink, site, &id, &format!("maturing-{j}"))?;
                left += stream_prepared(
                    uploader,
                    session,
                    site,
                    glm_on_server,
                    Instant::now(),
                    MATURING_SPEED,
                )
                .await?
                .left_in_outbox;
            }
            anyhow::Ok(left)
        }));
    }
    let streamed = async {
        let result = async {
            for stream in streams {
                let left = stream.await.context("robot task")??;
                anyhow::ensure!(
                    left == 0,
                    "a maturing session could not deliver everything ({left} batches left)"
                );
            }
            anyhow::Ok(())
        }
        .await;
        maturing_done.store(true, Ordering::Relaxed);
        result
    };
    let store_path = fleet.store.path();
    let growth = site_growth_until(&fleet.server, args.sites, store_path, &maturing_done);
    let (streamed, growth) = tokio::join!(streamed, growth);
    streamed?;
    fleet.wait_caught_up(args.sites).await;
    let mut maturing_growth = growth;
    for site in 0..args.sites {
        maturing_growth.extend(site_sizes(&fleet.server, site, store_path).await);
    }
    eprintln!(
        "  matured in {:.0} s; site sessions {:?}",
        maturing_started.elapsed().as_secs_f64(),
        (0..args.sites)
            .map(|s| fleet
                .server
                .site(&site_id(s))
                .map_or(0, |h| h.current().counts.sessions))
            .collect::<Vec<_>>()
    );
    Ok(maturing_growth)
}

/// What the measured window (phase 3) did.
struct MeasuredWindow {
    /// When the robots began streaming.
    started: Instant,
    /// Each robot's streaming outcome.
    outcomes: Vec<StreamOutcome>,
    /// Wall seconds until every robot had streamed everything.
    streaming_s: f64,
    /// Wall seconds until every robot's cache also held its site's last version.
    measured_s: f64,
    /// The process's CPU seconds over the window (`None` where not measurable).
    cpu_s: Option<f64>,
    bytes_in: u64,
    bytes_out: u64,
    /// Back-end runs in the window and their mean duration, ms.
    pgr_runs: u64,
    pgr_mean_ms: f64,
    deepest_site_queue: usize,
    /// What the end of every minute of robot time held.
    minute_samples: Vec<MinuteSample>,
    /// Site 0's version when the window began: where a robot that was offline throughout last synced.
    offline_version: u64,
}

/// Phase 3 (measured): every robot streams its `prepared` sessions back to back at `--speed`, the
/// starts spread over `--start-spread-s`, while a sampler records every minute of robot time; then
/// waits for every cache to catch up and stops the fleet's followers.
async fn stream_measured(
    args: &LoadArgs,
    fleet: &mut Fleet,
    prepared: Vec<Vec<PreparedSession>>,
) -> anyhow::Result<MeasuredWindow> {
    let metrics = Arc::clone(fleet.server.metrics());
    let (bytes_in_0, bytes_out_0) = (metrics.bytes_in(), metrics.bytes_out());
    let (pgr_runs_0, pgr_mean_0) = metrics.pgr_mean_ms();
    let cpu_0 = cpu_seconds();
    // A robot that goes offline now and comes back at the end: the version it last saw.
    let offline_version = fleet
        .server
        .site(&site_id(0))
        .map_or(0, |h| h.current().version);
    let stream_started = Instant::now();
    let max_queue = Arc::new(Mutex::new(0usize));
    let minute_samples = Arc::new(Mutex::new(Vec::<MinuteSample>::new()));
    let sampler = spawn_sampler(
        fleet,
        args,
        stream_started,
        bytes_in_0,
        Arc::clone(&max_queue),
        Arc::clone(&minute_samples),
    );
    // Kept until the end (see the module's documentation); the robots stream shared references.
    let prepared: Vec<Arc<Vec<PreparedSession>>> = prepared.into_iter().map(Arc::new).collect();
    let speed = args.speed;
    let mut streams = Vec::new();
    for (r, (robot, sessions)) in fleet.robots.iter().zip(&prepared).enumerate() {
        let robot_start =
            stream_started + seconds(args.start_spread_s * r as f64 / args.agents as f64);
        let (uplink, site, id) = (robot.uplink.clone(), robot.site, robot.id.clone());
        let sessions = Arc::clone(sessions);
        let glm_on_server = args.glm_on_server;
        streams.push(tokio::spawn(async move {
            let mut outcome = StreamOutcome::default();
            // Sessions back to back on the robot's clock.
            let mut session_start = robot_start;
            for (j, session) in sessions.iter().enumerate() {
                let uploader = session_uploader(&uplink, site, &id, &format!("cleaning-{j}"))?;
                outcome.add(
                    stream_prepared(uploader, session, site, glm_on_server, session_start, speed)
                        .await?,
                );
                session_start += seconds(session.duration_s / speed);
            }
            anyhow::Ok(outcome)
        }));
    }
    let mut outcomes = Vec::new();
    for stream in streams {
        outcomes.push(stream.await.context("robot task")??);
    }
    let streaming_s = stream_started.elapsed().as_secs_f64();
    fleet.wait_caught_up(args.sites).await;
    let measured_s = stream_started.elapsed().as_secs_f64();
    let cpu_s = match (cpu_0, cpu_seconds()) {
        (Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    let (pgr_runs_1, pgr_mean_1) = metrics.pgr_mean_ms();
    let pgr_runs = pgr_runs_1 - pgr_runs_0;
    let pgr_mean_ms = if pgr_runs > 0 {
        (pgr_mean_1 * pgr_runs_1 as f64 - pgr_mean_0 * pgr_runs_0 as f64) / pgr_runs as f64
    } else {
        0.0
    };
    let (bytes_in, bytes_out) = (
        metrics.bytes_in() - bytes_in_0,
        metrics.bytes_out() - bytes_out_0,
    );
    fleet.stop_following().await;
    let _ = sampler.await;
    Ok(MeasuredWindow {
        started: stream_started,
        outcomes,
        streaming_s,
        measured_s,
        cpu_s,
        bytes_in,
        bytes_out,
        pgr_runs,
        pgr_mean_ms,
        deepest_site_queue: max_queue.lock().map_or(0, |m| *m),
        minute_samples: minute_samples.lock().map(|s| s.clone()).unwrap_or_default(),
        offline_version,
    })
}

/// Samples the fleet every 100 ms until it stops following: the deepest site queue into `max_queue`,
/// memory and uplink (bytes since `bytes_in_0`) at the end of every minute of robot time into `minute_samples`, and a progress
/// line every 10 s.
fn spawn_sampler(
    fleet: &Fleet,
    args: &LoadArgs,
    stream_started: Instant,
    bytes_in_0: u64,
    max_queue: Arc<Mutex<usize>>,
    minute_samples: Arc<Mutex<Vec<MinuteSample>>>,
) -> tokio::task::JoinHandle<()> {
    let handles: Vec<_> = (0..args.sites)
        .filter_map(|s| fleet.server.site(&site_id(s)).cloned())
        .collect();
    let metrics = Arc::clone(fleet.server.metrics());
    let caches: Vec<_> = fleet.robots.iter().map(|r| Arc::clone(&r.cache)).collect();
    let store = Arc::clone(&fleet.store);
    let mut stop = fleet.stopped.clone();
    let speed = args.speed;
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_millis(100));
        let mut last_line = Instant::now();
        let mut next_minute = 1u32;
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = stop.changed() => return,
            }
            let robot_minutes = stream_started.elapsed().as_secs_f64() * speed / 60.0;
            if robot_minutes >= f64::from(next_minute) {
                let rss = current_rss_mb();
                let bytes = metrics.bytes_in() - bytes_in_0;
                let memory = MemoryAttribution::measure(&handles, &store, &caches);
                eprintln!(
                    "  minute {next_minute:>3} of robot time: RSS {} MiB, live heap {} MiB (history grids {:.0}, robot caches {:.0}, sled on disk {:.0}, held by sled {:.0}, {} reopens), {:.1} MB uplink so far",
                    rss.map_or("?".into(), |m| format!("{m:.0}")),
                    memory
                        .live_heap_mb
                        .map_or("?".into(), |m| format!("{m:.0}")),
                    memory.history_grids_mb(),
                    memory.robot_cache_grids_mb,
                    memory.store_disk_mb,
                    memory.store_held_mb,
                    memory.store_memory_reopens,
                    bytes as f64 / 1e6
                );
                if let Ok(mut samples) = minute_samples.lock() {
                    samples.push(MinuteSample {
                        minute: robot_minutes,
                        rss_mb: rss,
                        uplink_bytes: bytes,
                        memory,
                    });
                }
                next_minute += 1;
            }
            let depth = handles
                .iter()
                .map(server::site::SiteHandle::queue_depth)
                .max()
                .unwrap_or(0);
            if let Ok(mut m) = max_queue.lock() {
                *m = (*m).max(depth);
            }
            if last_line.elapsed() >= Duration::from_secs(10) {
                last_line = Instant::now();
                let versions: Vec<u64> = handles.iter().map(|h| h.current().version).collect();
                eprintln!(
                    "  {:>4.0} s: site versions {versions:?}, deepest site queue {depth}",
                    stream_started.elapsed().as_secs_f64()
                );
            }
        }
    })
}

/// Prints the soak's slopes (when the window held enough minutes) and the headline figures.
fn print_summary(args: &LoadArgs, report: &serde_json::Value, path: &std::path::Path) {
    let per_minute = &report["per_minute_of_robot_time"];
    let soak = &per_minute["after_warm_up"];
    if let Some(slope) = soak["rss_slope_mb_per_minute"].as_f64() {
        println!(
            "after minute {}: RSS {:.0} -> {:.0} MiB, slope {slope:+.2} MiB per minute; p95 slope {:+.3} s per minute (chart: {})",
            minute_figures::WARM_UP_MINUTES,
            soak["rss_first_mb"].as_f64().unwrap_or(f64::NAN),
            soak["rss_last_mb"].as_f64().unwrap_or(f64::NAN),
            soak["p95_slope_s_per_minute"].as_f64().unwrap_or(f64::NAN),
            args.out.join("minutes.png").display()
        );
    }
    let period = &soak["by_session_period"];
    if let Some(slope) = period["rss_mean_slope_mb_per_minute"].as_f64() {
        println!(
            "per whole {}-minute session period after minute {}: mean RSS slope {slope:+.2} MiB per minute, mean live heap {:+.2}, largest p95 {:+.3} s per minute",
            period["period_minutes"],
            minute_figures::WARM_UP_MINUTES,
            period["live_heap_mean_slope_mb_per_minute"]
                .as_f64()
                .unwrap_or(f64::NAN),
            period["p95_max_slope_s_per_minute"]
                .as_f64()
                .unwrap_or(f64::NAN),
        );
    }
    let latency = &report["submap_latency_s"];
    let to_every = &latency["to_every_robot_of_the_site"];
    let server_process = &report["server_process"];
    println!(
        "load done: {} robots on {} sites for {} s; submap to every robot of the site p50 {:.2} s, p95 {:.2} s ({} submaps, {} undelivered); uplink {:.0} B per robot-second; server process {} cores busy, peak RSS {} MB; report in {}",
        args.agents,
        args.sites,
        args.duration_s,
        to_every["p50"].as_f64().unwrap_or(f64::NAN),
        to_every["p95"].as_f64().unwrap_or(f64::NAN),
        latency["submaps"],
        latency["undelivered"],
        report["uplink_bytes_per_robot_second"]
            .as_f64()
            .unwrap_or(f64::NAN),
        server_process["cores_busy"]
            .as_f64()
            .map_or("?".into(), |c| format!("{c:.2}")),
        server_process["peak_rss_mb"]
            .as_f64()
            .map_or("?".into(), |m| format!("{m:.0}")),
        path.display()
    );
}
