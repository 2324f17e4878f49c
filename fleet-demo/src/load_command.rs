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
use mapping::geometry::Rigid2;
use mapping::global_slam::GlobalSlamOptions;
use mapping::lifelong::{MapMatcher, RelocalizationOptions, SessionStartOptions};
use mapping::local_slam::LocalTrajectoryBuilderOptions;
use proto::{SubmapSnapshot, UploadItem};
use robot_agent::map_image;
use robot_agent::outbox::Outbox;
use robot_agent::process_stats::{cpu_seconds, current_rss_mb, peak_rss_mb};
use robot_agent::source::{ReadReport, Recording};
use robot_agent::uplink::{
    GlobalSubmapCache, GrpcUplink, SessionOptions, Uploader, cached_submaps, follow_site_with,
    match_node, place_ahead, run_llo, stream_recording, sync_matcher,
};
use serde_json::json;
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use simulator::World;
use simulator::{SessionOptions as SimSessionOptions, Store};
use storage::{SledStore, SledStoreOptions};
use tokio::sync::watch;
use tracing::Instrument as _;

use crate::catch_up::catch_up_since;
use crate::command_runtime::{block_on, recreate_dir};
use crate::demo_command::MAX_MESSAGE_BYTES;
use crate::memory_attribution::MemoryAttribution;
use crate::minute_figures::{self, MinuteInputs, MinuteSample};
use crate::site_growth::{half_life_version, site_growth_until, site_sizes};

/// Nodes per upload batch (a batch holding a finished submap goes at once).
const NODES_PER_BATCH: usize = 10;
/// Robot time per wall-clock time of the unmeasured maturing sessions: as fast as the server takes them.
const MATURING_SPEED: f64 = 1e4;

/// Arguments of `load`.
#[derive(Args)]
pub struct LoadArgs {
    /// Output folder (deleted and recreated): `data/` (the server's sled), `report.json` and
    /// `submap_latencies.csv` (one line per finished submap: when, its site and version, its latencies).
    #[arg(long, default_value = "out/load")]
    out: PathBuf,
    /// Robots streaming at once, spread evenly over the sites.
    #[arg(long, default_value_t = 50)]
    agents: usize,
    /// Sites (stores), each with its own simulated store and map.
    #[arg(long, default_value_t = 10)]
    sites: usize,
    /// Seconds of robot time each robot streams (the measured window), 10..=3600.
    #[arg(long, default_value_t = 120.0)]
    duration_s: f64,
    /// Length of each cleaning session, seconds of robot time (30..=300): a robot streams
    /// ceil(duration / session) sessions back to back, each on a later simulated day. Default: one
    /// session of `--duration-s` (at most 300 s).
    #[arg(long)]
    session_s: Option<f64>,
    /// Robot time per wall-clock time (0.1..=20): 1 streams at real time, 10 replays ten minutes of robot
    /// time in one minute (the server then gets ten times the load of the same fleet).
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Cap on each site's mapping session 0, seconds of simulated time (default: the whole sweep of the
    /// store, as in `demo`).
    #[arg(long)]
    mapping_duration_s: Option<f64>,
    /// Seed of the stores and routes (site `s` uses `seed + s`).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Which simulated world each site is, at the demo's 48 × 30 m: `store` (a realistic supermarket)
    /// or `aisles` (identical shelf rows, adversarial).
    #[arg(long, value_enum, default_value_t = World::Store)]
    world: World,
    /// The server's sled page cache, MiB, 1..=65536 (the server's `[storage] cache_capacity_bytes`;
    /// default its default, 256 MiB).
    #[arg(long, default_value_t = 256)]
    store_cache_mib: u64,
    /// Let the server run GLM for every node (the design before GLM moved onto the robots) instead of
    /// the robots sending their own matches.
    #[arg(long)]
    glm_on_server: bool,
    /// Sessions each robot streams before the measured window, as fast as the server takes them (not
    /// measured; default 0): the sites start the soak with the map a store has after that many
    /// cleaning days instead of a fresh one. A fresh site's map grows until the fresh submaps over its
    /// routes form one layer (here about 4 sessions of 300 s per site; about a dozen of 120 s in the
    /// lifelong experiment); a server in production mostly holds sites past that. At most 100 (issue 34's
    /// site age).
    #[arg(long, default_value_t = 0)]
    mature_sessions: usize,
    /// Run the server without site checkpoints (`[checkpoints] enabled = false`): the store keeps its
    /// whole log and a restart replays it (the figure checkpoints are compared with).
    #[arg(long)]
    no_checkpoints: bool,
    /// Wall-clock seconds over which the robots start their first session, evenly spread (0..=3600).
    /// At the default every robot's sessions start and end within 2 s of each other's — the worst case:
    /// every site ends its sessions, and LLO finishes every robot's last submaps, in the same second. A
    /// fleet whose robots start cleaning at different times is a spread of a session's length or more.
    #[arg(long, default_value_t = 2.0)]
    start_spread_s: f64,
}

/// One robot of the benchmark.
struct Robot {
    site: usize,
    id: String,
    uplink: GrpcUplink,
    cache: Arc<Mutex<GlobalSubmapCache>>,
    /// When each site version reached this robot's cache.
    arrivals: Arc<Mutex<Vec<(u64, Instant)>>>,
}

/// A robot's cleaning session, run through LLO ahead of time.
struct PreparedSession {
    /// One entry per node: its items (the node, then the submaps it finished).
    steps: Vec<Vec<UploadItem>>,
    /// `global_from_local` where the robot's session start placed it.
    prior: Option<Rigid2>,
    duration_s: f64,
}

/// A finished submap on its way to the fleet.
struct SubmapTiming {
    site: usize,
    /// When the robot finished it (on the session's real-time schedule).
    finished: Instant,
    /// When the server acknowledged the batch holding it.
    acked: Instant,
    /// The site version that batch made.
    version: u64,
}

/// What one robot's streaming did.
#[derive(Default)]
struct StreamOutcome {
    submaps: Vec<SubmapTiming>,
    batches: u64,
    failed_flushes: u64,
    left_in_outbox: usize,
    /// Largest lag behind the recording's clock when a batch was sent, seconds.
    max_lag_s: f64,
    /// When the server acknowledged each batch.
    acks: Vec<Instant>,
}

impl StreamOutcome {
    /// Adds the outcome of the robot's next session.
    fn add(&mut self, other: Self) {
        self.submaps.extend(other.submaps);
        self.batches += other.batches;
        self.failed_flushes += other.failed_flushes;
        self.left_in_outbox += other.left_in_outbox;
        self.max_lag_s = self.max_lag_s.max(other.max_lag_s);
        self.acks.extend(other.acks);
    }
}

pub(crate) fn site_id(s: usize) -> String {
    format!("store-{}", s + 1)
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
    block_on(load(args))
}

async fn load(args: &LoadArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    recreate_dir(&args.out)?;
    let store_options = SledStoreOptions {
        path: args.out.join("data"),
        cache_capacity_bytes: args.store_cache_mib << 20,
        ..SledStoreOptions::default()
    };
    store_options.validate()?;
    let store = tokio::task::spawn_blocking(move || SledStore::open(&store_options))
        .await
        .context("storage thread")??;

    // Robot r belongs to site r % sites; robot k of a site is named robot-<site>-<k>.
    let mut site_robots: Vec<Vec<RobotConfig>> = vec![Vec::new(); args.sites];
    for r in 0..args.agents {
        let s = r % args.sites;
        let k = site_robots[s].len();
        site_robots[s].push(RobotConfig {
            id: format!("robot-{}-{k}", s + 1),
            token: format!("load-token-{}-{k}", s + 1),
        });
    }
    let config = ServerConfig {
        listen: "127.0.0.1:0".parse()?,
        metrics_listen: None,
        max_message_bytes: MAX_MESSAGE_BYTES,
        sites: site_robots
            .iter()
            .enumerate()
            .map(|(s, robots)| SiteConfig {
                id: site_id(s),
                robots: robots.clone(),
            })
            .collect(),
        checkpoints: if args.no_checkpoints {
            server::site::CheckpointOptions::DISABLED
        } else {
            server::site::CheckpointOptions::DEFAULT
        },
        ..ServerConfig::default()
    };
    let store = Arc::new(store);
    let server = RunningServer::start(&config, Arc::clone(&store) as Arc<_>).await?;
    let url = format!("http://{}", server.grpc_addr());
    eprintln!(
        "evermap load: server on {url} (sled in {}), {} robots on {} sites, {} s of robot time each at {}x real time",
        args.out.join("data").display(),
        args.agents,
        args.sites,
        args.duration_s,
        args.speed
    );

    let (stop, stopped) = watch::channel(false);
    let mut robots = Vec::new();
    let mut followers = Vec::new();
    for (s, configs) in site_robots.iter().enumerate() {
        for config in configs {
            let uplink = GrpcUplink::new(
                &url,
                &site_id(s),
                &config.token,
                MAX_MESSAGE_BYTES,
                Duration::from_secs(60),
            )?;
            let cache = Arc::new(Mutex::new(GlobalSubmapCache::default()));
            let arrivals = Arc::new(Mutex::new(Vec::new()));
            let record = Arc::clone(&arrivals);
            followers.push(tokio::spawn(follow_site_with(
                uplink.clone(),
                Arc::clone(&cache),
                stopped.clone(),
                Duration::from_millis(200),
                move |version| {
                    if let Ok(mut a) = record.lock() {
                        a.push((version, Instant::now()));
                    }
                },
            )));
            robots.push(Robot {
                site: s,
                id: config.id.clone(),
                uplink,
                cache,
                arrivals,
            });
        }
    }
    let worlds: Vec<Store> = (0..args.sites)
        .map(|s| Store::generate(args.world.demo_options(), args.seed + s as u64))
        .collect::<Result<_, _>>()?;

    // 1. Every site's robot 0 maps its store.
    eprintln!("phase 1/3: mapping {} stores", args.sites);
    let mapping_sim = SimSessionOptions {
        mapping_max_duration_s: args.mapping_duration_s.unwrap_or(0.0),
        ..SimSessionOptions::default()
    };
    let mut mappers = Vec::new();
    for (s, world) in worlds.iter().enumerate() {
        let robot = robots
            .iter()
            .find(|r| r.site == s)
            .context("every site has a robot")?;
        let (world, sim) = (world.clone(), mapping_sim.clone());
        let recording = tokio::task::spawn_blocking(move || {
            let simulated = world.session(0, &sim)?;
            anyhow::Ok(Arc::new(Recording::from_unsorted(
                simulated.events,
                simulated.base_from_laser,
                ReadReport::default(),
            )))
        })
        .await
        .context("simulator thread")??;
        let mut uploader = Uploader::new(
            robot.uplink.clone(),
            Outbox::in_memory(&site_id(s)),
            &site_id(s),
            &robot.id,
            &format!("load-{}-mapping", robot.id),
        )?;
        let options = SessionOptions {
            replay_speed: 0.0,
            final_flush_timeout: Duration::from_secs(300),
            ..SessionOptions::default()
        };
        mappers.push(tokio::spawn(async move {
            let span = uploader.session_span();
            stream_recording(recording, &options, &mut uploader)
                .instrument(span)
                .await
        }));
    }
    for mapper in mappers {
        let report = mapper.await.context("mapping task")??;
        anyhow::ensure!(
            report.left_in_outbox == 0,
            "a mapping session could not deliver everything ({} batches left)",
            report.left_in_outbox
        );
    }
    wait_caught_up(&server, &robots, args.sites).await;
    eprintln!(
        "  mapped in {:.0} s; site versions {:?}",
        started.elapsed().as_secs_f64(),
        (0..args.sites)
            .map(|s| server.site(&site_id(s)).map_or(0, |h| h.current().version))
            .collect::<Vec<_>>()
    );

    // 2. LLO and the session start of every cleaning session, ahead of time.
    eprintln!(
        "phase 2/3: LLO of the cleaning sessions of {} robots ahead of time",
        robots.len()
    );
    let prepare_started = Instant::now();
    let session_plan = session_lengths(args.duration_s, args.session_s);
    // The maturing sessions come first, on the robots' earlier days, as long as the measured ones.
    let maturing_plan = vec![session_plan[0]; args.mature_sessions];
    let robots_per_site = args.agents.div_ceil(args.sites);
    let mut preparing = Vec::new();
    for (r, robot) in robots.iter().enumerate() {
        for (j, &length) in maturing_plan.iter().chain(&session_plan).enumerate() {
            let world = worlds[robot.site].clone();
            let sim = SimSessionOptions {
                max_duration_s: length,
                ..SimSessionOptions::default()
            };
            // Robot k of a site cleans on day 1 + k, then every robots_per_site days.
            let session = u32::try_from(1 + r / args.sites + j * robots_per_site)?;
            preparing.push((
                r,
                tokio::task::spawn_blocking(
                    move || -> anyhow::Result<(Vec<Vec<UploadItem>>, f64)> {
                        let simulated = world.session(session, &sim)?;
                        let recording = Recording::from_unsorted(
                            simulated.events,
                            simulated.base_from_laser,
                            ReadReport::default(),
                        );
                        let mut steps = Vec::new();
                        run_llo(
                            &recording,
                            &LocalTrajectoryBuilderOptions::default(),
                            0.0,
                            None,
                            &mut |items| {
                                steps.push(items);
                                true
                            },
                        );
                        Ok((steps, simulated.duration_s))
                    },
                ),
            ));
        }
    }
    let mut prepared: Vec<Vec<PreparedSession>> = robots.iter().map(|_| Vec::new()).collect();
    let mut glm_matches = 0;
    for (r, task) in preparing {
        let robot = &robots[r];
        let (mut steps, duration_s) = task.await.context("LLO thread")??;
        let prior = place_ahead(
            &robot.cache,
            &RelocalizationOptions::default(),
            &SessionStartOptions::default(),
            steps.iter().flatten(),
        )
        .await;
        // GLM on the robot, also ahead of time (robots match on their own CPUs), against the robot's
        // cache of the site as it was when the session started (session 0's map).
        if let (false, Some(global_from_local)) = (args.glm_on_server, prior) {
            let submaps = cached_submaps(
                &*robot
                    .cache
                    .lock()
                    .map_err(|_| anyhow::anyhow!("a robot's cache lock is poisoned"))?,
                None,
            );
            let (matched, count) = tokio::task::spawn_blocking(move || {
                robot_glm_ahead(steps, &submaps, global_from_local)
            })
            .await
            .context("GLM thread")??;
            steps = matched;
            glm_matches += count;
        }
        prepared[r].push(PreparedSession {
            steps,
            prior,
            duration_s,
        });
    }
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

    // 2b. Not measured: the sites mature.
    let mut maturing_growth = Vec::new();
    if args.mature_sessions > 0 {
        let maturing_started = Instant::now();
        eprintln!(
            "phase 2b: every robot streams {} maturing session(s) as fast as the server takes them (not measured)",
            args.mature_sessions
        );
        let mut streams = Vec::new();
        let maturing_done = AtomicBool::new(false);
        for (robot, sessions) in robots.iter().zip(maturing) {
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
        let growth = site_growth_until(&server, args.sites, store.path(), &maturing_done);
        let (streamed, growth) = tokio::join!(streamed, growth);
        streamed?;
        wait_caught_up(&server, &robots, args.sites).await;
        maturing_growth = growth;
        for site in 0..args.sites {
            maturing_growth.extend(site_sizes(&server, site, store.path()).await);
        }
        eprintln!(
            "  matured in {:.0} s; site sessions {:?}",
            maturing_started.elapsed().as_secs_f64(),
            (0..args.sites)
                .map(|s| server
                    .site(&site_id(s))
                    .map_or(0, |h| h.current().counts.sessions))
                .collect::<Vec<_>>()
        );
    }

    // 3. Measured: everyone streams at real time.
    eprintln!(
        "phase 3/3: {} robots stream {} s of robot time each ({} session(s)) at {}x real time",
        robots.len(),
        args.duration_s,
        session_plan.len(),
        args.speed
    );
    let metrics = Arc::clone(server.metrics());
    let (bytes_in_0, bytes_out_0) = (metrics.bytes_in(), metrics.bytes_out());
    let (pgr_runs_0, pgr_mean_0) = metrics.pgr_mean_ms();
    let cpu_0 = cpu_seconds();
    // A robot that goes offline now and comes back at the end: the version it last saw.
    let offline_version = server.site(&site_id(0)).map_or(0, |h| h.current().version);
    let stream_started = Instant::now();
    let max_queue = Arc::new(Mutex::new(0usize));
    // What the end of every minute of robot time held.
    let minute_samples = Arc::new(Mutex::new(Vec::<MinuteSample>::new()));
    let speed = args.speed;
    let sampler = {
        let handles: Vec<_> = (0..args.sites)
            .filter_map(|s| server.site(&site_id(s)).cloned())
            .collect();
        let max_queue = Arc::clone(&max_queue);
        let minute_samples = Arc::clone(&minute_samples);
        let metrics = Arc::clone(&metrics);
        let caches: Vec<_> = robots.iter().map(|r| Arc::clone(&r.cache)).collect();
        let store = Arc::clone(&store);
        let mut stop = stopped.clone();
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
    };
    // Kept until the end (see the module's documentation); the robots stream shared references.
    let prepared: Vec<Arc<Vec<PreparedSession>>> = prepared.into_iter().map(Arc::new).collect();
    let mut streams = Vec::new();
    for (r, (robot, sessions)) in robots.iter().zip(&prepared).enumerate() {
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
    wait_caught_up(&server, &robots, args.sites).await;
    let measured_s = stream_started.elapsed().as_secs_f64();
    let cpu_s = match (cpu_0, cpu_seconds()) {
        (Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    let bytes_in = metrics.bytes_in() - bytes_in_0;
    let bytes_out = metrics.bytes_out() - bytes_out_0;
    let (pgr_runs_1, pgr_mean_1) = metrics.pgr_mean_ms();
    let pgr_runs = pgr_runs_1 - pgr_runs_0;
    let pgr_mean_ms = if pgr_runs > 0 {
        (pgr_mean_1 * pgr_runs_1 as f64 - pgr_mean_0 * pgr_runs_0 as f64) / pgr_runs as f64
    } else {
        0.0
    };
    let _ = stop.send(true);
    let _ = sampler.await;
    for follower in followers {
        let _ = follower.await;
    }

    // A robot of site 0 last seen halfway through the site's life (its session count then half of what it
    // is now, from the maturing samples) catches up: one delta holding every submap changed since.
    let catch_up = match half_life_version(&maturing_growth) {
        Some((sessions_then, from_version)) => {
            let caught = catch_up_since(robots[0].uplink.clone(), &metrics, from_version).await?;
            let sessions_now = server
                .site(&site_id(0))
                .map_or(0, |h| h.current().counts.sessions);
            json!({
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
            })
        }
        None => serde_json::Value::Null,
    };

    // The offline robot catches up by delta.
    let resync = {
        let caught = catch_up_since(robots[0].uplink.clone(), &metrics, offline_version).await?;
        json!({
            "site": site_id(0),
            "offline_s": measured_s,
            "from_version": offline_version,
            "to_version": caught.delta.to_version,
            "submaps_added": caught.delta.submaps_added.len(),
            "ms": caught.ms,
            "bytes": caught.bytes,
            "whole_map_ms": caught.whole_map_ms,
            "whole_map_bytes": caught.whole_map_bytes,
        })
    };

    // Latency from a finished submap to its version in every cache of the site.
    let arrivals: Vec<Vec<(u64, Instant)>> = robots
        .iter()
        .map(|r| r.arrivals.lock().map(|a| a.clone()).unwrap_or_default())
        .collect();
    let mut to_all = Vec::new();
    let mut to_ack = Vec::new();
    let mut undelivered = 0usize;
    // (when the submap was finished, its latency to every robot of the site).
    let mut latencies_by_finish: Vec<(Instant, f64)> = Vec::new();
    // One line per submap for `submap_latencies.csv`: when it was finished, its site, its latencies.
    let mut latency_lines = vec!["finished_s,site,version,to_ack_s,to_every_robot_s".to_owned()];
    for timing in outcomes.iter().flat_map(|o| &o.submaps) {
        to_ack.push(timing.acked.duration_since(timing.finished).as_secs_f64());
        let reached: Option<Vec<Instant>> = robots
            .iter()
            .zip(&arrivals)
            .filter(|(r, _)| r.site == timing.site)
            .map(|(_, a)| {
                a.iter()
                    .find(|(v, _)| *v >= timing.version)
                    .map(|(_, at)| *at)
            })
            .collect();
        let to_every_robot = reached.and_then(|r| r.into_iter().max()).map(|last| {
            last.saturating_duration_since(timing.finished)
                .as_secs_f64()
        });
        match to_every_robot {
            Some(latency) => {
                to_all.push(latency);
                latencies_by_finish.push((timing.finished, latency));
            }
            None => undelivered += 1,
        }
        latency_lines.push(format!(
            "{:.3},{},{},{:.3},{}",
            timing
                .finished
                .saturating_duration_since(stream_started)
                .as_secs_f64(),
            site_id(timing.site),
            timing.version,
            timing.acked.duration_since(timing.finished).as_secs_f64(),
            to_every_robot.map_or_else(|| "undelivered".to_owned(), |l| format!("{l:.3}"))
        ));
    }
    // Figures per minute of robot time.
    let robot_minute = |at: Instant| {
        at.saturating_duration_since(stream_started).as_secs_f64() * args.speed / 60.0
    };
    let minute_inputs = MinuteInputs {
        samples: minute_samples.lock().map(|s| s.clone()).unwrap_or_default(),
        submap_latencies: latencies_by_finish
            .iter()
            .map(|&(finished, latency)| (robot_minute(finished), latency))
            .collect(),
        batch_acks: outcomes
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
    let sites: BTreeMap<String, serde_json::Value> = (0..args.sites)
        .filter_map(|s| {
            let info = server.site(&site_id(s))?.current();
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
        .collect();
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
        "streaming_wall_s": streaming_s,
        "measured_wall_s": measured_s,
        "sessions_placed": placed,
        "server_process": {
            "cpu_s": cpu_s,
            "cores_busy": cpu_s.map(|c| c / measured_s),
            "peak_rss_mb": peak_rss_mb(),
            "final_rss_mb": current_rss_mb(),
            "note": "one process: server, the robots' replay and gRPC clients, the followers, and the prepared sessions (allocated before the measured phase)",
        },
        "uplink_bytes": bytes_in,
        "uplink_bytes_per_robot_second": bytes_in as f64 / data_seconds.max(1e-9),
        "downlink_bytes": bytes_out,
        "downlink_bytes_per_robot_second": bytes_out as f64 / data_seconds.max(1e-9),
        "backend_runs": pgr_runs,
        "backend_mean_ms": pgr_mean_ms,
        "deepest_site_queue": max_queue.lock().map_or(0, |m| *m),
        "batches": outcomes.iter().map(|o| o.batches).sum::<u64>(),
        "failed_flushes": outcomes.iter().map(|o| o.failed_flushes).sum::<u64>(),
        "left_in_outboxes": outcomes.iter().map(|o| o.left_in_outbox).sum::<usize>(),
        "max_lag_behind_real_time_s": outcomes.iter().map(|o| o.max_lag_s).fold(0.0, f64::max),
        "submap_latency_s": {
            "submaps": to_all.len() + undelivered,
            "undelivered": undelivered,
            "to_ack": quantiles(&mut to_ack),
            "to_every_robot_of_the_site": quantiles(&mut to_all),
        },
        "resync_after_offline": resync,
        "catch_up_after_half_the_sites_life": catch_up,
        "per_minute_of_robot_time": per_minute,
        "sites_final": sites,
        "maturing_growth": maturing_growth,
        "robot_data_s": data_seconds,
        "wall_time_s": started.elapsed().as_secs_f64(),
    });
    std::fs::write(
        args.out.join("submap_latencies.csv"),
        latency_lines.join("\n") + "\n",
    )
    .context("writing submap_latencies.csv")?;
    let path = args.out.join("report.json");
    std::fs::write(&path, serde_json::to_string_pretty(&report)? + "\n")
        .with_context(|| format!("cannot write {}", path.display()))?;
    server.shutdown().await?;
    let latency = &report["submap_latency_s"]["to_every_robot_of_the_site"];
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
    println!(
        "load done: {} robots on {} sites for {} s; submap to every robot of the site p50 {:.2} s, p95 {:.2} s ({} submaps, {undelivered} undelivered); uplink {:.0} B per robot-second; server process {} cores busy, peak RSS {} MB; report in {}",
        args.agents,
        args.sites,
        args.duration_s,
        latency["p50"].as_f64().unwrap_or(f64::NAN),
        latency["p95"].as_f64().unwrap_or(f64::NAN),
        to_all.len() + undelivered,
        bytes_in as f64 / data_seconds.max(1e-9),
        cpu_s.map_or("?".into(), |c| format!("{:.2}", c / measured_s)),
        peak_rss_mb().map_or("?".into(), |m| format!("{m:.0}")),
        path.display()
    );
    Ok(())
}

/// The uploader of robot `id`'s session `name` on site number `site`, with an outbox in memory.
fn session_uploader(
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
fn seconds(s: f64) -> Duration {
    Duration::try_from_secs_f64(s).unwrap_or(Duration::ZERO)
}

/// Lengths of a robot's consecutive sessions, seconds of robot time: `duration_s` cut into sessions
/// of `session_s` (the last one shorter), or one session of `duration_s`.
fn session_lengths(duration_s: f64, session_s: Option<f64>) -> Vec<f64> {
    let Some(session_s) = session_s.filter(|s| *s > 0.0) else {
        return vec![duration_s];
    };
    let mut lengths = Vec::new();
    let mut left = duration_s;
    // Bounded: at most 3600 / 30 sessions with validated arguments.
    while left > 1e-6 && lengths.len() < 10_000 {
        lengths.push(left.min(session_s));
        left -= session_s;
    }
    lengths
}

/// p50, p95 and max of `values` (sorted in place), `null` when empty.
fn quantiles(values: &mut [f64]) -> serde_json::Value {
    if values.is_empty() {
        return serde_json::Value::Null;
    }
    values.sort_by(f64::total_cmp);
    let at = |q: f64| values[((values.len() - 1) as f64 * q).round() as usize];
    json!({ "p50": at(0.5), "p95": at(0.95), "max": values[values.len() - 1], "count": values.len() })
}

/// [`stream_prepared_session`] in the robot session's span.
async fn stream_prepared(
    uploader: Uploader<GrpcUplink>,
    session: &PreparedSession,
    site: usize,
    glm_on_server: bool,
    start: Instant,
    speed: f64,
) -> anyhow::Result<StreamOutcome> {
    let span = uploader.session_span();
    stream_prepared_session(uploader, session, site, glm_on_server, start, speed)
        .instrument(span)
        .await
}

/// Streams a prepared session on its recording's clock divided by `speed`, starting at `start`.
async fn stream_prepared_session(
    mut uploader: Uploader<GrpcUplink>,
    session: &PreparedSession,
    site: usize,
    glm_on_server: bool,
    start: Instant,
    speed: f64,
) -> anyhow::Result<StreamOutcome> {
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
        });
    }
    let mut nodes_in_batch = 0;
    // Finish times of the submaps in the batch being filled.
    let mut finished_in_batch: Vec<Instant> = Vec::new();
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
        finished_in_batch.extend(std::iter::repeat_n(due, finishes));
        batch.extend(step.iter().cloned());
        nodes_in_batch += 1;
        if nodes_in_batch >= NODES_PER_BATCH || finishes > 0 {
            send(
                &mut uploader,
                &mut batch,
                &mut finished_in_batch,
                &mut outcome,
            )
            .await?;
            nodes_in_batch = 0;
        }
    }
    // Until the recording's end, then the session ends.
    tokio::time::sleep_until((start + seconds(session.duration_s / speed)).into()).await;
    batch.push(UploadItem::SessionEnd);
    send(
        &mut uploader,
        &mut batch,
        &mut finished_in_batch,
        &mut outcome,
    )
    .await?;
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

/// Matches every node of a prepared session against the given site submaps, as the robot's GLM would,
/// and appends the accepted matches to its items. Returns the steps and the number of matches.
fn robot_glm_ahead(
    mut steps: Vec<Vec<UploadItem>>,
    submaps: &[SubmapSnapshot],
    global_from_local: Rigid2,
) -> anyhow::Result<(Vec<Vec<UploadItem>>, u64)> {
    let mut matcher = MapMatcher::new(
        GlobalSlamOptions::default().constraint_builder,
        global_from_local,
    )?;
    sync_matcher(&mut matcher, submaps);
    let mut count = 0;
    for items in &mut steps {
        let Some(UploadItem::NodeAdded(node)) = items.first() else {
            continue;
        };
        let found = match_node(&mut matcher, node);
        count += found.len() as u64;
        items.extend(found);
    }
    Ok((steps, count))
}

/// Waits (at most 60 s) until every robot's cache holds its site's current version.
async fn wait_caught_up(server: &RunningServer, robots: &[Robot], sites: usize) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while Instant::now() < deadline {
        let targets: Vec<u64> = (0..sites)
            .map(|s| server.site(&site_id(s)).map_or(0, |h| h.current().version))
            .collect();
        if robots
            .iter()
            .all(|r| r.cache.lock().is_ok_and(|c| c.version() >= targets[r.site]))
        {
            return;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[cfg(test)]
mod tests {
    use super::session_lengths;

    #[test]
    fn a_duration_is_cut_into_back_to_back_sessions() {
        assert_eq!(session_lengths(120.0, None), vec![120.0]);
        assert_eq!(session_lengths(1800.0, Some(300.0)), vec![300.0; 6]);
        assert_eq!(
            session_lengths(700.0, Some(300.0)),
            vec![300.0, 300.0, 100.0]
        );
        assert_eq!(session_lengths(100.0, Some(300.0)), vec![100.0]);
    }
}
