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
    /// The map refused the session's start or one of its nodes (the batch does not fit the map).
    #[error("invalid batch: {0}")]
    Rejected(#[source] mapping::lifelong::LifelongError),
    /// The batch's stored form would not decode, so it could not be replayed: refused before anything
    /// is stored.
    #[error("invalid batch: its stored form would not decode: {0}")]
    Unstorable(#[source] proto::ConversionError),
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
    /// A stored log entry cannot be decoded.
    #[error("corrupt site log at entry {index}: {source}")]
    CorruptEntry {
        /// The entry's index (= the site version it made).
        index: u64,
        /// Why.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A stored log entry cannot be replayed (out of order, closing an unknown session, the log ending
    /// short of the store's version).
    #[error("corrupt site log at entry {index}: {reason}")]
    CorruptLog {
        /// The entry's index (= the site version it made).
        index: u64,
        /// Why.
        reason: String,
    },
    /// A stored checkpoint decodes but contradicts itself (its versions, its sessions' trajectories, its
    /// map): an older checkpoint is used instead, when there is one.
    #[error("corrupt site checkpoint at log index {index}: {reason}")]
    CorruptCheckpoint {
        /// The log index it covers.
        index: u64,
        /// Why (with the text of `source`, when there is one).
        reason: String,
        /// The error that found it (the decoder's, the conversion's, the map's restore), kept for
        /// `source()`; `None` where the check is the server's own.
        source: Option<Box<dyn std::error::Error + Send + Sync>>,
    },
    /// A stored checkpoint this build must not restore: written in a format version it does not read (by
    /// a newer build, or one older than any this build migrates). The site is not rebuilt behind it (the
    /// log it covers may be compacted away): run a build that reads it.
    #[error(
        "site checkpoint at log index {index} refused, the site is not rebuilt without it: {source}"
    )]
    CheckpointRefused {
        /// The log index it covers.
        index: u64,
        /// Why.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The site's task has stopped (server shutting down, or a bug).
    #[error("site {0:?} is not running")]
    Stopped(String),
    /// What the site should never see happened (its map lost by a failed worker, the store disagreeing
    /// on the version it wrote).
    #[error("internal error: {0}")]
    Internal(String),
    /// The operating system refused a thread for site work (out of memory or of threads).
    #[error("internal error: cannot start the {what} thread: {source}")]
    ThreadStart {
        /// The work the thread was for.
        what: &'static str,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// A worker task failed (panicked or was cancelled).
    #[error("internal error: {0}")]
    Worker(#[source] tokio::task::JoinError),
    /// The map failed where it should not have (a bug: the site had checked the request).
    #[error("internal error: {0}")]
    Map(#[source] mapping::lifelong::LifelongError),
    /// Ending a session in the map failed (a bug: the map had accepted the session).
    #[error("internal error: ending session {session:?}: {source}")]
    EndSession {
        /// The session.
        session: String,
        /// Why.
        source: mapping::lifelong::LifelongError,
    },
    /// The map's options were refused (a bug: the server validated them at start).
    #[error("internal error: {0}")]
    Options(#[source] mapping::lifelong::LifelongOptionsError),
}
