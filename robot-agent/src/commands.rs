//! The agent's subcommands, one file each.

pub mod offline;
pub mod perturb_args;
pub mod relocalize;
pub mod run;
pub mod sessions;
