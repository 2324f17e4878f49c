//! The two overlapping submaps LLO inserts into: every scan goes into both, a new submap starts when
//! the newer one has `num_range_data` scans, and the older is finished when it has twice that — so
//! consecutive submaps overlap by half and every finished submap has the same amount of data.

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
    /// Cell size in metres. Default 0.05 m.
    pub resolution: f64,
    /// Hit/miss update strengths.
    pub range_data_inserter: RangeDataInserterOptions,
}

impl Default for SubmapsOptions {
    fn default() -> Self {
        Self {
            num_range_data: 90,
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
        self.next_index += 1;
    }

    /// Inserts one scan (in the local frame) into every active submap. Returns the submaps it went into
    /// and the submaps this insertion finished, moved out.
    pub fn insert(&mut self, range_data: &RangeData) -> (Vec<SubmapRef>, Vec<(usize, Submap)>) {
        if self.submaps.is_empty() {
            self.add_submap(range_data.origin);
        }
        let mut inserted = Vec::with_capacity(2);
        for (index, submap) in &mut self.submaps {
            self.inserter.insert(range_data, &mut submap.grid);
            submap.num_range_data += 1;
            inserted.push(SubmapRef {
                index: *index,
                local_pose: submap.local_pose,
            });
        }
        let mut finished = Vec::new();
        let n = self.options.num_range_data;
        if self
            .submaps
            .first()
            .is_some_and(|(_, s)| s.num_range_data >= 2 * n)
        {
            let (index, mut submap) = self.submaps.remove(0);
            submap.finished = true;
            submap.grid = submap.grid.cropped_to_known();
            finished.push((index, submap));
        }
        if self
            .submaps
            .last()
            .is_some_and(|(_, s)| s.num_range_data >= n)
            && self.submaps.len() < 2
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
}
