//! The fuzz targets: every decoder of hostile input we have, seeded from the real files in
//! `../shared/datasets` (and from messages and archives built the way the fleet builds them).

mod configs;
mod fleet_site;
mod mapping_io;
mod protobuf;
mod recordings;
mod ros2_live;
mod rosbag2;

use std::path::{Path, PathBuf};

use super::fuzz_target::FuzzTarget;

/// Why a target could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum SetupError {
    /// A seed could not be read or built.
    #[error("seed {path}: {reason}")]
    Seed {
        /// The file (or what was being built).
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// No target has this name.
    #[error("no fuzz target named {0:?} (known: {known})", known = TARGET_NAMES.join(", "))]
    UnknownTarget(String),
}

/// Every target's name, in the order they run.
pub const TARGET_NAMES: [&str; 19] = [
    "ros1_bag",
    "ros1_messages",
    "rosbag2_mcap",
    "rosbag2_sqlite3",
    "rosbag2_sqlite3_rows",
    "rosbag2_metadata",
    "ros2_messages",
    "ros2_live",
    "carmen",
    "g2o",
    "relations",
    "server_config",
    "slam_config",
    "sessions_config",
    "agent_config",
    "protobuf",
    "zenoh_request",
    "zenoh_upload",
    "site_archive",
];

pub(super) fn read_file(path: &Path) -> Result<Vec<u8>, SetupError> {
    std::fs::read(path).map_err(|e| SetupError::Seed {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })
}

/// Builds the target `name`, reading seeds under `datasets` (`tests::datasets_dir()`).
pub fn target(name: &str, datasets: &Path) -> Result<FuzzTarget, SetupError> {
    match name {
        "ros1_bag" => recordings::ros1_bag(datasets),
        "ros1_messages" => recordings::ros1_messages(datasets),
        "rosbag2_mcap" => rosbag2::mcap_files(datasets),
        "rosbag2_sqlite3" => rosbag2::sqlite3_files(datasets),
        "rosbag2_sqlite3_rows" => rosbag2::sqlite3_rows(datasets),
        "rosbag2_metadata" => rosbag2::metadata_files(datasets),
        "ros2_messages" => rosbag2::ros2_messages(datasets),
        "ros2_live" => ros2_live::ros2_live(datasets),
        "carmen" => recordings::carmen(datasets),
        "g2o" => mapping_io::pose_graphs(datasets),
        "relations" => mapping_io::relation_files(datasets),
        "server_config" => configs::server_config(),
        "slam_config" => configs::slam_config(),
        "sessions_config" => configs::sessions_config(),
        "agent_config" => configs::agent_config(),
        "protobuf" => Ok(protobuf::protobuf()),
        "zenoh_request" => fleet_site::zenoh_requests(),
        "zenoh_upload" => fleet_site::zenoh_uploads(),
        "site_archive" => fleet_site::site_archive(),
        other => Err(SetupError::UnknownTarget(other.to_owned())),
    }
}
