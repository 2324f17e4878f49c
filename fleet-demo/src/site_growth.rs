//! How a site grows with its age while the load benchmark matures it (`maturing_growth` in the load
//! report, issue 34): its sessions, graph and the store's bytes on disk, sampled each time its session
//! count goes up.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use serde_json::json;
use server::RunningServer;

use crate::load_fleet::site_id;
use crate::memory_attribution::folder_bytes;

/// A site's sizes now (`None` for a site the server does not hold): its sessions, map version, graph and
/// the whole store's bytes on disk, for the maturing phase's growth (`maturing_growth` in the report).
pub(crate) async fn site_sizes(
    server: &RunningServer,
    site: usize,
    store_dir: &Path,
) -> Option<serde_json::Value> {
    let current = server.site(&site_id(site))?.current();
    let counts = current.counts;
    // Walking the store's folders is blocking file I/O: off the async threads.
    let dir = store_dir.to_path_buf();
    let store_bytes = tokio::task::spawn_blocking(move || folder_bytes(&dir, 4))
        .await
        .unwrap_or(0);
    Some(json!({
        "site": site_id(site),
        "sessions": counts.sessions,
        "version": current.version,
        "nodes": counts.nodes,
        "submaps": counts.submaps,
        "finished_submaps": counts.finished_submaps,
        "constraints": counts.constraints,
        "trimmed_submaps": counts.trimmed_submaps,
        "store_disk_mb": store_bytes as f64 / (1024.0 * 1024.0),
    }))
}

/// Samples every site's sizes each time its session count goes up, until `done`: how a site grows with
/// its age while it matures (issue 34).
pub(crate) async fn site_growth_until(
    server: &RunningServer,
    sites: usize,
    store_dir: &Path,
    done: &AtomicBool,
) -> Vec<serde_json::Value> {
    let mut samples = Vec::new();
    let mut seen = vec![0u64; sites];
    while !done.load(Ordering::Relaxed) {
        for (site, seen) in seen.iter_mut().enumerate() {
            let sessions = server
                .site(&site_id(site))
                .map_or(0, |h| h.current().counts.sessions);
            if sessions > *seen {
                *seen = sessions;
                samples.extend(site_sizes(server, site, store_dir).await);
            }
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    samples
}

/// Site 0's session count and map version at the maturing sample where its session count first reached
/// half its final one (`None` without maturing samples of it).
pub(crate) fn half_life_version(growth: &[serde_json::Value]) -> Option<(u64, u64)> {
    let site = site_id(0);
    let samples: Vec<(u64, u64)> = growth
        .iter()
        .filter(|s| s["site"] == site.as_str())
        .filter_map(|s| Some((s["sessions"].as_u64()?, s["version"].as_u64()?)))
        .collect();
    let last = samples.iter().map(|(sessions, _)| *sessions).max()?;
    samples
        .into_iter()
        .find(|(sessions, _)| *sessions >= last.div_ceil(2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_half_life_version_is_the_first_sample_at_half_the_final_session_count() {
        let sample = |site: usize, sessions: u64, version: u64| json!({"site": site_id(site), "sessions": sessions, "version": version});
        let growth = [
            sample(0, 1, 10),
            sample(1, 4, 99),
            sample(0, 2, 20),
            sample(0, 3, 30),
            sample(0, 4, 40),
            sample(0, 5, 50),
        ];
        assert_eq!(half_life_version(&growth), Some((3, 30)));
        assert_eq!(half_life_version(&growth[1..2]), None);
    }
}
