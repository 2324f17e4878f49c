//! `evermap-demo` (or `evermap-demo demo`): the fleet in one process, on one machine, with no set-up.
//!
//! A map server on embedded sled (in `<out>/data`) serves one site, `store-1`, over gRPC on 127.0.0.1; N
//! robot agents (the real agent code: LLO, sled outbox, exactly-once uploader, site follower with its
//! submap cache) drive sessions of the simulated changing store. Robot 1 maps the store first (session 0);
//! then the robots clean it concurrently on later simulated days (goods, pallets, displays and doors
//! changed; people and carts about), each session starting with no prior: the agent holds back its first
//! nodes, relocalizes them against its cache of the site's submaps and opens the session with that prior.
//!
//! The store is smaller than the `lifelong` experiment's 10,800 m² (48 × 30 m, two shelf blocks) so the
//! whole demo fits in a few minutes on two cores. Versions are printed at most every 2 s and a map picture
//! is written at most every 5 s (`maps/version-NNNNN.png`, named by the version it shows), plus the final
//! one. The agents reach the server over loopback zenoh by default (the server's zenoh front end listens
//! on 127.0.0.1, peer mode, no multicast scouting); `--transport grpc` uses gRPC instead.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context as _;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use mapping::geometry::Rigid2;
use mapping::lifelong::{
    MAP_CHANGE_TOLERANCE_M, PlacedGrid, RelocalizationOptions, map_change_rate,
    render_submaps_newest,
};
use mapping::metrics::{
    Placement, ScoringOptions, SessionScore, SessionTrack, align_to_truth, score_run, score_session,
};
use mapping::pose_graph::NodeId;
use mapping::sensor::Timestamp;
use robot_agent::map_image;
use robot_agent::outbox::Outbox;
use robot_agent::source::{ReadReport, Recording};
use robot_agent::uplink::{
    FleetUplink, GlobalSubmapCache, GrpcUplink, MapUplink as _, SessionOptions, SessionStart,
    Uploader, ZenohLinkOptions, ZenohUplink, follow_site, session_span, stream_session,
};
use serde_json::json;
use server::site::SiteHandle;
use server::{HttpConfig, RobotConfig, RunningServer, ServerConfig, SiteConfig};
use simulator::World;
use simulator::{SessionOptions as SimSessionOptions, Store};
use storage::{SledStore, SledStoreOptions};
use tokio::sync::watch;
use tracing::Instrument as _;

use crate::command_runtime::{block_on, recreate_dir};

const SITE: &str = "store-1";
/// gRPC message cap of the demo's server and agents.
pub(crate) const MAX_MESSAGE_BYTES: usize = 64 << 20;

/// Arguments of `demo`.
#[derive(Args)]
pub struct DemoArgs {
    /// Output folder (deleted and recreated): `data/` (sled), `agent-N/` (outboxes), `maps/`,
    /// `map_change.png`, `report.json`.
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Robots (agents) of the site (1..=8).
    #[arg(long, default_value_t = 3)]
    agents: usize,
    /// Cleaning sessions per robot after the mapping session (0..=10).
    #[arg(long, default_value_t = 2)]
    sessions_per_agent: usize,
    /// Seed of the store layout, its change schedule and the routes.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Which simulated world, at 48 × 30 m: `store` (a realistic supermarket) or `aisles` (identical
    /// shelf rows, adversarial).
    #[arg(long, value_enum, default_value_t = World::Store)]
    world: World,
    /// Length of each cleaning session, seconds of simulated time.
    #[arg(long, default_value_t = 90.0)]
    session_duration_s: f64,
    /// Cap on the mapping session 0, seconds of simulated time (default: the whole sweep of the store).
    #[arg(long)]
    mapping_duration_s: Option<f64>,
    /// How the agents reach the server: `zenoh` (loopback TCP, peer mode) or `grpc`.
    #[arg(long, default_value = "zenoh", value_parser = ["zenoh", "grpc"])]
    transport: String,
    /// Serve the web console on this address during the demo (e.g. `127.0.0.1:8080`; port 0 picks a
    /// free one). The URL, with a fresh operator token, is printed when the server starts.
    #[arg(long)]
    http: Option<std::net::SocketAddr>,
    /// With `--http`: keep serving the console this long after the demo ends, seconds.
    #[arg(long, default_value_t = 0.0, requires = "http")]
    linger_s: f64,
}

/// One session as run by one agent.
struct SessionRun {
    session: u32,
    robot: usize,
    trajectory: u32,
    truth: Vec<(Timestamp, Rigid2)>,
    node_times: Vec<Timestamp>,
    /// The robot's own estimate of each node's global pose at its time (see `SessionTrace`).
    node_estimates: Vec<Option<Rigid2>>,
    prior: Option<Rigid2>,
    /// Every placement the robot acted on (tentative, on probation).
    placements: Vec<Placement>,
    /// The placement the robot committed to (probation passed on its GLM matches).
    committed: Option<Placement>,
    /// Whether the robot's placement was revoked.
    revoked: bool,
    score: Option<f32>,
    relocalization_ms: f64,
    distance_m: f64,
    duration_s: f64,
    batches: u64,
    failed_flushes: u64,
    left_in_outbox: usize,
    wall_s: f64,
    /// The session's node poses in the site map right after it ended (later sessions may trim them).
    end_poses: BTreeMap<NodeId, Rigid2>,
}

struct Agent {
    robot: usize,
    uplink: FleetUplink,
    cache: Arc<Mutex<GlobalSubmapCache>>,
    out: PathBuf,
    /// The server's site, read (not written) to score each session when it ends.
    site: SiteHandle,
}

/// Runs the command.
pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    anyhow::ensure!((1..=8).contains(&args.agents), "--agents must be in 1..=8");
    anyhow::ensure!(
        args.sessions_per_agent <= 10,
        "--sessions-per-agent must be at most 10"
    );
    anyhow::ensure!(
        args.session_duration_s.is_finite() && args.session_duration_s >= 10.0,
        "--session-duration-s must be at least 10"
    );
    Duration::try_from_secs_f64(args.linger_s)
        .context("--linger-s must be a number of seconds ≥ 0")?;
    block_on(demo(args))
}

async fn demo(args: &DemoArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    recreate_dir(&args.out)?;
    std::fs::create_dir_all(args.out.join("maps"))
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let fleet = DemoServer::start(args).await?;
    let site = fleet.site.clone();
    let world = Store::generate(args.world.demo_options(), args.seed)?;
    let sim = SimSessionOptions {
        max_duration_s: args.session_duration_s,
        mapping_max_duration_s: args.mapping_duration_s.unwrap_or(0.0),
        ..SimSessionOptions::default()
    };
    sim.validate()?;

    let (stop, stopped) = watch::channel(false);
    let (agents, followers) = fleet.connect_agents(args, &stopped).await?;
    let caches: Vec<_> = agents.iter().map(|a| Arc::clone(&a.cache)).collect();
    let total_sessions = 1 + args.agents * args.sessions_per_agent;
    let bar = ProgressBar::new(total_sessions as u64);
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} sessions {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let printer = tokio::spawn(print_versions(
        site.clone(),
        caches.clone(),
        args.out.join("maps"),
        bar.clone(),
        stopped.clone(),
    ));
    let runs =
        clean_the_store(agents, &world, &sim, args.sessions_per_agent, &bar, &caches).await?;
    let _ = stop.send(true);
    let _ = printer.await;
    for follower in followers {
        let _ = follower.await;
    }
    bar.finish_and_clear();

    // The final map picture, then the scores.
    let final_version = site.current();
    write_final_map(&site, &args.out).await?;
    let mcr = write_map_change(&caches[0], &args.out)?;
    let poses: BTreeMap<NodeId, Rigid2> = runs
        .iter()
        .flat_map(|r| r.end_poses.iter().map(|(id, pose)| (*id, *pose)))
        .collect();
    let scoring = ScoringOptions::default();
    let report = score(&runs, &poses, &scoring);
    let agents_at: Vec<u64> = caches
        .iter()
        .map(|c| c.lock().map_or(0, |c| c.version()))
        .collect();
    let wall_time_s = started.elapsed().as_secs_f64();
    let robot_seconds: f64 = runs.iter().map(|r| r.duration_s).sum();
    let metrics = fleet.server.metrics();
    let (pgr_runs, pgr_mean_ms) = metrics.pgr_mean_ms();
    let summary = json!({
        "site": SITE,
        "world": args.world.name(),
        "transport": args.transport,
        "final_version": final_version.version,
        "counts": {
            "sessions": final_version.counts.sessions,
            "nodes": final_version.counts.nodes,
            "submaps": final_version.counts.submaps,
            "constraints": final_version.counts.constraints,
            "loop_closures": final_version.counts.loop_closures,
            "trimmed_submaps": final_version.counts.trimmed_submaps,
            "dropped_sessions": final_version.counts.dropped_sessions,
        },
        "agents_at_version": agents_at,
        "cri": report.run.cri,
        "cri_committed": report.run.cri_committed,
        "mrcl": report.run.mrcl,
        "mrcl_smoothed": report.run.mrcl_smoothed,
        "wrong_placements": report.run.wrong_placements,
        "mrwl": report.run.mrwl,
        "score": report.run,
        "scoring": scoring,
        "relocalization_score_mean": report.score_mean,
        "mcr": mcr,
        "wall_time_s": wall_time_s,
        "robot_data_s": robot_seconds,
        "uplink_bytes": metrics.bytes_in(),
        "uplink_bytes_per_robot_second": metrics.bytes_in() as f64 / robot_seconds.max(1e-9),
        "downlink_bytes": metrics.bytes_out(),
        "backend_runs": pgr_runs,
        "backend_mean_ms": pgr_mean_ms,
        "sessions": report.sessions,
    });
    let report_path = args.out.join("report.json");
    std::fs::write(&report_path, serde_json::to_string_pretty(&summary)? + "\n")
        .with_context(|| format!("cannot write {}", report_path.display()))?;
    if let Some(addr) = fleet.server.console_addr()
        && args.linger_s > 0.0
    {
        eprintln!(
            "evermap demo: done; the web console at http://{addr}/ stays up for {} s",
            args.linger_s
        );
        tokio::time::sleep(Duration::try_from_secs_f64(args.linger_s)?).await;
    }
    fleet.server.shutdown().await?;
    println!(
        "demo done in {wall_time_s:.0} s: version {} ({} sessions, {} nodes, {} submaps, {} trimmed); every robot at version {:?}; CRI {}, MRCL {:.3} (smoothed {:.3}), {} wrong placements, driven wrongly localized {:.3}, MCR {}; maps in {}",
        final_version.version,
        final_version.counts.sessions,
        final_version.counts.nodes,
        final_version.counts.submaps,
        final_version.counts.trimmed_submaps,
        agents_at,
        report.run.cri.map_or("-".into(), |c| format!("{c:.2}")),
        report.run.mrcl,
        report.run.mrcl_smoothed,
        report.run.wrong_placements,
        report.run.mrwl,
        mcr.map_or("-".into(), |m| format!("{m:.3}")),
        args.out.display()
    );
    Ok(())
}

/// The demo's map server on sled in `<out>/data`, serving [`SITE`] to its robots over loopback zenoh or
/// gRPC, with the web console when asked.
struct DemoServer {
    server: RunningServer,
    robots: Vec<RobotConfig>,
    zenoh_endpoint: Option<String>,
    /// The gRPC URL.
    url: String,
    site: SiteHandle,
}

impl DemoServer {
    async fn start(args: &DemoArgs) -> anyhow::Result<Self> {
        let store_options = SledStoreOptions {
            path: args.out.join("data"),
            ..SledStoreOptions::default()
        };
        let store = tokio::task::spawn_blocking(move || SledStore::open(&store_options))
            .await
            .context("storage thread")??;
        let robots: Vec<RobotConfig> = (1..=args.agents)
            .map(|k| RobotConfig {
                id: robot_id(k),
                token: format!("demo-token-robot-{k}"),
            })
            .collect();
        let zenoh_endpoint = match args.transport.as_str() {
            "zenoh" => Some(format!("tcp/127.0.0.1:{}", free_loopback_port()?)),
            _ => None,
        };
        let config = ServerConfig {
            listen: "127.0.0.1:0".parse()?,
            metrics_listen: None,
            max_message_bytes: MAX_MESSAGE_BYTES,
            zenoh: zenoh_endpoint.as_ref().map(|endpoint| ZenohLinkOptions {
                listen: vec![endpoint.clone()],
                ..ZenohLinkOptions::default()
            }),
            sites: vec![SiteConfig {
                id: SITE.into(),
                robots: robots.clone(),
            }],
            http: args.http.map(|listen| HttpConfig {
                listen,
                operator_token: Some(format!("demo-operator-{:016x}", rand::random::<u64>())),
                ..HttpConfig::default()
            }),
            ..ServerConfig::default()
        };
        let server = RunningServer::start(&config, Arc::new(store)).await?;
        if let (Some(addr), Some(token)) = (
            server.console_addr(),
            config.http.as_ref().and_then(|h| h.operator_token.as_ref()),
        ) {
            eprintln!("evermap demo: web console at http://{addr}/?token={token}");
        }
        let url = format!("http://{}", server.grpc_addr());
        let site = server
            .site(SITE)
            .context("the demo site is not served")?
            .clone();
        eprintln!(
            "evermap demo: map server on {} ({}; sled in {}), site {SITE}, {} robots, {} cleaning sessions each",
            zenoh_endpoint.as_deref().unwrap_or(&url),
            args.transport,
            args.out.join("data").display(),
            args.agents,
            args.sessions_per_agent
        );
        Ok(Self {
            server,
            robots,
            zenoh_endpoint,
            url,
            site,
        })
    }

    /// One agent per robot: its uplink (zenoh or gRPC) and a site follower keeping its submap cache at
    /// the site's version until `stopped`.
    async fn connect_agents(
        &self,
        args: &DemoArgs,
        stopped: &watch::Receiver<bool>,
    ) -> anyhow::Result<(Vec<Agent>, Vec<tokio::task::JoinHandle<()>>)> {
        let mut agents = Vec::new();
        let mut followers = Vec::new();
        for (k, robot) in self.robots.iter().enumerate() {
            let call_timeout = Duration::from_secs(30);
            let uplink = match &self.zenoh_endpoint {
                Some(endpoint) => {
                    let options = ZenohLinkOptions {
                        connect: vec![endpoint.clone()],
                        ..ZenohLinkOptions::default()
                    };
                    FleetUplink::Zenoh(
                        ZenohUplink::connect(&options, SITE, &robot.token, call_timeout).await?,
                    )
                }
                None => FleetUplink::Grpc(Box::new(GrpcUplink::new(
                    &self.url,
                    SITE,
                    &robot.token,
                    MAX_MESSAGE_BYTES,
                    call_timeout,
                )?)),
            };
            let cache = Arc::new(Mutex::new(GlobalSubmapCache::default()));
            followers.push(tokio::spawn(follow_site(
                uplink.clone(),
                Arc::clone(&cache),
                stopped.clone(),
                Duration::from_millis(200),
            )));
            agents.push(Agent {
                robot: k + 1,
                uplink,
                cache,
                out: args.out.join(format!("agent-{}", k + 1)),
                site: self.site.clone(),
            });
        }
        Ok((agents, followers))
    }
}

/// Day 0, robot 1 maps the store; then on later days every robot cleans it, `per_agent` sessions each,
/// concurrently. Every session run, once every agent's cache has caught up with the site.
async fn clean_the_store(
    agents: Vec<Agent>,
    world: &Store,
    sim: &SimSessionOptions,
    per_agent: usize,
    bar: &ProgressBar,
    caches: &[Arc<Mutex<GlobalSubmapCache>>],
) -> anyhow::Result<Vec<SessionRun>> {
    let site = agents[0].site.clone();
    // Day 0: robot 1 maps the store.
    let mut runs = Vec::new();
    say(
        bar,
        "session 0: robot-1 maps the store (the whole sweep)".into(),
    );
    runs.push(run_session(&agents[0], world, sim, 0, false).await?);
    bar.inc(1);
    wait_caught_up(&site, caches).await;

    // Later days: every robot cleans, concurrently.
    let count = agents.len();
    let mut tasks = Vec::new();
    for agent in agents {
        let world = world.clone();
        let sim = sim.clone();
        let bar = bar.clone();
        tasks.push(tokio::spawn(async move {
            let mut done = Vec::new();
            for j in 0..per_agent {
                let session = u32::try_from(1 + j * count + (agent.robot - 1))?;
                say(
                    &bar,
                    format!("session {session}: robot-{} starts cleaning", agent.robot),
                );
                let run = run_session(&agent, &world, &sim, session, true).await?;
                say(
                    &bar,
                    format!(
                        "session {session}: robot-{} done ({} nodes, relocalized: {})",
                        agent.robot,
                        run.node_times.len(),
                        run.prior.is_some()
                    ),
                );
                bar.inc(1);
                done.push(run);
            }
            anyhow::Ok(done)
        }));
    }
    for task in tasks {
        runs.extend(task.await.context("agent task")??);
    }
    wait_caught_up(&site, caches).await;
    Ok(runs)
}

/// The site's final map, as `maps/version-NNNNN.png` and `map.png` in `out`.
async fn write_final_map(site: &SiteHandle, out: &Path) -> anyhow::Result<()> {
    let rendered = site.render(0.05).await?;
    if let Some(grid) = &rendered.grid {
        let (w, h, pixels) = map_image::grid_to_gray(grid);
        map_image::write_gray_png(
            &out.join("maps")
                .join(format!("version-{:05}.png", rendered.version)),
            w,
            h,
            &pixels,
        )?;
        map_image::write_gray_png(&out.join("map.png"), w, h, &pixels)?;
    }
    Ok(())
}

fn robot_id(k: usize) -> String {
    format!("robot-{k}")
}

fn say(bar: &ProgressBar, line: String) {
    if bar.is_hidden() {
        eprintln!("{line}");
    } else {
        bar.println(line);
    }
}

/// A TCP port on 127.0.0.1 free right now (zenoh cannot report the port it bound, so the demo picks one).
fn free_loopback_port() -> anyhow::Result<u16> {
    let probe =
        std::net::TcpListener::bind("127.0.0.1:0").context("finding a free loopback port")?;
    Ok(probe.local_addr()?.port())
}

/// One simulated session streamed by `agent` (relocalizing its start against its cache when `relocalize`).
async fn run_session(
    agent: &Agent,
    world: &Store,
    sim: &SimSessionOptions,
    session: u32,
    relocalize: bool,
) -> anyhow::Result<SessionRun> {
    let started = Instant::now();
    let simulated = world.session(session, sim)?;
    let recording = Arc::new(Recording::from_unsorted(
        simulated.events,
        simulated.base_from_laser,
        ReadReport::default(),
    ));
    let outbox_dir = agent.out.clone();
    let outbox = tokio::task::spawn_blocking(move || Outbox::open(&outbox_dir, SITE))
        .await
        .context("outbox thread")??;
    let uuid = format!("demo-robot-{}-session-{session}", agent.robot);
    let robot = robot_id(agent.robot);
    let mut uploader = Uploader::new(agent.uplink.clone(), outbox, SITE, &robot, &uuid)?;
    let options = SessionOptions {
        replay_speed: 0.0,
        final_flush_timeout: Duration::from_secs(120),
        ..SessionOptions::default()
    };
    let start = relocalize.then(|| SessionStart {
        cache: &agent.cache,
        relocalization: RelocalizationOptions::default(),
        session_start: mapping::lifelong::SessionStartOptions::default(),
        // The simulated robots start wherever the session generator puts them.
        dock: None,
    });
    let (report, trace) = stream_session(recording, &options, &mut uploader, start)
        .instrument(session_span(SITE, &robot, &uuid))
        .await?;
    // Opening is idempotent: this returns the trajectory the server gave the session.
    let opened = uploader.uplink_mut().open_session(&robot, &uuid).await?;
    let end_poses = agent
        .site
        .node_poses()
        .await?
        .into_iter()
        .filter(|(id, _)| id.trajectory == opened.trajectory)
        .collect();
    Ok(SessionRun {
        session,
        robot: agent.robot,
        trajectory: opened.trajectory,
        truth: simulated.ground_truth,
        node_times: trace.node_times,
        node_estimates: trace.node_estimates,
        prior: trace.prior,
        placements: trace.start.placements,
        committed: trace.start.committed,
        revoked: trace.start.revoked,
        score: trace.score,
        relocalization_ms: trace.relocalization_ms,
        distance_m: simulated.distance_m,
        duration_s: simulated.duration_s,
        batches: report.batches,
        failed_flushes: report.failed_flushes,
        left_in_outbox: report.left_in_outbox,
        wall_s: started.elapsed().as_secs_f64(),
        end_poses,
    })
}

/// Waits (at most 30 s) until every agent's cache holds the site's current version.
async fn wait_caught_up(site: &SiteHandle, caches: &[Arc<Mutex<GlobalSubmapCache>>]) {
    let deadline = Instant::now() + Duration::from_secs(30);
    let target = site.current().version;
    while Instant::now() < deadline {
        if caches
            .iter()
            .all(|c| c.lock().is_ok_and(|c| c.version() >= target))
        {
            return;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Prints the site's versions (at most every 2 s) and writes a map picture at most every 5 s.
async fn print_versions(
    site: SiteHandle,
    caches: Vec<Arc<Mutex<GlobalSubmapCache>>>,
    maps: PathBuf,
    bar: ProgressBar,
    mut stop: watch::Receiver<bool>,
) {
    let mut versions = site.subscribe();
    let (mut last_line, mut last_png) = (Instant::now(), Instant::now());
    loop {
        tokio::select! {
            changed = versions.changed() => if changed.is_err() { return },
            _ = stop.changed() => return,
        }
        let info = *versions.borrow_and_update();
        if last_line.elapsed() >= Duration::from_secs(2) {
            last_line = Instant::now();
            let at: Vec<u64> = caches
                .iter()
                .map(|c| c.lock().map_or(0, |c| c.version()))
                .collect();
            let c = info.counts;
            say(
                &bar,
                format!(
                    "version {:>5}: {} sessions, {} nodes, {} submaps ({} finished), {} constraints, {} loop closures, {} trimmed; robots at versions {at:?}",
                    info.version,
                    c.sessions,
                    c.nodes,
                    c.submaps,
                    c.finished_submaps,
                    c.constraints,
                    c.loop_closures,
                    c.trimmed_submaps
                ),
            );
        }
        if last_png.elapsed() >= Duration::from_secs(5) {
            last_png = Instant::now();
            if let Ok(rendered) = site.render(0.1).await
                && let Some(grid) = rendered.grid
            {
                let (w, h, pixels) = map_image::grid_to_gray(&grid);
                let path = maps.join(format!("version-{:05}.png", rendered.version));
                if let Err(e) = map_image::write_gray_png(&path, w, h, &pixels) {
                    say(&bar, format!("cannot write {}: {e}", path.display()));
                }
            }
        }
    }
}

/// MCR between session 0's submaps and the map as its newest submaps describe it, from a robot's cache
/// (what the fleet sees); writes the picture.
fn write_map_change(cache: &Mutex<GlobalSubmapCache>, out: &Path) -> anyhow::Result<Option<f64>> {
    let placed: Vec<_> = cache
        .lock()
        .map_err(|_| anyhow::anyhow!("the submap cache lock is poisoned"))?
        .submaps()
        .values()
        .map(|s| {
            (
                s.id,
                s.global_pose * s.local_pose.inverse(),
                Arc::clone(&s.grid),
            )
        })
        .collect();
    let grids = |first_only: bool| {
        placed
            .iter()
            .filter(move |(id, _, _)| !first_only || id.trajectory == 0)
            .map(|(_, global_from_grid, grid)| PlacedGrid {
                global_from_grid: *global_from_grid,
                grid,
            })
    };
    let (Some(before), Some(after)) = (
        render_submaps_newest(grids(true), 0.05),
        render_submaps_newest(grids(false), 0.05),
    ) else {
        return Ok(None);
    };
    let change = map_change_rate(&before, &after, MAP_CHANGE_TOLERANCE_M);
    let (w, h, pixels) = map_image::map_change_to_rgb(&change);
    map_image::write_rgb_png(&out.join("map_change.png"), w, h, &pixels)?;
    Ok(Some(change.rate))
}

struct Scores {
    run: mapping::metrics::RunScore,
    score_mean: Option<f64>,
    sessions: Vec<serde_json::Value>,
}

/// Each session scored by `mapping::metrics` (as `lifelong` scores its sessions) at node level: the
/// robot's own estimate of each node at its time, and the node poses the site map had right after the
/// session ended (`poses`, smoothed), against the simulator's truth in session 0's frame. The placement
/// a session committed to is its robot's, once its probation passed (a session the server placed later never had a pose
/// of its own on the robot). AMS is not measured here.
fn score(
    runs: &[SessionRun],
    poses: &BTreeMap<NodeId, Rigid2>,
    scoring: &ScoringOptions,
) -> Scores {
    let smoothed = |run: &SessionRun| -> Vec<(Timestamp, Rigid2)> {
        run.node_times
            .iter()
            .enumerate()
            .filter_map(|(i, t)| {
                let id = NodeId {
                    trajectory: run.trajectory,
                    index: u32::try_from(i).ok()?,
                };
                Some((*t, *poses.get(&id)?))
            })
            .collect()
    };
    let world_from_map = runs
        .iter()
        .find(|r| r.session == 0)
        .map_or_else(Rigid2::identity, |r| align_to_truth(&smoothed(r), &r.truth));
    let mut later: Vec<SessionScore> = Vec::new();
    let mut relocalization_scores = Vec::new();
    let mut sessions = Vec::new();
    for run in runs {
        let smoothed = smoothed(run);
        let online: Vec<(Timestamp, Rigid2)> = if run.session == 0 {
            // The mapping session defines the map: its own estimate is the map's.
            smoothed.clone()
        } else {
            run.node_times
                .iter()
                .zip(&run.node_estimates)
                .filter_map(|(t, e)| Some((*t, (*e)?)))
                .collect()
        };
        // Every placement the robot acted on, and the one it committed to (the mapping session has none).
        let (placements, committed): (&[Placement], _) = if run.session > 0 {
            (&run.placements, run.committed)
        } else {
            (&[], None)
        };
        // The robots report an estimate per node (scans that passed the motion filter), not per scan:
        // the session is scored on its nodes' scans.
        let node_times: std::collections::BTreeSet<Timestamp> =
            run.node_times.iter().copied().collect();
        let truth: Vec<(Timestamp, Rigid2)> = run
            .truth
            .iter()
            .filter(|(t, _)| node_times.contains(t))
            .copied()
            .collect();
        let track = SessionTrack {
            truth: &truth,
            start_time: run.truth.first().map_or(Timestamp::default(), |(t, _)| *t),
            online: &online,
            smoothed: &smoothed,
            placements,
            committed,
            match_scores: &[],
            search_bests: &[],
        };
        let score = score_session(&track, &world_from_map, scoring);
        if run.session > 0 {
            later.push(score);
            relocalization_scores.extend(run.score.map(f64::from));
        }
        sessions.push(json!({
            "session": run.session, "robot": run.robot, "trajectory": run.trajectory,
            "nodes": run.node_times.len(), "nodes_in_map": smoothed.len(),
            "score": score,
            "relocalization_score": run.score, "relocalization_ms": run.relocalization_ms,
            "placed_tentatively": run.prior.is_some(), "committed": run.committed.is_some(),
            "revoked": run.revoked,
            "distance_m": run.distance_m, "batches": run.batches,
            "failed_flushes": run.failed_flushes, "left_in_outbox": run.left_in_outbox,
            "wall_s": run.wall_s,
        }));
    }
    Scores {
        run: score_run(&later),
        score_mean: (!relocalization_scores.is_empty()).then(|| {
            relocalization_scores.iter().sum::<f64>() / relocalization_scores.len() as f64
        }),
        sessions,
    }
}
