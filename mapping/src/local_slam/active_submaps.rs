//! The two overlapping submaps LLO inserts into: every scan goes into both, a new submap starts when
//! the newer one has `num_range_data` scans, and the older is finished when it has twice that — so
//! consecutive submaps overlap by half and every finished submap has the same amount of data. With
//! `max_path_m`, a submap is also bounded by the path it was built over (the scans' origins), so a slow
//! scanner's submaps do not span several times the path a fast one's do.

use nalgebra::Vector2;
use serde::{Deserialize, Serialize};

use super::{Submap, SubmapRef};
use crate::geometry::rigid2;
use crate::grid::{MapLimits, ProbabilityGrid, RangeDataInserter, RangeDataInserterOptions};
use crate::sensor::RangeData;

/// Submap shape.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SubmapsOptions {
    /// Scans after which a new submap starts; each finished submap holds twice this. Default 90.
    pub num_range_data: usize,
    /// Path (m, along the inserted scans' origins) after which a new submap starts even if it has fewer
    /// than `num_range_data` scans; the older finishes at twice this. 0: by scans only. Default 0
    /// (measured, not a default). Why: `docs/TUNING.md#llo-max-path-m`.
    pub max_path_m: f64,
    /// Cell size in metres. Default 0.05 m.
    pub resolution: f64,
    /// Hit/miss update strengths.
    pub range_data_inserter: RangeDataInserterOptions,
}

impl Default for SubmapsOptions {
    fn default() -> Self {
        Self {
            num_range_data: 90,
            max_path_m: 0.0,
            resolution: 0.05,
            range_data_inserter: RangeDataInserterOptions::default(),
        }
    }
}

/// The active submaps of one trajectory.
#[derive(Debug)]
pub struct ActiveSubmaps {
    options: SubmapsOptions,
    inserter: RangeDataInserter,
    /// `(index, submap)`, oldest first; at most two.
    submaps: Vec<(usize, Submap)>,
    /// The path (m) each active submap was built over, in the order of `submaps`.
    paths_m: Vec<f64>,
    /// The origin of the last inserted scan.
    last_origin: Option<Vector2<f64>>,
    next_index: usize,
}

impl ActiveSubmaps {
    /// No submaps yet; the first insertion creates one.
    pub fn new(options: SubmapsOptions) -> Self {
        let inserter = RangeDataInserter::new(options.range_data_inserter.clone());
        Self {
            options,
            inserter,
            submaps: Vec::new(),
            paths_m: Vec::new(),
            last_origin: None,
            next_index: 0,
        }
    }

    /// The active submaps with their per-trajectory indices, oldest first.
    pub fn submaps(&self) -> &[(usize, Submap)] {
        &self.submaps
    }

    /// The submap scans are matched against: the older one, which holds more data.
    pub fn matching_submap(&self) -> Option<&Submap> {
        self.submaps.first().map(|(_, s)| s)
    }

    fn add_submap(&mut self, origin: Vector2<f64>) {
        // A small grid centred on the origin; it grows as scans arrive.
        let half = 100;
        let limits = MapLimits::new(
            self.options.resolution,
            origin - Vector2::new(f64::from(half), f64::from(half)) * self.options.resolution,
            2 * half,
            2 * half,
        );
        self.submaps.push((
            self.next_index,
            Submap {
                local_pose: rigid2(origin.x, origin.y, 0.0),
                grid: ProbabilityGrid::new(limits),
                num_range_data: 0,
                finished: false,
            },
        ));
        self.paths_m.push(0.0);
        self.next_index += 1;
    }

    /// Inserts one scan (in the local frame) into every active submap. Returns the submaps it went into
    /// and the submaps this insertion finished, moved out.
    pub fn insert(&mut self, range_data: &RangeData) -> (Vec<SubmapRef>, Vec<(usize, Submap)>) {
        if self.submaps.is_empty() {
            self.add_submap(range_data.origin);
        }
        let step_m = self
            .last_origin
            .map_or(0.0, |last| (range_data.origin - last).norm());
        self.last_origin = Some(range_data.origin);
        let mut inserted = Vec::with_capacity(2);
        for ((index, submap), path_m) in self.submaps.iter_mut().zip(&mut self.paths_m) {
            self.inserter.insert(range_data, &mut submap.grid);
            submap.num_range_data += 1;
            *path_m += step_m;
            inserted.push(SubmapRef {
                index: *index,
                local_pose: submap.local_pose,
            });
        }
        let mut finished = Vec::new();
        let n = self.options.num_range_data;
        let max_path_m = self.options.max_path_m;
        let full = |scans: usize, path_m: f64, times: usize| {
            scans >= times * n || (max_path_m > 0.0 && path_m >= times as f64 * max_path_m)
        };
        if self
            .submaps
            .first()
            .is_some_and(|(_, s)| full(s.num_range_data, self.paths_m[0], 2))
        {
            let (index, mut submap) = self.submaps.remove(0);
            self.paths_m.remove(0);
            submap.finished = true;
            submap.grid = submap.grid.cropped_to_known();
            finished.push((index, submap));
        }
        if self.submaps.len() < 2
            && self.submaps.last().is_some_and(|(_, s)| {
                full(
                    s.num_range_data,
                    self.paths_m.last().copied().unwrap_or(0.0),
                    1,
                )
            })
        {
            self.add_submap(range_data.origin);
        }
        (inserted, finished)
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::Point2;

    use super::*;

    #[test]
    fn submaps_overlap_by_half_and_finish_full() {
        let mut active = ActiveSubmaps::new(SubmapsOptions {
            num_range_data: 3,
            ..Default::default()
        });
        let data = RangeData {
            origin: Vector2::zeros(),
            returns: vec![Point2::new(1.0f32, 0.0)],
            misses: vec![],
        };
        let mut finished = Vec::new();
        let mut inserted_counts = Vec::new();
        for _ in 0..12 {
            let (inserted, done) = active.insert(&data);
            inserted_counts.push(inserted.len());
            finished.extend(done);
        }
        // Scan 1–3 go into submap 0 only; from then on every scan goes into two submaps.
        assert_eq!(inserted_counts, vec![1, 1, 1, 2, 2, 2, 2, 2, 2, 2, 2, 2]);
        let indices: Vec<usize> = finished.iter().map(|(i, _)| *i).collect();
        assert_eq!(indices, vec![0, 1, 2]);
        assert!(
            finished
                .iter()
                .all(|(_, s)| s.finished && s.num_range_data == 6)
        );
        assert_eq!(active.submaps().len(), 2);
    }

    #[test]
    fn a_slow_scanners_submaps_are_bounded_by_path() {
        let options = SubmapsOptions {
            num_range_data: 90,
            max_path_m: 3.0,
            ..Default::default()
        };
        // Scans 1 m apart: far fewer than 90 scans, but 3 m of path, start the next submap.
        let scan = |k: u32| RangeData {
            origin: Vector2::new(f64::from(k), 0.0),
            returns: vec![Point2::new(f64::from(k) as f32 + 1.0, 0.0)],
            misses: vec![],
        };
        let mut active = ActiveSubmaps::new(options.clone());
        let mut inserted_counts = Vec::new();
        let mut finished = Vec::new();
        for k in 0..10 {
            let (inserted, done) = active.insert(&scan(k));
            inserted_counts.push(inserted.len());
            finished.extend(done);
        }
        // Submap 1 starts after the scan 3 m from submap 0's first; submap 0 finishes at 6 m, and so on.
        assert_eq!(inserted_counts, vec![1, 1, 1, 1, 2, 2, 2, 2, 2, 2]);
        let indices: Vec<usize> = finished.iter().map(|(i, _)| *i).collect();
        assert_eq!(indices, vec![0, 1]);
        // Submap 0 holds the scans at 0–6 m; submap 1, started at 3 m, those at 4–9 m.
        let scans: Vec<usize> = finished.iter().map(|(_, s)| s.num_range_data).collect();
        assert_eq!(scans, vec![7, 6]);
        assert!(finished.iter().all(|(_, s)| s.finished));
        // Without the bound the same scans stay in one submap.
        let mut by_scans = ActiveSubmaps::new(SubmapsOptions {
            max_path_m: 0.0,
            ..options
        });
        for k in 0..10 {
            let (inserted, done) = by_scans.insert(&scan(k));
            assert_eq!(inserted.len(), 1);
            assert!(done.is_empty());
        }
    }
}
