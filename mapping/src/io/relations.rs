//! Ground-truth relation files of the Freiburg SLAM benchmark (Kümmerle et al. 2009):
//! one line per relation, `t1 t2 x y z roll pitch yaw`, the motion `X(t1)⁻¹·X(t2)` in the frame of
//! the pose at `t1`; lines starting with `#` are comments.

use std::io::BufRead;

use crate::geometry::{Rigid2, rigid2};
use crate::sensor::Timestamp;

/// One reference relative motion.
#[derive(Clone, Debug, PartialEq)]
pub struct Relation {
    /// Stamp of the first pose.
    pub t1: Timestamp,
    /// Stamp of the second pose.
    pub t2: Timestamp,
    /// `pose(t1)⁻¹ · pose(t2)`.
    pub delta: Rigid2,
}

/// A relation file that could not be read.
#[derive(Debug, thiserror::Error)]
pub enum RelationsError {
    /// Reading failed.
    #[error("cannot read relations: {0}")]
    Io(#[from] std::io::Error),
    /// A line is not `t1 t2 x y z roll pitch yaw`.
    #[error("relations line {line}: {what}")]
    Parse {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        what: String,
        /// The number parser's error, when a value is not a number.
        #[source]
        source: Option<std::num::ParseFloatError>,
    },
}

/// Latest time accepted, seconds (ROS1's u32 seconds since the epoch): stamps and their differences then
/// fit `Timestamp`'s i64 nanoseconds.
const MAX_TIME_S: f64 = 4_294_967_296.0;

/// Reads every relation.
pub fn read_relations(input: impl BufRead) -> Result<Vec<Relation>, RelationsError> {
    let mut out = Vec::new();
    for (i, line) in input.lines().enumerate() {
        let line = line?;
        let text = line.trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let values: Result<Vec<f64>, _> = text.split_whitespace().map(str::parse::<f64>).collect();
        let values = values.map_err(|e| RelationsError::Parse {
            line: i + 1,
            what: e.to_string(),
            source: Some(e),
        })?;
        if values.len() != 8 || values.iter().any(|v| !v.is_finite()) {
            return Err(RelationsError::Parse {
                line: i + 1,
                what: format!(
                    "expected 8 finite numbers `t1 t2 x y z roll pitch yaw`, got {}",
                    values.len()
                ),
                source: None,
            });
        }
        if let Some(t) = values[..2].iter().find(|t| !(0.0..MAX_TIME_S).contains(*t)) {
            return Err(RelationsError::Parse {
                line: i + 1,
                what: format!("time {t} s is outside 0..{MAX_TIME_S} s"),
                source: None,
            });
        }
        out.push(Relation {
            t1: Timestamp::from_secs_f64(values[0]),
            t2: Timestamp::from_secs_f64(values[1]),
            delta: rigid2(values[2], values[3], values[7]),
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_comments_and_reports_bad_lines() {
        let text = "# t1 t2 x y z roll pitch yaw\n10.5 11.0 1 2 0 0 0 0.5\n\n";
        let r = read_relations(text.as_bytes()).unwrap();
        assert_eq!(r.len(), 1);
        assert_eq!(r[0].t1, Timestamp::from_secs_f64(10.5));
        assert!((r[0].delta.rotation.angle() - 0.5).abs() < 1e-12);
        let err = read_relations("1 2 3\n".as_bytes())
            .unwrap_err()
            .to_string();
        assert!(err.contains("line 1"), "{err}");
        assert!(read_relations("1 2 3 4 5 6 7 x\n".as_bytes()).is_err());
    }

    #[test]
    fn a_value_that_is_not_a_number_keeps_the_parser_error_as_source() {
        let err = read_relations("1 2 3 4 5 6 7 x\n".as_bytes()).unwrap_err();
        assert_eq!(err.to_string(), "relations line 1: invalid float literal");
        assert!(std::error::Error::source(&err).is_some());
    }

    /// Fuzz finding (regression): times beyond i64 nanoseconds saturated silently, and differences of
    /// such stamps overflow.
    #[test]
    fn times_outside_the_ros1_range_are_refused() {
        for line in ["1e300 11 1 2 0 0 0 0.5\n", "10 -1 1 2 0 0 0 0.5\n"] {
            let err = read_relations(line.as_bytes()).unwrap_err().to_string();
            assert!(err.contains("outside"), "{err}");
        }
    }
}
