//! In-place recovery after a real full disk (issue 16 §1): the server's sled store and the robot's sled
//! outbox each on a small tmpfs mounted for the test, filled by a filler file mid-session (the
//! server's first, until it refuses; then the robot's too). sled refuses
//! every write after its first failed one until the database is reopened (measured in
//! `storage/tests/disk_full_tmpfs.rs`); here neither the server nor the agent is restarted: once the
//! filler is removed, both stores reopen themselves (`storage::SledStore`), the site task rebuilds its
//! map from the store's log, and the robot's outbox drains. Afterwards the site's log holds every batch
//! exactly once, the map holds every node, and a restart replays the same version.
//!
//! Mounting needs root, so the test runs only with `EVERMAP_TMPFS_TESTS=1` (and then fails if it cannot
//! mount); CI covers the same paths with `storage::DiskFullStore`'s `FailAt::Wedge`
//! (`server/tests/disk_full_in_place.rs`).
//! `EVERMAP_TMPFS_TESTS=1 cargo nextest run --workspace -E 'test(tmpfs)'`

#![allow(
    clippy::unwrap_used,
    reason = "integration test helpers: a failed unwrap is a failed test"
)]
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use mapping::geometry::rigid2;
use mapping::sensor::Timestamp;
use nalgebra::Point2;
use prost::Message as _;
use proto::{NodeAdded, UploadItem, pb};
use robot_agent::outbox::Outbox;
use robot_agent::uplink::{GrpcUplink, Uploader};
use server::site::SITE_LOG_KIND;
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::{MapStore, SledStore, SledStoreOptions};
use test_support::{Tmpfs, fill};

const SITE: &str = "store-tmpfs-fleet";
const TOKEN: &str = "token-tmpfs-fleet-r1";
const SIZE_MIB: u64 = 16;

fn sled(path: &Path) -> Arc<SledStore> {
    Arc::new(
        SledStore::open(&SledStoreOptions {
            background_flush_ms: 0,
            cache_capacity_bytes: 1 << 20,
            reopen_interval_ms: 0,
            ..SledStoreOptions::at(path)
        })
        .unwrap(),
    )
}

/// Node `i`, with a few hundred points so that the disk fills in a bounded number of them.
fn node(i: i64) -> Vec<UploadItem> {
    vec![UploadItem::NodeAdded(NodeAdded {
        time: Timestamp(i * 100_000_000),
        local_pose: rigid2(0.1 * i as f64, 0.0, 0.0),
        points: (0..400)
            .map(|k| Point2::new(1.0 + 0.01 * k as f32, 0.5))
            .collect(),
        insertion_submaps: vec![(0, rigid2(0.0, 0.0, 0.0))],
        recovered: false,
    })]
}

fn config() -> ServerConfig {
    ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        metrics_listen: None,
        sites: vec![SiteConfig {
            id: SITE.into(),
            robots: vec![RobotConfig {
                id: "r1".into(),
                token: TOKEN.into(),
            }],
        }],
        ..ServerConfig::default()
    }
}

/// The sequence numbers of the uploads in the site's log, in log order.
fn logged_seqs(store: &dyn MapStore) -> Vec<u64> {
    store
        .scan(SITE, SITE_LOG_KIND)
        .unwrap()
        .filter_map(|record| {
            let (_, bytes) = record.unwrap();
            match pb::SiteLogEntry::decode(bytes.as_slice()).unwrap().entry {
                Some(pb::site_log_entry::Entry::Upload(upload)) => Some(upload.seq),
                _ => None,
            }
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_and_outbox_on_a_full_tmpfs_recover_in_place_and_nothing_is_lost_or_doubled() {
    if !test_support::tmpfs_tests_enabled() {
        return;
    }
    let server_fs = Tmpfs::mount(SIZE_MIB);
    let robot_fs = Tmpfs::mount(SIZE_MIB);
    let server_store = sled(&server_fs.path().join("server"));
    let outbox_store = sled(&robot_fs.path().join("outbox"));
    let server = RunningServer::start(&config(), Arc::clone(&server_store) as Arc<dyn MapStore>)
        .await
        .unwrap();
    let site = server.site(SITE).unwrap().clone();
    let url = format!("http://{}", server.grpc_addr());
    let uplink = GrpcUplink::new(&url, SITE, TOKEN, 4 << 20, Duration::from_secs(10)).unwrap();
    let outbox = Outbox::with_store(Arc::clone(&outbox_store) as Arc<dyn MapStore>, SITE);
    let mut robot = Uploader::new(uplink, outbox, SITE, "r1", "s-1").unwrap();
    let mut nodes = 0;
    for _ in 0..4 {
        nodes += 1;
        robot.enqueue(&node(nodes)).unwrap();
    }
    robot.flush().await.unwrap();

    // The server's disk fills: the robot goes on mapping until the server refuses (bounded).
    let server_filler = server_fs.path().join("filler");
    fill(&server_filler, SIZE_MIB);
    let refusal = loop {
        nodes += 1;
        robot.enqueue(&node(nodes)).unwrap();
        match robot.flush().await {
            Ok(_) => assert!(nodes < 200, "the server never felt the full disk"),
            Err(e) => break e,
        }
    };
    assert!(
        matches!(
            refusal,
            robot_agent::uplink::UplinkError::Unavailable { .. }
        ),
        "the server refuses: {refusal}"
    );
    eprintln!("after {nodes} nodes: {refusal}");
    let published_while_full = site.current().version;
    // Then the robot's disk fills too: it keeps its batches in memory.
    let robot_filler = robot_fs.path().join("filler");
    fill(&robot_filler, SIZE_MIB);
    for _ in 0..3 {
        nodes += 1;
        robot.enqueue(&node(nodes)).unwrap();
        let error = robot.flush().await.unwrap_err();
        assert!(error.is_transient(), "{error}");
    }
    assert!(server_store.is_wedged(), "sled wedged after the full disk");
    assert_eq!(
        site.current().version,
        published_while_full,
        "nothing published while the disk is full"
    );

    // Space returns: no restart; both stores reopen themselves and everything drains (bounded).
    std::fs::remove_file(&server_filler).unwrap();
    std::fs::remove_file(&robot_filler).unwrap();
    let mut refusals = 0;
    loop {
        match robot.flush().await {
            Ok(_) if robot.outbox().is_empty().unwrap() && robot.unstored() == 0 => break,
            Ok(_) => {}
            Err(e) => {
                assert!(e.is_transient(), "{e}");
                refusals += 1;
                assert!(refusals < 20, "never recovered: {e}");
            }
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(
        server_store.generation() >= 1,
        "the server's store reopened"
    );
    let expected: Vec<u64> = (1..=nodes as u64).collect();
    assert_eq!(
        logged_seqs(server_store.as_ref()),
        expected,
        "every batch stored exactly once"
    );
    assert_eq!(site.node_poses().await.unwrap().len(), nodes as usize);
    let version = site.current().version;
    eprintln!(
        "recovered in place: {nodes} nodes, version {version}, {refusals} refusals after space \
         returned; server store reopened {} times, outbox store {} times",
        server_store.generation(),
        outbox_store.generation()
    );
    server.shutdown().await.unwrap();
    drop(site);

    // A restart replays the same.
    let server = RunningServer::start(&config(), server_store as Arc<dyn MapStore>)
        .await
        .unwrap();
    assert_eq!(server.site(SITE).unwrap().current().version, version);
    server.shutdown().await.unwrap();
}
