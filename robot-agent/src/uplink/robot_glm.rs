//! GLM on the robot during a streamed session: each node is matched against the agent's cache of the
//! site's submaps ([`MapMatcher`]) and the accepted matches travel with the node as `GlobalMatch` items.
//! The matcher is re-synced with the cache whenever a new site version has arrived (fresh submaps in,
//! trimmed ones out, moved poses updated); the session's own submaps are left out (the server finds the
//! session's own loop closures).

use std::sync::{Arc, Mutex};

use mapping::geometry::Rigid2;
use mapping::global_slam::ConstraintBuilderOptions;
use mapping::grid::ProbabilityGrid;
use mapping::lifelong::{GlobalSubmap, MapMatcher};
use mapping::pose_graph::SubmapId;
use proto::UploadItem;

use super::GlobalSubmapCache;

/// A cached submap as the matcher needs it: id, `global_from_submap`, `local_from_submap`, grid.
type Snapshot = (SubmapId, Rigid2, Rigid2, Arc<ProbabilityGrid>);

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

    /// Matches the node of `items` (a node's items: `NodeAdded` then its `SubmapFinished`s) and appends
    /// the accepted matches. `own_trajectory`: the session's trajectory in the site map, once known.
    pub async fn match_items(
        &mut self,
        cache: &Mutex<GlobalSubmapCache>,
        own_trajectory: Option<u32>,
        items: &mut Vec<UploadItem>,
    ) {
        let Some(UploadItem::NodeAdded(node)) = items.first() else {
            return;
        };
        let (local_pose, points) = (node.local_pose, Arc::new(node.points.clone()));
        let snapshot: Option<Vec<Snapshot>> = cache.lock().ok().and_then(|cache| {
            (self.synced_version != Some(cache.version())).then(|| {
                self.synced_version = Some(cache.version());
                cache
                    .submaps()
                    .values()
                    .filter(|s| Some(s.id.trajectory) != own_trajectory)
                    .map(|s| (s.id, s.global_pose, s.local_pose, Arc::clone(&s.grid)))
                    .collect()
            })
        });
        let Some(mut matcher) = self.matcher.take() else {
            return;
        };
        let work = tokio::task::spawn_blocking(move || {
            if let Some(snapshot) = snapshot {
                matcher.sync_submaps(snapshot.iter().map(|(id, global, local, grid)| {
                    GlobalSubmap {
                        id: *id,
                        global_pose: *global,
                        local_pose: *local,
                        grid,
                    }
                }));
            }
            let found = matcher.match_node(&local_pose, &points);
            (matcher, found)
        })
        .await;
        let Ok((matcher, found)) = work else {
            tracing::warn!(
                "the GLM thread failed: GLM on the robot is off for the rest of the session"
            );
            return;
        };
        self.matcher = Some(matcher);
        self.matches += found.len() as u64;
        items.extend(found.into_iter().map(|m| UploadItem::GlobalMatch {
            submap: m.submap,
            submap_from_node: m.submap_from_node,
            score: m.score,
        }));
    }
}
