//! The one place where errors become gRPC statuses (and refused requests are counted).

use proto::ConversionError;
use storage::StorageError;
use tonic::{Code, Status};

use crate::ServerMetrics;
use crate::site::SiteError;

/// Metadata key carrying the next sequence number a session accepts, on a sequence-gap refusal.
pub const EXPECTED_SEQ_METADATA: &str = "evermap-expected-seq";

fn code_name(code: Code) -> &'static str {
    match code {
        Code::InvalidArgument => "invalid_argument",
        Code::NotFound => "not_found",
        Code::PermissionDenied => "permission_denied",
        Code::Unauthenticated => "unauthenticated",
        Code::FailedPrecondition => "failed_precondition",
        Code::ResourceExhausted => "resource_exhausted",
        Code::Unavailable => "unavailable",
        Code::DataLoss => "data_loss",
        Code::Internal => "internal",
        _ => "other",
    }
}

/// Counts a refused request by its status code and passes the status on.
pub fn counted(metrics: &ServerMetrics, status: Status) -> Status {
    metrics.refused(code_name(status.code()));
    status
}

/// An internal failure of the handler itself (a worker task that panicked): `what` failed, and the
/// error stays attached as the status's source for the server's own log.
pub fn internal(what: &str, error: impl std::error::Error + Send + Sync + 'static) -> Status {
    let mut status = Status::internal(format!("{what}: {error}"));
    status.set_source(std::sync::Arc::new(error));
    status
}

/// The status of a malformed message.
pub fn from_conversion(metrics: &ServerMetrics, error: &ConversionError) -> Status {
    counted(metrics, Status::invalid_argument(error.to_string()))
}

/// The status of a site's refusal.
pub fn from_site(metrics: &ServerMetrics, error: &SiteError) -> Status {
    let message = error.to_string();
    let status = match error {
        SiteError::UnknownSession(_) | SiteError::NotFound(_) => Status::not_found(message),
        SiteError::WrongRobot { .. } => Status::permission_denied(message),
        SiteError::SessionClosed(_) => Status::failed_precondition(message),
        SiteError::SequenceGap { expected, .. } => {
            let expected = *expected;
            let mut status = Status::failed_precondition(message);
            if let Ok(value) = expected.to_string().parse() {
                status.metadata_mut().insert(EXPECTED_SEQ_METADATA, value);
            }
            status
        }
        SiteError::InvalidBatch(_)
        | SiteError::Rejected(_)
        | SiteError::Unstorable(_)
        | SiteError::Storage(
            StorageError::InvalidSessionId { .. }
            | StorageError::InvalidSiteId { .. }
            | StorageError::TooLarge { .. },
        ) => Status::invalid_argument(message),
        SiteError::Storage(_) | SiteError::Stopped(_) => Status::unavailable(message),
        SiteError::CorruptLog { .. }
        | SiteError::CorruptEntry { .. }
        | SiteError::CorruptCheckpoint { .. }
        | SiteError::CheckpointRefused { .. } => Status::data_loss(message),
        SiteError::Internal(_)
        | SiteError::ThreadStart { .. }
        | SiteError::Worker(_)
        | SiteError::Map(_)
        | SiteError::EndSession { .. }
        | SiteError::Options(_) => Status::internal(message),
    };
    counted(metrics, status)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sequence_gap_says_which_seq_is_expected() {
        let metrics = ServerMetrics::default();
        let status = from_site(
            &metrics,
            &SiteError::SequenceGap {
                session: "s".into(),
                expected: 7,
                got: 9,
            },
        );
        assert_eq!(status.code(), Code::FailedPrecondition);
        assert_eq!(status.metadata().get(EXPECTED_SEQ_METADATA).unwrap(), "7");
        assert!(status.message().contains("expected seq 7"));
        assert_eq!(metrics.refused_count("failed_precondition"), 1);
    }

    // Reference: issue 35 item 6 — an internal failure says what failed and keeps the error as the source.
    #[test]
    fn an_internal_failure_keeps_its_error_as_the_source() {
        let error = std::io::Error::other("worker panicked");
        let status = internal("encoding the map", error);
        assert_eq!(status.code(), Code::Internal);
        assert_eq!(status.message(), "encoding the map: worker panicked");
        let source = std::error::Error::source(&status).expect("the error is kept");
        assert_eq!(source.to_string(), "worker panicked");
    }
}
