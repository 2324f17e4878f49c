//! The load benchmark's idle sites (`load --idle-store`): the sites of a store made beforehand (hundreds
//! of copies of mapped sites: `scripts/clone_sites.sh`), served by the same instance beside the load's
//! active sites. They start unloaded (a checkpoint covers each) and stay idle, but for a few requests
//! spread over the measured phase, each to another site, timed: how long an unloaded site takes to
//! answer while the active sites stream (issue 34: 500 sites on one instance, 40 of them active).

use std::time::{Duration, Instant};

use robot_agent::uplink::{GrpcUplink, MapUplink as _};
use server::{RobotConfig, SiteConfig};
use storage::MapStore;

use crate::demo_command::MAX_MESSAGE_BYTES;

/// An idle site and the token of the one robot the benchmark lets ask it.
#[derive(Clone, Debug)]
pub(crate) struct IdleSite {
    pub id: String,
    pub token: String,
}

impl IdleSite {
    /// The server's configuration of the site.
    pub fn config(&self) -> SiteConfig {
        SiteConfig {
            id: self.id.clone(),
            robots: vec![RobotConfig {
                id: "idle-probe".into(),
                token: self.token.clone(),
            }],
        }
    }
}

/// Every site `store` holds, as idle sites; refuses a store that already holds one of `active` (the
/// load's own site ids), whose sessions would land on an old map.
pub(crate) fn idle_sites(store: &dyn MapStore, active: &[String]) -> anyhow::Result<Vec<IdleSite>> {
    let sites = store.list_sites()?;
    if let Some(taken) = sites.iter().find(|s| active.contains(s)) {
        anyhow::bail!(
            "the idle store already holds site {taken:?}, one of the load's own: give a store of other \
             sites (scripts/clone_sites.sh names its copies <site>-c0001, ...)"
        );
    }
    Ok(sites
        .into_iter()
        .enumerate()
        .map(|(i, id)| IdleSite {
            id,
            token: format!("idle-token-{i}"),
        })
        .collect())
}

/// One timed request to an idle site.
#[derive(Clone, Debug, serde::Serialize)]
pub(crate) struct IdleProbe {
    pub site: String,
    /// Whether the site was unloaded when asked (a restore answered it).
    pub was_unloaded: bool,
    /// From the request to its answer: the delta since the site's current version (read beforehand),
    /// which an unloaded site answers after restoring its map.
    pub answered_s: f64,
}

/// Asks `count` of `sites` (evenly chosen), one every `spacing`, for the delta since their current
/// version, timing each answer; `is_unloaded` says whether a site was unloaded just before its request.
pub(crate) async fn probe_idle_sites(
    url: String,
    sites: Vec<IdleSite>,
    count: usize,
    spacing: Duration,
    is_unloaded: impl Fn(&str) -> bool,
) -> anyhow::Result<Vec<IdleProbe>> {
    let count = count.min(sites.len());
    let mut probes = Vec::with_capacity(count);
    for k in 0..count {
        tokio::time::sleep(spacing).await;
        let site = &sites[k * sites.len() / count];
        let mut uplink = GrpcUplink::new(
            &url,
            &site.id,
            &site.token,
            MAX_MESSAGE_BYTES,
            Duration::from_secs(60),
        )?;
        let version = uplink.map_version().await?;
        let was_unloaded = is_unloaded(&site.id);
        let asked = Instant::now();
        uplink.delta_since(version).await?;
        probes.push(IdleProbe {
            site: site.id.clone(),
            was_unloaded,
            answered_s: asked.elapsed().as_secs_f64(),
        });
    }
    Ok(probes)
}
