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
use std::future::Future;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

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

/// A zenoh router on `port` (TCP, loopback, no scouting): a `zenohd` in process.
async fn router(port: u16) -> zenoh::Session {
    let mut config = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"router\"".to_owned()),
        ("listen/endpoints", format!("[\"tcp/127.0.0.1:{port}\"]")),
        ("scouting/multicast/enabled", "false".to_owned()),
        ("scouting/gossip/enabled", "false".to_owned()),
    ] {
        config.insert_json5(key, &value).unwrap();
    }
    zenoh::open(config).await.unwrap()
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
/// transient failure leaves the batches in its outbox), then drains its outbox (bounded).
async fn run_robot(
    router_port: u16,
    site: &'static str,
    outbox_dir: std::path::PathBuf,
    stop: Arc<AtomicBool>,
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
    let zenohd = router(router_port).await;
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
            while let Err(UplinkError::Unavailable(_)) = probe.map_version().await {
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
            tokio::spawn(run_robot(router_port, site, dir, Arc::clone(&stop))),
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
        assert!(run.outbox_empty, "{site}: the outbox drains: {run:?}");
        // Exactly once and in order: the owner's log holds seqs 1..=batches, each once.
        let (uploads, nodes) = logged_uploads(store.as_ref(), site);
        let expected: Vec<(String, u64)> = (1..=run.batches)
            .map(|seq| ("session-1".to_owned(), seq))
            .collect();
        assert_eq!(uploads, expected, "{site}: every batch stored exactly once");
        assert_eq!(nodes as i64, run.batches as i64 * NODES_PER_BATCH, "{site}");
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
