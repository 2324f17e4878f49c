//! Disk full on the server (issue 16 §1): the server's sled store, behind `storage::DiskFullStore`,
//! runs out of space mid-session — the write failing outright, or applied but not flushable (what sled
//! does when its flush hits the full disk). The robot gets a clear, retryable refusal naming the full
//! disk, nothing is acknowledged or published that is not durable, and once space returns the robot's
//! retries land exactly once; a restart then replays a log without a corrupt record to the same map as
//! an uninterrupted run. (Injected rather than a real full filesystem: mounting a size-limited one needs
//! privileges CI may lack; see `storage::DiskFullStore`.) Every wait is bounded.

use std::sync::Arc;
use std::time::Duration;

use mapping::geometry::{Rigid2, rigid2};
use mapping::pose_graph::NodeId;
use mapping::sensor::Timestamp;
use nalgebra::Point2;
use proto::{NodeAdded, UploadItem};
use robot_agent::outbox::Outbox;
use robot_agent::uplink::{GrpcUplink, UplinkError, Uploader};
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::{DiskFullStore, FailAt, MapStore, MemStore, SledStore, SledStoreOptions};

const SITE: &str = "store-full";
const TOKEN: &str = "token-full-r1";

fn node(i: i64) -> Vec<UploadItem> {
    vec![UploadItem::NodeAdded(NodeAdded {
        time: Timestamp(i * 100_000_000),
        local_pose: rigid2(0.1 * i as f64, 0.0, 0.0),
        points: vec![Point2::new(1.0, 0.5), Point2::new(2.0, 0.0)],
        insertion_submaps: vec![(0, rigid2(0.0, 0.0, 0.0))],
    })]
}

fn config() -> ServerConfig {
    ServerConfig {
        listen: "127.0.0.1:0".parse().expect("addr"),
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

fn uploader(server: &RunningServer, session: &str) -> Uploader<GrpcUplink> {
    let url = format!("http://{}", server.grpc_addr());
    let uplink =
        GrpcUplink::new(&url, SITE, TOKEN, 4 << 20, Duration::from_secs(10)).expect("uplink");
    Uploader::new(uplink, Outbox::in_memory(SITE), SITE, "r1", session).expect("uploader")
}

type NodePoses = std::collections::BTreeMap<NodeId, Rigid2>;

/// The node poses of a server fed nodes 1..=5 of one session without faults.
async fn uninterrupted() -> NodePoses {
    let server = RunningServer::start(&config(), Arc::new(MemStore::new()))
        .await
        .expect("server");
    let mut robot = uploader(&server, "s-1");
    for i in 1..=5 {
        robot.enqueue(&node(i)).expect("enqueue");
    }
    robot.flush().await.expect("flush");
    let poses = server
        .site(SITE)
        .expect("site")
        .node_poses()
        .await
        .expect("poses");
    server.shutdown().await.expect("shutdown");
    poses
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_is_a_clear_retryable_refusal_and_nothing_is_lost_or_doubled() {
    let expected = uninterrupted().await;
    for fail_at in [FailAt::Apply, FailAt::Flush] {
        let dir = tempfile::tempdir().expect("tempdir");
        let sled: Arc<dyn MapStore> =
            Arc::new(SledStore::open(&SledStoreOptions::at(dir.path())).expect("sled"));
        let disk = Arc::new(DiskFullStore::new(sled, fail_at));
        let server = RunningServer::start(&config(), Arc::clone(&disk) as Arc<dyn MapStore>)
            .await
            .expect("server");
        let site = server.site(SITE).expect("site").clone();
        let mut robot = uploader(&server, "s-1");
        robot.enqueue(&node(1)).expect("enqueue");
        robot.enqueue(&node(2)).expect("enqueue");
        assert_eq!(robot.flush().await.expect("flush").applied, 2);
        let before = site.current();

        disk.fill();
        robot.enqueue(&node(3)).expect("enqueue");
        robot.enqueue(&node(4)).expect("enqueue");
        for _ in 0..3 {
            match robot.flush().await {
                Err(UplinkError::Unavailable(message)) => assert!(
                    message.contains("No space left on device"),
                    "{fail_at:?}: the refusal names the full disk: {message}"
                ),
                other => panic!("{fail_at:?}: expected a retryable refusal, got {other:?}"),
            }
        }
        assert!(disk.failures() >= 3, "{fail_at:?}");
        assert_eq!(
            site.current(),
            before,
            "{fail_at:?}: nothing published that is not durable"
        );
        assert_eq!(robot.outbox().len().expect("len"), 2, "{fail_at:?}");

        disk.free();
        robot.enqueue(&node(5)).expect("enqueue");
        let stats = robot.flush().await.expect("flush once space returns");
        // Batch 3, stored but not flushable, is acknowledged (as already applied) once it is flushed,
        // never applied twice.
        let stored_before = usize::from(fail_at == FailAt::Flush);
        assert_eq!(
            (stats.applied, stats.already_acked + stats.duplicates),
            (3 - stored_before, stored_before),
            "{fail_at:?}: {stats:?}"
        );
        assert!(robot.outbox().is_empty().expect("empty"), "{fail_at:?}");
        let version = site.current().version;
        let served = site.node_poses().await.expect("poses");
        assert_eq!(
            served, expected,
            "{fail_at:?}: the same map as without faults"
        );
        server.shutdown().await.expect("shutdown");
        drop(site);
        drop(disk);

        // A restart replays every stored record (each CRC-checked, in sequence) to the same map.
        let sled: Arc<dyn MapStore> =
            Arc::new(SledStore::open(&SledStoreOptions::at(dir.path())).expect("reopen"));
        let server = RunningServer::start(&config(), sled)
            .await
            .expect("restart");
        let site = server.site(SITE).expect("site");
        assert_eq!(site.current().version, version, "{fail_at:?}");
        let replayed = site.node_poses().await.expect("poses");
        assert_eq!(replayed, expected, "{fail_at:?}: replayed");
        server.shutdown().await.expect("shutdown");
    }
}
