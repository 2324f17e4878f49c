//! # storage — persistence of site maps
//!
//! Will hold the `MapStore` trait with its sled and in-memory implementations (tracked by the
//! fleet-service issue). Nothing is stored through this crate yet.
