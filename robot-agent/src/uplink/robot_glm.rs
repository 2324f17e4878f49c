//! GLM on the robot during a streamed session: each node is matched against the agent's cache of the
//! site's submaps ([`MapMatcher`]) and the accepted matches travel with the node as `GlobalMatch` items.
//! The matcher is re-synced with the cache whenever a new site version has arrived (fresh submaps in,
//! trimmed ones out, moved poses updated); the session's own submaps are left out (the server finds the
//! session's own loop closures).
//!
//! [`cached_submaps`], [`sync_matcher`] and [`match_node`] are the synchronous steps; the load
//! benchmark uses them to run the robots' GLM ahead of time.

use std::sync::{Arc, Mutex};

use mapping::geometry::Rigid2;
use mapping::global_slam::ConstraintBuilderOptions;
use mapping::lifelong::{GlobalSubmap, MapMatcher};
use proto::{NodeAdded, SubmapSnapshot, UploadItem};

use super::GlobalSubmapCache;

/// The cached submaps the matcher works with: all but those of `own_trajectory` (cheap clones: the grids
/// are shared).
pub fn cached_submaps(
    cache: &GlobalSubmapCache,
    own_trajectory: Option<u32>,
) -> Vec<SubmapSnapshot> {
    cache
        .submaps()
        .values()
        .filter(|s| Some(s.id.trajectory) != own_trajectory)
        .cloned()
        .collect()
}

/// Makes `matcher`'s submaps exactly `submaps` (see [`MapMatcher::sync_submaps`]).
pub fn sync_matcher(matcher: &mut MapMatcher, submaps: &[SubmapSnapshot]) {
    matcher.sync_submaps(submaps.iter().map(|s| GlobalSubmap {
        id: s.id,
        global_pose: s.global_pose,
        local_pose: s.local_pose,
        grid: &s.grid,
    }));
}

/// Matches `node` against the matcher's submaps and returns the accepted matches as `GlobalMatch`
/// items, to follow the node's own items.
pub fn match_node(matcher: &mut MapMatcher, node: &NodeAdded) -> Vec<UploadItem> {
    let points = Arc::new(node.points.clone());
    matcher
        .match_node(&node.local_pose, &points)
        .into_iter()
        .map(|m| UploadItem::GlobalMatch {
            submap: m.submap,
            submap_from_node: m.submap_from_node,
            score: m.score,
        })
        .collect()
}

/// The session's matcher and where it stands against the cache.
pub(super) struct RobotGlm {
    matcher: Option<MapMatcher>,
    synced_version: Option<u64>,
    /// Matches sent.
    pub matches: u64,
}

impl RobotGlm {
    /// GLM for a session placed at `global_from_local` (its relocalized start).
    pub fn new(options: &ConstraintBuilderOptions, global_from_local: Rigid2) -> Option<Self> {
        match MapMatcher::new(options.clone(), global_from_local) {
            Ok(matcher) => Some(Self {
                matcher: Some(matcher),
                synced_version: None,
                matches: 0,
            }),
            Err(e) => {
                tracing::warn!("GLM on the robot is off: {e}");
                None
            }
        }
    }

    /// Matches the node of `items` (a node's items: `NodeAdded` then its `SubmapFinished`s) on a
    /// blocking thread, first re-syncing the matcher when the cache has a new version, and appends the
    /// accepted matches. `own_trajectory`: the session's trajectory in the site map, once known.
    /// Returns the robot's estimate of the node's global pose after the match (`world_from_tracking`;
    /// `None` when `items` holds no node or GLM has stopped).
    pub async fn match_items(
        &mut self,
        cache: &Mutex<GlobalSubmapCache>,
        own_trajectory: Option<u32>,
        items: &mut Vec<UploadItem>,
    ) -> Option<Rigid2> {
        let Some(UploadItem::NodeAdded(node)) = items.first() else {
            return None;
        };
        let node = node.clone();
        let local_pose = node.local_pose;
        let snapshot: Option<Vec<SubmapSnapshot>> = cache.lock().ok().and_then(|cache| {
            (self.synced_version != Some(cache.version())).then(|| {
                self.synced_version = Some(cache.version());
                cached_submaps(&cache, own_trajectory)
            })
        });
        let mut matcher = self.matcher.take()?;
        let work = tokio::task::spawn_blocking(move || {
            if let Some(snapshot) = snapshot {
                sync_matcher(&mut matcher, &snapshot);
            }
            let found = match_node(&mut matcher, &node);
            (matcher, found)
        })
        .await;
        let Ok((matcher, found)) = work else {
            tracing::warn!(
                "the GLM thread failed: GLM on the robot is off for the rest of the session"
            );
            return None;
        };
        let estimate = matcher.global_from_local() * local_pose;
        self.matcher = Some(matcher);
        self.matches += found.len() as u64;
        items.extend(found);
        Some(estimate)
    }
}
