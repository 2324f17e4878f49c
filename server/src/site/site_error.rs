//! Why a site refused a request.

/// A request a site cannot serve. Front ends map each variant to their own status (gRPC: see
/// `grpc::status`).
#[derive(Debug, thiserror::Error)]
pub enum SiteError {
    /// The session was never opened on this site.
    #[error("unknown session {0:?}: open it first")]
    UnknownSession(String),
    /// The session belongs to another robot.
    #[error("session {session:?} belongs to robot {owner:?}, not {robot:?}")]
    WrongRobot {
        /// The session.
        session: String,
        /// Its robot.
        owner: String,
        /// The robot that asked.
        robot: String,
    },
    /// The session was closed; nothing more can be uploaded to it.
    #[error("session {0:?} is closed")]
    SessionClosed(String),
    /// A batch skipped sequence numbers.
    #[error("sequence gap in session {session:?}: expected seq {expected}, got {got}")]
    SequenceGap {
        /// The session.
        session: String,
        /// The next sequence number the site accepts.
        expected: u64,
        /// The one received.
        got: u64,
    },
    /// The batch is well-formed but does not fit the session (e.g. finishes a submap no node was inserted
    /// into).
    #[error("invalid batch: {0}")]
    InvalidBatch(String),
    /// A requested version or revision does not exist.
    #[error("{0}")]
    NotFound(String),
    /// Storage failed (a full disk included): the request was not acknowledged; retry it. Either
    /// nothing was applied, or the change is applied but not yet durable and a retry acknowledges it
    /// once a flush succeeds (it is never applied twice).
    #[error("storage: {0}")]
    Storage(#[from] storage::StorageError),
    /// A stored log entry cannot be decoded or replayed.
    #[error("corrupt site log at entry {index}: {reason}")]
    CorruptLog {
        /// The entry's index (= the site version it made).
        index: u64,
        /// Why.
        reason: String,
    },
    /// The site's task has stopped (server shutting down, or a bug).
    #[error("site {0:?} is not running")]
    Stopped(String),
    /// A worker thread failed.
    #[error("internal error: {0}")]
    Internal(String),
}
