//! Tokens never reach the logs, and a wrong token costs the caller, not the server (issue 16 §3): over
//! loopback gRPC and zenoh, with the server's log captured at DEBUG (the most `serve --verbose` prints)
//! while wrong, other-site and right tokens are used; a peer past its failure limit is refused with
//! `RESOURCE_EXHAUSTED` before its token is looked at, even a right one; and a token of one site opens
//! nothing of another, over either transport. Every wait is bounded.
//!
//! One test per process (nextest), so the global log subscriber installed here sees this test only.

#![allow(
    clippy::unwrap_used,
    reason = "integration test helpers: a failed unwrap is a failed test"
)]
use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use robot_agent::uplink::{GrpcUplink, MapUplink as _, UplinkError, ZenohLinkOptions, ZenohUplink};
use server::grpc::AuthLimitOptions;
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::MemStore;
use tests::free_port;

const TOKEN_A: &str = "secret-token-of-site-a-robot-1";
const TOKEN_B: &str = "secret-token-of-site-b-robot-1";
const WRONG: &str = "guessed-token-0123456789";
const WAIT: Duration = Duration::from_secs(10);

/// The log as written, shared with the subscriber's writer.
#[derive(Clone, Default)]
struct Captured(Arc<Mutex<Vec<u8>>>);

impl Write for Captured {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(bytes);
        Ok(bytes.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

fn config(zenoh_port: u16, max_failures: u32) -> ServerConfig {
    let site = |id: &str, token: &str| SiteConfig {
        id: id.into(),
        robots: vec![RobotConfig {
            id: "robot-1".into(),
            token: token.into(),
        }],
    };
    ServerConfig {
        listen: "127.0.0.1:0".parse().unwrap(),
        metrics_listen: None,
        zenoh: Some(ZenohLinkOptions {
            listen: vec![format!("tcp/127.0.0.1:{zenoh_port}")],
            ..ZenohLinkOptions::default()
        }),
        auth: AuthLimitOptions {
            max_failures,
            ..AuthLimitOptions::default()
        },
        sites: vec![site("site-a", TOKEN_A), site("site-b", TOKEN_B)],
        ..ServerConfig::default()
    }
}

fn grpc(server: &RunningServer, site: &str, token: &str) -> GrpcUplink {
    GrpcUplink::new(
        &format!("http://{}", server.grpc_addr()),
        site,
        token,
        4 << 20,
        WAIT,
    )
    .unwrap()
}

async fn zenoh_session(port: u16) -> zenoh::Session {
    let options = ZenohLinkOptions {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..ZenohLinkOptions::default()
    };
    let session = zenoh::open(options.to_zenoh_config().unwrap())
        .await
        .unwrap();
    // Declarations propagate after the link comes up: wait until the site answers.
    let mut probe = ZenohUplink::with_session(session.clone(), "site-a", TOKEN_A, WAIT);
    let deadline = Instant::now() + Duration::from_secs(20);
    while let Err(e @ UplinkError::Unavailable { .. }) = probe.map_version().await {
        assert!(Instant::now() < deadline, "site-a does not answer: {e}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    session
}

fn code(result: Result<impl std::fmt::Debug, UplinkError>) -> tonic::Code {
    match result {
        Err(UplinkError::Rejected { code, .. }) => code,
        other => panic!("expected a refusal, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tokens_stay_out_of_the_logs_and_guessing_costs_the_guesser() {
    let log = Captured::default();
    let writer = log.clone();
    tracing::subscriber::set_global_default(
        tracing_subscriber::fmt()
            .with_max_level(tracing::Level::DEBUG)
            .with_ansi(false)
            .with_writer(move || writer.clone())
            .finish(),
    )
    .unwrap();

    let max_failures = 3;
    let port = free_port();
    let server = RunningServer::start(&config(port, max_failures), Arc::new(MemStore::new()))
        .await
        .unwrap();

    // gRPC: the right token works; a token of site B opens nothing of site A.
    let mut a = grpc(&server, "site-a", TOKEN_A);
    a.open_session("robot-1", "a-1").await.unwrap();
    let mut b_on_a = grpc(&server, "site-a", TOKEN_B);
    assert_eq!(
        code(b_on_a.open_session("robot-1", "b-on-a").await),
        tonic::Code::PermissionDenied
    );
    // A guesser fails up to the limit (the other-site try above counts), then is refused unchecked:
    // even the right token, from the same peer for the same site.
    let mut guesser = grpc(&server, "site-a", WRONG);
    for _ in 1..max_failures {
        assert_eq!(
            code(guesser.map_version().await),
            tonic::Code::Unauthenticated
        );
    }
    assert_eq!(
        code(guesser.map_version().await),
        tonic::Code::ResourceExhausted
    );
    match a.map_version().await {
        Err(UplinkError::Rejected {
            code: tonic::Code::ResourceExhausted,
            message,
        }) => assert!(
            message.contains("too many failed authentications"),
            "{message}"
        ),
        other => panic!("expected the right token to be refused unchecked, got {other:?}"),
    }
    // Another site is counted apart.
    let mut b = grpc(&server, "site-b", TOKEN_B);
    b.open_session("robot-1", "b-1").await.unwrap();

    // zenoh: the same handlers, counted apart from gRPC (the server sees only the router or peer).
    let session = zenoh_session(port).await;
    let mut z_a = ZenohUplink::with_session(session.clone(), "site-a", TOKEN_A, WAIT);
    z_a.open_session("robot-1", "z-a-1").await.unwrap();
    let mut z_b_on_a = ZenohUplink::with_session(session.clone(), "site-a", TOKEN_B, WAIT);
    assert_eq!(
        code(z_b_on_a.map_version().await),
        tonic::Code::PermissionDenied
    );
    let mut z_guesser = ZenohUplink::with_session(session.clone(), "site-a", WRONG, WAIT);
    for _ in 1..max_failures {
        assert_eq!(
            code(z_guesser.map_version().await),
            tonic::Code::Unauthenticated
        );
    }
    assert_eq!(
        code(z_a.map_version().await),
        tonic::Code::ResourceExhausted
    );
    let refused = server.metrics().refused_count("resource_exhausted");
    assert!(refused >= 3, "{refused} refusals counted");
    session.close().await.unwrap();
    server.shutdown().await.unwrap();

    // The log saw all of it, and none of the tokens.
    let text = String::from_utf8_lossy(&log.0.lock().unwrap()).into_owned();
    assert!(
        text.contains("session opened") && text.lines().count() > 10,
        "the log was captured:\n{text}"
    );
    for token in [TOKEN_A, TOKEN_B, WRONG] {
        assert!(!text.contains(token), "token {token:?} was logged:\n{text}");
    }
}
