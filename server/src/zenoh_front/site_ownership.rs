//! One owner per site among the server instances behind the zenoh routers.
//!
//! Sites are sharded over instances by configuration (ARCHITECTURE.md, "Scaling out to many stores").
//! Were two instances to serve the same site — a site moved without taking it off its old owner's
//! configuration — the routers would deliver a robot's queries to both, both would answer, and each
//! would apply uploads to its own copy: the site would split in two (`tests/tests/zenoh_sharding.rs`
//! saw a robot's upload answered by an empty second owner). So before the zenoh front end serves its
//! sites it looks for another owner of each: it sends an empty `ZenohRequest` (no token, no request) to
//! `evermap/<site>/api`, which any instance serving the site answers — with a refusal that touches
//! neither the site nor the token checks and their failure limits — and refuses to start while one
//! answers. A queryable dies with its instance's session (a graceful close at once; a killed instance
//! as soon as the router sees its link drop), so a restarted owner waits up to [`OWNER_WAIT`] for its
//! predecessor to go before it refuses. Two instances starting within the same instant can still both
//! serve a site (look, then declare): moves are an operator's procedure, done one at a time. With no
//! `connect` endpoint, or when the routers cannot be reached at start, there is no one to ask: the
//! look is skipped (with a warning).
//!
//! (A zenoh liveliness token per site was tried first: in zenoh 1.10.2 a peer's liveliness query
//! through the router did not see another peer's token, so the site's own queryable is the marker.)

use std::time::Duration;

use prost::Message as _;
use proto::{FORMAT_VERSION, pb};
use proto::{ZenohLinkOptions, zenoh_api_key};

use super::ZenohFrontError;

/// How long another owner of a site may take to go before the start is refused.
pub const OWNER_WAIT: Duration = Duration::from_secs(3);
/// How long one look waits for answers.
const LOOK_TIMEOUT: Duration = Duration::from_millis(500);
/// Pause between two looks.
const LOOK_INTERVAL: Duration = Duration::from_millis(250);

/// Refuses with [`ZenohFrontError::SiteServedElsewhere`] if another instance still serves one of
/// `sites` after `wait` (see the module docs).
pub async fn ensure_no_other_owner<'a>(
    options: &ZenohLinkOptions,
    sites: impl IntoIterator<Item = &'a String>,
    wait: Duration,
) -> Result<(), ZenohFrontError> {
    if options.connect.is_empty() {
        return Ok(());
    }
    let mut config = options.to_zenoh_config()?;
    config
        .insert_json5("mode", "\"client\"")
        .map_err(ZenohFrontError::Zenoh)?;
    let session = match zenoh::open(config).await {
        Ok(session) => session,
        Err(e) => {
            tracing::warn!(
                "cannot reach the zenoh routers to check that no other instance serves this one's \
                 sites ({e}): serving them unchecked"
            );
            return Ok(());
        }
    };
    let mut result = Ok(());
    'sites: for site in sites {
        let started = tokio::time::Instant::now();
        loop {
            match owners(&session, site).await {
                Ok(0) => break,
                Ok(_) if started.elapsed() >= wait => {
                    result = Err(ZenohFrontError::SiteServedElsewhere { site: site.clone() });
                    break 'sites;
                }
                Ok(_) => tokio::time::sleep(LOOK_INTERVAL).await,
                Err(e) => {
                    result = Err(e);
                    break 'sites;
                }
            }
        }
    }
    let _ = session.close().await;
    result
}

/// How many answers `site`'s api key gives (one per serving instance) (bounded by [`LOOK_TIMEOUT`]).
async fn owners(session: &zenoh::Session, site: &str) -> Result<usize, ZenohFrontError> {
    let probe = pb::ZenohRequest {
        format_version: FORMAT_VERSION,
        token: String::new(),
        request: None,
    };
    let replies = session
        .get(zenoh_api_key(site))
        .payload(probe.encode_to_vec())
        .timeout(LOOK_TIMEOUT)
        .await
        .map_err(ZenohFrontError::Zenoh)?;
    let mut answers = 0;
    // The query ends (and the channel closes) at the latest after LOOK_TIMEOUT.
    while replies.recv_async().await.is_ok() {
        answers += 1;
    }
    Ok(answers)
}
