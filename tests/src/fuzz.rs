//! A fuzz harness for every decoder of hostile input, on the stable toolchain.
//!
//! Engine: proptest (already a dev-dependency of `mapping` and `proto`), used for its deterministic
//! generator and its value-tree shrinking, with our own mutation strategy over real seed files
//! ([`mutation`]: bit flips, truncation, splices, length fields and varints blown up, hostile number
//! tokens) and our own driver ([`fuzz`]: every input under `catch_unwind`, heap measured per input,
//! distinct findings shrunk, inputs/s reported). Compared (`cargo info`): `arbtest` 0.3 generates
//! structured values from random bytes but has no notion of seed files to mutate; `bolero` 0.13 runs
//! libFuzzer/AFL only through `cargo bolero` (sanitizers want nightly) and on stable only replays a corpus
//! or draws random bytes, with a larger dependency tree. Mutating the real files is what reaches deep
//! into these formats, and proptest gives that with no new dependency.
//!
//! `evermap-fuzz` (this crate's binary) runs every target for N inputs and prints inputs/s and findings;
//! `tests/tests/fuzz_decoders.rs` runs a short slice of each in CI.

mod fuzz_driver;
mod fuzz_target;
pub mod mutation;
mod targets;

pub use fuzz_driver::{Finding, FindingKind, FuzzOptions, FuzzOptionsError, FuzzReport, fuzz};
pub use fuzz_target::{FixupFn, FuzzTarget, RunFn, Verdict};
pub use targets::{SetupError, TARGET_NAMES, target};
