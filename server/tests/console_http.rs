//! The web console as `evermap-server serve` runs it: `[http]` in the config starts it beside gRPC on
//! 127.0.0.1, refuses requests without the operator token (robot tokens do not open it either), and
//! answers with it; without `[http]` there is no console. Plain HTTP/1.1 over a TCP socket, every wait
//! bounded.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use server::{HttpConfig, RobotConfig, RunningServer, ServerConfig, SiteConfig};
use storage::MemStore;
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};

const OPERATOR: &str = "operator-token-1";
const ROBOT: &str = "robot-token-1";

/// One GET; returns the status code and the body.
async fn get(addr: SocketAddr, path: &str, token: Option<&str>) -> (u16, String) {
    let exchange = async {
        let mut stream = tokio::net::TcpStream::connect(addr).await.expect("connect");
        let auth = token.map_or_else(String::new, |t| format!("authorization: Bearer {t}\r\n"));
        let request =
            format!("GET {path} HTTP/1.1\r\nhost: {addr}\r\n{auth}connection: close\r\n\r\n");
        stream.write_all(request.as_bytes()).await.expect("write");
        let mut response = Vec::new();
        stream.read_to_end(&mut response).await.expect("read");
        String::from_utf8_lossy(&response).into_owned()
    };
    let response = tokio::time::timeout(Duration::from_secs(20), exchange)
        .await
        .expect("an answer within 20 s");
    let status = response
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .expect("a status line");
    let body = response
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_owned())
        .unwrap_or_default();
    (status, body)
}

fn config(http: Option<HttpConfig>) -> ServerConfig {
    ServerConfig {
        listen: "127.0.0.1:0".parse().expect("address"),
        metrics_listen: None,
        http,
        sites: vec![SiteConfig {
            id: "store-1".into(),
            robots: vec![RobotConfig {
                id: "robot-1".into(),
                token: ROBOT.into(),
            }],
        }],
        ..ServerConfig::default()
    }
}

#[tokio::test]
async fn serve_runs_the_console_behind_the_operator_token() {
    let http = HttpConfig {
        listen: "127.0.0.1:0".parse().expect("address"),
        operator_token: Some(OPERATOR.into()),
        ..HttpConfig::default()
    };
    let server = RunningServer::start(&config(Some(http)), Arc::new(MemStore::new()))
        .await
        .expect("start");
    let addr = server.console_addr().expect("the console is on");

    let (status, body) = get(addr, "/health", None).await;
    assert_eq!(status, 200);
    let health: serde_json::Value = serde_json::from_str(&body).expect("JSON");
    assert_eq!(
        health,
        serde_json::json!({ "status": "serving", "sites": 1 })
    );
    for token in [None, Some(ROBOT), Some("guess-guess")] {
        for path in ["/", "/api/sites", "/api/sites/store-1/map.png", "/metrics"] {
            let (status, body) = get(addr, path, token).await;
            assert_eq!(status, 401, "{path} with {token:?}: {body}");
        }
    }
    let (status, body) = get(addr, "/api/sites", Some(OPERATOR)).await;
    assert_eq!(status, 200, "{body}");
    let sites: serde_json::Value = serde_json::from_str(&body).expect("JSON");
    assert_eq!(sites[0]["site"], "store-1");
    assert_eq!(sites[0]["version"], 0);
    let (status, _) = get(addr, "/api/sites/store-2", Some(OPERATOR)).await;
    assert_eq!(status, 404);
    let (status, body) = get(addr, "/api/sites/store-1/map.png", Some(OPERATOR)).await;
    assert_eq!(status, 404, "no map yet: {body}");
    let (status, body) = get(addr, &format!("/?token={OPERATOR}"), None).await;
    assert_eq!(status, 200);
    assert!(body.contains("<title>evermap console</title>"));
    server.shutdown().await.expect("shutdown");
}

#[tokio::test]
async fn without_an_http_section_there_is_no_console() {
    let server = RunningServer::start(&config(None), Arc::new(MemStore::new()))
        .await
        .expect("start");
    assert!(server.console_addr().is_none());
    server.shutdown().await.expect("shutdown");
}
