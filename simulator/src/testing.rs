//! Shared test helpers (`cfg(test)`, or the `testing` feature for other crates' tests).
//!
//! [`checkpoint_sessions`]: a few short real sessions (a small simulated store, LLO, GLM by the real
//! constraint builder, Chow–Liu trimming) fed to a [`mapping::lifelong::LifelongMap`] the way every shell
//! does, resumable at any node, for the checkpoint round-trip tests of `mapping` and `proto`.

pub mod checkpoint_sessions;
