//! More stores than one server holds (issue 16 §4): sites sharded over two server instances behind one
//! zenoh router, and a site moved from one instance to the other while its robot keeps mapping.
//!
//! Two in-process [`RunningServer`]s, each on its own sled directory, each configured with half of the
//! sites (the static site → instance table of ARCHITECTURE.md "Scaling out to many stores"); one zenoh
//! router in process (TCP on loopback, no scouting); one robot per site, whose only link is a zenoh
//! client session to the router: each instance declares queryables for its own sites only, so the
//! router delivers every robot's requests to its site's owner. In-process instances rather than
//! `evermap-server serve` processes: the test reads both stores directly (the log of the moved site,
//! entry by entry) and the binary is not a dependency of this crate; the path through the router is
//! the same zenoh one as between processes.
//!
//! The move is the deployed procedure: instance A is restarted with a configuration that no longer
//! lists the site (it stops serving it; its store is untouched), the site is exported from A's store
//! and imported into B's, B is restarted with a configuration that lists it, and A's copy is deleted.
//! The site's table is configuration, read at start, so a configuration change is a restart of the
//! instance (its other sites are replayed from its store: the robots of those sites ride it out on
//! their outboxes too). At no moment do both instances serve the site: each instance claims its sites
//! (`server::zenoh_front::ensure_no_other_owner`: it asks the routers whether anyone answers for each
//! of its sites before it serves them), and a third instance
//! configured with the moved site while B serves it refuses to start. Meanwhile every robot keeps
//! making batches into its outbox every `BATCH_INTERVAL`; the moved site's robot gets no answer while
//! nobody owns it (zenoh finds no queryable) and keeps its batches.
//!
//! Afterwards, for every site: the owner's log holds each of the robot's batches exactly once, in
//! sequence order (a duplicate would be a second entry, a loss a gap), the site holds every node the
//! robot made, the outbox is empty, and the versions the robot was acknowledged never went backwards —
//! on the moved site, B continues A's version sequence. Every wait is bounded.

#![allow(
    clippy::unwrap_used,
    reason = "integration test helpers: a failed unwrap is a failed test"
)]
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs::File;
use std::future::Future;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use mapping::geometry::rigid2;
use mapping::sensor::Timestamp;
use nalgebra::Point2;
use prost::Message as _;
use proto::{NodeAdded, UploadItem, pb};
use robot_agent::outbox::Outbox;
use robot_agent::uplink::{MapUplink as _, UplinkError, Uploader, ZenohLinkOptions, ZenohUplink};
use server::site::SITE_LOG_KIND;
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::{MapStore, SledStore, SledStoreOptions};

/// Sites of instance A, then of instance B; `MOVED` goes from A to B.
const SITES_A: [&str; 2] = ["store-a0", "store-a1"];
const SITES_B: [&str; 2] = ["store-b0", "store-b1"];
const MOVED: &str = "store-a1";
/// Nodes per batch, and how often each robot makes a batch.
const NODES_PER_BATCH: i64 = 2;
const BATCH_INTERVAL: Duration = Duration::from_millis(150);

async fn bounded<T>(what: &str, seconds: u64, f: impl Future<Output = T>) -> T {
    tokio::time::timeout(Duration::from_secs(seconds), f)
        .await
        .unwrap_or_else(|_| panic!("{what} did not finish within {seconds} s"))
}

fn token(site: &str) -> String {
    format!("token-{site}-robot")
}

fn robot(site: &str) -> String {
    format!("{site}-robot")
}

/// An instance's configuration: gRPC on a free port (unused here), zenoh to the router only, `sites`.
fn config(router_port: u16, sites: &[&str]) -> ServerConfig {
    ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        metrics_listen: None,
        zenoh: Some(ZenohLinkOptions {
            connect: vec![format!("tcp/127.0.0.1:{router_port}")],
            ..ZenohLinkOptions::default()
        }),
        sites: sites
            .iter()
            .map(|site| SiteConfig {
                id: (*site).to_owned(),
                robots: vec![RobotConfig {
                    id: robot(site),
                    token: token(site),
                }],
            })
            .collect(),
        ..ServerConfig::default()
    }
}

/// Batch `k` (1-based) of a robot: `NODES_PER_BATCH` nodes along a line.
fn batch(k: i64) -> Vec<UploadItem> {
    (0..NODES_PER_BATCH)
        .map(|j| {
            let i = (k - 1) * NODES_PER_BATCH + j;
            UploadItem::NodeAdded(NodeAdded {
                time: Timestamp(i * 100_000_000),
                local_pose: rigid2(0.05 * i as f64, 0.0, 0.0),
                points: vec![Point2::new(1.0, 0.5), Point2::new(2.0, 0.0)],
                insertion_submaps: vec![(0, rigid2(0.0, 0.0, 0.0))],
                recovered: false,
            })
        })
        .collect()
}

/// What one robot did.
#[derive(Debug)]
struct RobotRun {
    batches: u64,
    /// Site versions of the acknowledgements, in the order they came.
    acked_versions: Vec<u64>,
    failed_flushes: u64,
    outbox_empty: bool,
}

/// One robot of `site`: makes a batch every `BATCH_INTERVAL` until `stop`, flushing after each (a
/// transient failure leaves the batches in its outbox), then drains its outbox (bounded). `acked` holds
/// the site version of its latest acknowledgement.
async fn run_robot(
    router_port: u16,
    site: &'static str,
    outbox_dir: std::path::PathBuf,
    stop: Arc<AtomicBool>,
    acked: Arc<AtomicU64>,
) -> RobotRun {
    let options = ZenohLinkOptions {
        mode: "client".into(),
        connect: vec![format!("tcp/127.0.0.1:{router_port}")],
        ..ZenohLinkOptions::default()
    };
    let uplink = ZenohUplink::connect(&options, site, &token(site), Duration::from_secs(1))
        .await
        .unwrap();
    let outbox = Outbox::open(&outbox_dir, site).unwrap();
    let mut uploader = Uploader::new(uplink, outbox, site, &robot(site), "session-1").unwrap();
    let mut run = RobotRun {
        batches: 0,
        acked_versions: Vec::new(),
        failed_flushes: 0,
        outbox_empty: false,
    };
    let flush = async |uploader: &mut Uploader<ZenohUplink>, run: &mut RobotRun| match uploader
        .flush()
        .await
    {
        Ok(stats) => {
            if stats.applied + stats.duplicates > 0 {
                run.acked_versions.push(stats.map_version);
                acked.fetch_max(stats.map_version, Ordering::SeqCst);
            }
            true
        }
        Err(e) => {
            assert!(e.is_transient(), "{site}: {e}");
            run.failed_flushes += 1;
            false
        }
    };
    // Bounded: the test stops the robots well within this many batches.
    for k in 1..=2_000 {
        if stop.load(Ordering::SeqCst) {
            break;
        }
        uploader.enqueue(&batch(k)).unwrap();
        run.batches += 1;
        flush(&mut uploader, &mut run).await;
        tokio::time::sleep(BATCH_INTERVAL).await;
    }
    bounded("draining the outbox", 60, async {
        while !flush(&mut uploader, &mut run).await || !uploader.outbox().is_empty().unwrap() {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await;
    run.outbox_empty = uploader.outbox().is_empty().unwrap();
    run
}

/// The (session, seq) of every upload in `site`'s log in `store`, in log order, and the number of
/// nodes they carry.
fn logged_uploads(store: &dyn MapStore, site: &str) -> (Vec<(String, u64)>, usize) {
    let mut uploads = Vec::new();
    let mut nodes = 0;
    for record in store.scan(site, SITE_LOG_KIND).unwrap() {
        let (_, bytes) = record.unwrap();
        let entry = pb::SiteLogEntry::decode(bytes.as_slice()).unwrap();
        if let Some(pb::site_log_entry::Entry::Upload(upload)) = entry.entry {
            nodes += upload
                .items
                .iter()
                .filter(|i| matches!(i.item, Some(pb::upload_item::Item::NodeAdded(_))))
                .count();
            uploads.push((upload.session_uuid, upload.seq));
        }
    }
    (uploads, nodes)
}

/// The robot's outbox drained, and `store`'s log of `site` holds each of its batches exactly once and in
/// order (sequence numbers 1..=batches, each once: a duplicate would be a second entry, a loss a gap).
fn assert_stored_exactly_once(store: &dyn MapStore, site: &str, run: &RobotRun) {
    assert!(run.outbox_empty, "{site}: the outbox drains: {run:?}");
    let (uploads, nodes) = logged_uploads(store, site);
    let expected: Vec<(String, u64)> = (1..=run.batches)
        .map(|seq| ("session-1".to_owned(), seq))
        .collect();
    assert_eq!(uploads, expected, "{site}: every batch stored exactly once");
    assert_eq!(nodes as i64, run.batches as i64 * NODES_PER_BATCH, "{site}");
}

/// Waits (bounded) until `site` on `server` is at `version` or beyond.
async fn version_at_least(server: &RunningServer, site: &str, version: u64) {
    let handle = server.site(site).unwrap();
    bounded(&format!("{site} reaching version {version}"), 30, async {
        while handle.current().version < version {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

fn sled(dir: &std::path::Path) -> Arc<dyn MapStore> {
    Arc::new(
        SledStore::open(&SledStoreOptions {
            background_flush_ms: 0,
            ..SledStoreOptions::at(dir)
        })
        .unwrap(),
    )
}

// Reference: issue 16 §4 "two instances each owning half the sites, one zenoh router, robots of every
// site reaching their owner through the router only; a site moved from one instance to the other
// (export, import, config change) while its robots keep their outboxes, nothing lost, versions
// continuing".
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sites_sharded_over_two_instances_and_one_moved_lose_nothing_and_keep_their_versions() {
    let router_port = tests::free_port();
    let zenohd = tests::zenoh_router(router_port).await;
    let dirs = tempfile::tempdir().unwrap();
    let store_a = sled(&dirs.path().join("a"));
    let store_b = sled(&dirs.path().join("b"));
    let mut a = RunningServer::start(&config(router_port, &SITES_A), Arc::clone(&store_a))
        .await
        .unwrap();
    let mut b = RunningServer::start(&config(router_port, &SITES_B), Arc::clone(&store_b))
        .await
        .unwrap();

    // Every robot reaches its site's owner through the router (and only the owner serves it).
    for site in SITES_A.iter().chain(&SITES_B) {
        let options = ZenohLinkOptions {
            mode: "client".into(),
            connect: vec![format!("tcp/127.0.0.1:{router_port}")],
            ..ZenohLinkOptions::default()
        };
        let mut probe = ZenohUplink::connect(&options, site, &token(site), Duration::from_secs(1))
            .await
            .unwrap();
        bounded("the owner's queryable reaching the robot", 30, async {
            while let Err(UplinkError::Unavailable { .. }) = probe.map_version().await {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        })
        .await;
    }

    let stop = Arc::new(AtomicBool::new(false));
    let mut robots = BTreeMap::new();
    for site in SITES_A.iter().chain(&SITES_B) {
        let dir = dirs.path().join(format!("outbox-{site}"));
        robots.insert(
            *site,
            tokio::spawn(run_robot(
                router_port,
                site,
                dir,
                Arc::clone(&stop),
                Arc::new(AtomicU64::new(0)),
            )),
        );
    }

    // Every site maps for a while on its first owner.
    for site in SITES_A {
        version_at_least(&a, site, 8).await;
    }
    for site in SITES_B {
        version_at_least(&b, site, 8).await;
    }

    // The move. A stops serving the site (restarted without it)...
    let a_sites: Vec<&str> = SITES_A.iter().copied().filter(|s| *s != MOVED).collect();
    a.shutdown().await.unwrap();
    a = RunningServer::start(&config(router_port, &a_sites), Arc::clone(&store_a))
        .await
        .unwrap();
    assert!(a.site(MOVED).is_none());
    let version_on_a = store_a.map_version(MOVED).unwrap();
    // ... while nobody serves it, its robot keeps mapping into its outbox ...
    tokio::time::sleep(BATCH_INTERVAL * 6).await;
    // ... it is exported from A's store and imported into B's ...
    let mut archive = Vec::new();
    let exported = store_a.export_site(MOVED, &mut archive).unwrap();
    let imported = store_b.import_site(MOVED, &mut archive.as_slice()).unwrap();
    assert_eq!(exported, imported);
    assert_eq!(store_b.map_version(MOVED).unwrap(), version_on_a);
    // ... B starts serving it (restarted with it), and A's copy goes.
    let b_sites: Vec<&str> = SITES_B.iter().copied().chain([MOVED]).collect();
    b.shutdown().await.unwrap();
    let restart = std::time::Instant::now();
    b = RunningServer::start(&config(router_port, &b_sites), Arc::clone(&store_b))
        .await
        .unwrap();
    let b_restart_s = restart.elapsed().as_secs_f64();
    assert_eq!(
        b.site(MOVED).unwrap().current().version,
        version_on_a,
        "B continues A's version sequence"
    );
    store_a.delete_site(MOVED).unwrap();
    assert!(!store_a.list_sites().unwrap().contains(&MOVED.to_owned()));
    // A third instance configured with the site (a move done wrong: the new owner started while the
    // old one still serves it) refuses to start rather than split the site in two.
    let refused = RunningServer::start(
        &config(router_port, &[MOVED]),
        Arc::new(storage::MemStore::new()),
    )
    .await;
    assert!(
        matches!(
            refused,
            Err(server::ServeError::Zenoh(
                server::zenoh_front::ZenohFrontError::SiteServedElsewhere { .. }
            ))
        ),
        "a second owner of {MOVED} must be refused"
    );

    // The moved site's robot resumes uploading to B, and every other robot goes on.
    version_at_least(&b, MOVED, version_on_a + 5).await;
    for site in a_sites {
        let now = a.site(site).unwrap().current().version;
        version_at_least(&a, site, now + 3).await;
    }
    for site in SITES_B {
        let now = b.site(site).unwrap().current().version;
        version_at_least(&b, site, now + 3).await;
    }
    stop.store(true, Ordering::SeqCst);

    let mut report = Vec::new();
    for (site, robot) in robots {
        let run = bounded("a robot finishing", 90, robot).await.unwrap();
        let (owner, store) = if site == MOVED || SITES_B.contains(&site) {
            (&b, &store_b)
        } else {
            (&a, &store_a)
        };
        assert_stored_exactly_once(store.as_ref(), site, &run);
        let handle = owner.site(site).unwrap();
        assert_eq!(
            handle.node_poses().await.unwrap().len() as i64,
            run.batches as i64 * NODES_PER_BATCH,
            "{site}: the map holds every node"
        );
        // Versions never went backwards, and the robot never saw one its owner does not have.
        assert!(
            run.acked_versions.windows(2).all(|w| w[0] <= w[1]),
            "{site}: acknowledged versions went backwards: {:?}",
            run.acked_versions
        );
        let last = run.acked_versions.last().copied().unwrap_or(0);
        assert!(last <= handle.current().version, "{site}");
        if site == MOVED {
            assert!(run.failed_flushes > 0, "the move was felt: {run:?}");
            assert!(
                run.acked_versions.iter().any(|v| *v > version_on_a),
                "acknowledged on B after the move: {run:?}"
            );
        }
        report.push(format!(
            "{site}: {} batches, {} failed flushes, version {}",
            run.batches,
            run.failed_flushes,
            handle.current().version
        ));
    }
    // Each site lives in exactly one store.
    let mut on_a = store_a.list_sites().unwrap();
    let mut on_b = store_b.list_sites().unwrap();
    on_a.sort();
    on_b.sort();
    assert_eq!(on_a, ["store-a0"]);
    assert_eq!(on_b, ["store-a1", "store-b0", "store-b1"]);
    eprintln!(
        "sharding: moved {MOVED} at version {version_on_a} ({} records, {} bytes); B restarted in \
         {b_restart_s:.2} s; {}",
        exported.records,
        archive.len(),
        report.join("; ")
    );
    a.shutdown().await.unwrap();
    b.shutdown().await.unwrap();
    zenohd.close().await.unwrap();
}

/// `evermap-server`, built beside this crate's `evermap-fuzz` (`cargo nextest run --workspace` builds
/// every binary of the workspace).
fn server_binary() -> PathBuf {
    let fuzz = PathBuf::from(env!("CARGO_BIN_EXE_evermap-fuzz"));
    let binary = fuzz.with_file_name(format!("evermap-server{}", std::env::consts::EXE_SUFFIX));
    assert!(
        binary.is_file(),
        "{} is missing: build the workspace (cargo nextest run --workspace builds it)",
        binary.display()
    );
    binary
}

/// One `evermap-server serve` instance: its configuration file, store and log.
struct Instance {
    name: &'static str,
    dir: PathBuf,
    router_port: u16,
    child: Option<Child>,
}

impl Instance {
    fn new(name: &'static str, dir: &Path, router_port: u16) -> Self {
        let dir = dir.join(name);
        std::fs::create_dir_all(&dir).unwrap();
        Self {
            name,
            dir,
            router_port,
            child: None,
        }
    }

    fn config_path(&self) -> PathBuf {
        self.dir.join("server.toml")
    }

    /// Writes the instance's configuration serving `sites`: gRPC and metrics on any free port (the
    /// robots reach it through the router only), zenoh to the router, its own store.
    fn configure(&self, sites: &[&str]) {
        let store = toml::Value::String(self.dir.join("data").display().to_string());
        let mut text = format!(
            "listen = \"127.0.0.1:0\"\nmetrics_listen = \"127.0.0.1:0\"\n\n[storage]\npath = {store}\n\n\
             [zenoh]\nmode = \"peer\"\nconnect = [\"tcp/127.0.0.1:{}\"]\n",
            self.router_port
        );
        for site in sites {
            writeln!(
                text,
                "\n[[sites]]\nid = \"{site}\"\nrobots = [{{ id = \"{}\", token = \"{}\" }}]",
                robot(site),
                token(site)
            )
            .unwrap();
        }
        std::fs::write(self.config_path(), text).unwrap();
    }

    fn start(&mut self) {
        let log = File::options()
            .create(true)
            .append(true)
            .open(self.dir.join("serve.log"))
            .unwrap();
        let child = Command::new(server_binary())
            .arg("serve")
            .arg("--config")
            .arg(self.config_path())
            .env("NO_COLOR", "1")
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap();
        self.child = Some(child);
    }

    /// Stops the instance as a service manager does (SIGTERM) and checks that it shut down cleanly.
    fn stop(&mut self) {
        let mut child = self.child.take().expect("a running instance");
        let sent = Command::new("kill")
            .args(["-TERM", &child.id().to_string()])
            .status()
            .unwrap();
        assert!(sent.success());
        let deadline = Instant::now() + Duration::from_secs(30);
        let status = loop {
            if let Some(status) = child.try_wait().unwrap() {
                break status;
            }
            if Instant::now() > deadline {
                let _ = child.kill();
                panic!(
                    "{} did not stop within 30 s of SIGTERM:\n{}",
                    self.name,
                    self.log()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        assert!(status.success(), "{}: {status}\n{}", self.name, self.log());
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self.dir.join("serve.log")).unwrap_or_default()
    }

    /// Runs `evermap-server site <args> --config <this instance's>`; its exit status and output.
    fn site_command(&self, args: &[&str]) -> (bool, String) {
        let output = Command::new(server_binary())
            .arg("site")
            .args(args)
            .arg("--config")
            .arg(self.config_path())
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&output.stdout).into_owned()
            + &String::from_utf8_lossy(&output.stderr);
        (output.status.success(), text)
    }

    /// Opens the stopped instance's store.
    fn store(&self) -> Arc<dyn MapStore> {
        sled(&self.dir.join("data"))
    }
}

impl Drop for Instance {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Waits (bounded) until `acked` reaches `version`.
async fn acked_at_least(site: &str, acked: &AtomicU64, version: u64) {
    bounded(
        &format!("{site}'s robot acknowledged at version {version}"),
        60,
        async {
            while acked.load(Ordering::SeqCst) < version {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        },
    )
    .await;
}

/// The version an `evermap-server site export|import` line names ("... at version V: ...").
fn version_in(line: &str) -> u64 {
    line.split("at version ")
        .nth(1)
        .and_then(|rest| rest.split(':').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no version in {line:?}"))
}

// Reference: issue 16 §4, the same move with `evermap-server serve` processes and the operator's
// commands: "two `evermap-server serve` instances each owning half the sites, one zenoh router, ... a
// site moved from one instance to the other (export, import, config change) while its robots keep
// their outboxes, nothing lost, versions continuing".
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_site_moved_between_serve_processes_with_the_site_commands_loses_nothing() {
    const KEPT_A: &str = "store-a0";
    const KEPT_B: &str = "store-b0";
    let router_port = tests::free_port();
    let zenohd = tests::zenoh_router(router_port).await;
    let dirs = tempfile::tempdir().unwrap();
    let mut a = Instance::new("a", dirs.path(), router_port);
    let mut b = Instance::new("b", dirs.path(), router_port);
    a.configure(&[KEPT_A, MOVED]);
    b.configure(&[KEPT_B]);
    a.start();
    b.start();

    let stop = Arc::new(AtomicBool::new(false));
    let mut robots = BTreeMap::new();
    for site in [KEPT_A, MOVED, KEPT_B] {
        let acked = Arc::new(AtomicU64::new(0));
        let task = tokio::spawn(run_robot(
            router_port,
            site,
            dirs.path().join(format!("outbox-{site}")),
            Arc::clone(&stop),
            Arc::clone(&acked),
        ));
        robots.insert(site, (task, acked));
    }
    for (site, (_, acked)) in &robots {
        acked_at_least(site, acked, 8).await;
    }

    // A serving instance's store is refused, with the advice to stop it.
    let (ok, text) = b.site_command(&["list"]);
    assert!(!ok && text.contains("stop it first"), "{text}");

    // The move. A stops; its robots keep their batches.
    a.stop();
    // The site cannot be deleted while A's configuration still serves it.
    let (ok, text) = a.site_command(&["delete", "--site", MOVED, "--yes"]);
    assert!(!ok && text.contains("still serves"), "{text}");
    let archive = dirs.path().join("moved.evermap-site");
    let export = [
        "export",
        "--site",
        MOVED,
        "--out",
        archive.to_str().unwrap(),
    ];
    let (ok, exported) = a.site_command(&export);
    assert!(ok, "{exported}");
    let version_on_a = version_in(&exported);
    // An archive is never overwritten.
    let (ok, text) = a.site_command(&export);
    assert!(!ok && text.contains("exists"), "{text}");
    // B stops, imports the site and starts again serving it.
    b.stop();
    b.configure(&[KEPT_B, MOVED]);
    let import = [
        "import",
        "--site",
        MOVED,
        "--archive",
        archive.to_str().unwrap(),
    ];
    let (ok, imported) = b.site_command(&import);
    assert!(ok, "{imported}");
    assert_eq!(version_in(&imported), version_on_a, "{imported}");
    b.start();
    // A's copy goes, and A starts again without the site.
    a.configure(&[KEPT_A]);
    let (ok, text) = a.site_command(&["delete", "--site", MOVED, "--yes"]);
    assert!(ok, "{text}");
    let (ok, listed) = a.site_command(&["list"]);
    assert!(
        ok && listed.contains(KEPT_A) && !listed.contains(MOVED),
        "{listed}"
    );
    a.start();

    // The moved site's robot resumes on B, and the other robots on their restarted owners.
    acked_at_least(MOVED, &robots[MOVED].1, version_on_a + 5).await;
    for site in [KEPT_A, KEPT_B] {
        let now = robots[site].1.load(Ordering::SeqCst);
        acked_at_least(site, &robots[site].1, now + 3).await;
    }
    stop.store(true, Ordering::SeqCst);
    let mut runs = BTreeMap::new();
    for (site, (task, _)) in robots {
        runs.insert(site, bounded("a robot finishing", 90, task).await.unwrap());
    }
    a.stop();
    b.stop();
    // A second import of the site is refused (B holds it), and so is exporting a site a store lacks.
    let (ok, text) = b.site_command(&import);
    assert!(!ok && text.contains("already holds data"), "{text}");
    let elsewhere = dirs.path().join("elsewhere.evermap-site");
    let (ok, text) = a.site_command(&[
        "export",
        "--site",
        MOVED,
        "--out",
        elsewhere.to_str().unwrap(),
    ]);
    assert!(!ok && text.contains("holds no site"), "{text}");
    assert!(!elsewhere.exists(), "a refused export writes nothing");
    let (store_a, store_b) = (a.store(), b.store());
    for (site, run) in &runs {
        let store = if *site == KEPT_A { &store_a } else { &store_b };
        assert_stored_exactly_once(store.as_ref(), site, run);
        assert!(
            run.acked_versions.windows(2).all(|w| w[0] <= w[1]),
            "{site}: acknowledged versions went backwards: {:?}",
            run.acked_versions
        );
        assert!(
            run.failed_flushes > 0,
            "{site}: the restarts were felt: {run:?}"
        );
    }
    assert!(
        runs[MOVED].acked_versions.iter().any(|v| *v > version_on_a),
        "acknowledged on B after the move: {:?}",
        runs[MOVED]
    );
    assert_eq!(store_a.list_sites().unwrap(), [KEPT_A]);
    let mut on_b = store_b.list_sites().unwrap();
    on_b.sort();
    assert_eq!(on_b, [MOVED, KEPT_B]);
    eprintln!(
        "site commands: moved {MOVED} at version {version_on_a}; {}",
        runs.iter()
            .map(|(site, run)| format!(
                "{site}: {} batches, {} failed flushes",
                run.batches, run.failed_flushes
            ))
            .collect::<Vec<_>>()
            .join("; ")
    );
    zenohd.close().await.unwrap();
}
