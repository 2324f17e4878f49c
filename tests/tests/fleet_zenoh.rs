//! The fleet map service over zenoh on loopback: an agent streams a piece of the MIT CSAIL recording
//! through `ZenohUplink` into a server whose zenoh front end listens on 127.0.0.1 (peer mode, multicast
//! and gossip scouting off, explicit endpoints, a distinct port per test); what it stores equals what the
//! same data gives over gRPC, versions arrive by publication, and refusals carry the gRPC codes. Every
//! wait is bounded.

#![allow(
    clippy::unwrap_used,
    reason = "integration test helpers: a failed unwrap is a failed test"
)]
use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use prost::Message as _;
use proto::{FORMAT_VERSION, pb};
use robot_agent::outbox::Outbox;
use robot_agent::source::{Recording, read_recording};
use robot_agent::uplink::{
    GlobalSubmapCache, GrpcUplink, MapUplink, SessionOptions, UplinkError, Uploader,
    ZenohLinkOptions, ZenohUplink, follow_site, stream_recording, zenoh_api_key,
};
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::MemStore;

const SITE: &str = "store-z";
const TOKEN: &str = "token-store-z-r1";
const WAIT: Duration = Duration::from_secs(10);

fn endpoint(port: u16) -> String {
    format!("tcp/127.0.0.1:{port}")
}

fn config(port: u16) -> ServerConfig {
    ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        metrics_listen: None,
        zenoh: Some(ZenohLinkOptions {
            listen: vec![endpoint(port)],
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
    }
}

async fn bounded<T>(what: &str, f: impl Future<Output = T>) -> T {
    tokio::time::timeout(Duration::from_secs(120), f)
        .await
        .unwrap_or_else(|_| panic!("{what} did not finish within 120 s"))
}

/// An agent's uplink to the server's zenoh endpoint, once the site's queryable is reachable (declarations
/// propagate asynchronously after the link comes up).
async fn zenoh_uplink(port: u16, token: &str) -> ZenohUplink {
    let options = ZenohLinkOptions {
        connect: vec![endpoint(port)],
        ..ZenohLinkOptions::default()
    };
    let mut uplink = ZenohUplink::connect(&options, SITE, token, WAIT)
        .await
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        match uplink.map_version().await {
            Err(e @ UplinkError::Unavailable { .. }) if Instant::now() < deadline => {
                eprintln!("waiting for the server's queryable: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            _ => return uplink,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_agent_streams_over_zenoh_and_follows_published_versions() {
    let port = 27447;
    let server = RunningServer::start(&config(port), Arc::new(MemStore::new()))
        .await
        .unwrap();
    let uplink = zenoh_uplink(port, TOKEN).await;
    let cache = Arc::new(Mutex::new(GlobalSubmapCache::default()));
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let follower = tokio::spawn(follow_site(
        uplink.clone(),
        Arc::clone(&cache),
        stopped,
        Duration::from_millis(100),
    ));
    let recording: Arc<Recording> = Arc::new(
        read_recording(&tests::datasets_dir().join("rosbag1/mit-csail.orig.bag")).unwrap(),
    );
    let options = SessionOptions {
        nodes_per_batch: 7,
        replay_speed: 0.0,
        max_scans: Some(400),
        final_flush_timeout: WAIT,
        ..SessionOptions::default()
    };
    let mut uploader =
        Uploader::new(uplink.clone(), Outbox::in_memory(SITE), SITE, "r1", "z-1").unwrap();
    let report = bounded(
        "streaming over zenoh",
        stream_recording(recording, &options, &mut uploader),
    )
    .await
    .unwrap();
    assert_eq!(report.left_in_outbox, 0, "{report:?}");
    assert!(report.llo.submaps_finished >= 2, "{report:?}");

    let site = server.site(SITE).unwrap();
    assert_eq!(site.node_poses().await.unwrap().len(), report.llo.nodes);
    let final_version = site.current().version;

    // The published versions bring the follower's cache to the final version.
    bounded("the follower catching up", async {
        while cache.lock().unwrap().version() < final_version {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    let _ = stop.send(true);
    bounded("the follower stopping", follower).await.unwrap();

    // The same map whichever transport reads it.
    let mut over_zenoh = uplink.clone();
    let mut over_grpc = GrpcUplink::new(
        &format!("http://{}", server.grpc_addr()),
        SITE,
        TOKEN,
        64 << 20,
        WAIT,
    )
    .unwrap();
    let a = over_zenoh.delta_since(0).await.unwrap();
    let b = over_grpc.delta_since(0).await.unwrap();
    assert_eq!(a.to_version, final_version);
    assert_eq!(a.to_version, b.to_version);
    assert_eq!(a.submaps_added.len(), b.submaps_added.len());
    assert!(!a.submaps_added.is_empty());
    for (x, y) in a.submaps_added.iter().zip(&b.submaps_added) {
        assert_eq!((x.id, x.revision), (y.id, y.revision));
        assert_eq!(x.global_pose, y.global_pose);
        assert_eq!(*x.grid, *y.grid);
    }
    let cached = cache.lock().unwrap().submaps().len();
    assert_eq!(cached, a.submaps_added.len());
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zenoh_refusals_carry_the_grpc_codes_and_store_nothing() {
    let port = 27448;
    let server = RunningServer::start(&config(port), Arc::new(MemStore::new()))
        .await
        .unwrap();
    let mut wrong = zenoh_uplink(port, "not-a-token").await;
    assert!(matches!(
        wrong.map_version().await,
        Err(UplinkError::Rejected {
            code: tonic::Code::Unauthenticated,
            ..
        })
    ));
    let mut agent = zenoh_uplink(port, TOKEN).await;
    let opened = agent.open_session("r1", "z-gap").await.unwrap();
    assert!(opened.created);
    let before = agent.map_version().await.unwrap();
    let batch = pb::UploadBatch {
        format_version: FORMAT_VERSION,
        site: SITE.into(),
        robot_id: "r1".into(),
        session_uuid: "z-gap".into(),
        seq: 3,
        items: vec![pb::UploadItem {
            item: Some(pb::upload_item::Item::SessionEnd(pb::SessionEnd {})),
        }],
    };
    let gap = agent.upload(&batch).await;
    assert!(
        matches!(gap, Err(UplinkError::SequenceGap { expected: 1 })),
        "{gap:?}"
    );
    assert!(matches!(
        agent.open_session("r2", "z-other").await,
        Err(UplinkError::Rejected {
            code: tonic::Code::PermissionDenied,
            ..
        })
    ));
    assert_eq!(agent.map_version().await.unwrap(), before, "nothing stored");

    // Bytes that are not a ZenohRequest get an InvalidArgument refusal, not silence.
    let session = zenoh::open(
        ZenohLinkOptions {
            connect: vec![endpoint(port)],
            ..ZenohLinkOptions::default()
        }
        .to_zenoh_config()
        .unwrap(),
    )
    .await
    .unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    let refusal = loop {
        let replies = session
            .get(zenoh_api_key(SITE))
            .payload(vec![0xff_u8, 0xff, 0xff])
            .timeout(WAIT)
            .await
            .unwrap();
        if let Ok(reply) = replies.recv_async().await {
            let bytes = reply.result().unwrap().payload().to_bytes().into_owned();
            break pb::ZenohReply::decode(bytes.as_slice()).unwrap();
        }
        assert!(Instant::now() < deadline, "no reply to a malformed query");
    };
    let Some(pb::zenoh_reply::Reply::Error(status)) = refusal.reply else {
        panic!("expected a refusal, got {refusal:?}");
    };
    assert_eq!(status.code, tonic::Code::InvalidArgument as i32);
    session.close().await.unwrap();
    server.shutdown().await.unwrap();
}
