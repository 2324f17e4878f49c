//! The robot's link to the map server: [`MapUplink`] (one trait, several transports), the durable
//! [`Uploader`] on top of it, the LLO pipeline that feeds it, and the cache of the site's global submaps
//! kept current from the server's versions.
//!
//! Exactly-once delivery: each batch gets the session's next sequence number and is written to the
//! [`crate::outbox::Outbox`] before any send; it leaves the outbox only once acknowledged. After a
//! reconnect, `OpenSession` (idempotent) returns the server's last applied sequence number, everything up
//! to it is dropped from the outbox and the rest is re-sent in order; the server applies each
//! (session, seq) once.

mod agent_session;
mod fleet_uplink;
mod global_submap_cache;
mod grpc_uplink;
mod in_memory_uplink;
mod llo_stream;
mod robot_glm;
mod uploader;
mod zenoh_uplink;

use std::future::Future;
use std::pin::Pin;

pub use agent_session::{
    DockOutcome, SessionInput, SessionOptions, SessionReport, SessionStart, SessionTrace,
    follow_site, follow_site_with, place_ahead, session_span, stream_recording, stream_session,
    stream_session_from,
};
pub use fleet_uplink::FleetUplink;
pub use global_submap_cache::{CacheError, GlobalSubmapCache};
pub use grpc_uplink::{ClientTls, GrpcUplink};
pub use in_memory_uplink::InMemoryUplink;
pub use llo_stream::{LloStats, run_llo, run_llo_stream};
use mapping::geometry::Rigid2;
pub use proto::MapDelta;
use proto::pb;
pub use proto::{
    ZenohLinkOptions, ZenohLinkOptionsError, ZenohTlsOptions, zenoh_api_key, zenoh_version_key,
};
pub use robot_glm::{cached_submaps, match_node, sync_matcher};
pub use uploader::{FlushStats, SessionEnded, Uploader};
pub use zenoh_uplink::ZenohUplink;

/// Why an uplink call failed.
#[derive(Debug, thiserror::Error)]
pub enum UplinkError {
    /// The server cannot be reached now (connection refused or lost, timeout, server unavailable):
    /// try again later; nothing is lost.
    #[error("server unavailable: {what}")]
    Unavailable {
        /// What failed, in words (the server's message, or which wait ran out).
        what: String,
        /// The transport's own error, where there is one (a gRPC status and what caused it, a zenoh
        /// error): kept as [`std::error::Error::source`] so a report shows the whole chain.
        #[source]
        source: Option<Box<dyn std::error::Error + Send + Sync>>,
    },
    /// The server refused a batch because it skipped sequence numbers.
    #[error("sequence gap: the server expects seq {expected}")]
    SequenceGap {
        /// The next sequence number the server accepts.
        expected: u64,
    },
    /// The server refused the request for good (bad token, malformed data, ...).
    #[error("refused by the server ({code}): {message}")]
    Rejected {
        /// gRPC status code.
        code: tonic::Code,
        /// The server's message.
        message: String,
    },
    /// The server sent something malformed.
    #[error("malformed answer: {0}")]
    Malformed(#[from] proto::ConversionError),
    /// The outbox failed.
    #[error(transparent)]
    Outbox(#[from] crate::outbox::OutboxError),
    /// The uplink's own settings are unusable (the server URL, TLS, the token, zenoh's options): fix the
    /// configuration; retrying cannot help.
    #[error("uplink settings: {what}")]
    Settings {
        /// Which setting, and why (with the text of `source`, when there is one).
        what: String,
        /// The library's own error, where one found it.
        source: Option<Box<dyn std::error::Error + Send + Sync>>,
    },
}

impl UplinkError {
    /// [`UplinkError::Unavailable`] with no underlying error (a wait that ran out, a link taken down).
    pub fn unavailable(what: impl Into<String>) -> Self {
        Self::Unavailable {
            what: what.into(),
            source: None,
        }
    }

    /// [`UplinkError::Unavailable`] caused by the transport's `source`.
    pub fn unavailable_because(
        what: impl Into<String>,
        source: impl std::error::Error + Send + Sync + 'static,
    ) -> Self {
        Self::Unavailable {
            what: what.into(),
            source: Some(Box::new(source)),
        }
    }

    /// Whether retrying later can help (a full outbox disk too: space may return).
    pub fn is_transient(&self) -> bool {
        match self {
            Self::Unavailable { .. } | Self::SequenceGap { .. } => true,
            Self::Outbox(e) => e.is_out_of_space(),
            Self::Rejected { .. } | Self::Malformed(_) | Self::Settings { .. } => false,
        }
    }
}

/// What opening a session returned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OpenedSession {
    /// The session's trajectory in the site map.
    pub trajectory: u32,
    /// Last sequence number the server applied (0: none).
    pub last_acked_seq: u64,
    /// Whether this call created the session.
    pub created: bool,
    /// The site's version.
    pub map_version: u64,
}

/// The server's acknowledgement of one batch.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Acked {
    /// The batch's sequence number.
    pub seq: u64,
    /// Site version after it.
    pub map_version: u64,
    /// The server already had it.
    pub duplicate: bool,
    /// For a batch that ended its session: the session's last node in the site map, when the session
    /// is placed there (the robot's next dock).
    pub session_end_pose: Option<Rigid2>,
}

impl Acked {
    /// The server's ack as it came over the wire (gRPC or zenoh); a malformed end pose is refused.
    pub fn from_wire(ack: &pb::Ack) -> Result<Self, UplinkError> {
        Ok(Self {
            seq: ack.seq,
            map_version: ack.map_version,
            duplicate: ack.duplicate,
            session_end_pose: ack
                .session_end_pose
                .as_ref()
                .map(|pose| proto::pose_from_pb(Some(pose), "Ack", "session_end_pose"))
                .transpose()?,
        })
    }
}

/// A stream of site versions.
pub type VersionStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<u64, UplinkError>> + Send>>;

/// A connection to the map server for one site. Implementations: [`GrpcUplink`], [`ZenohUplink`],
/// [`FleetUplink`] (either, chosen at run time) and, for tests, [`InMemoryUplink`]. Every call is bounded in time by the implementation.
pub trait MapUplink: Send {
    /// Opens (or re-opens) a session; idempotent on (robot, session uuid).
    fn open_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> impl Future<Output = Result<OpenedSession, UplinkError>> + Send;

    /// Uploads one batch.
    fn upload(
        &mut self,
        batch: &pb::UploadBatch,
    ) -> impl Future<Output = Result<Acked, UplinkError>> + Send;

    /// Closes a session (idempotent); returns the site version.
    fn close_session(
        &mut self,
        robot_id: &str,
        session_uuid: &str,
    ) -> impl Future<Output = Result<u64, UplinkError>> + Send;

    /// The site's current version.
    fn map_version(&mut self) -> impl Future<Output = Result<u64, UplinkError>> + Send;

    /// What changed in the site map after version `since`.
    fn delta_since(
        &mut self,
        since: u64,
    ) -> impl Future<Output = Result<MapDelta, UplinkError>> + Send;

    /// The site's current version, then each new one.
    fn watch_versions(&mut self)
    -> impl Future<Output = Result<VersionStream, UplinkError>> + Send;
}
