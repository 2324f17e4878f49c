//! Kill -9 anywhere (issue 16 §1): a real `evermap-server serve` and two real `evermap-agent run`
//! processes on loopback gRPC, both robots mapping one site. The server is SIGKILLed at seeded random
//! moments while the robots stream, and restarted on the same port and sled directory; each agent is
//! SIGKILLed once mid-session and restarted (it ends its interrupted session, then maps a new one).
//! Afterwards:
//! - every batch an agent had acknowledged before its kill is stored, every session's batches are
//!   stored exactly once (sequence numbers 1..=n, each once), and their nodes are exactly the nodes an
//!   independent in-process LLO run makes of the robot's recording (a prefix of them for an interrupted
//!   session);
//! - the site versions a client saw never went backwards, across every restart;
//! - every outbox drains (each agent exits 0 with nothing left), and no session stays open;
//! - the served map equals the map of a site that was never killed (an in-process `SiteMap`) fed the
//!   same sessions in the same order.
//!
//! Checkpoints (issue 34 item 3): the server checkpoints the site every `EVERMAP_CHAOS_CHECKPOINT_EVERY`
//! versions (default 10) besides every session end, and some server kills wait for a checkpoint write to
//! begin (the server's DEBUG line "writing the site's checkpoint") and land a few milliseconds into it: into `put_checkpoint` or the compaction after it. Each restart starts from the newest
//! checkpoint and the log after it, so the served map above is a restored one. The server keeps the whole
//! log for audit (`keep_log_entries`): the checks above read every batch from it; compaction still
//! deletes every checkpoint but the newest 2 (deleting log entries under kill -9 is
//! `storage/tests/kill_nine.rs`'s). Asserted besides: checkpoints were written, and the server restarted
//! from one.
//!
//! Why not "equal to a second, uninterrupted run": what a robot sends besides its LLO output (the
//! session-start placement it finds against its cache of the site, its GLM matches) and how two robots'
//! batches interleave depend on timing, and a killed agent's new session replays its recording from the
//! start, so a second run makes a different, equally valid map. What the robots sent is fixed once it is
//! stored: a map that is fed exactly that without being killed is the comparable one, and the nodes
//! themselves are checked against LLO run here.
//!
//! Two tests: the agents' uplink over gRPC, and over zenoh (the agents reach the server's zenoh
//! endpoint, which dies with it: their zenoh links drop at every kill and come back by zenoh's own
//! reconnection). Server kills: `EVERMAP_CHAOS_SERVER_KILLS` (default 4 over gRPC and 2 over zenoh, CI;
//! the 20 in the benchmark of BENCHMARKS.md); seed: `EVERMAP_CHAOS_SEED` (default 16); scans
//! each robot replays: `EVERMAP_CHAOS_SCANS` (default 600), robot 2's slice starting 45 % of that later
//! than robot 1's. Needs `evermap-server` and `evermap-agent` built beside
//! `evermap-demo` (this crate depends on both crates, not on their binaries), as `cargo nextest run
//! --workspace` does. Every wait is bounded.

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mapping::lifelong::LifelongOptions;
use mapping::sensor::SensorEvent;
use prost::Message as _;
use proto::pb::map_service_client::MapServiceClient;
use proto::{MapDelta, NodeAdded, UploadBatch, UploadItem, pb};
use rand::{Rng as _, SeedableRng as _};
use robot_agent::outbox::Outbox;
use robot_agent::source::{ReadReport, Recording, read_recording, write_bag};
use robot_agent::uplink::{SessionOptions, run_llo};
use server::site::SiteMap;
use storage::{MapStore as _, RecordKind, SledStore, SledStoreOptions};
use test_support::{datasets_dir, free_port};
use tonic::transport::{Channel, Endpoint};

const SITE: &str = "store-k9";
/// (robot id, token, where its slice of CSAIL starts as a fraction of the slice length).
const ROBOTS: [(&str, &str, f64); 2] = [
    ("r1", "token-k9-robot-1", 0.0),
    ("r2", "token-k9-robot-2", 0.45),
];
/// Longest any single wait may take.
const WAIT: Duration = Duration::from_secs(60);
/// Longest the whole run may take.
const RUN_LIMIT: Duration = Duration::from_secs(600);
/// The server's log: INFO, and the site task's DEBUG line that a checkpoint write begins.
const SERVER_LOG_FILTER: &str = "info,server::site::site_task=debug";
/// The server's line before a checkpoint's `put_checkpoint` and compaction, and the ones after them.
const CHECKPOINT_BEGINS: &str = "writing the site's checkpoint";
const CHECKPOINT_ENDS: [&str; 2] = ["site checkpointed", "cannot store the site's checkpoint"];
/// Longest a kill waits for a checkpoint write to begin.
const CHECKPOINT_WAIT: Duration = Duration::from_secs(2);

/// The server's log from byte `from` on (`from` itself when it is past the end).
fn log_from(log: &Path, from: usize) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    text.get(from..).unwrap_or_default().to_owned()
}

/// Waits until the server's log (from its current end) says a checkpoint write begins, at most
/// [`CHECKPOINT_WAIT`]; polls the new bytes only, every 0.2 ms.
fn wait_for_checkpoint_write(log: &Path) {
    use std::io::{Read as _, Seek as _, SeekFrom};
    let Ok(mut file) = File::open(log) else {
        return;
    };
    if file.seek(SeekFrom::End(0)).is_err() {
        return;
    }
    let (waiting, mut new) = (Instant::now(), Vec::new());
    while waiting.elapsed() < CHECKPOINT_WAIT {
        if file.read_to_end(&mut new).is_err() {
            return;
        }
        if new
            .windows(CHECKPOINT_BEGINS.len())
            .any(|w| w == CHECKPOINT_BEGINS.as_bytes())
        {
            return;
        }
        std::thread::sleep(Duration::from_micros(200));
    }
}

/// Whether `text` (one run's log) ends inside a checkpoint write: it began and neither ended nor failed.
fn inside_checkpoint(text: &str) -> bool {
    let began = text.rfind(CHECKPOINT_BEGINS);
    let ended = CHECKPOINT_ENDS
        .iter()
        .filter_map(|line| text.rfind(line))
        .max();
    began.is_some_and(|began| ended.is_none_or(|ended| ended < began))
}

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// A binary of another crate of the workspace (`evermap-server`, `evermap-agent`), built beside this
/// crate's `evermap-demo`.
fn sibling_binary(name: &str) -> PathBuf {
    let demo = PathBuf::from(env!("CARGO_BIN_EXE_evermap-demo"));
    let binary = demo.with_file_name(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    assert!(
        binary.is_file(),
        "{} is missing: build the workspace (cargo nextest run --workspace builds it)",
        binary.display()
    );
    binary
}

fn agent_binary() -> PathBuf {
    sibling_binary("evermap-agent")
}

/// `s` seconds (finite and non-negative here).
fn seconds(s: f64) -> Duration {
    Duration::try_from_secs_f64(s).expect("a duration")
}

/// Scans `from..from + scans` of `recording` with the odometry between them.
fn slice(recording: &Recording, from: usize, scans: usize) -> Recording {
    let scan_times: Vec<_> = recording
        .events
        .iter()
        .filter(|e| matches!(e, SensorEvent::Scan(_)))
        .map(SensorEvent::time)
        .collect();
    let last = (from + scans).min(scan_times.len()) - 1;
    let (start, end) = (scan_times[from], scan_times[last]);
    Recording::from_unsorted(
        recording
            .events
            .iter()
            .filter(|e| e.time() >= start && e.time() <= end)
            .cloned()
            .collect(),
        recording.base_from_laser,
        ReadReport::default(),
    )
}

/// The nodes LLO makes of `recording`, through the conversions the stored ones went through: the agent
/// sends the wire form, the server converts it and stores the wire form of that, the test reads it (a
/// pose's angle goes through `atan2` and `sin`/`cos` twice).
fn llo_nodes(recording: &Recording) -> Vec<NodeAdded> {
    let mut nodes = Vec::new();
    run_llo(
        recording,
        &SessionOptions::default().local,
        0.0,
        None,
        &mut |items| {
            for item in &items {
                let received = UploadItem::try_from(&pb::UploadItem::from(item));
                let stored = received.and_then(|r| UploadItem::try_from(&pb::UploadItem::from(&r)));
                if let Ok(UploadItem::NodeAdded(node)) = stored {
                    nodes.push(node);
                }
            }
            true
        },
    );
    nodes
}

/// Runs `binary` with its output appended to `log`, logging at INFO, or as `rust_log` says.
fn spawn_logged(binary: &Path, args: &[&str], log: &Path, rust_log: Option<&str>) -> Child {
    let out = File::options()
        .create(true)
        .append(true)
        .open(log)
        .expect("log file");
    let err = out.try_clone().expect("log file");
    let mut command = Command::new(binary);
    command.args(args).env("NO_COLOR", "1");
    // The test reads the binaries' INFO lines ("starting session"): whatever RUST_LOG the runner has
    // must not filter them out.
    match rust_log {
        Some(filter) => command.env("RUST_LOG", filter),
        None => command.env_remove("RUST_LOG"),
    };
    command
        .stdout(out)
        .stderr(err)
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {}: {e}", binary.display()))
}

fn tail(log: &Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(40)..].join("\n")
}

fn kill(child: &mut Child) {
    let _ = child.kill();
    let _ = child.wait();
}

fn authed<T>(message: T, token: &str) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    request.metadata_mut().insert(
        "authorization",
        format!("Bearer {token}").parse().expect("header"),
    );
    request
}

async fn get_version(client: &mut MapServiceClient<Channel>) -> Option<pb::MapVersion> {
    let request = authed(pb::GetVersionRequest { site: SITE.into() }, ROBOTS[0].1);
    client
        .get_version(request)
        .await
        .ok()
        .map(tonic::Response::into_inner)
}

/// Waits until the server answers (restarting it if it died starting, e.g. on a port not yet free).
async fn wait_up(
    server: &mut Child,
    start: &dyn Fn() -> Child,
    client: &mut MapServiceClient<Channel>,
) -> Duration {
    let began = Instant::now();
    let mut restarts = 0;
    loop {
        assert!(
            began.elapsed() < WAIT,
            "the server did not come up within {WAIT:?}"
        );
        if get_version(client).await.is_some() {
            return began.elapsed();
        }
        if let Ok(Some(status)) = server.try_wait() {
            restarts += 1;
            assert!(restarts <= 5, "the server keeps exiting: {status}");
            tokio::time::sleep(Duration::from_millis(200)).await;
            *server = start();
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The session uuid an agent's log announces ("starting session ... session=<uuid>").
fn announced_session(log: &Path) -> Option<String> {
    let text = std::fs::read_to_string(log).ok()?;
    let line = text.lines().find(|l| l.contains("starting session"))?;
    line.split(|c: char| !(c.is_ascii_hexdigit() || c == '-'))
        .find(|word| word.len() == 36 && word.matches('-').count() == 4)
        .map(str::to_owned)
}

/// One robot's process and what its kill left behind.
struct Agent {
    robot: &'static str,
    config: PathBuf,
    outbox: PathBuf,
    log: PathBuf,
    child: Child,
    /// How long after it announced its first session the agent is killed (once the server knows it).
    kill_after: Duration,
    /// When the first run's session was first seen in the agent's own log. Counted from the agent's
    /// side, not from when the server first logged it: a server killed and restarting for a while under
    /// load learns of the session late, and a kill timed from then could fall after the robot had
    /// already ended its session.
    streaming_since: Option<Instant>,
    /// At the kill: each unfinished session and the highest sequence number still in the outbox
    /// (0: none pending, everything the session made was acknowledged).
    at_kill: Option<BTreeMap<String, u64>>,
    /// Whether the outbox already held the session's end at the kill: the robot had ended it itself and
    /// the kill only interrupted the delivery (a server restart under load can hold the test's loop past
    /// the robot's own end of its 8-second session).
    ended_at_kill: bool,
    exit: Option<ExitStatus>,
}

impl Agent {
    fn start(&mut self) {
        self.child = spawn_logged(
            &agent_binary(),
            &["run", "--config", &self.config.to_string_lossy()],
            &self.log,
            None,
        );
    }

    /// Whether it is time to kill the first run: it announced its session `kill_after` ago and the
    /// server knows the session.
    fn due(&mut self, server_log: &Path) -> bool {
        if self.at_kill.is_some() {
            return false;
        }
        let Some(session) = announced_session(&self.log) else {
            return false;
        };
        let since = *self.streaming_since.get_or_insert_with(Instant::now);
        since.elapsed() >= self.kill_after
            && std::fs::read_to_string(server_log).is_ok_and(|log| log.contains(&session))
    }

    fn kill_and_inspect(&mut self) {
        kill(&mut self.child);
        let outbox = Outbox::open(&self.outbox, SITE).expect("the killed agent's outbox");
        let mut at_kill: BTreeMap<String, u64> = outbox
            .unfinished_sessions()
            .expect("unfinished sessions")
            .into_iter()
            .map(|(session, _)| (session, 0))
            .collect();
        for batch in outbox.pending().expect("pending") {
            let batch = UploadBatch::try_from(&batch).expect("a pending batch");
            self.ended_at_kill |= batch.items.contains(&UploadItem::SessionEnd);
            let seq = at_kill.entry(batch.session_uuid).or_default();
            *seq = (*seq).max(batch.seq);
        }
        self.at_kill = Some(at_kill);
    }
}

/// One session as the site log holds it.
#[derive(Default)]
struct StoredSession {
    robot: String,
    seqs: Vec<u64>,
    nodes: Vec<NodeAdded>,
    ended_by_robot: bool,
    closed: bool,
}

// Reference: issue 16 §1 "Kill -9, anywhere".
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_and_agents_killed_anywhere_lose_nothing_and_duplicate_nothing() {
    chaos("grpc", 4, ROBOTS.len(), 0.5, false).await;
}

// Reference: issue 16 §1 "the same for the zenoh path: the link ... drop[s] mid-session; nothing is lost
// or duplicated".
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zenoh_links_dropping_with_a_killed_server_lose_nothing_and_duplicate_nothing() {
    chaos("zenoh", 2, ROBOTS.len(), 0.5, false).await;
}

// Reference: issue 34 item 3 "kill -9 at random points during checkpoint writing and compaction ...
// loses nothing acknowledged and always restarts from a consistent checkpoint". One robot: a site's
// first session is placed at once, so the site can be checkpointed all along it (with two robots one
// session is mid-start most of the time, and no checkpoint is taken then); most server kills are timed
// for a checkpoint write.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_killed_while_writing_checkpoints_loses_nothing_and_restarts_from_one() {
    chaos("grpc", 6, 1, 0.8, true).await;
}

/// `robots`: the first this many of [`ROBOTS`] map the site; `timed_kills`: the share of server kills
/// timed for a checkpoint write; `require_checkpoint_restart`: at least one restart must start from a
/// checkpoint (with few kills all may land before the first checkpoint is stored).
async fn chaos(
    transport: &str,
    default_kills: usize,
    robots: usize,
    timed_kills: f64,
    require_checkpoint_restart: bool,
) {
    let mapping_robots = &ROBOTS[..robots];
    let server_kills: usize = env_or("EVERMAP_CHAOS_SERVER_KILLS", default_kills);
    let seed: u64 = env_or("EVERMAP_CHAOS_SEED", 16);
    let scans: usize = env_or("EVERMAP_CHAOS_SCANS", 600);
    let checkpoint_every: u64 = env_or("EVERMAP_CHAOS_CHECKPOINT_EVERY", 10);
    let zenoh_endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let (server_zenoh, agent_zenoh) = if transport == "zenoh" {
        (
            format!("[zenoh]\nlisten = [\"{zenoh_endpoint}\"]\n"),
            format!("[zenoh]\nconnect = [\"{zenoh_endpoint}\"]\n"),
        )
    } else {
        (String::new(), String::new())
    };
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let dir = tempfile::tempdir().expect("tempdir");
    let csail = read_recording(&datasets_dir().join("rosbag1/mit-csail.orig.bag")).expect("CSAIL");

    // Each robot's recording and its duration; the nodes LLO makes of it are computed beside the run.
    let mut bags = BTreeMap::new();
    let mut duration_s: f64 = 0.0;
    for &(robot, _, from) in mapping_robots {
        let path = dir.path().join(format!("{robot}.bag"));
        let part = slice(&csail, (from * scans as f64) as usize, scans);
        let mut out = std::io::BufWriter::new(File::create(&path).expect("bag"));
        write_bag(&mut out, &part.events, &part.base_from_laser).expect("write bag");
        drop(out);
        let (first, last) = (part.events.first(), part.events.last());
        if let (Some(first), Some(last)) = (first, last) {
            duration_s = duration_s.max((last.time().0 - first.time().0) as f64 * 1e-9);
        }
        bags.insert(robot, path);
    }
    let llo = {
        let bags = bags.clone();
        std::thread::Builder::new()
            .name("expected-llo".into())
            .spawn(move || {
                bags.into_iter()
                    .map(|(robot, path)| {
                        (robot, llo_nodes(&read_recording(&path).expect("read back")))
                    })
                    .collect::<BTreeMap<_, _>>()
            })
            .expect("a thread")
    };
    // A session lasts long enough for every server kill to land while the robots stream (a kill timed
    // for a checkpoint write waits for one, about a second).
    let session_s = ((1.2 + timed_kills) * server_kills as f64).max(8.0);
    let replay_speed = duration_s / session_s;

    let port = free_port();
    let data = dir.path().join("server-data");
    let server_config = dir.path().join("server.toml");
    let robots = ROBOTS
        .iter()
        .map(|(id, token, _)| format!("{{ id = \"{id}\", token = \"{token}\" }}"))
        .collect::<Vec<_>>()
        .join(", ");
    std::fs::write(
        &server_config,
        format!(
            "listen = \"127.0.0.1:{port}\"\nmetrics_listen = \"127.0.0.1:0\"\n\
             session_idle_timeout_s = 600.0\n[storage]\npath = \"{}\"\n\
             [checkpoints]\nevery_n_versions = {checkpoint_every}\nkeep_log_entries = 1000000000\n\
             {server_zenoh}[[sites]]\nid = \"{SITE}\"\nrobots = [{robots}]\n",
            data.display()
        ),
    )
    .expect("server config");
    let server_log = dir.path().join("server.log");
    let server_binary = sibling_binary("evermap-server");
    let start_server = || {
        spawn_logged(
            &server_binary,
            &["serve", "--config", &server_config.to_string_lossy()],
            &server_log,
            Some(SERVER_LOG_FILTER),
        )
    };
    let url = format!("http://127.0.0.1:{port}");
    let endpoint = Endpoint::from_shared(url.clone())
        .expect("url")
        .connect_timeout(Duration::from_millis(500))
        .timeout(Duration::from_secs(5));
    let mut client = MapServiceClient::new(endpoint.connect_lazy());
    let mut server = start_server();
    wait_up(&mut server, &start_server, &mut client).await;

    // Every version a client sees, in order, while the server lives and dies.
    let seen = Arc::new(Mutex::new(Vec::<u64>::new()));
    let (stop_watching, mut stopped) = tokio::sync::watch::channel(false);
    let watcher = {
        let (seen, mut client) = (Arc::clone(&seen), client.clone());
        tokio::spawn(async move {
            while !*stopped.borrow() {
                if let Some(v) = get_version(&mut client).await
                    && let Ok(mut seen) = seen.lock()
                {
                    seen.push(v.version);
                }
                tokio::select! {
                    () = tokio::time::sleep(Duration::from_millis(50)) => {}
                    _ = stopped.changed() => {}
                }
            }
        })
    };

    let mut agents: Vec<Agent> = mapping_robots
        .iter()
        .map(|(robot, token, _)| {
            let config = dir.path().join(format!("{robot}.toml"));
            let outbox = dir.path().join(format!("{robot}-outbox"));
            std::fs::write(
                &config,
                format!(
                    "server_url = \"{url}\"\nsite = \"{SITE}\"\nrobot_id = \"{robot}\"\n\
                     token = \"{token}\"\nsource = \"{}\"\nreplay_speed = {replay_speed}\n\
                     outbox_dir = \"{}\"\nnodes_per_batch = 5\ncall_timeout_s = 5.0\n\
                     retry_interval_s = 0.2\nfinal_flush_timeout_s = 120.0\n{agent_zenoh}",
                    bags[robot].display(),
                    outbox.display()
                ),
            )
            .expect("agent config");
            let log = dir.path().join(format!("{robot}.log"));
            let kill_after = seconds(session_s * rng.random_range(0.3..0.6));
            let child = spawn_logged(
                &agent_binary(),
                &["run", "--config", &config.to_string_lossy()],
                &log,
                None,
            );
            Agent {
                robot,
                config,
                outbox,
                log,
                child,
                kill_after,
                streaming_since: None,
                at_kill: None,
                ended_at_kill: false,
                exit: None,
            }
        })
        .collect();

    let began = Instant::now();
    let mut kills = 0;
    let mut kills_while_streaming = 0;
    let mut restart_s = Vec::new();
    let mut next_kill = Instant::now() + seconds(rng.random_range(0.3..1.2));
    let (mut targeted_kills, mut kills_in_checkpoint) = (0, 0);
    let (mut checkpointed_before_kill, mut restart_log_from) = (Vec::new(), Vec::new());
    // Where the log of the server run that the next kill ends begins.
    let mut run_from = 0;
    while agents.iter().any(|a| a.exit.is_none()) {
        assert!(
            began.elapsed() < RUN_LIMIT,
            "the run did not end within {RUN_LIMIT:?}"
        );
        for agent in &mut agents {
            if agent.exit.is_some() {
                continue;
            }
            if let Ok(Some(status)) = agent.child.try_wait() {
                assert!(
                    agent.at_kill.is_some(),
                    "{} ended before its kill: make its session longer",
                    agent.robot
                );
                agent.exit = Some(status);
            } else if agent.due(&server_log) {
                agent.kill_and_inspect();
                agent.start();
            }
        }
        if kills < server_kills && Instant::now() >= next_kill {
            kills_while_streaming += usize::from(agents.iter().any(|a| a.exit.is_none()));
            // Some kills (at random) wait for a checkpoint write to begin, then land 0-1.5 ms after the
            // test saw it (a write and its compaction take a few ms here).
            if rng.random_bool(timed_kills) {
                wait_for_checkpoint_write(&server_log);
                targeted_kills += 1;
                std::thread::sleep(Duration::from_micros(rng.random_range(0..1_500)));
            }
            kill(&mut server);
            kills_in_checkpoint += usize::from(inside_checkpoint(&log_from(&server_log, run_from)));
            run_from = std::fs::metadata(&server_log).map_or(0, |m| m.len() as usize);
            // Whether a checkpoint was stored before this kill: the restart must then start from one.
            checkpointed_before_kill.push(log_from(&server_log, 0).contains(CHECKPOINT_ENDS[0]));
            restart_log_from.push(run_from);
            kills += 1;
            tokio::time::sleep(seconds(rng.random_range(0.05..0.5))).await;
            server = start_server();
            restart_s.push(
                wait_up(&mut server, &start_server, &mut client)
                    .await
                    .as_secs_f64(),
            );
            next_kill = Instant::now() + seconds(rng.random_range(0.3..1.2));
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let run_s = began.elapsed().as_secs_f64();
    for agent in &agents {
        let status = agent.exit.expect("exited");
        assert!(
            status.success(),
            "{} failed ({status}):\n{}",
            agent.robot,
            tail(&agent.log)
        );
        let log = std::fs::read_to_string(&agent.log).unwrap_or_default();
        assert!(
            log.contains(&format!("transport=\"{transport}\""))
                || log.contains(&format!("transport={transport}")),
            "{} did not use {transport}",
            agent.robot
        );
        let outbox = Outbox::open(&agent.outbox, SITE).expect("outbox");
        assert!(outbox.is_empty().expect("outbox"), "{}", agent.robot);
        assert!(
            outbox.unfinished_sessions().expect("outbox").is_empty(),
            "{}",
            agent.robot
        );
    }
    assert_eq!(kills, server_kills);
    let log = std::fs::read_to_string(&server_log).expect("the server's log");
    let checkpoint_s: Vec<f64> = log
        .lines()
        .filter(|line| line.contains(CHECKPOINT_ENDS[0]))
        .filter_map(|line| {
            line.split_whitespace()
                .find_map(|word| word.strip_prefix("seconds="))
                .and_then(|s| s.parse().ok())
        })
        .collect();
    let checkpoints_written = checkpoint_s.len();
    let checkpoint_max_s = checkpoint_s.iter().copied().fold(0.0, f64::max);
    // Each restart's start: from a checkpoint (the log after it replayed, or the site left unloaded
    // because the checkpoint covers its whole log) or from the whole log.
    let restarted_from_checkpoint: Vec<bool> = restart_log_from
        .iter()
        .map(|&from| {
            let run = log.get(from..).unwrap_or_default();
            let start = run
                .lines()
                .find(|line| {
                    line.contains("site log replayed") || line.contains("site starts unloaded")
                })
                .unwrap_or_default();
            start.contains("site starts unloaded")
                || start
                    .split_whitespace()
                    .any(|w| w.starts_with("checkpoint="))
        })
        .collect();
    assert!(
        !log.contains(CHECKPOINT_ENDS[1]) && !log.contains("cannot checkpoint the site"),
        "a checkpoint failed:\n{}",
        tail(&server_log)
    );
    // One way only: a kill may land after a checkpoint is stored and before its line is logged.
    assert!(
        checkpointed_before_kill
            .iter()
            .zip(&restarted_from_checkpoint)
            .all(|(&logged, &restored)| !logged || restored),
        "each restart after a stored checkpoint starts from one: checkpoints logged before each kill \
         {checkpointed_before_kill:?}, restarts from one {restarted_from_checkpoint:?}"
    );
    if require_checkpoint_restart {
        assert!(
            checkpoints_written > 0 && restarted_from_checkpoint.contains(&true),
            "the server must checkpoint the site and restart from a checkpoint: \
             {checkpoints_written} written, restarts from one: {restarted_from_checkpoint:?}"
        );
    }

    // The live server: no session open, no version lost.
    let _ = stop_watching.send(true);
    let _ = tokio::time::timeout(WAIT, watcher).await;
    let live = get_version(&mut client).await.expect("the final version");
    let live_counts = live.counts.expect("counts");
    let seen = seen.lock().expect("seen").clone();
    assert!(
        seen.windows(2).all(|w| w[0] <= w[1]),
        "versions went backwards: {seen:?}"
    );
    assert!(seen.last().is_some_and(|v| *v <= live.version));
    assert_eq!(live_counts.open_sessions, 0, "{live_counts:?}");
    let mut chunks = Vec::new();
    let mut stream = client
        .get_delta(authed(
            pb::GetDeltaRequest {
                site: SITE.into(),
                since_version: 0,
            },
            ROBOTS[0].1,
        ))
        .await
        .expect("delta")
        .into_inner();
    while let Some(chunk) = tokio::time::timeout(WAIT, stream.message())
        .await
        .expect("a delta chunk in time")
        .expect("delta chunk")
    {
        chunks.push(chunk);
    }
    let live_delta = MapDelta::from_pb_chunks(&chunks).expect("delta");
    // A last kill -9, then the log as stored.
    kill(&mut server);

    let store = SledStore::open(&SledStoreOptions::at(&data)).expect("the server's store");
    // Every stored checkpoint reads back from its file, and the files are exactly the stored ones (what
    // a kill between a file and its index entry leaves is deleted when the store opens).
    let checkpoints = store
        .checkpoint_indexes(SITE)
        .expect("the checkpoint indexes");
    for &index in &checkpoints {
        store
            .checkpoint(SITE, index)
            .unwrap_or_else(|e| panic!("checkpoint {index} does not read back: {e}"))
            .unwrap_or_else(|| panic!("checkpoint {index} is listed but absent"));
    }
    let files = std::fs::read_dir(data.join("checkpoints").join(SITE)).map_or(0, Iterator::count);
    assert_eq!(
        files,
        checkpoints.len(),
        "checkpoint files left beside the stored checkpoints {checkpoints:?}"
    );
    let expected = llo.join().expect("the expected LLO output");
    let mut reference = SiteMap::new(SITE, LifelongOptions::default()).expect("site map");
    let mut sessions: BTreeMap<String, StoredSession> = BTreeMap::new();
    let mut order = Vec::new();
    for (index, record) in store
        .scan(SITE, RecordKind::Trajectory)
        .expect("the site log")
        .enumerate()
    {
        let (id, bytes) = record.expect("a log record");
        let version = index as u64 + 1;
        assert_eq!(id.as_u64(), Some(version), "the log has no holes");
        let entry = pb::SiteLogEntry::decode(bytes.as_slice()).expect("a log entry");
        match entry.entry.expect("an entry") {
            pb::site_log_entry::Entry::SessionOpened(open) => {
                reference
                    .open_session(&open.robot_id, &open.session_uuid, open.trajectory, version)
                    .expect("open");
                assert!(!sessions.contains_key(&open.session_uuid), "opened twice");
                order.push(open.session_uuid.clone());
                sessions.insert(
                    open.session_uuid,
                    StoredSession {
                        robot: open.robot_id,
                        ..StoredSession::default()
                    },
                );
            }
            pb::site_log_entry::Entry::Upload(upload) => {
                let batch = UploadBatch::try_from(&upload).expect("a stored batch");
                let session = sessions
                    .get_mut(&batch.session_uuid)
                    .expect("an upload to an opened session");
                assert!(!session.closed, "an upload after the session's end");
                session.seqs.push(batch.seq);
                for item in &batch.items {
                    match item {
                        UploadItem::NodeAdded(node) => session.nodes.push(node.clone()),
                        UploadItem::SessionEnd => {
                            session.ended_by_robot = true;
                            session.closed = true;
                        }
                        _ => {}
                    }
                }
                reference.apply_upload(&batch, version).expect("apply");
            }
            pb::site_log_entry::Entry::SessionClosed(close) => {
                let session = sessions
                    .get_mut(&close.session_uuid)
                    .expect("a close of an opened session");
                assert!(!session.closed, "closed twice");
                session.closed = true;
                reference
                    .close_session(&session.robot, &close.session_uuid, version)
                    .expect("close");
            }
        }
    }
    assert_eq!(
        store.map_version(SITE).expect("version"),
        reference.version()
    );

    // Every robot: its interrupted session (everything acknowledged before the kill and everything
    // still in its outbox then, a prefix of its nodes, ended by the restarted agent) and its complete
    // one (all its nodes, ended by itself); every batch exactly once.
    for agent in &agents {
        let at_kill = agent.at_kill.as_ref().expect("killed");
        let nodes = &expected[agent.robot];
        let mine: Vec<&String> = order
            .iter()
            .filter(|s| sessions[*s].robot == agent.robot)
            .collect();
        assert_eq!(
            mine.len(),
            2,
            "{}: one interrupted and one complete session (at the kill: {at_kill:?})",
            agent.robot
        );
        let (interrupted, complete) = (&sessions[mine[0]], &sessions[mine[1]]);
        assert_eq!(
            at_kill.keys().collect::<Vec<_>>(),
            [mine[0]],
            "{}: killed mid-session",
            agent.robot
        );
        for session in [interrupted, complete] {
            let numbered: Vec<u64> = (1..=session.seqs.len() as u64).collect();
            assert_eq!(session.seqs, numbered, "{}: each batch once", agent.robot);
            assert!(session.closed);
        }
        assert!(
            interrupted.seqs.len() as u64 >= at_kill[mine[0]],
            "{}: what the outbox held at the kill was delivered",
            agent.robot
        );
        assert_eq!(
            (interrupted.ended_by_robot, complete.ended_by_robot),
            (agent.ended_at_kill, true),
            "{}: (interrupted, complete) session ended by the robot, as the outbox held at the kill",
            agent.robot
        );
        assert!(!interrupted.nodes.is_empty());
        assert_eq!(
            interrupted.nodes.len() == nodes.len(),
            agent.ended_at_kill,
            "{}: the interrupted session holds every node only if the robot had ended it",
            agent.robot
        );
        let first_difference = |stored: &[NodeAdded]| {
            stored
                .iter()
                .zip(nodes)
                .position(|(a, b)| a != b)
                .map(|i| format!("node {i}: stored {:?}, LLO {:?}", stored[i], nodes[i]))
        };
        assert_eq!(
            first_difference(&interrupted.nodes),
            None,
            "{}: the interrupted session's nodes are LLO's",
            agent.robot
        );
        assert!(
            complete.nodes == *nodes,
            "{}: the complete session's nodes are LLO's ({} stored, {} made)",
            agent.robot,
            complete.nodes.len(),
            nodes.len()
        );
    }
    assert!(reference.open_sessions().is_empty());

    // The served map is the never-killed map of the same sessions.
    let counts = reference.counts();
    assert_eq!(live.version, reference.version());
    assert_eq!(
        (
            live_counts.sessions,
            live_counts.nodes,
            live_counts.submaps,
            live_counts.finished_submaps,
            live_counts.constraints,
            live_counts.trimmed_submaps,
            live_counts.dropped_sessions,
            live_counts.loop_closures
        ),
        (
            counts.sessions,
            counts.nodes,
            counts.submaps,
            counts.finished_submaps,
            counts.constraints,
            counts.trimmed_submaps,
            counts.dropped_sessions,
            counts.loop_closures
        )
    );
    // Through the wire form, as the live one came.
    let reference_delta = MapDelta::from_pb_chunks(
        &reference
            .delta_since(0)
            .expect("delta")
            .to_pb_chunks(1 << 20),
    )
    .expect("delta");
    assert_eq!(
        live_delta.submaps_added.len(),
        reference_delta.submaps_added.len()
    );
    for (live, reference) in live_delta
        .submaps_added
        .iter()
        .zip(&reference_delta.submaps_added)
    {
        assert_eq!(
            (live.id, live.revision, live.global_pose, live.local_pose),
            (
                reference.id,
                reference.revision,
                reference.global_pose,
                reference.local_pose
            ),
            "a served submap differs from the never-killed map's"
        );
        assert!(
            live.grid == reference.grid,
            "submap {:?}'s grid differs",
            live.id
        );
    }
    assert_eq!(
        (&live_delta.pose_updates, &live_delta.trimmed),
        (&reference_delta.pose_updates, &reference_delta.trimmed)
    );
    assert!(live_delta == reference_delta, "the served map differs");
    eprintln!(
        "kill -9 chaos ({transport}, seed {seed}): {kills} server kills ({kills_while_streaming} while robots \
         streamed, {targeted_kills} timed for a checkpoint write, {kills_in_checkpoint} inside one), \
         {checkpoints_written} checkpoints written (at most {checkpoint_max_s:.3} s each), restarts from a checkpoint {restarted_from_checkpoint:?}, 2 agent kills ({} mid-session), {run_s:.1} s; restarts answered after {restart_s:.2?} s; final \
         version {}, {} sessions, {} nodes ({:?} per complete session), {} constraints, {} finished \
         submaps, {} trimmed, {} dropped; versions seen {}",
        agents.iter().filter(|a| !a.ended_at_kill).count(),
        live.version,
        counts.sessions,
        counts.nodes,
        expected.values().map(Vec::len).collect::<Vec<_>>(),
        counts.constraints,
        counts.finished_submaps,
        counts.trimmed_submaps,
        counts.dropped_sessions,
        seen.len()
    );
}
