//! Accuracy measures of SLAM results, and the scores of a lifelong run (what each session lived).

mod map_world_agreement;
mod match_judgement;
mod match_score;
mod placement_verdict;
mod relations_metric;
mod run_score;
mod scoring_options;
mod session_score;
mod start_record;
mod trajectory_metric;

pub use map_world_agreement::{MAP_WORLD_TOLERANCE_M, MapWorldAgreement, map_world_agreement};
pub use match_judgement::{
    JudgedMatch, MATCH_TOLERANCE, MatchCounts, MatchFate, judge_matches, match_counts,
};
pub use match_score::MatchScorer;
pub use placement_verdict::{
    PLACEMENT_WINDOW_S, PlacementVerdict, SpanVerdict, Verdict, judge_placements,
};
pub(crate) use relations_metric::median;
pub use relations_metric::{
    RelationError, RelationsErrorStats, pose_at, relation_error, relation_error_stats,
    relation_errors, relations_error, relations_error_at_scans,
};
pub use run_score::{RunScore, score_run};
pub use scoring_options::{ScoringOptions, ScoringOptionsError};
pub use session_score::{
    Placement, SessionScore, SessionTrack, average_match_score, score_session, truth_at,
};
pub use start_record::StartRecord;
pub use trajectory_metric::{
    PoseTolerance, TrajectoryAccuracy, align_to_truth, pose_error, rigid_alignment,
    trajectory_accuracy, wrong_distance_m,
};
