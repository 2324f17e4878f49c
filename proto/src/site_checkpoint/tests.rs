use mapping::lifelong::LifelongMap;
use prost::Message as _;
use simulator::testing::checkpoint_sessions::{
    Log, Position, SESSIONS, feed, options, session_inputs, snapshot,
};

use super::*;
use crate::FieldValue;

#[test]
fn a_checkpoint_of_an_unknown_format_version_is_refused_with_an_error_naming_it() {
    for got in [
        0,
        OLDEST_CHECKPOINT_FORMAT_VERSION - 1,
        CHECKPOINT_FORMAT_VERSION + 6,
    ] {
        let wire = pb::SiteCheckpoint {
            format_version: got,
            ..pb::SiteCheckpoint::default()
        };
        let error = SiteCheckpoint::try_from(&wire).expect_err("unknown version accepted");
        assert!(
            matches!(
                error,
                ConversionError::UnsupportedFormatVersion {
                    message: "SiteCheckpoint",
                    got: g,
                    oldest: OLDEST_CHECKPOINT_FORMAT_VERSION,
                    newest: CHECKPOINT_FORMAT_VERSION,
                } if g == got
            ),
            "{error:?}"
        );
        let text = error.to_string();
        let reads =
            format!("reads {OLDEST_CHECKPOINT_FORMAT_VERSION} to {CHECKPOINT_FORMAT_VERSION}");
        assert!(
            text.contains("SiteCheckpoint")
                && text.contains(&format!("format_version {got},"))
                && text.contains(&reads),
            "{text}"
        );
    }
}

#[test]
fn every_format_version_from_the_oldest_read_decodes() {
    for version in OLDEST_CHECKPOINT_FORMAT_VERSION..=CHECKPOINT_FORMAT_VERSION {
        check_checkpoint_format_version(version).expect("read");
        // Past the version check: a version-2 record reads as far as its first missing field.
        let wire = pb::SiteCheckpoint {
            format_version: version,
            ..pb::SiteCheckpoint::default()
        };
        assert!(matches!(
            SiteCheckpoint::try_from(&wire),
            Err(ConversionError::MissingField { field: "map", .. })
        ));
    }
}

#[test]
fn a_checkpoint_without_its_map_is_refused() {
    let wire = pb::SiteCheckpoint {
        format_version: CHECKPOINT_FORMAT_VERSION,
        ..pb::SiteCheckpoint::default()
    };
    assert!(matches!(
        SiteCheckpoint::try_from(&wire),
        Err(ConversionError::MissingField {
            message: "SiteCheckpoint",
            field: "map"
        })
    ));
}

#[test]
fn a_rotation_off_the_unit_circle_is_refused() {
    let pose = pb::ExactPose2 {
        x: Some(0.0),
        y: Some(0.0),
        cos: Some(2.0),
        sin: Some(0.0),
    };
    let error = pose_from_exact(Some(&pose), "ExactPose2", "pose").unwrap_err();
    assert_eq!(
        error,
        ConversionError::OutOfRange {
            message: "ExactPose2",
            field: "pose",
            value: FieldValue::Float(2.0),
            expected: "a rotation (cos, sin) of norm 1 (to 1e-6)",
        }
    );
    let missing = pb::ExactPose2 {
        sin: None,
        cos: Some(1.0),
        ..pose
    };
    assert!(matches!(
        pose_from_exact(Some(&missing), "ExactPose2", "pose"),
        Err(ConversionError::MissingField { .. })
    ));
}

/// Issue 34, item 2, through the encoding: a map checkpointed mid-session (queued searches, a session on
/// probation, matches waiting for agreement), encoded to bytes, decoded and restored, equals the original
/// and gives the same outputs, bit for bit, for the rest of its sessions.
#[test]
fn a_map_restored_from_its_encoded_checkpoint_behaves_bit_for_bit_like_the_original() {
    let inputs = session_inputs();
    let start = Position {
        session: 0,
        nodes: 0,
        started: false,
    };
    let at = Position {
        session: 2,
        nodes: 17,
        started: true,
    };
    let end = Position {
        session: SESSIONS,
        nodes: 0,
        started: false,
    };
    let mut original = LifelongMap::new(options()).expect("map");
    feed(&mut original, &inputs, start, at, &mut Log::new());
    let checkpoint = SiteCheckpoint::of(&original, 1234, 99);
    let bytes = pb::SiteCheckpoint::from(&checkpoint).encode_to_vec();
    let decoded =
        SiteCheckpoint::try_from(&pb::SiteCheckpoint::decode(bytes.as_slice()).expect("protobuf"))
            .expect("checkpoint");
    assert!(decoded == checkpoint, "the decoded checkpoint differs");
    // `{:?}` tells −0.0 from 0.0, which `==` does not.
    assert_eq!(format!("{decoded:?}"), format!("{checkpoint:?}"));
    assert!(
        !decoded.map.global.pending_jobs.is_empty()
            || !decoded.map.global.accepted_loop_closures.is_empty(),
        "a checkpoint with nothing in flight proves little"
    );

    let mut restored = decoded.restore(options()).expect("restore");
    assert_eq!(snapshot(&restored), snapshot(&original));
    let (mut log_original, mut log_restored) = (Log::new(), Log::new());
    feed(&mut original, &inputs, at, end, &mut log_original);
    feed(&mut restored, &inputs, at, end, &mut log_restored);
    assert!(log_original.len() > 50, "{log_original:?}");
    for (k, (a, b)) in log_original.iter().zip(&log_restored).enumerate() {
        assert_eq!(a, b, "output {k} after the checkpoint");
    }
    assert_eq!(log_original.len(), log_restored.len());
    assert_eq!(snapshot(&restored), snapshot(&original));
}

/// Where the fixture checkpoints stand: session 1, 8 nodes in (placed after 5), at log index and map
/// version 1234.
const FIXTURE_AT: Position = Position {
    session: 1,
    nodes: 8,
    started: true,
};

/// `tests/fixtures/site_checkpoint_v{version}.bin`.
fn fixture(version: u32) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(format!("site_checkpoint_v{version}.bin"))
}

/// A server upgraded to this build restores the sites an earlier build checkpointed (their log before
/// the checkpoint is compacted away): each build that wrote a format version left one checkpoint of it
/// here, a map mid-session of `checkpoint_sessions` (options `options()`), and every one this build
/// reads restores and maps on. A new format version adds its own: `EVERMAP_WRITE_CHECKPOINT_FIXTURE=1
/// cargo nextest run --workspace -E 'test(fixture)'` writes it.
#[test]
fn every_fixture_checkpoint_an_earlier_build_wrote_restores_and_maps_on() {
    let current = fixture(CHECKPOINT_FORMAT_VERSION);
    if std::env::var_os("EVERMAP_WRITE_CHECKPOINT_FIXTURE").is_some() && !current.exists() {
        let inputs = session_inputs();
        let start = Position {
            session: 0,
            nodes: 0,
            started: false,
        };
        let mut map = LifelongMap::new(options()).expect("map");
        feed(&mut map, &inputs, start, FIXTURE_AT, &mut Log::new());
        let checkpoint = SiteCheckpoint::of(&map, 1234, 1234);
        std::fs::create_dir_all(current.parent().expect("dir")).expect("fixture dir");
        std::fs::write(
            &current,
            pb::SiteCheckpoint::from(&checkpoint).encode_to_vec(),
        )
        .expect("fixture written");
    }
    assert!(
        current.exists(),
        "no fixture checkpoint of format version {CHECKPOINT_FORMAT_VERSION} (this build's): write it \
         with EVERMAP_WRITE_CHECKPOINT_FIXTURE=1 and commit it"
    );
    let inputs = session_inputs();
    let end = Position {
        session: SESSIONS,
        nodes: 0,
        started: false,
    };
    let mut read = 0;
    for version in OLDEST_CHECKPOINT_FORMAT_VERSION..=CHECKPOINT_FORMAT_VERSION {
        let path = fixture(version);
        let Ok(bytes) = std::fs::read(&path) else {
            continue; // formats older than the fixtures (version 3 was the first to leave one)
        };
        let message = pb::SiteCheckpoint::decode(bytes.as_slice()).expect("protobuf");
        assert_eq!(message.format_version, version, "{}", path.display());
        let checkpoint = SiteCheckpoint::try_from(&message).expect("a format this build reads");
        assert_eq!((checkpoint.log_index, checkpoint.map_version), (1234, 1234));
        let nodes = checkpoint.map.global.nodes.len();
        let mut map = checkpoint.restore(options()).expect("restored");
        assert!(nodes > 100, "{nodes} nodes: the fixture proves little");
        let mut log = Log::new();
        feed(&mut map, &inputs, FIXTURE_AT, end, &mut log);
        assert!(log.len() > 20, "it mapped on: {log:?}");
        read += 1;
    }
    assert!(read >= 1);
}

#[test]
fn a_checkpoint_is_restored_under_the_options_given_and_says_whether_they_changed() {
    let map = LifelongMap::new(options()).expect("map");
    let checkpoint = SiteCheckpoint::of(&map, 5, 2);
    assert!(!checkpoint.written_under_other_options(&options()));
    assert!(checkpoint.clone().restore(options()).is_ok());
    let mut other = options();
    other.global.loop_closure_retraction_chi2 += 1.0;
    assert!(checkpoint.written_under_other_options(&other));
    let restored = checkpoint.clone().restore(other.clone()).expect("restored");
    assert_eq!(restored.options(), &other, "the options given govern it");
    let mut invalid = options();
    invalid.global.loop_closure_retraction_chi2 = -1.0;
    assert!(
        checkpoint.restore(invalid).is_err(),
        "invalid options restored"
    );
}

#[test]
fn the_servers_part_of_a_checkpoint_round_trips_bit_for_bit() {
    use mapping::geometry::rigid2;
    use mapping::pose_graph::SubmapId;

    let odd_pose = Rigid2::from_parts(
        Translation2::new(-0.0, 1e-300),
        UnitComplex::new_unchecked(Complex::new(0.6, 0.8000000000000002)),
    );
    let mut site = SiteServerState {
        optimizations: 17,
        dropped_sessions: 2,
        robot_revoked: [3, 5].into_iter().collect(),
        base: Some(0),
        session_starts: crate::testing::distinct_session_start_counts(),
        ..SiteServerState::default()
    };
    site.sessions.insert(
        "uuid-b".into(),
        SiteSessionState {
            robot_id: "r2".into(),
            trajectory: 1,
            last_seq: 42,
            closed: false,
            prior: Some(RobotPrior {
                global_from_local: odd_pose,
                at_dock: true,
                fitted: Some((0, 11)),
            }),
            glm_on_robot: true,
            nodes: 99,
            dropped: false,
        },
    );
    site.sessions.insert(
        "uuid-a".into(),
        SiteSessionState {
            robot_id: "r1".into(),
            trajectory: 0,
            last_seq: 7,
            closed: true,
            prior: None,
            glm_on_robot: false,
            nodes: 12,
            dropped: true,
        },
    );
    let id = |t, i| SubmapId {
        trajectory: t,
        index: i,
    };
    site.published.insert(
        id(1, 4),
        PublishedSubmapState {
            revision: 8,
            pose_version: 11,
            pose: odd_pose,
        },
    );
    site.published.insert(
        id(0, 0),
        PublishedSubmapState {
            revision: 2,
            pose_version: 2,
            pose: rigid2(1.5, -2.25, 0.3),
        },
    );
    site.trimmed.insert(id(0, 1), 9);
    let mut checkpoint = SiteCheckpoint::of(&LifelongMap::new(options()).expect("map"), 12, 12);
    checkpoint.site = site;
    let wire = pb::SiteCheckpoint::from(&checkpoint);
    let decoded = SiteCheckpoint::try_from(
        &pb::SiteCheckpoint::decode(wire.encode_to_vec().as_slice()).expect("protobuf"),
    )
    .expect("checkpoint");
    assert_eq!(format!("{decoded:?}"), format!("{checkpoint:?}"));
    assert!(decoded == checkpoint);

    let mut twice = wire.clone();
    let site_pb = twice.site.as_mut().expect("site");
    site_pb.sessions.push(site_pb.sessions[0].clone());
    let error = SiteCheckpoint::try_from(&twice).expect_err("a session listed twice");
    assert!(
        matches!(
            error,
            ConversionError::Duplicate {
                field: "session_uuid",
                ..
            }
        ),
        "{error:?}"
    );
    assert!(error.to_string().contains("\"uuid-a\" twice"), "{error}");

    let mut without = wire;
    without.site = None;
    assert!(matches!(
        SiteCheckpoint::try_from(&without),
        Err(ConversionError::MissingField {
            message: "SiteCheckpoint",
            field: "site"
        })
    ));
}

/// A graph whose parts are each valid but not together (a variable listed twice) is refused with the
/// pose graph's own error as the source.
#[test]
fn a_graph_the_pose_graph_refuses_keeps_its_error_as_the_source() {
    use mapping::pose_graph::{NodeId, PoseGraphError};

    let node = VariableId::Node(NodeId {
        trajectory: 0,
        index: 3,
    });
    let variable = pb::GraphVariable {
        id: Some(variable_to_pb(node)),
        pose: Some(pose_to_exact(&Rigid2::identity())),
        fixed: false,
    };
    let graph = pb::PoseGraphState {
        variables: vec![variable, variable],
        constraints: Vec::new(),
        next_constraint: 0,
    };
    let error = graph_from_pb(Some(&graph)).unwrap_err();
    assert!(
        matches!(
            error,
            ConversionError::Invalid {
                message: "PoseGraphState",
                field: "graph",
                ..
            }
        ),
        "{error:?}"
    );
    let source = std::error::Error::source(&error).expect("the pose graph's error");
    assert_eq!(
        source.to_string(),
        PoseGraphError::DuplicateVariable(node).to_string()
    );
}

/// Corrections on probation and kept ones (none arise in the simulated sessions above) come back field for
/// field, and a checkpoint of a build without them decodes as having none.
#[test]
fn corrections_on_probation_round_trip() {
    use mapping::geometry::rigid2;
    use mapping::global_slam::CorrectionProbation;

    let mut map = LifelongMap::new(options()).expect("map");
    feed(
        &mut map,
        &session_inputs(),
        Position {
            session: 0,
            nodes: 0,
            started: false,
        },
        Position {
            session: 1,
            nodes: 0,
            started: false,
        },
        &mut Log::new(),
    );
    let mut state = SiteCheckpoint::of(&map, 1, 1).map.global;
    let node = |index| NodeId {
        trajectory: 0,
        index,
    };
    let submap = SubmapId {
        trajectory: 0,
        index: 1,
    };
    let on_probation = CorrectionProbation {
        closures: vec![(node(7), submap), (node(9), submap)],
        newest: LoopClosure {
            submap,
            node: node(9),
            submap_from_node: rigid2(1.5, -0.25, 0.3),
            score: 0.71,
            runner_up_score: Some(0.6),
            information: None,
        },
        after_node: 12,
        old_submaps_to: 1,
        agreeing: [node(14)].into_iter().collect(),
        disagreeing: [node(15), node(16)].into_iter().collect(),
        nodes_judging: 4,
        kept: false,
    };
    let kept = CorrectionProbation {
        agreeing: [node(20), node(21)].into_iter().collect(),
        disagreeing: std::collections::BTreeSet::new(),
        kept: true,
        ..on_probation.clone()
    };
    state.correction_probations = vec![on_probation, kept];
    let decoded = global_from_pb(Some(&global_to_pb(&state))).expect("decode");
    assert_eq!(decoded.correction_probations, state.correction_probations);
    let mut older = global_to_pb(&state);
    older.correction_probations.clear();
    assert!(
        global_from_pb(Some(&older))
            .expect("decode")
            .correction_probations
            .is_empty()
    );
}

#[test]
fn submap_bends_round_trip_and_older_checkpoints_have_none() {
    use mapping::global_slam::{BendGrowth, SubmapBend};

    let map = LifelongMap::new(options()).expect("map");
    let mut state = SiteCheckpoint::of(&map, 1, 1).map.global;
    let node = |index| NodeId {
        trajectory: 2,
        index,
    };
    let submap = |index| SubmapId {
        trajectory: 2,
        index,
    };
    state.submap_bends = vec![
        SubmapBend {
            closures: vec![(node(40), submap(1)), (node(52), submap(0))],
            submaps: vec![submap(2), submap(3)],
            growth: BendGrowth {
                translation_per_m: 0.1,
                rotation_per_m: 0.01,
            },
        },
        SubmapBend {
            closures: vec![(node(90), submap(3))],
            submaps: vec![submap(5)],
            growth: BendGrowth {
                translation_per_m: 0.031,
                rotation_per_m: 0.0043,
            },
        },
    ];
    let decoded = global_from_pb(Some(&global_to_pb(&state))).expect("decode");
    assert_eq!(decoded.submap_bends, state.submap_bends);
    let mut older = global_to_pb(&state);
    older.submap_bends.clear();
    assert!(
        global_from_pb(Some(&older))
            .expect("decode")
            .submap_bends
            .is_empty()
    );
    let mut missing = global_to_pb(&state);
    missing.submap_bends[0].closures[0].node = None;
    let err = global_from_pb(Some(&missing)).unwrap_err().to_string();
    assert!(err.contains("ClosureRef"), "{err}");
}

#[test]
fn the_path_of_an_llo_recovery_round_trips_and_a_non_finite_one_is_refused() {
    let map = LifelongMap::new(options()).expect("map");
    let mut state = SiteCheckpoint::of(&map, 1, 1).map.global;
    state.recovery_path = [(0, 12.5), (3, 0.0)].into_iter().collect();
    let decoded = global_from_pb(Some(&global_to_pb(&state))).expect("decode");
    assert_eq!(decoded.recovery_path, state.recovery_path);
    state.recovery_path.insert(4, f64::NAN);
    assert!(global_from_pb(Some(&global_to_pb(&state))).is_err());
}

#[test]
fn the_nodes_that_fitted_a_placement_round_trip_and_a_reversed_span_is_refused() {
    let map = LifelongMap::new(options()).expect("map");
    let mut state = SiteCheckpoint::of(&map, 1, 1).map.global;
    state.placement_fits = [(2, (0, 9)), (5, (120, 519))].into_iter().collect();
    let decoded = global_from_pb(Some(&global_to_pb(&state))).expect("decode");
    assert_eq!(decoded.placement_fits, state.placement_fits);
    state.placement_fits.insert(6, (10, 9));
    let error = global_from_pb(Some(&global_to_pb(&state))).expect_err("reversed span");
    assert!(
        error.to_string().contains("PlacementFit.fitted.first"),
        "{error}"
    );
}
