//! What changed in a site map between two versions, and how it is split into messages.

use std::sync::Arc;

use mapping::geometry::Rigid2;
use mapping::grid::ProbabilityGrid;
use mapping::pose_graph::SubmapId;
use prost::Message as _;

use crate::{
    ConversionError, FORMAT_VERSION, check_format_version, grid_from_pb, grid_to_pb, pb,
    pose_from_pb, pose_to_pb,
};

/// A finished submap of a site map.
#[derive(Clone, Debug, PartialEq)]
pub struct SubmapSnapshot {
    /// The submap.
    pub id: SubmapId,
    /// Site map version at which its grid was stored.
    pub revision: u64,
    /// `global_from_submap`.
    pub global_pose: Rigid2,
    /// `local_from_submap` in its session's local frame.
    pub local_pose: Rigid2,
    /// The grid, in the session's local frame.
    pub grid: Arc<ProbabilityGrid>,
}

impl From<&SubmapSnapshot> for pb::Submap {
    fn from(s: &SubmapSnapshot) -> Self {
        Self {
            format_version: FORMAT_VERSION,
            id: Some(s.id.into()),
            revision: s.revision,
            global_pose: Some(pose_to_pb(&s.global_pose)),
            local_pose: Some(pose_to_pb(&s.local_pose)),
            grid: Some(grid_to_pb(&s.grid)),
        }
    }
}

impl TryFrom<&pb::Submap> for SubmapSnapshot {
    type Error = ConversionError;

    fn try_from(s: &pb::Submap) -> Result<Self, ConversionError> {
        const M: &str = "Submap";
        check_format_version(M, s.format_version)?;
        let missing = |field| ConversionError::MissingField { message: M, field };
        Ok(Self {
            id: s.id.ok_or(missing("id"))?.into(),
            revision: s.revision,
            global_pose: pose_from_pb(s.global_pose.as_ref(), M, "global_pose")?,
            local_pose: pose_from_pb(s.local_pose.as_ref(), M, "local_pose")?,
            grid: Arc::new(grid_from_pb(s.grid.as_ref().ok_or(missing("grid"))?)?),
        })
    }
}

/// The changes of a site map from `from_version` (exclusive) to `to_version` (inclusive).
#[derive(Clone, Debug, PartialEq)]
pub struct MapDelta {
    /// The site.
    pub site: String,
    /// The version the receiver has (0: nothing).
    pub from_version: u64,
    /// The version the receiver has after applying the delta.
    pub to_version: u64,
    /// Submaps finished after `from_version`, with their grids.
    pub submaps_added: Vec<SubmapSnapshot>,
    /// `global_from_submap` of every submap whose pose changed after `from_version`.
    pub pose_updates: Vec<(SubmapId, Rigid2)>,
    /// Submaps removed after `from_version`.
    pub trimmed: Vec<SubmapId>,
}

impl MapDelta {
    /// Splits the delta into messages of roughly at most `max_message_bytes` each (a single submap larger
    /// than that still travels whole): the first carries the pose updates and trimmed ids, the others the
    /// submaps; the last one has `last` set. There is always at least one message.
    pub fn to_pb_chunks(&self, max_message_bytes: usize) -> Vec<pb::MapDelta> {
        let empty = || pb::MapDelta {
            format_version: FORMAT_VERSION,
            site: self.site.clone(),
            from_version: self.from_version,
            to_version: self.to_version,
            submaps_added: Vec::new(),
            pose_updates: Vec::new(),
            trimmed: Vec::new(),
            last: false,
        };
        let mut first = empty();
        first.pose_updates = self
            .pose_updates
            .iter()
            .map(|(id, pose)| pb::SubmapPose {
                id: Some((*id).into()),
                global_pose: Some(pose_to_pb(pose)),
            })
            .collect();
        first.trimmed = self.trimmed.iter().map(|id| (*id).into()).collect();
        let mut chunks = vec![first];
        let mut size = chunks[0].encoded_len();
        for submap in &self.submaps_added {
            let wire = pb::Submap::from(submap);
            let len = wire.encoded_len() + 8;
            if size + len > max_message_bytes && !chunks.last().is_some_and(is_empty_chunk) {
                chunks.push(empty());
                size = 0;
            }
            size += len;
            if let Some(chunk) = chunks.last_mut() {
                chunk.submaps_added.push(wire);
            }
        }
        if let Some(last) = chunks.last_mut() {
            last.last = true;
        }
        chunks
    }

    /// Reassembles a delta from the messages of [`Self::to_pb_chunks`] (in order). Refuses an empty list,
    /// chunks of different versions or sites, and a list whose only `last` chunk is not the final one.
    pub fn from_pb_chunks<'a>(
        chunks: impl IntoIterator<Item = &'a pb::MapDelta>,
    ) -> Result<Self, ConversionError> {
        const M: &str = "MapDelta";
        let mut delta: Option<Self> = None;
        let mut finished = false;
        for (index, chunk) in chunks.into_iter().enumerate() {
            check_format_version(M, chunk.format_version)?;
            if finished {
                return Err(ConversionError::Misplaced {
                    message: M,
                    field: "last",
                    index,
                    rule: "no chunk may follow the one marked last",
                });
            }
            let delta = delta.get_or_insert_with(|| Self {
                site: chunk.site.clone(),
                from_version: chunk.from_version,
                to_version: chunk.to_version,
                submaps_added: Vec::new(),
                pose_updates: Vec::new(),
                trimmed: Vec::new(),
            });
            let other_delta = if chunk.site != delta.site {
                Some("site")
            } else if chunk.from_version != delta.from_version {
                Some("from_version")
            } else if chunk.to_version != delta.to_version {
                Some("to_version")
            } else {
                None
            };
            if let Some(field) = other_delta {
                return Err(ConversionError::Misplaced {
                    message: M,
                    field,
                    index,
                    rule: "a chunk of another delta (each must carry the first chunk's site and versions)",
                });
            }
            for submap in &chunk.submaps_added {
                delta.submaps_added.push(SubmapSnapshot::try_from(submap)?);
            }
            for update in &chunk.pose_updates {
                let id = update.id.ok_or(ConversionError::MissingField {
                    message: "SubmapPose",
                    field: "id",
                })?;
                let pose = pose_from_pb(update.global_pose.as_ref(), "SubmapPose", "global_pose")?;
                delta.pose_updates.push((id.into(), pose));
            }
            delta
                .trimmed
                .extend(chunk.trimmed.iter().map(|id| SubmapId::from(*id)));
            finished = chunk.last;
        }
        match delta {
            Some(delta) if finished => Ok(delta),
            Some(_) => Err(ConversionError::MissingField {
                message: M,
                field: "last",
            }),
            None => Err(ConversionError::BadSize {
                message: M,
                field: "chunks",
                expected: 1,
                got: 0,
            }),
        }
    }
}

fn is_empty_chunk(chunk: &pb::MapDelta) -> bool {
    chunk.submaps_added.is_empty() && chunk.pose_updates.is_empty() && chunk.trimmed.is_empty()
}

#[cfg(test)]
mod tests {
    use mapping::geometry::rigid2;
    use mapping::grid::{CellIndex, MapLimits};
    use nalgebra::Vector2;

    use super::*;

    fn submap(index: u32, cells: i32) -> SubmapSnapshot {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::zeros(), cells, cells));
        for i in 0..cells {
            grid.set_probability(&CellIndex::new(i, (i * 7 + index as i32) % cells), 0.3);
        }
        SubmapSnapshot {
            id: SubmapId {
                trajectory: 1,
                index,
            },
            revision: u64::from(index) + 10,
            global_pose: rigid2(f64::from(index), 0.0, 0.1),
            local_pose: rigid2(0.0, f64::from(index), -0.1),
            grid: Arc::new(grid),
        }
    }

    fn delta(n: u32) -> MapDelta {
        MapDelta {
            site: "s".into(),
            from_version: 3,
            to_version: 9,
            submaps_added: (0..n).map(|i| submap(i, 50)).collect(),
            pose_updates: vec![(submap(0, 1).id, rigid2(1.0, 2.0, 3.0))],
            trimmed: vec![SubmapId {
                trajectory: 0,
                index: 4,
            }],
        }
    }

    #[test]
    fn deltas_split_into_bounded_chunks_and_reassemble() {
        let d = delta(12);
        let one_submap = pb::Submap::from(&d.submaps_added[0]).encoded_len();
        let chunks = d.to_pb_chunks(3 * one_submap + 100);
        assert!(chunks.len() >= 4, "{} chunks", chunks.len());
        assert!(chunks.iter().rev().skip(1).all(|c| !c.last));
        assert!(chunks.last().unwrap().last);
        let back = MapDelta::from_pb_chunks(&chunks).unwrap();
        assert_eq!(back.submaps_added.len(), 12);
        assert_eq!(back.trimmed, d.trimmed);
        assert_eq!(back.pose_updates.len(), 1);
        for (a, b) in back.submaps_added.iter().zip(&d.submaps_added) {
            assert_eq!((a.id, a.revision, &a.grid), (b.id, b.revision, &b.grid));
        }
        // Everything in one message when it fits.
        assert_eq!(d.to_pb_chunks(usize::MAX).len(), 1);
        // An empty delta is still one (last) message.
        let empty = MapDelta {
            submaps_added: vec![],
            pose_updates: vec![],
            trimmed: vec![],
            ..d
        };
        let chunks = empty.to_pb_chunks(10);
        assert_eq!(chunks.len(), 1);
        assert_eq!(MapDelta::from_pb_chunks(&chunks).unwrap(), empty);
    }

    #[test]
    fn incomplete_or_mixed_chunks_are_refused() {
        let chunks = delta(4).to_pb_chunks(1);
        assert!(MapDelta::from_pb_chunks(&chunks[..chunks.len() - 1]).is_err());
        assert!(MapDelta::from_pb_chunks(&[]).is_err());
        let mut mixed = chunks.clone();
        mixed[1].to_version = 10;
        assert!(matches!(
            MapDelta::from_pb_chunks(&mixed),
            Err(ConversionError::Misplaced {
                field: "to_version",
                index: 1,
                ..
            })
        ));
        let mut twice = chunks.clone();
        twice.push(chunks[0].clone());
        assert!(matches!(
            MapDelta::from_pb_chunks(&twice),
            Err(ConversionError::Misplaced {
                field: "last",
                index,
                ..
            }) if index == chunks.len()
        ));
    }
}
