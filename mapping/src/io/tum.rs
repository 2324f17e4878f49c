//! TUM trajectory format (`t x y z qx qy qz qw`, one pose per line), readable by evo and the TUM tools.

use std::io::{BufRead, Write};

use crate::geometry::{Rigid2, Rigid2Ext as _, rigid2, yaw_from_quaternion};
use crate::sensor::Timestamp;

/// A TUM file that could not be read.
#[derive(Debug, thiserror::Error)]
pub enum TumError {
    /// Reading failed.
    #[error("cannot read the trajectory: {0}")]
    Io(#[from] std::io::Error),
    /// A line is not `t x y z qx qy qz qw` with finite numbers, or its stamp goes back in time.
    #[error("trajectory line {line}: {what}")]
    Parse {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        what: String,
    },
}

/// A TUM stamp, `seconds[.fraction]`, read to the nanosecond (an `f64` of seconds since 1970 is not).
fn parse_stamp(text: &str) -> Option<Timestamp> {
    let (whole, fraction) = text.split_once('.').unwrap_or((text, ""));
    if whole.is_empty() || !whole.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    if !fraction.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let seconds: i64 = whole.parse().ok()?;
    let digits = &fraction[..fraction.len().min(9)];
    let nanos: i64 = if digits.is_empty() {
        0
    } else {
        digits.parse::<i64>().ok()? * 10i64.pow(9 - digits.len() as u32)
    };
    Some(Timestamp(
        seconds.checked_mul(1_000_000_000)?.checked_add(nanos)?,
    ))
}

/// Reads planar poses from TUM lines (the rotation's yaw; z, roll and pitch ignored), in time order;
/// blank lines and lines starting with `#` are skipped.
pub fn read_tum(input: impl BufRead) -> Result<Vec<(Timestamp, Rigid2)>, TumError> {
    let mut poses: Vec<(Timestamp, Rigid2)> = Vec::new();
    for (i, line) in input.lines().enumerate() {
        let line = line?;
        let text = line.trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let bad = |what: &str| TumError::Parse {
            line: i + 1,
            what: what.to_owned(),
        };
        let fields: Vec<&str> = text.split_whitespace().collect();
        if fields.len() != 8 {
            return Err(bad("expected 8 fields: t x y z qx qy qz qw"));
        }
        let t = parse_stamp(fields[0]).ok_or_else(|| bad("the stamp is not seconds since 1970"))?;
        let values: Option<Vec<f64>> = fields[1..]
            .iter()
            .map(|f| f.parse::<f64>().ok().filter(|v| v.is_finite()))
            .collect();
        let v = values.ok_or_else(|| bad("a pose field is not a finite number"))?;
        let yaw = yaw_from_quaternion([v[3], v[4], v[5], v[6]]);
        if poses.last().is_some_and(|(last, _)| *last > t) {
            return Err(bad("the stamp goes back in time"));
        }
        poses.push((t, rigid2(v[0], v[1], yaw)));
    }
    Ok(poses)
}

/// Writes planar poses as TUM lines (z = 0, rotation about z).
pub fn write_tum(mut out: impl Write, poses: &[(Timestamp, Rigid2)]) -> std::io::Result<()> {
    for (t, pose) in poses {
        let half = pose.theta() / 2.0;
        writeln!(
            out,
            "{t} {:.6} {:.6} 0 0 0 {:.9} {:.9}",
            pose.x(),
            pose.y(),
            half.sin(),
            half.cos()
        )?;
    }
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::rigid2;

    #[test]
    fn writes_quaternion_about_z() {
        let mut buf = Vec::new();
        write_tum(
            &mut buf,
            &[(
                Timestamp(1_500_000_000),
                rigid2(1.0, 2.0, std::f64::consts::FRAC_PI_2),
            )],
        )
        .unwrap();
        let line = String::from_utf8(buf).unwrap();
        assert_eq!(
            line,
            "1.500000000 1.000000 2.000000 0 0 0 0.707106781 0.707106781\n"
        );
    }

    #[test]
    fn reads_what_it_writes_to_the_nanosecond() {
        let poses = vec![
            (Timestamp(1_234_567_890_123_456_789), rigid2(1.0, -2.0, 0.7)),
            (
                Timestamp(1_234_567_891_000_000_000),
                rigid2(0.5, 0.25, -3.0),
            ),
        ];
        let mut buf = Vec::new();
        write_tum(&mut buf, &poses).unwrap();
        let text = format!(
            "# t x y z qx qy qz qw\n\n{}",
            String::from_utf8(buf).unwrap()
        );
        let read = read_tum(text.as_bytes()).unwrap();
        assert_eq!(read.len(), 2);
        for ((ta, a), (tb, b)) in poses.iter().zip(&read) {
            assert_eq!(ta, tb);
            assert!((a.x() - b.x()).abs() < 1e-6 && (a.y() - b.y()).abs() < 1e-6);
            assert!((a.theta() - b.theta()).abs() < 1e-8);
        }
    }

    #[test]
    fn a_bad_line_is_named() {
        let err = read_tum("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 x 1\n".as_bytes()).unwrap_err();
        assert!(err.to_string().contains("line 2"), "{err}");
        let err = read_tum("2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n".as_bytes()).unwrap_err();
        assert!(err.to_string().contains("back in time"), "{err}");
        assert!(read_tum("-1.0 0 0 0 0 0 0 1\n".as_bytes()).is_err());
        assert!(read_tum("1.0 0 0 0 0 0 1\n".as_bytes()).is_err());
    }
}
