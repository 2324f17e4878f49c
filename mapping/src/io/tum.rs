//! TUM trajectory format (`t x y z qx qy qz qw`, one pose per line), readable by evo and the TUM tools.

use std::io::Write;

use crate::geometry::{Rigid2, Rigid2Ext as _};
use crate::sensor::Timestamp;

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
}
