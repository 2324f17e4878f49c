//! An idle site leaves memory after `site_unload_after_s` and the next request restores it (issue 34
//! item 4), over real loopback gRPC with the real agent uplink and a small timeout: the site's version
//! still answers while it is unloaded, a map query and a robot's new session each wait for the restore
//! and get what a site that never left would give. Every wait is bounded; nothing asserts how long
//! anything took.

use std::sync::Arc;
use std::time::{Duration, Instant};

use proto::UploadItem;
use robot_agent::outbox::Outbox;
use robot_agent::uplink::{GrpcUplink, MapUplink as _, Uploader};
use server::{RunningServer, ServerConfig};
use storage::MemStore;
use tests::OneRobotSite;

const SITE: &str = "store-unload";
const TOKEN: &str = "token-unload-r1";
const WAIT: Duration = Duration::from_secs(30);

const FIXTURE: OneRobotSite = OneRobotSite {
    site: SITE,
    token: TOKEN,
};

/// Waits (bounded) until the site is unloaded.
async fn until_unloaded(server: &RunningServer) {
    let site = server.site(SITE).expect("site");
    let began = Instant::now();
    while site.is_loaded() {
        assert!(
            began.elapsed() < WAIT,
            "the idle site was not unloaded within {WAIT:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_idle_site_is_unloaded_and_restored_by_a_query_and_by_a_robot() {
    let config = ServerConfig {
        site_unload_after_s: 0.5,
        ..FIXTURE.config()
    };
    let server = RunningServer::start(&config, Arc::new(MemStore::new()))
        .await
        .expect("server");
    let url = format!("http://{}", server.grpc_addr());
    let mut uplink =
        GrpcUplink::new(&url, SITE, TOKEN, 4 << 20, Duration::from_secs(5)).expect("uplink");
    let outbox = Outbox::in_memory(SITE);
    let mut robot =
        Uploader::new(uplink.clone(), outbox.clone(), SITE, "r1", "first").expect("uploader");
    robot.enqueue(&OneRobotSite::node(1)).expect("enqueue");
    robot.enqueue(&OneRobotSite::node(2)).expect("enqueue");
    robot.enqueue(&[UploadItem::SessionEnd]).expect("enqueue");
    assert_eq!(robot.flush().await.expect("flush").applied, 3);
    let site = server.site(SITE).expect("site").clone();
    let version = site.current().version;
    let delta = uplink.delta_since(0).await.expect("delta");

    until_unloaded(&server).await;
    assert_eq!(server.metrics().site_unloads_and_restores(), (1, 0));
    // The version answers without the map.
    assert_eq!(uplink.map_version().await.expect("version"), version);
    assert!(!site.is_loaded());
    // A map query waits for the restore and gets what it got before.
    assert_eq!(uplink.delta_since(0).await.expect("delta"), delta);
    assert!(site.is_loaded());
    assert_eq!(server.metrics().site_unloads_and_restores(), (1, 1));

    // So does a robot's new session, and the versions go on.
    until_unloaded(&server).await;
    let mut back = Uploader::new(uplink, outbox, SITE, "r1", "second").expect("uploader");
    back.enqueue(&OneRobotSite::node(3)).expect("enqueue");
    assert_eq!(back.flush().await.expect("flush").applied, 1);
    assert_eq!(server.metrics().site_unloads_and_restores(), (2, 2));
    let counts = site.current().counts;
    assert_eq!((counts.sessions, counts.open_sessions), (2, 1));
    assert_eq!(
        site.current().version,
        version + 2,
        "the open and the batch"
    );
    // An open session keeps it in memory.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(site.is_loaded());
    server.shutdown().await.expect("shutdown");
}
