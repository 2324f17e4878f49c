//! # proto — evermap's wire types
//!
//! Protobuf messages shared by the server and the robot agents, and their conversions to and from
//! `mapping` types. The fleet protocol itself is not written yet (tracked by the fleet-service issue);
//! this crate currently only reserves its place in the workspace.
