//! The agent's subcommands, one file each.

pub mod offline;
pub mod relocalize;
pub mod simulate;
pub mod sessions;
pub mod run;
