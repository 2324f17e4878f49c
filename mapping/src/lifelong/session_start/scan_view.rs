//! What a scan (or a cloud of scans) saw, as a set of cells of the session's local frame: the measure of
//! whether two matches are independent evidence for a placement ([`ScanView::overlap`]).

use std::collections::HashSet;

use nalgebra::Point2;

use crate::geometry::Rigid2;

/// Side of a view cell, metres: coarse enough that two scans of one wall from nearby poses share their
/// cells despite LLO's local drift and the beams' spacing, fine enough that a wall seen from the other
/// side of a shelf is another view.
const VIEW_CELL_M: f64 = 0.3;

/// The cells of the session's local frame that some scans' points fall in.
#[derive(Clone, Debug, Default)]
pub(super) struct ScanView {
    cells: HashSet<(i32, i32)>,
}

impl ScanView {
    /// The view of `scans` (`(local_from_tracking, points)`).
    pub(super) fn of<'a>(scans: impl IntoIterator<Item = (&'a Rigid2, &'a [Point2<f32>])>) -> Self {
        let mut cells = HashSet::new();
        for (local_from_tracking, points) in scans {
            cells.extend(points.iter().map(|p| {
                let local = local_from_tracking * Point2::new(f64::from(p.x), f64::from(p.y));
                (
                    (local.x / VIEW_CELL_M).floor() as i32,
                    (local.y / VIEW_CELL_M).floor() as i32,
                )
            }));
        }
        Self { cells }
    }

    /// Share of this view's cells that `other` saw too, 0–1 (0 for an empty view).
    pub(super) fn overlap(&self, other: &ScanView) -> f64 {
        if self.cells.is_empty() {
            return 0.0;
        }
        let shared = self
            .cells
            .iter()
            .filter(|c| other.cells.contains(c))
            .count();
        shared as f64 / self.cells.len() as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;

    fn wall(x0: f32, x1: f32, y: f32) -> Vec<Point2<f32>> {
        (0..=((x1 - x0) / 0.05) as i32)
            .map(|i| Point2::new(x0 + i as f32 * 0.05, y))
            .collect()
    }

    #[test]
    fn a_wall_seen_again_from_a_nearby_pose_overlaps_and_a_new_wall_does_not() {
        let points = wall(-2.0, 2.0, 3.0);
        let here = ScanView::of([(&rigid2(0.0, 0.0, 0.0), points.as_slice())]);
        // The same wall from 0.5 m further along it: the points shift back by 0.5 m in the scan.
        let shifted = wall(-2.5, 1.5, 3.0);
        let nearby = ScanView::of([(&rigid2(0.5, 0.0, 0.0), shifted.as_slice())]);
        assert!(nearby.overlap(&here) > 0.8, "{}", nearby.overlap(&here));
        // Turned round: the wall behind the robot.
        let behind = ScanView::of([(&rigid2(0.0, 0.0, std::f64::consts::PI), points.as_slice())]);
        assert!(behind.overlap(&here) < 1e-12);
        assert!(ScanView::default().overlap(&here) < 1e-12);
    }
}
