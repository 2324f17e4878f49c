//! The gRPC front end (tonic): [`AgentApi`] and [`MapApi`] only authenticate, convert wire messages and
//! hand them to the site tasks; every error becomes a `tonic::Status` in [`status`].

mod agent_api;
mod auth;
mod auth_limiter;
mod map_api;
pub mod status;

pub use agent_api::AgentApi;
pub use auth::{Auth, Grant};
pub use auth_limiter::{AuthLimitOptions, AuthLimitOptionsError, AuthLimiter};
pub use map_api::{MapApi, version_to_pb};

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::ServerMetrics;
use crate::site::SiteHandle;

/// What every handler needs: the sites, who may use them, and the counters.
#[derive(Clone)]
pub struct ApiContext {
    /// The sites, by id.
    pub sites: Arc<BTreeMap<String, SiteHandle>>,
    /// Tokens and their grants.
    pub auth: Arc<Auth>,
    /// Server counters.
    pub metrics: Arc<ServerMetrics>,
    /// Target size of one streamed `MapDelta` message, bytes.
    pub delta_chunk_bytes: usize,
}

impl ApiContext {
    /// Checks the request's token against `site` (a peer failing too often is refused unchecked, see
    /// [`AuthLimiter`]) and finds the site's task.
    pub fn site<T>(
        &self,
        request: &tonic::Request<T>,
        site: &str,
    ) -> Result<(&Grant, &SiteHandle), tonic::Status> {
        let grant = self
            .auth
            .authorize_from(request.metadata(), peer_ip(request), site, now())
            .map_err(|s| status::counted(&self.metrics, s))?;
        let handle = self.sites.get(site).ok_or_else(|| {
            status::counted(
                &self.metrics,
                tonic::Status::not_found(format!("unknown site {site:?}")),
            )
        })?;
        Ok((grant, handle))
    }
}

/// The request's TCP peer address (`None` through zenoh, whose requests are built in process).
pub fn peer_ip<T>(request: &tonic::Request<T>) -> Option<std::net::IpAddr> {
    request.remote_addr().map(|a| a.ip())
}

/// The clock of the failure counters (tokio's, so paused-time tests can move it).
pub fn now() -> std::time::Instant {
    tokio::time::Instant::now().into_std()
}
