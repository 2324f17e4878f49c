//! Who may do what over zenoh (issue 16 §3), on loopback: a router running the shipped
//! `deploy/zenohd.json5` (mutual TLS and access control by certificate common name; only its
//! certificate paths and listen endpoint are replaced), the server's zenoh front end and two robots of
//! two sites, every participant with a certificate from a test CA made by `rcgen`.
//!
//! Robots of store-1 try everything against store-2: querying it with their own token and with a
//! stolen store-2 token, forging a version publication, and declaring a queryable that answers for the
//! server. With the deploy config nothing of it reaches store-2; the same scenario against the same
//! router with access control switched off shows every attack landing, so the test fails if the rules
//! stop working. A robot whose certificate another CA signed cannot even connect. Every wait is bounded.

#![allow(
    clippy::unwrap_used,
    reason = "integration test helpers: a failed unwrap is a failed test"
)]
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use prost::Message as _;
use proto::{FORMAT_VERSION, pb};
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose,
};
use robot_agent::uplink::{
    MapUplink as _, UplinkError, ZenohLinkOptions, ZenohTlsOptions, ZenohUplink, zenoh_api_key,
    zenoh_version_key,
};
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::MemStore;

const TOKEN_1: &str = "token-store-1-robot-1";
const TOKEN_2: &str = "token-store-2-robot-1";
/// How long a refused query waits for an answer that never comes.
const REFUSED_WAIT: Duration = Duration::from_secs(2);
const WAIT: Duration = Duration::from_secs(20);

/// A test certificate authority and the identities it signs, as PEM files in a temporary directory.
struct Pki {
    dir: tempfile::TempDir,
    ca_pem: PathBuf,
    issuer: Issuer<'static, KeyPair>,
}

impl Pki {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let key = KeyPair::generate().unwrap();
        let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
        params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        params.key_usages = vec![
            KeyUsagePurpose::KeyCertSign,
            KeyUsagePurpose::CrlSign,
            KeyUsagePurpose::DigitalSignature,
        ];
        params
            .distinguished_name
            .push(DnType::CommonName, "evermap test CA");
        let ca = params.self_signed(&key).unwrap();
        let ca_pem = dir.path().join("ca.pem");
        std::fs::write(&ca_pem, ca.pem()).unwrap();
        Self {
            dir,
            ca_pem,
            issuer: Issuer::new(params, key),
        }
    }

    /// A certificate with common name `cn`, valid for 127.0.0.1 and localhost, signed by this CA.
    fn identity(&self, cn: &str) -> ZenohTlsOptions {
        let key = KeyPair::generate().unwrap();
        let mut params =
            CertificateParams::new(vec!["127.0.0.1".to_owned(), "localhost".to_owned()]).unwrap();
        params.distinguished_name.push(DnType::CommonName, cn);
        params.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        let cert = params.signed_by(&key, &self.issuer).unwrap();
        let file = cn.replace('/', "_");
        let (cert_pem, key_pem) = (
            self.dir.path().join(format!("{file}.pem")),
            self.dir.path().join(format!("{file}.key")),
        );
        std::fs::write(&cert_pem, cert.pem()).unwrap();
        std::fs::write(&key_pem, key.serialize_pem()).unwrap();
        ZenohTlsOptions {
            root_ca_pem: self.ca_pem.clone(),
            cert_pem,
            key_pem,
        }
    }
}

/// The deploy router configuration, listening on `port` with `identity`; access control as shipped, or
/// switched off.
async fn router(port: u16, identity: &ZenohTlsOptions, access_control: bool) -> zenoh::Session {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/zenohd.json5");
    let mut config = zenoh::Config::from_file(path).unwrap();
    config
        .insert_json5("listen/endpoints", &format!("[\"tls/127.0.0.1:{port}\"]"))
        .unwrap();
    for (key, value) in identity.entries().unwrap() {
        config.insert_json5(key, &value).unwrap();
    }
    config
        .insert_json5("access_control/enabled", &access_control.to_string())
        .unwrap();
    zenoh::open(config).await.unwrap()
}

fn client(port: u16, identity: &ZenohTlsOptions) -> ZenohLinkOptions {
    ZenohLinkOptions {
        mode: "client".into(),
        connect: vec![format!("tls/127.0.0.1:{port}")],
        tls: Some(identity.clone()),
        ..ZenohLinkOptions::default()
    }
}

fn server_config(port: u16, identity: &ZenohTlsOptions) -> ServerConfig {
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
            connect: vec![format!("tls/127.0.0.1:{port}")],
            tls: Some(identity.clone()),
            ..ZenohLinkOptions::default()
        }),
        sites: vec![site("store-1", TOKEN_1), site("store-2", TOKEN_2)],
        ..ServerConfig::default()
    }
}

/// Asks until the site answers (declarations propagate asynchronously after links come up).
async fn answering(uplink: &mut ZenohUplink) -> u64 {
    let deadline = Instant::now() + WAIT;
    loop {
        match uplink.map_version().await {
            Ok(version) => return version,
            Err(e @ UplinkError::Unavailable { .. }) if Instant::now() < deadline => {
                eprintln!("waiting for the site to answer: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(e) => panic!("the site does not answer its own robot: {e}"),
        }
    }
}

/// What store-1's robot achieved against store-2.
#[derive(Debug)]
struct Attempts {
    /// Opening a store-2 session with a stolen store-2 token.
    stolen_token: Result<u64, UplinkError>,
    /// Reading store-2's version with its own (store-1) token.
    own_token: Result<u64, UplinkError>,
    /// Its forged publication on `evermap/store-2/version` reached store-2's robot.
    forged_version_delivered: bool,
    /// What store-2's robot got asking its own site while store-1's robot answered for the server.
    store_2_read: Result<u64, UplinkError>,
    /// store-2's version as the server has it.
    store_2_version: u64,
}

async fn attack(access_control: bool) -> Attempts {
    let pki = Pki::new();
    let port = tests::free_port();
    let router = router(port, &pki.identity("zenohd"), access_control).await;
    let server = RunningServer::start(
        &server_config(port, &pki.identity("evermap-server")),
        Arc::new(MemStore::new()),
    )
    .await
    .unwrap();
    let open = |cn: &str| {
        let config = client(port, &pki.identity(cn)).to_zenoh_config().unwrap();
        async move { zenoh::open(config).await.unwrap() }
    };
    let (robot_a, robot_b) = (open("store-1/robot-1").await, open("store-2/robot-1").await);
    let mut a_home = ZenohUplink::with_session(robot_a.clone(), "store-1", TOKEN_1, WAIT);
    let mut b_home = ZenohUplink::with_session(robot_b.clone(), "store-2", TOKEN_2, WAIT);
    answering(&mut a_home).await;
    answering(&mut b_home).await;

    // Robot A asks store-2 directly, with a stolen store-2 token and with its own.
    let mut stolen = ZenohUplink::with_session(robot_a.clone(), "store-2", TOKEN_2, REFUSED_WAIT);
    let stolen_token = stolen
        .open_session("robot-1", "stolen")
        .await
        .map(|o| o.map_version);
    let mut own = ZenohUplink::with_session(robot_a.clone(), "store-2", TOKEN_1, REFUSED_WAIT);
    let own_token = own.map_version().await;

    // Another store-1 robot answers store-2's queries in the server's place, if the router lets it
    // declare that (its own session: a session's queries also reach its own queryables, router or not).
    let robot_a2 = open("store-1/robot-2").await;
    let impostor = robot_a2
        .declare_queryable(zenoh_api_key("store-2"))
        .await
        .unwrap();
    let forged_reply = pb::ZenohReply {
        format_version: FORMAT_VERSION,
        reply: Some(pb::zenoh_reply::Reply::Version(pb::MapVersion {
            format_version: FORMAT_VERSION,
            site: "store-2".into(),
            version: 999_999,
            counts: None,
        })),
    }
    .encode_to_vec();
    let impostor_task = tokio::spawn(async move {
        while let Ok(query) = impostor.recv_async().await {
            let _ = query
                .reply(query.key_expr().clone(), forged_reply.clone())
                .await;
        }
    });

    // Robot B listens to its site's versions; a server publication proves the subscription is live.
    let versions = robot_b
        .declare_subscriber(zenoh_version_key("store-2"))
        .await
        .unwrap();
    let is_forged = |bytes: &[u8]| pb::MapVersion::decode(bytes).is_err();
    let mut forged_version_delivered = false;
    // Whether a publication of version `at_least` or later arrives within `wait` (noting forgeries).
    let await_version = async |at_least: u64, wait: Duration, forged: &mut bool| {
        let deadline = Instant::now() + wait;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            let Ok(sample) = tokio::time::timeout(left, versions.recv_async()).await else {
                return false;
            };
            let sample = sample.unwrap();
            let bytes = sample.payload().to_bytes();
            if is_forged(&bytes[..]) {
                *forged = true;
            } else if pb::MapVersion::decode(&*bytes).unwrap().version >= at_least {
                return true;
            }
        }
    };
    // New versions are made in process, so that making them does not depend on what the attack does to
    // the robots' queries. The subscription reaches the server asynchronously: make versions until one
    // arrives.
    let store_2 = server.site("store-2").unwrap().clone();
    let mut live = false;
    for i in 0..40 {
        let (_, version) = store_2
            .open_session("robot-1", &format!("warm-up-{i}"))
            .await
            .unwrap();
        if await_version(
            version,
            Duration::from_millis(500),
            &mut forged_version_delivered,
        )
        .await
        {
            live = true;
            break;
        }
    }
    assert!(live, "store-2's publications never reached its robot");

    // Robot A2 makes a round trip through the router, so its queryable declaration is handled before
    // anything later. Robot A forges a version of store-2, then makes a round trip through the router:
    // the router has handled the forgery (and queued it to B, if allowed) before it forwards anything
    // later.
    ZenohUplink::with_session(robot_a2.clone(), "store-1", TOKEN_1, WAIT)
        .map_version()
        .await
        .unwrap();
    robot_a
        .put(zenoh_version_key("store-2"), b"forged".to_vec())
        .await
        .unwrap();
    a_home.map_version().await.unwrap();
    let (_, later) = store_2.open_session("robot-1", "later").await.unwrap();
    assert!(
        await_version(later, WAIT, &mut forged_version_delivered).await,
        "store-2's publication did not arrive"
    );

    let store_2_read = b_home.map_version().await;
    let store_2_version = store_2.current().version;
    drop(store_2);
    impostor_task.abort();
    for session in [robot_a, robot_a2, robot_b] {
        session.close().await.unwrap();
    }
    server.shutdown().await.unwrap();
    router.close().await.unwrap();
    Attempts {
        stolen_token,
        own_token,
        forged_version_delivered,
        store_2_read,
        store_2_version,
    }
}

fn unanswered(result: &Result<u64, UplinkError>) -> bool {
    matches!(result, Err(UplinkError::Unavailable { what: m, .. }) if m.contains("no answer"))
}

// Reference: issue 16 §3 "a robot of site A cannot query or publish on site B, over zenoh as over gRPC".
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_robot_reaches_only_its_own_site_through_the_deploy_router() {
    let guarded = attack(true).await;
    eprintln!("with the deploy access control: {guarded:?}");
    assert!(unanswered(&guarded.stolen_token), "{guarded:?}");
    assert!(unanswered(&guarded.own_token), "{guarded:?}");
    assert!(!guarded.forged_version_delivered, "{guarded:?}");
    assert_eq!(
        guarded.store_2_read.as_ref().ok(),
        Some(&guarded.store_2_version),
        "store-2's robot hears only the server: {guarded:?}"
    );

    // The same router with access control off: the attacks land, so the rules above are what stopped
    // them (a valid token of another site is accepted by the server itself; only the router can tell
    // the robot is not of that site).
    let open = attack(false).await;
    eprintln!("without access control: {open:?}");
    assert!(open.stolen_token.is_ok(), "{open:?}");
    assert!(
        matches!(
            open.own_token,
            Err(UplinkError::Rejected {
                code: tonic::Code::PermissionDenied,
                ..
            })
        ),
        "the token check still refuses a store-1 token for store-2: {open:?}"
    );
    assert!(open.forged_version_delivered, "{open:?}");
    assert_ne!(
        open.store_2_read.as_ref().ok(),
        Some(&open.store_2_version),
        "the impostor's answer reaches store-2's robot: {open:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_robot_whose_certificate_another_ca_signed_cannot_connect() {
    let (pki, stranger) = (Pki::new(), Pki::new());
    let port = tests::free_port();
    let router = router(port, &pki.identity("zenohd"), true).await;
    let server = RunningServer::start(
        &server_config(port, &pki.identity("evermap-server")),
        Arc::new(MemStore::new()),
    )
    .await
    .unwrap();
    // A trusted robot gets answers through this router...
    let trusted = zenoh::open(
        client(port, &pki.identity("store-1/robot-1"))
            .to_zenoh_config()
            .unwrap(),
    )
    .await
    .unwrap();
    answering(&mut ZenohUplink::with_session(
        trusted.clone(),
        "store-1",
        TOKEN_1,
        WAIT,
    ))
    .await;
    // ...one with the right common name signed by another CA does not get a session at all (or, if
    // zenoh kept retrying in the background, no answer).
    let mut impostor = client(port, &stranger.identity("store-1/robot-1"));
    // It trusts our CA, so only its own certificate is wrong.
    if let Some(tls) = impostor.tls.as_mut() {
        tls.root_ca_pem.clone_from(&pki.ca_pem);
    }
    match tokio::time::timeout(WAIT, zenoh::open(impostor.to_zenoh_config().unwrap())).await {
        Err(_) | Ok(Err(_)) => {}
        Ok(Ok(session)) => {
            let mut uplink =
                ZenohUplink::with_session(session.clone(), "store-1", TOKEN_1, REFUSED_WAIT);
            assert!(unanswered(&uplink.map_version().await));
            session.close().await.unwrap();
        }
    }
    trusted.close().await.unwrap();
    server.shutdown().await.unwrap();
    router.close().await.unwrap();
}
