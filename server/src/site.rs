//! Sites: one multi-session map per store, owned by one task that applies every change in order.
//!
//! [`SiteMap`] is the synchronous, transport-agnostic state (an adapter over the `mapping` core);
//! [`SiteTask`] owns a `SiteMap`, persists every accepted change through a [`storage::MapStore`] before
//! answering, and publishes each new version; [`SiteHandle`] is how any front end (gRPC today, zenoh
//! later) talks to it.

mod checkpoint_options;
mod maintenance_thread;
mod map_history;
mod published_submaps;
mod request_clock;
mod session_view;
mod site_error;
mod site_handle;
mod site_map;
mod site_summary;
mod site_task;
mod site_view;

pub use checkpoint_options::{CheckpointOptions, CheckpointOptionsError};
pub use map_history::{
    DEFAULT_HISTORY_CAPACITY, DEFAULT_HISTORY_PAST_GRID_BUDGET_BYTES, HistoryEntry, MapHistory,
    PlacedGrids,
};
pub use published_submaps::PublishedSubmaps;
pub use session_view::{PlacementState, SessionView};
pub use site_error::SiteError;
pub use site_handle::{RenderedMap, SiteHandle, UploadAck, VersionInfo};
pub(crate) use site_map::copy_counts;
pub use site_map::{MapCounts, SessionOpened, SessionStartCounts, SiteMap, UploadCheck};
pub(crate) use site_task::site_span;
pub use site_task::{DEFAULT_SITE_UNLOAD_AFTER, SITE_LOG_KIND, SiteTask, SiteTaskOptions};
pub use site_view::SiteView;
