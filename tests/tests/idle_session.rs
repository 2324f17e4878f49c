//! A session whose robot falls silent is ended by the server after `session_idle_timeout_s` (issue 16
//! §1), over real loopback gRPC with a small timeout; and an agent that comes back with batches of that
//! session drops them and goes on instead of retrying for ever. Every wait is bounded; nothing asserts
//! how long anything took.

use std::sync::Arc;
use std::time::{Duration, Instant};

use mapping::geometry::rigid2;
use mapping::sensor::Timestamp;
use nalgebra::Point2;
use proto::{NodeAdded, UploadItem};
use robot_agent::outbox::Outbox;
use robot_agent::uplink::{GrpcUplink, Uploader};
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::MemStore;

const SITE: &str = "store-idle";
const TOKEN: &str = "token-idle-r1";
const WAIT: Duration = Duration::from_secs(30);

fn node(i: i64) -> Vec<UploadItem> {
    vec![UploadItem::NodeAdded(NodeAdded {
        time: Timestamp(i * 100_000_000),
        local_pose: rigid2(0.1 * i as f64, 0.0, 0.0),
        points: vec![Point2::new(1.0, 0.5), Point2::new(2.0, 0.0)],
        insertion_submaps: vec![(0, rigid2(0.0, 0.0, 0.0))],
        recovered: false,
    })]
}

fn open_sessions(server: &RunningServer) -> u64 {
    server
        .site(SITE)
        .expect("site")
        .current()
        .counts
        .open_sessions
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_robots_session_is_ended_and_its_late_batches_are_dropped_by_the_agent() {
    let config = ServerConfig {
        listen: "127.0.0.1:0".parse().expect("addr"),
        metrics_listen: None,
        session_idle_timeout_s: 0.5,
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
        .expect("server");
    let url = format!("http://{}", server.grpc_addr());
    let uplink =
        GrpcUplink::new(&url, SITE, TOKEN, 4 << 20, Duration::from_secs(5)).expect("uplink");
    let outbox = Outbox::in_memory(SITE);
    {
        // A robot streams two batches, then dies with a third one in its outbox.
        let mut robot =
            Uploader::new(uplink.clone(), outbox.clone(), SITE, "r1", "gone").expect("uploader");
        robot.enqueue(&node(1)).expect("enqueue");
        robot.enqueue(&node(2)).expect("enqueue");
        assert_eq!(robot.flush().await.expect("flush").applied, 2);
        robot.enqueue(&node(3)).expect("enqueue");
    }
    assert_eq!(open_sessions(&server), 1);
    let began = Instant::now();
    while open_sessions(&server) > 0 {
        assert!(
            began.elapsed() < WAIT,
            "the silent session was not ended within {WAIT:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(server.metrics().sessions_timed_out(), 1);
    let counts = server.site(SITE).expect("site").current().counts;
    assert_eq!(
        (counts.sessions, counts.nodes),
        (1, 2),
        "what was acked stays"
    );

    // The robot comes back (a new run, a new session): the server refuses the dead session's last batch,
    // the agent drops it and maps on.
    let mut back = Uploader::new(uplink, outbox.clone(), SITE, "r1", "back").expect("uploader");
    let stats = back.flush().await.expect("flush");
    assert_eq!(
        (stats.dropped_after_server_end, stats.interrupted_ended),
        (1, 1)
    );
    assert!(outbox.is_empty().expect("outbox"));
    back.enqueue(&node(4)).expect("enqueue");
    assert_eq!(back.flush().await.expect("flush").applied, 1);
    assert_eq!(open_sessions(&server), 1);
    server.shutdown().await.expect("shutdown");
}
