//! Accuracy measures of SLAM results.

mod relations_metric;

pub use relations_metric::{RelationsErrorStats, relations_error};
