//! The zenoh path under faults (issue 16 §1): an agent streams a piece of the MIT CSAIL recording
//! through a zenoh router (in process, TCP on loopback) to the server's zenoh front end; mid-session the
//! robot's link to the router is cut and restored, and later the router itself dies (both its links cut
//! at once, as when its host vanishes, and the router closed) and a fresh router with empty routing
//! tables starts on the same port. Client and server reconnect by themselves; the agent's outbox holds
//! what could not be sent. Afterwards every node the robot made is stored exactly once, the outbox is
//! empty, and the versions the robot saw never went backwards. Every wait is bounded.

#![allow(
    clippy::unwrap_used,
    reason = "integration test helpers: a failed unwrap is a failed test"
)]
use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use robot_agent::outbox::Outbox;
use robot_agent::source::{Recording, read_recording};
use robot_agent::uplink::{
    MapUplink as _, SessionOptions, UplinkError, Uploader, ZenohLinkOptions, ZenohUplink,
    stream_recording,
};
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::MemStore;
use tests::CuttableLink;

const SITE: &str = "store-zf";
const TOKEN: &str = "token-store-zf-r1";

async fn bounded<T>(what: &str, f: impl Future<Output = T>) -> T {
    tokio::time::timeout(Duration::from_secs(180), f)
        .await
        .unwrap_or_else(|_| panic!("{what} did not finish within 180 s"))
}

fn endpoint(addr: SocketAddr) -> String {
    format!("tcp/{addr}")
}

/// Waits (bounded) until the site holds at least `nodes` nodes.
async fn nodes_at_least(server: &RunningServer, nodes: u64) {
    let site = server.site(SITE).unwrap();
    bounded("the site growing", async {
        while site.current().counts.nodes < nodes {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

// Reference: issue 16 §1 "the same for the zenoh path: the link and the router drop mid-session;
// nothing is lost or duplicated".
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_robots_link_and_the_router_drop_mid_session_and_nothing_is_lost_or_duplicated() {
    let router_port = tests::free_port();
    let router_addr: SocketAddr = format!("127.0.0.1:{router_port}").parse().unwrap();
    let mut zenohd = tests::zenoh_router(router_port).await;
    let robot_link = CuttableLink::start(router_addr).await.unwrap();
    let server_link = CuttableLink::start(router_addr).await.unwrap();

    let config = ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        metrics_listen: None,
        zenoh: Some(ZenohLinkOptions {
            connect: vec![endpoint(server_link.addr())],
            ..ZenohLinkOptions::default()
        }),
        sites: vec![SiteConfig {
            id: SITE.into(),
            robots: vec![RobotConfig {
                id: "r1".into(),
                token: TOKEN.into(),
            }],
        }],
        ..ServerConfig::default()
    };
    let server = RunningServer::start(&config, Arc::new(MemStore::new()))
        .await
        .unwrap();
    let options = ZenohLinkOptions {
        mode: "client".into(),
        connect: vec![endpoint(robot_link.addr())],
        ..ZenohLinkOptions::default()
    };
    let mut uplink = ZenohUplink::connect(&options, SITE, TOKEN, Duration::from_secs(2))
        .await
        .unwrap();
    bounded("the server's queryable reaching the robot", async {
        while let Err(UplinkError::Unavailable { .. }) = uplink.map_version().await {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
    .await;

    let recording: Arc<Recording> = Arc::new(
        read_recording(&tests::datasets_dir().join("rosbag1/mit-csail.orig.bag")).unwrap(),
    );
    let session = SessionOptions {
        nodes_per_batch: 5,
        // Paced, so that mapping goes on while the link or the router is down.
        replay_speed: 8.0,
        max_scans: Some(700),
        retry_interval: Duration::from_millis(100),
        final_flush_timeout: Duration::from_secs(90),
        ..SessionOptions::default()
    };
    let dir = tempfile::tempdir().unwrap();
    let outbox = Outbox::open(dir.path(), SITE).unwrap();
    let mut uploader = Uploader::new(uplink.clone(), outbox, SITE, "r1", "zf-1").unwrap();
    let streaming = tokio::spawn(async move {
        let report = stream_recording(recording, &session, &mut uploader).await;
        (report, uploader)
    });

    // The robot's link drops for a while.
    nodes_at_least(&server, 40).await;
    robot_link.set_up(false);
    tokio::time::sleep(Duration::from_secs(2)).await;
    robot_link.set_up(true);
    let link_back = std::time::Instant::now();
    let at_link_back = server.site(SITE).unwrap().current().counts.nodes;
    nodes_at_least(&server, at_link_back + 1).await;
    let link_resumed_s = link_back.elapsed().as_secs_f64();

    // Later the router dies: its host vanishes from the network (both links cut at once), the process
    // is gone, and a new one with empty routing tables starts on the same port.
    let before_crash = server.site(SITE).unwrap().current().counts.nodes;
    nodes_at_least(&server, before_crash + 30).await;
    assert!(
        !streaming.is_finished(),
        "the session ended before the router drop: pace it slower"
    );
    robot_link.set_up(false);
    server_link.set_up(false);
    zenohd.close().await.unwrap();
    tokio::time::sleep(Duration::from_secs(1)).await;
    zenohd = tests::zenoh_router(router_port).await;
    robot_link.set_up(true);
    server_link.set_up(true);
    let router_back = std::time::Instant::now();
    let at_router_back = server.site(SITE).unwrap().current().counts.nodes;
    assert!(
        !streaming.is_finished(),
        "the session ended during the router drop: pace it slower"
    );

    nodes_at_least(&server, at_router_back + 1).await;
    let router_resumed_s = router_back.elapsed().as_secs_f64();
    let (report, uploader) = bounded("streaming", streaming).await.unwrap();
    let report = report.unwrap();
    assert_eq!(report.left_in_outbox, 0, "the outbox drains: {report:?}");
    assert!(uploader.outbox().is_empty().unwrap());
    assert!(report.failed_flushes > 0, "the drops were felt: {report:?}");

    // Exactly once: every node the robot made is stored, none twice (a duplicate would be a new node).
    let site = server.site(SITE).unwrap();
    let served = site.node_poses().await.unwrap();
    assert_eq!(served.len(), report.llo.nodes, "{report:?}");
    let final_version = site.current().version;
    assert!(
        report.map_version <= final_version,
        "the robot never saw a version the server does not have: {} > {final_version}",
        report.map_version
    );
    // The robot reads the final map through the new router.
    let mut reader = uplink.clone();
    let read = bounded("reading through the new router", async {
        loop {
            match reader.map_version().await {
                Ok(version) => break version,
                Err(e) => {
                    assert!(e.is_transient(), "{e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }
        }
    })
    .await;
    assert_eq!(read, final_version);
    eprintln!(
        "zenoh faults: {} nodes, {} batches, {} failed flushes, final version {final_version}; \
         uploads resumed {link_resumed_s:.2} s after the link came back, {router_resumed_s:.2} s \
         after the new router started",
        report.llo.nodes, report.batches, report.failed_flushes
    );
    server.shutdown().await.unwrap();
    zenohd.close().await.unwrap();
}
