//! Every `evermap.fleet.v1` message, decoded with prost and, where one exists, converted into `mapping`
//! types as the server and agent do (`UploadBatch`, `MapDelta`, `Submap`, `Node`, `Constraint`, `Grid`,
//! the site log's and zenoh's envelopes, a site checkpoint restored into a map). The first byte of an
//! input picks the message. An accepted
//! conversion must survive the trip back: after one trip (poses normalise through (x, y, θ)),
//! `T → pb → T` gives `T` again.

use std::sync::Arc;

use mapping::geometry::{Rigid2, Rigid2Ext as _, rigid2};
use mapping::grid::{CellIndex, MapLimits, ProbabilityGrid};
use mapping::lifelong::{LifelongMap, LifelongOptions};
use mapping::pose_graph::{Constraint, ConstraintKind, NodeId, RobustLoss, SubmapId, VariableId};
use mapping::sensor::Timestamp;
use nalgebra::{Matrix3, Point2, Vector2};
use prost::Message;
use proto::{
    FORMAT_VERSION, MapDelta, NodeAdded, NodeSnapshot, SiteCheckpoint, SubmapSnapshot, UploadBatch,
    UploadItem, pb,
};

use super::super::fuzz_target::{FuzzTarget, Verdict};

fn grid(width: i32, height: i32, salt: i32) -> ProbabilityGrid {
    let mut grid =
        ProbabilityGrid::new(MapLimits::new(0.05, Vector2::new(-1.0, 2.0), width, height));
    for i in 0..width.min(height) {
        grid.set_probability(&CellIndex::new(i, (i * 7 + salt) % height), 0.75);
        grid.set_probability(&CellIndex::new((i * 3) % width, i), 0.2);
    }
    grid
}

/// A batch with one item of every kind.
pub(super) fn sample_upload_batch() -> UploadBatch {
    UploadBatch {
        site: "store-1".into(),
        robot_id: "robot-1".into(),
        session_uuid: "4f1c2a9e-0000-4000-8000-000000000001".into(),
        seq: 7,
        items: vec![
            UploadItem::SessionStartPrior {
                global_from_local: rigid2(1.0, 2.0, 0.5),
                glm_on_robot: true,
                at_dock: true,
                fitted: Some((0, 9)),
            },
            UploadItem::NodeAdded(NodeAdded {
                time: Timestamp(1_700_000_000_123_456_789),
                local_pose: rigid2(0.25, 0.5, 0.125),
                points: (0..40)
                    .map(|i| Point2::new(i as f32 * 0.1, (i as f32 * 0.3).sin()))
                    .collect(),
                insertion_submaps: vec![(0, rigid2(0.0, 0.0, 0.0)), (1, rigid2(0.5, 0.0, 0.0))],
                recovered: false,
            }),
            UploadItem::SubmapFinished {
                index: 0,
                grid: grid(24, 20, 1),
            },
            UploadItem::GlobalMatch {
                submap: SubmapId {
                    trajectory: 3,
                    index: 9,
                },
                submap_from_node: rigid2(0.5, -0.25, 0.0625),
                score: 0.75,
            },
            UploadItem::DockPlacementKept,
            UploadItem::SessionEnd,
        ],
    }
}

fn submap(index: u32) -> SubmapSnapshot {
    SubmapSnapshot {
        id: SubmapId {
            trajectory: 1,
            index,
        },
        revision: u64::from(index) + 10,
        global_pose: rigid2(f64::from(index), 0.0, 0.1),
        local_pose: rigid2(0.0, f64::from(index), -0.1),
        grid: Arc::new(grid(16, 12, index as i32)),
    }
}

fn map_delta() -> pb::MapDelta {
    pb::MapDelta {
        format_version: FORMAT_VERSION,
        site: "store-1".into(),
        from_version: 3,
        to_version: 9,
        submaps_added: vec![pb::Submap::from(&submap(0)), pb::Submap::from(&submap(1))],
        pose_updates: vec![pb::SubmapPose {
            id: Some(
                SubmapId {
                    trajectory: 0,
                    index: 2,
                }
                .into(),
            ),
            global_pose: Some(proto::pose_to_pb(&rigid2(1.0, 1.0, 0.2))),
        }],
        trimmed: vec![
            SubmapId {
                trajectory: 0,
                index: 1,
            }
            .into(),
        ],
        last: true,
    }
}

fn constraint() -> Constraint {
    Constraint {
        kind: ConstraintKind::NodeToSubmapInter,
        from: VariableId::Submap(SubmapId {
            trajectory: 2,
            index: 5,
        }),
        to: VariableId::Node(NodeId {
            trajectory: 1,
            index: 77,
        }),
        from_from_to: rigid2(1.5, -0.25, 0.3),
        information: Matrix3::new(400.0, 1.0, 2.0, 1.0, 300.0, 3.0, 2.0, 3.0, 1000.0),
        loss: RobustLoss::Huber { delta: 0.5 },
    }
}

fn node() -> NodeSnapshot {
    NodeSnapshot {
        id: NodeId {
            trajectory: 1,
            index: 4,
        },
        time: Timestamp(1_700_000_000_000_000_000),
        local_pose: rigid2(3.0, -1.0, 0.7),
        points: (0..30).map(|i| Point2::new(i as f32 * 0.2, 1.0)).collect(),
    }
}

/// Poses equal up to rounding (they travel as (x, y, θ) and come back through sin/cos).
fn close(a: &Rigid2, b: &Rigid2) -> bool {
    let d = a.inverse() * b;
    let scale = 1.0 + a.x().abs() + a.y().abs();
    d.x().abs() <= 1e-9 * scale && d.y().abs() <= 1e-9 * scale && d.theta().abs() <= 1e-9
}

fn tagged(tag: u8, message: &impl Message) -> Vec<u8> {
    let mut out = vec![tag];
    out.extend(message.encode_to_vec());
    out
}

fn seeds() -> Vec<Vec<u8>> {
    let batch = pb::UploadBatch::from(&sample_upload_batch());
    let delta = map_delta();
    let zlib_grid = proto::grid_to_pb_with(&grid(30, 30, 2), pb::GridEncoding::U16LeZlib);
    let raw_grid = proto::grid_to_pb_with(&grid(12, 9, 3), pb::GridEncoding::U16Le);
    let open = pb::OpenSessionRequest {
        format_version: FORMAT_VERSION,
        site: "store-1".into(),
        robot_id: "robot-1".into(),
        session_uuid: "s-1".into(),
    };
    let close = pb::CloseSessionRequest {
        format_version: FORMAT_VERSION,
        site: "store-1".into(),
        robot_id: "robot-1".into(),
        session_uuid: "s-1".into(),
    };
    let version = pb::MapVersion {
        format_version: FORMAT_VERSION,
        site: "store-1".into(),
        version: 12,
        ..Default::default()
    };
    let zenoh_request = |request| pb::ZenohRequest {
        format_version: FORMAT_VERSION,
        token: "change-me-robot-1".into(),
        request: Some(request),
    };
    vec![
        tagged(0, &batch),
        tagged(1, &delta),
        tagged(2, &pb::Submap::from(&submap(3))),
        tagged(3, &pb::Node::from(&node())),
        tagged(4, &pb::Constraint::from(&constraint())),
        tagged(5, &zlib_grid),
        tagged(5, &raw_grid),
        tagged(
            6,
            &pb::SiteLogEntry {
                format_version: FORMAT_VERSION,
                map_version: 5,
                entry: Some(pb::site_log_entry::Entry::Upload(batch.clone())),
            },
        ),
        tagged(
            6,
            &pb::SiteLogEntry {
                format_version: FORMAT_VERSION,
                map_version: 1,
                entry: Some(pb::site_log_entry::Entry::SessionOpened(
                    pb::SessionOpened {
                        robot_id: "robot-1".into(),
                        session_uuid: "s-1".into(),
                        trajectory: 1,
                    },
                )),
            },
        ),
        tagged(7, &zenoh_request(pb::zenoh_request::Request::Upload(batch))),
        tagged(
            7,
            &zenoh_request(pb::zenoh_request::Request::OpenSession(open.clone())),
        ),
        tagged(
            8,
            &pb::ZenohReply {
                format_version: FORMAT_VERSION,
                reply: Some(pb::zenoh_reply::Reply::Delta(delta)),
            },
        ),
        tagged(9, &open),
        tagged(
            10,
            &pb::OpenSessionResponse {
                format_version: FORMAT_VERSION,
                trajectory: 2,
                last_acked_seq: 9,
                created: true,
                map_version: 4,
            },
        ),
        tagged(
            11,
            &pb::Ack {
                format_version: FORMAT_VERSION,
                session_uuid: "s-1".into(),
                seq: 3,
                map_version: 8,
                duplicate: false,
                session_end_pose: Some(pb::Pose2 {
                    x: 1.0,
                    y: 2.0,
                    theta: 0.5,
                }),
            },
        ),
        tagged(12, &close),
        tagged(14, &version),
        tagged(
            15,
            &pb::MapImage {
                format_version: FORMAT_VERSION,
                site: "store-1".into(),
                version: 3,
                resolution: 0.05,
                width: 4,
                height: 4,
                png: vec![0x89, b'P', b'N', b'G'],
                ..Default::default()
            },
        ),
        tagged(
            16,
            &pb::GetDeltaRequest {
                site: "store-1".into(),
                since_version: 4,
            },
        ),
        tagged(
            18,
            &pb::ListSitesResponse {
                sites: vec![version],
            },
        ),
        tagged(20, &checkpoint()),
    ]
}

/// The checkpoint of a new site's map (no session yet).
fn checkpoint() -> pb::SiteCheckpoint {
    let map = LifelongMap::new(LifelongOptions::default())
        .unwrap_or_else(|e| panic!("default lifelong options are valid: {e}"));
    pb::SiteCheckpoint::from(&SiteCheckpoint::of(&map, 7, 3))
}

/// A checkpoint as a restarting server takes it: converted, then restored into a map. An accepted one
/// converts back to itself, and the restored map's state is the one it was restored from.
fn restore(message: &pb::SiteCheckpoint) -> Verdict {
    let result = SiteCheckpoint::try_from(message);
    let Ok(once) = result else {
        return Verdict::of(&result);
    };
    let twice = SiteCheckpoint::try_from(&pb::SiteCheckpoint::from(&once))
        .unwrap_or_else(|e| panic!("invariant: checkpoint does not convert back: {e}"));
    assert!(
        twice == once,
        "invariant: SiteCheckpoint round trip differs"
    );
    let state = once.map.clone();
    let restored = once.restore(LifelongOptions::default());
    if let Ok(map) = &restored {
        assert!(
            map.to_state() == state,
            "invariant: a restored map's state differs from its checkpoint's"
        );
    }
    Verdict::of(&restored)
}

/// Decodes `M` from `bytes`, `Rejected` when prost refuses.
fn decode<M: Message + Default>(bytes: &[u8]) -> Result<M, Verdict> {
    M::decode(bytes).map_err(|e| Verdict::Rejected(e.to_string()))
}

fn upload(batch: &pb::UploadBatch) -> Verdict {
    let result = UploadBatch::try_from(batch);
    if let Ok(once) = &result {
        // Poses go through (x, y, θ): compare after one trip, as proto's own tests do.
        let trip = |b: &UploadBatch| {
            UploadBatch::try_from(&pb::UploadBatch::from(b)).unwrap_or_else(|e| {
                panic!("invariant: a converted batch does not convert back: {e}")
            })
        };
        let (twice, thrice) = (trip(once), trip(&trip(once)));
        let shape = |b: &UploadBatch| {
            let kinds: Vec<_> = b.items.iter().map(std::mem::discriminant).collect();
            (
                b.site.clone(),
                b.robot_id.clone(),
                b.session_uuid.clone(),
                b.seq,
                kinds,
            )
        };
        assert_eq!(
            shape(&twice),
            shape(&thrice),
            "invariant: UploadBatch round trip differs"
        );
    }
    Verdict::of(&result)
}

fn delta(chunk: &pb::MapDelta) -> Verdict {
    let result = MapDelta::from_pb_chunks([chunk]);
    if let Ok(once) = &result {
        let chunks = once.to_pb_chunks(4 << 20);
        let twice = MapDelta::from_pb_chunks(&chunks)
            .unwrap_or_else(|e| panic!("invariant: a converted delta does not convert back: {e}"));
        assert_eq!(
            (
                twice.submaps_added.len(),
                twice.pose_updates.len(),
                twice.trimmed.len()
            ),
            (
                once.submaps_added.len(),
                once.pose_updates.len(),
                once.trimmed.len()
            ),
            "invariant: MapDelta round trip differs"
        );
    }
    Verdict::of(&result)
}

fn run(input: &[u8]) -> Result<Verdict, Verdict> {
    let Some((&tag, bytes)) = input.split_first() else {
        return Ok(Verdict::Rejected("empty".into()));
    };
    Ok(match tag % 22 {
        0 => upload(&decode(bytes)?),
        1 => delta(&decode(bytes)?),
        2 => {
            let result = SubmapSnapshot::try_from(&decode::<pb::Submap>(bytes)?);
            if let Ok(once) = &result {
                let trip = |s: &SubmapSnapshot| {
                    SubmapSnapshot::try_from(&pb::Submap::from(s))
                        .unwrap_or_else(|e| panic!("invariant: submap does not convert back: {e}"))
                };
                let (twice, thrice) = (trip(once), trip(&trip(once)));
                assert!(
                    (twice.id, twice.revision, &twice.grid)
                        == (thrice.id, thrice.revision, &thrice.grid)
                        && close(&twice.global_pose, &thrice.global_pose)
                        && close(&twice.local_pose, &thrice.local_pose),
                    "invariant: Submap round trip differs"
                );
            }
            Verdict::of(&result)
        }
        3 => {
            let result = NodeSnapshot::try_from(&decode::<pb::Node>(bytes)?);
            if let Ok(once) = &result {
                let trip = |n: &NodeSnapshot| {
                    NodeSnapshot::try_from(&pb::Node::from(n))
                        .unwrap_or_else(|e| panic!("invariant: node does not convert back: {e}"))
                };
                let (twice, thrice) = (trip(once), trip(&trip(once)));
                assert!(
                    (twice.id, twice.time, &twice.points)
                        == (thrice.id, thrice.time, &thrice.points)
                        && close(&twice.local_pose, &thrice.local_pose),
                    "invariant: Node round trip differs"
                );
            }
            Verdict::of(&result)
        }
        4 => {
            let result = Constraint::try_from(&decode::<pb::Constraint>(bytes)?);
            if let Ok(once) = &result {
                let twice = Constraint::try_from(&pb::Constraint::from(once))
                    .unwrap_or_else(|e| panic!("invariant: constraint does not convert back: {e}"));
                assert_eq!(
                    (twice.kind, twice.from, twice.to),
                    (once.kind, once.from, once.to),
                    "invariant: Constraint round trip differs"
                );
            }
            Verdict::of(&result)
        }
        5 => {
            let result = proto::grid_from_pb(&decode::<pb::Grid>(bytes)?);
            if let Ok(once) = &result {
                let twice = proto::grid_from_pb(&proto::grid_to_pb(once))
                    .unwrap_or_else(|e| panic!("invariant: grid does not convert back: {e}"));
                assert!(
                    twice.values() == once.values(),
                    "invariant: Grid round trip differs"
                );
            }
            Verdict::of(&result)
        }
        6 => {
            let entry: pb::SiteLogEntry = decode(bytes)?;
            if let Err(e) = proto::check_format_version("SiteLogEntry", entry.format_version) {
                return Ok(Verdict::Rejected(e.to_string()));
            }
            match &entry.entry {
                Some(pb::site_log_entry::Entry::Upload(batch)) => upload(batch),
                Some(_) => Verdict::Accepted,
                None => Verdict::Rejected("empty entry".into()),
            }
        }
        7 => {
            let request: pb::ZenohRequest = decode(bytes)?;
            if let Err(e) = proto::check_format_version("ZenohRequest", request.format_version) {
                return Ok(Verdict::Rejected(e.to_string()));
            }
            match &request.request {
                Some(pb::zenoh_request::Request::Upload(batch)) => upload(batch),
                Some(_) => Verdict::Accepted,
                None => Verdict::Rejected("no request".into()),
            }
        }
        8 => {
            let reply: pb::ZenohReply = decode(bytes)?;
            if let Err(e) = proto::check_format_version("ZenohReply", reply.format_version) {
                return Ok(Verdict::Rejected(e.to_string()));
            }
            match &reply.reply {
                Some(pb::zenoh_reply::Reply::Delta(chunk)) => delta(chunk),
                Some(_) => Verdict::Accepted,
                None => Verdict::Rejected("no reply".into()),
            }
        }
        9 => decode::<pb::OpenSessionRequest>(bytes).map(|_| Verdict::Accepted)?,
        10 => decode::<pb::OpenSessionResponse>(bytes).map(|_| Verdict::Accepted)?,
        11 => decode::<pb::Ack>(bytes).map(|_| Verdict::Accepted)?,
        12 => decode::<pb::CloseSessionRequest>(bytes).map(|_| Verdict::Accepted)?,
        13 => decode::<pb::CloseSessionResponse>(bytes).map(|_| Verdict::Accepted)?,
        14 => decode::<pb::MapVersion>(bytes).map(|_| Verdict::Accepted)?,
        15 => decode::<pb::MapImage>(bytes).map(|_| Verdict::Accepted)?,
        16 => decode::<pb::GetDeltaRequest>(bytes).map(|_| Verdict::Accepted)?,
        17 => decode::<pb::GetSubmapRequest>(bytes).map(|_| Verdict::Accepted)?,
        18 => decode::<pb::ListSitesResponse>(bytes).map(|_| Verdict::Accepted)?,
        19 => decode::<pb::GetMapImageRequest>(bytes).map(|_| Verdict::Accepted)?,
        20 => restore(&decode(bytes)?),
        _ => decode::<pb::WatchRequest>(bytes).map(|_| Verdict::Accepted)?,
    })
}

/// Every protobuf message and its conversion.
pub fn protobuf() -> FuzzTarget {
    let mut target = FuzzTarget::new(
        "protobuf",
        "every evermap.fleet.v1 message (prost) and its conversion into mapping types",
        seeds(),
        false,
        Box::new(|input| run(input).unwrap_or_else(|rejected| rejected)),
    );
    // zlib-compressed grids: up to 1032:1 (zlib's best ratio).
    target.heap_per_input_byte = 1100;
    target
}
