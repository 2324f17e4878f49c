//! A minimal HTTP/1.1 endpoint serving the Prometheus metrics: every request gets the current text.
//!
//! Hand-written on tokio's TCP listener (a handful of lines) rather than pulling in an HTTP server crate:
//! it only ever answers `GET /metrics`-style scrapes, one short response per connection.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
use tokio::net::TcpListener;

use crate::ServerMetrics;
use crate::site::SiteHandle;

/// Longest time a scrape connection may take.
const SCRAPE_TIMEOUT: Duration = Duration::from_secs(5);

/// Serves metrics on `listener` until the task is dropped or aborted.
pub async fn serve_metrics(
    listener: TcpListener,
    metrics: Arc<ServerMetrics>,
    sites: Arc<Vec<SiteHandle>>,
) {
    loop {
        let Ok((mut stream, _)) = listener.accept().await else {
            continue;
        };
        let body = metrics.render(&sites);
        tokio::spawn(async move {
            let _ = tokio::time::timeout(SCRAPE_TIMEOUT, async move {
                // Read (and ignore) the request head; answer whatever was asked.
                let mut buffer = [0_u8; 2048];
                let _ = stream.read(&mut buffer).await;
                let head = format!(
                    "HTTP/1.1 200 OK\r\ncontent-type: text/plain; version=0.0.4\r\ncontent-length: {}\r\nconnection: close\r\n\r\n",
                    body.len()
                );
                let _ = stream.write_all(head.as_bytes()).await;
                let _ = stream.write_all(body.as_bytes()).await;
                let _ = stream.shutdown().await;
            })
            .await;
        });
    }
}

/// Binds the metrics listener.
pub async fn bind_metrics(addr: SocketAddr) -> std::io::Result<TcpListener> {
    TcpListener::bind(addr).await
}
