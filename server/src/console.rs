//! The web console for the people who run the fleet, and its JSON API (`[http]` in the server config).
//!
//! One static HTML page (plain JS and CSS, embedded with `include_str!`, no build step) and a JSON API
//! under `/api/`, served by axum over hyper on the server's own tokio runtime: axum and hyper are in the
//! build already through tonic (`cargo tree -e normal -i axum`), so the console adds no HTTP stack.
//! (The Prometheus endpoint, `metrics_endpoint`, stays the tiny hand-written responder it is; the
//! console serves the same text at `/metrics` beside its own routes.)
//!
//! The page shows every site with its version, counts and whether its map is in memory (an idle site's
//! leaves it: `site_unload_after_s`); the selected site's map (PNG rendered like
//! `GetMapImage`) with each robot's latest pose and its sessions' trajectories drawn over it; the
//! version history with a slider and the map-change overlay (unchanged / removed / added occupied cells
//! between any earlier version and the one shown, `mapping::lifelong::map_change_rate`); the sessions
//! with their placement state. It updates itself with **server-sent events** (`GET /api/events`): a
//! version lands, every open page hears of it at once (no polling delay, no load when nothing
//! happens), and `EventSource` reconnects by itself after a restart; WebSockets would add a dependency
//! for a channel that only ever flows one way.
//!
//! Every route but `/health` needs the read-only operator token when one is configured
//! ([`HttpConfig::operator_token`]); see `console_auth`. Routes (also in the README):
//!
//! | route | answer |
//! |---|---|
//! | `GET /` | the page |
//! | `GET /health` | `{"status":"serving","sites":N}` (no token needed) |
//! | `GET /metrics` | the Prometheus text |
//! | `GET /api/sites` | every site: version, counts, when the version landed, `loaded` (its map in memory) |
//! | `GET /api/sites/{site}` | one site, the same fields |
//! | `GET /api/sites/{site}/versions` | the map's history: versions with their counts (an unloaded site is restored first, as for every route below but `robots`) |
//! | `GET /api/sites/{site}/sessions` | sessions: robot, placement state, trajectory, latest pose |
//! | `GET /api/sites/{site}/robots` | each robot's latest session and pose |
//! | `GET /api/sites/{site}/map[?version=V]` | where the map image lies in the site frame |
//! | `GET /api/sites/{site}/map.png[?version=V]` | the map at version V (default: now); `ETag`, 304 when held |
//! | `GET /api/sites/{site}/change?from=A[&to=B]` | map change between two versions: rate, counts, placement |
//! | `GET /api/sites/{site}/change.png?from=A[&to=B]` | the change as an image (blue unchanged, green removed, red added) |
//! | `GET /api/events` | server-sent events: `version` on every new site version, `site` when a site's map leaves memory or comes back (`{"site", "loaded"}`) |

mod console_api;
mod console_auth;
mod console_error;
mod console_state;
mod http_config;
mod map_images;

pub use console_api::router;
pub use console_auth::{COOKIE_NAME, ConsoleAuth};
pub use console_error::ConsoleError;
pub use console_state::{ConsoleState, LoadEvent, VersionEvent};
pub use http_config::{HttpConfig, HttpConfigError, MIN_OPERATOR_TOKEN_CHARS};
pub use map_images::{ChangeImage, MapImage, render_change_image, render_map_image};

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::oneshot;
use tokio::task::JoinHandle;

use crate::ServerMetrics;
use crate::site::SiteHandle;

/// How long [`RunningConsole::shutdown`] waits for open requests (event streams never end by
/// themselves) before cutting them.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);

/// The console's HTTP server, started by [`RunningConsole::start`].
pub struct RunningConsole {
    addr: SocketAddr,
    stop: oneshot::Sender<()>,
    server: JoinHandle<std::io::Result<()>>,
    watchers: Vec<JoinHandle<()>>,
}

impl RunningConsole {
    /// Binds `config.listen` and serves the console for `sites` until [`Self::shutdown`].
    pub async fn start(
        config: &HttpConfig,
        sites: Arc<BTreeMap<String, SiteHandle>>,
        metrics: Arc<ServerMetrics>,
    ) -> std::io::Result<Self> {
        let listener = tokio::net::TcpListener::bind(config.listen).await?;
        let addr = listener.local_addr()?;
        let state = Arc::new(ConsoleState::new(config, sites, metrics));
        let watchers = state.watch_versions();
        let (stop, stopped) = oneshot::channel::<()>();
        let app = router(Arc::clone(&state));
        let server = tokio::spawn(async move {
            axum::serve(listener, app)
                .with_graceful_shutdown(async move {
                    let _ = stopped.await;
                })
                .await
        });
        tracing::info!(console = %format!("http://{addr}/"), "web console serving");
        Ok(Self {
            addr,
            stop,
            server,
            watchers,
        })
    }

    /// The bound address (useful with port 0).
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Stops accepting, waits up to 2 s for open requests, then cuts them (event streams).
    pub async fn shutdown(self) {
        let _ = self.stop.send(());
        let mut server = self.server;
        if tokio::time::timeout(SHUTDOWN_GRACE, &mut server)
            .await
            .is_err()
        {
            server.abort();
            let _ = server.await;
        }
        for watcher in self.watchers {
            watcher.abort();
            let _ = watcher.await;
        }
    }
}
