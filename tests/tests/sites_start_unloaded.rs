//! Sites start unloaded (issue 34: one instance holds hundreds of sites): a server restarted on a sled
//! store of several mapped sites serves each one unloaded — its version, counts and `/metrics` lines
//! without its map — and the first query to each restores it and answers what the server answered
//! before the restart. A site with a session open and a site never mapped load at the start as
//! before. Over real loopback gRPC with the real agent uplink; every wait is bounded and nothing
//! asserts how long anything took.

use std::sync::Arc;
use std::time::Duration;

use proto::{MapDelta, UploadItem};
use robot_agent::outbox::Outbox;
use robot_agent::uplink::{GrpcUplink, MapUplink as _, Uploader};
use server::{RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::{MapStore, SledStore, SledStoreOptions};
use tests::OneRobotSite;
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};

/// Sites mapped by one session each, then closed.
const MAPPED: [&str; 3] = ["store-a", "store-b", "store-c"];
/// A site whose session is still open at the restart.
const OPEN: &str = "store-open";
/// A site never mapped.
const EMPTY: &str = "store-empty";
const WAIT: Duration = Duration::from_secs(30);

fn token(site: &str) -> String {
    format!("token-{site}")
}

fn config() -> ServerConfig {
    let sites = MAPPED
        .iter()
        .chain(&[OPEN, EMPTY])
        .map(|site| SiteConfig {
            id: (*site).into(),
            robots: vec![RobotConfig {
                id: "r1".into(),
                token: token(site),
            }],
        })
        .collect();
    ServerConfig {
        listen: "127.0.0.1:0".parse().expect("addr"),
        metrics_listen: Some("127.0.0.1:0".parse().expect("addr")),
        // The default (600 s): nothing goes idle during the test, what is unloaded started so.
        site_unload_after_s: 600.0,
        sites,
        ..ServerConfig::default()
    }
}

fn uplink(server: &RunningServer, site: &str) -> GrpcUplink {
    let url = format!("http://{}", server.grpc_addr());
    GrpcUplink::new(&url, site, &token(site), 4 << 20, Duration::from_secs(10)).expect("uplink")
}

/// `/metrics`, scraped over HTTP as Prometheus does.
async fn scrape(server: &RunningServer) -> String {
    let addr = server.metrics_addr().expect("metrics address");
    let mut stream = tokio::time::timeout(WAIT, tokio::net::TcpStream::connect(addr))
        .await
        .expect("bounded")
        .expect("connect");
    stream
        .write_all(b"GET /metrics HTTP/1.1\r\nhost: evermap\r\n\r\n")
        .await
        .expect("request");
    let mut text = String::new();
    tokio::time::timeout(WAIT, stream.read_to_string(&mut text))
        .await
        .expect("bounded")
        .expect("response");
    text
}

fn has_line(text: &str, line: &str) -> bool {
    text.lines().any(|l| l == line)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_server_serves_its_mapped_sites_unloaded_and_restores_each_at_its_first_query()
{
    let dir = tempfile::tempdir().expect("tempdir");
    let open_store = || -> Arc<dyn MapStore> {
        Arc::new(SledStore::open(&SledStoreOptions::at(dir.path())).expect("sled"))
    };
    let config = config();
    let server = RunningServer::start(&config, open_store())
        .await
        .expect("server");
    let mut before: Vec<(u64, MapDelta)> = Vec::new();
    for (k, site) in MAPPED.iter().enumerate() {
        let mut robot = Uploader::new(
            uplink(&server, site),
            Outbox::in_memory(site),
            site,
            "r1",
            "first",
        )
        .expect("uploader");
        // Sites of different sizes, so that a mix-up shows.
        for i in 1..=(2 + i64::try_from(k).expect("small")) {
            robot.enqueue(&OneRobotSite::node(i)).expect("enqueue");
        }
        robot.enqueue(&[UploadItem::SessionEnd]).expect("enqueue");
        tokio::time::timeout(WAIT, robot.flush())
            .await
            .expect("bounded")
            .expect("flush");
        let mut uplink = uplink(&server, site);
        let version = uplink.map_version().await.expect("version");
        before.push((version, uplink.delta_since(0).await.expect("delta")));
    }
    let mut open = Uploader::new(
        uplink(&server, OPEN),
        Outbox::in_memory(OPEN),
        OPEN,
        "r1",
        "still-open",
    )
    .expect("uploader");
    open.enqueue(&OneRobotSite::node(1)).expect("enqueue");
    tokio::time::timeout(WAIT, open.flush())
        .await
        .expect("bounded")
        .expect("flush");
    let counts_before: Vec<_> = MAPPED
        .iter()
        .map(|site| server.site(site).expect("site").current())
        .collect();
    server.shutdown().await.expect("shutdown");

    let server = RunningServer::start(&config, open_store())
        .await
        .expect("restarted server");
    // Before any query: the mapped sites are unloaded, the open one and the empty one loaded.
    let metrics = scrape(&server).await;
    for line in [
        "evermap_sites 5",
        "evermap_sites_loaded 2",
        "evermap_sites_unloaded 3",
        "evermap_site_unloads_total 0",
        "evermap_site_restore_seconds_count 0",
        "evermap_site_loaded{site=\"store-open\"} 1",
        "evermap_site_loaded{site=\"store-empty\"} 1",
    ] {
        assert!(has_line(&metrics, line), "{line:?} in\n{metrics}");
    }
    for (site, info) in MAPPED.iter().zip(&counts_before) {
        assert!(
            has_line(
                &metrics,
                &format!("evermap_site_loaded{{site=\"{site}\"}} 0")
            ),
            "{site} unloaded in\n{metrics}"
        );
        assert!(
            has_line(
                &metrics,
                &format!("evermap_site_version{{site=\"{site}\"}} {}", info.version)
            ),
            "{site}'s version in\n{metrics}"
        );
        let handle = server.site(site).expect("site");
        assert!(!handle.is_loaded());
        assert_eq!(
            handle.current(),
            *info,
            "{site}: the same version and counts"
        );
    }
    assert!(server.site(OPEN).expect("site").is_loaded());

    // A query to each is answered as before the restart, after its restore.
    for ((k, site), (version, delta)) in MAPPED.iter().enumerate().zip(&before) {
        let mut uplink = uplink(&server, site);
        assert_eq!(uplink.map_version().await.expect("version"), *version);
        assert!(
            !server.site(site).expect("site").is_loaded(),
            "a version needs no map"
        );
        let answered = tokio::time::timeout(WAIT, uplink.delta_since(0))
            .await
            .expect("bounded")
            .expect("delta");
        assert_eq!(answered, *delta, "{site}");
        assert!(server.site(site).expect("site").is_loaded());
        assert_eq!(
            server.metrics().site_unloads_and_restores(),
            (0, u64::try_from(k).expect("small") + 1)
        );
    }
    let metrics = scrape(&server).await;
    for line in [
        "evermap_sites_loaded 5",
        "evermap_sites_unloaded 0",
        "evermap_site_restore_seconds_count 3",
    ] {
        assert!(has_line(&metrics, line), "{line:?} in\n{metrics}");
    }
    server.shutdown().await.expect("shutdown");
}
