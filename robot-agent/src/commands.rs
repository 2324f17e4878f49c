//! The agent's subcommands, one file each.

pub mod offline;
pub mod relocalize;
pub mod run;
