//! Shared test fixtures (`cfg(test)`): a straight route whose node `k` lies at x = 0.1 k and is
//! inserted into submaps that lie at x = their index, as the site map's and the metrics' tests feed it.

use mapping::geometry::rigid2;
use mapping::grid::{CellIndex, MapLimits, ProbabilityGrid};
use mapping::pose_graph::SubmapId;
use mapping::sensor::Timestamp;
use nalgebra::{Point2, Vector2};
use proto::{NodeAdded, UploadItem};

/// A 2 m × 2 m grid (5 cm cells) with one wall, the row of cells 30.
pub(crate) fn grid() -> ProbabilityGrid {
    let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::new(-1.0, -1.0), 40, 40));
    for i in 0..40 {
        grid.set_probability(&CellIndex::new(i, 30), 0.9);
    }
    grid
}

/// Node `i` of the route (at x = 0.1 i, stamped i × 0.1 s), inserted into `submaps`.
pub(crate) fn node(i: u32, submaps: &[u32]) -> UploadItem {
    UploadItem::NodeAdded(NodeAdded {
        time: Timestamp(i64::from(i) * 100_000_000),
        local_pose: rigid2(0.1 * f64::from(i), 0.0, 0.0),
        points: vec![Point2::new(1.0, 0.5), Point2::new(1.0, -0.5)],
        insertion_submaps: submaps
            .iter()
            .map(|s| (*s, rigid2(f64::from(*s), 0.0, 0.0)))
            .collect(),
        recovered: false,
    })
}

/// The robot's match (score 0.9) of its node `k` to submap `k` of trajectory 0, where both are on the
/// route.
pub(crate) fn match_to_submap(k: u32) -> UploadItem {
    UploadItem::GlobalMatch {
        submap: SubmapId {
            trajectory: 0,
            index: k,
        },
        submap_from_node: rigid2(0.1 * f64::from(k) - f64::from(k), 0.0, 0.0),
        score: 0.9,
    }
}
