//! # proto — evermap's wire types
//!
//! The fleet protocol (`evermap/fleet/v1/*.proto`, compiled at build time with protox, no system `protoc`):
//! the generated prost messages and tonic services in [`pb`], the reflection descriptor set
//! [`FILE_DESCRIPTOR_SET`], and conversions between wire messages and the `mapping` crate's types; and
//! the zenoh side of the protocol, its key expressions ([`zenoh_api_key`], [`zenoh_version_key`]) and
//! link settings ([`ZenohLinkOptions`], [`ZenohTlsOptions`]), shared by the agent and the server.
//! Both also encode map pictures here ([`encode_png`]: the `GetMapImage` reply's PNG, the agent's
//! picture files, the web console's images).
//!
//! [`memory_release`]: handing memory freed by a session's end back to the system, for the server's sites
//! and the agent's lifelong runs alike.
//!
//! [`testing`] (feature `testing`): shared test values for this crate's tests and its users'.
//!
//! Conversions from the wire are `TryFrom` and check everything a peer could get wrong (missing fields,
//! NaN or infinite numbers, sizes that do not match, unknown `format_version`), returning a
//! [`ConversionError`]; conversions to the wire are infallible. Conversions do no I/O.
//!
//! ```
//! use mapping::geometry::rigid2;
//! use proto::pb;
//!
//! let wire = proto::pose_to_pb(&rigid2(1.0, 2.0, 0.5));
//! let back = proto::pose_from_pb(Some(&wire), "Pose2", "pose")?;
//! assert!((back.translation.vector.x - 1.0).abs() < 1e-12);
//! let bad = pb::Pose2 { x: f64::NAN, y: 0.0, theta: 0.0 };
//! assert!(proto::pose_from_pb(Some(&bad), "Pose2", "pose").is_err());
//! # Ok::<(), proto::ConversionError>(())
//! ```

mod conversion_error;
mod convert;
mod error_report;
pub mod logging;
mod map_delta;
pub mod memory_release;
mod png_image;
mod site_checkpoint;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
mod upload_batch;
mod zenoh_link_options;
mod zenoh_tls_options;

pub use conversion_error::{ConversionError, ErrorSource, FieldValue};
pub use convert::{
    NodeSnapshot, check_format_version, grid_from_pb, grid_to_pb, grid_to_pb_with, pose_from_pb,
    pose_to_pb,
};
pub use error_report::{error_report, exit_code};
pub use map_delta::{MapDelta, SubmapSnapshot};
pub use png_image::{PngCompression, PngError, PngPixels, encode_png};
pub use site_checkpoint::{
    CHECKPOINT_FORMAT_VERSION, OLDEST_CHECKPOINT_FORMAT_VERSION, PublishedSubmapState, RobotPrior,
    SessionStartCounts, SiteCheckpoint, SiteServerState, SiteSessionState,
    check_checkpoint_format_version, options_fingerprint, pose_from_exact, pose_to_exact,
};
pub use upload_batch::{NodeAdded, UploadBatch, UploadItem};
pub use zenoh_link_options::{
    ZenohLinkOptions, ZenohLinkOptionsError, zenoh_api_key, zenoh_version_key,
};
pub use zenoh_tls_options::ZenohTlsOptions;

/// The `format_version` every record written by this build carries, and the only one it reads.
pub const FORMAT_VERSION: u32 = 1;

/// Largest grid accepted from the wire, in cells (64 Mi cells = 128 MiB of values, a 800 m square at 0.1 m).
pub const MAX_GRID_CELLS: usize = 64 << 20;

/// Encoded `FileDescriptorSet` of every evermap proto file, for gRPC reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/evermap_fleet_v1_descriptor.bin"));

/// The generated messages (prost) and services (tonic) of package `evermap.fleet.v1`.
#[expect(
    missing_docs,
    clippy::all,
    clippy::pedantic,
    reason = "generated code; the .proto files document every message"
)]
pub mod pb {
    include!(concat!(env!("OUT_DIR"), "/evermap.fleet.v1.rs"));
}
