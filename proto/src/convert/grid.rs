//! Occupancy grids: u16 cell values, little-endian, optionally zlib-compressed.

use std::io::{Read as _, Write as _};

use mapping::grid::{MapLimits, ProbabilityGrid};
use nalgebra::Vector2;

use crate::convert::check_finite;
use crate::{
    ConversionError, ErrorSource, FORMAT_VERSION, MAX_GRID_CELLS, check_format_version, pb,
};

/// Largest valid stored cell value (see `mapping::grid`).
const MAX_CELL_VALUE: u16 = 32767;

/// The wire form of a grid, compressed ([`pb::GridEncoding::U16LeZlib`]).
pub fn grid_to_pb(grid: &ProbabilityGrid) -> pb::Grid {
    grid_to_pb_with(grid, pb::GridEncoding::U16LeZlib)
}

/// The wire form of a grid with the given encoding ([`pb::GridEncoding::Unspecified`] is taken as
/// uncompressed).
pub fn grid_to_pb_with(grid: &ProbabilityGrid, encoding: pb::GridEncoding) -> pb::Grid {
    let limits = grid.limits();
    let mut raw = Vec::with_capacity(grid.values().len() * 2);
    for value in grid.values() {
        raw.extend_from_slice(&value.to_le_bytes());
    }
    let (encoding, values) = match encoding {
        pb::GridEncoding::U16LeZlib => {
            let mut encoder =
                flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
            // Writing into a Vec cannot fail; fall back to raw bytes if it somehow did.
            match encoder.write_all(&raw).and_then(|()| encoder.finish()) {
                Ok(compressed) => (pb::GridEncoding::U16LeZlib, compressed),
                Err(_) => (pb::GridEncoding::U16Le, raw),
            }
        }
        pb::GridEncoding::U16Le | pb::GridEncoding::Unspecified => (pb::GridEncoding::U16Le, raw),
    };
    pb::Grid {
        format_version: FORMAT_VERSION,
        resolution: limits.resolution,
        origin_x: limits.origin.x,
        origin_y: limits.origin.y,
        width: limits.width.max(0) as u32,
        height: limits.height.max(0) as u32,
        encoding: encoding.into(),
        values,
    }
}

/// zlib's best compression ratio (a stream of one repeated byte): no valid stream inflates further.
const ZLIB_MAX_RATIO: usize = 1032;

/// What to reserve for inflating `compressed` bytes that should give `expected` bytes: never more than
/// they can inflate to, so a tiny message claiming a huge grid does not reserve 128 MiB.
fn zlib_capacity(expected: usize, compressed: usize) -> usize {
    expected.min(compressed.saturating_mul(ZLIB_MAX_RATIO))
}

/// A grid from the wire: checks the version, the geometry (positive finite resolution, finite origin, at
/// most [`MAX_GRID_CELLS`] cells), that the values are exactly `width × height` u16s and that every value
/// is a valid cell value.
pub fn grid_from_pb(grid: &pb::Grid) -> Result<ProbabilityGrid, ConversionError> {
    const M: &str = "Grid";
    check_format_version(M, grid.format_version)?;
    let resolution = check_finite(grid.resolution, M, "resolution")?;
    if resolution <= 0.0 {
        return Err(ConversionError::OutOfRange {
            message: M,
            field: "resolution",
            value: resolution.into(),
            expected: "positive",
        });
    }
    let origin = Vector2::new(
        check_finite(grid.origin_x, M, "origin_x")?,
        check_finite(grid.origin_y, M, "origin_y")?,
    );
    let (width, height) = (grid.width as usize, grid.height as usize);
    let cells = width.saturating_mul(height);
    if cells > MAX_GRID_CELLS || i32::try_from(width).is_err() || i32::try_from(height).is_err() {
        return Err(ConversionError::BadSize {
            message: M,
            field: "width*height",
            expected: MAX_GRID_CELLS,
            got: cells,
        });
    }
    let expected_bytes = cells * 2;
    let decompressed;
    let raw: &[u8] = match pb::GridEncoding::try_from(grid.encoding) {
        Ok(pb::GridEncoding::U16Le) => &grid.values,
        Ok(pb::GridEncoding::U16LeZlib) => {
            let mut out = Vec::with_capacity(zlib_capacity(expected_bytes, grid.values.len()));
            // Read at most one byte more than expected, so a bomb cannot exhaust memory.
            flate2::read::ZlibDecoder::new(grid.values.as_slice())
                .take(expected_bytes as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| ConversionError::Decompress {
                    message: M,
                    field: "values",
                    source: ErrorSource::new(e),
                })?;
            decompressed = out;
            &decompressed
        }
        _ => {
            return Err(ConversionError::OutOfRange {
                message: M,
                field: "encoding",
                value: grid.encoding.into(),
                expected: "a known GridEncoding",
            });
        }
    };
    if raw.len() != expected_bytes {
        return Err(ConversionError::BadSize {
            message: M,
            field: "values",
            expected: expected_bytes,
            got: raw.len(),
        });
    }
    let mut out = ProbabilityGrid::new(MapLimits::new(
        resolution,
        origin,
        width as i32,
        height as i32,
    ));
    // Converted whole, then checked whole: two loops without an exit, which the compiler vectorizes.
    for (cell, bytes) in out.values_mut().iter_mut().zip(raw.chunks_exact(2)) {
        *cell = u16::from_le_bytes([bytes[0], bytes[1]]);
    }
    if let Some(value) = out.values().iter().find(|&&v| v > MAX_CELL_VALUE) {
        return Err(ConversionError::OutOfRange {
            message: M,
            field: "values",
            value: (*value).into(),
            expected: "at most 32767 (MAX_CELL_VALUE)",
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use mapping::grid::CellIndex;
    use proptest::prelude::*;

    use super::*;
    use crate::FieldValue;

    /// Fuzz finding (regression): a zlib grid reserved its declared size (up to 128 MiB) before
    /// inflating, whatever the size of the message.
    #[test]
    fn zlib_reservation_is_bounded_by_the_compressed_size() {
        assert_eq!(zlib_capacity(MAX_GRID_CELLS * 2, 12), 12 * ZLIB_MAX_RATIO);
        assert_eq!(zlib_capacity(100, 1 << 20), 100);
        let claimed = pb::Grid {
            format_version: FORMAT_VERSION,
            resolution: 0.05,
            width: 8192,
            height: 8192,
            encoding: pb::GridEncoding::U16LeZlib.into(),
            values: vec![0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
            ..Default::default()
        };
        let err = grid_from_pb(&claimed).unwrap_err().to_string();
        assert!(err.contains("values"), "{err}");
    }

    fn sample_grid(width: i32, height: i32, seed: u32) -> ProbabilityGrid {
        let mut grid = ProbabilityGrid::new(MapLimits::new(
            0.05,
            Vector2::new(-1.25, 3.5),
            width,
            height,
        ));
        for iy in 0..height {
            for ix in 0..width {
                let k = (ix as u32 * 31 + iy as u32 * 17 + seed) % 7;
                if k < 3 {
                    grid.set_probability(&CellIndex::new(ix, iy), 0.1 + 0.1 * k as f32);
                }
            }
        }
        grid
    }

    proptest! {
        #[test]
        fn grids_round_trip_in_both_encodings(w in 0..40_i32, h in 0..40_i32, seed in 0..100_u32) {
            let grid = sample_grid(w, h, seed);
            for encoding in [pb::GridEncoding::U16Le, pb::GridEncoding::U16LeZlib] {
                let back = grid_from_pb(&grid_to_pb_with(&grid, encoding)).unwrap();
                prop_assert_eq!(back.limits(), grid.limits());
                prop_assert_eq!(back.values(), grid.values());
            }
        }
    }

    #[test]
    fn compression_shrinks_a_mostly_unknown_submap() {
        let mut grid = ProbabilityGrid::new(MapLimits::new(0.05, Vector2::zeros(), 400, 400));
        for i in 0..400 {
            grid.set_probability(&CellIndex::new(i, 200), 0.8);
        }
        let wire = grid_to_pb(&grid);
        assert!(
            wire.values.len() * 20 < 400 * 400 * 2,
            "{}",
            wire.values.len()
        );
    }

    #[test]
    fn malformed_grids_are_refused() {
        let good = grid_to_pb_with(&sample_grid(4, 3, 1), pb::GridEncoding::U16Le);
        let mut short = good.clone();
        short.values.pop();
        assert!(matches!(
            grid_from_pb(&short),
            Err(ConversionError::BadSize {
                expected: 24,
                got: 23,
                ..
            })
        ));
        let mut nan = good.clone();
        nan.resolution = f64::NAN;
        assert!(matches!(
            grid_from_pb(&nan),
            Err(ConversionError::NotFinite { .. })
        ));
        let mut zero = good.clone();
        zero.resolution = 0.0;
        assert!(matches!(
            grid_from_pb(&zero),
            Err(ConversionError::OutOfRange { .. })
        ));
        let mut huge = good.clone();
        huge.width = u32::MAX;
        huge.height = u32::MAX;
        assert!(matches!(
            grid_from_pb(&huge),
            Err(ConversionError::BadSize { .. })
        ));
        let mut marker = good.clone();
        marker.values[0] = 0xff;
        marker.values[1] = 0xff;
        let error = grid_from_pb(&marker).unwrap_err();
        assert_eq!(
            error,
            ConversionError::OutOfRange {
                message: "Grid",
                field: "values",
                value: FieldValue::Unsigned(0xffff),
                expected: "at most 32767 (MAX_CELL_VALUE)",
            }
        );
        // The limit the message states is the one checked.
        assert!(
            error
                .to_string()
                .contains(&format!("at most {MAX_CELL_VALUE} ")),
            "{error}"
        );
        let mut garbage = grid_to_pb(&sample_grid(4, 3, 1));
        garbage.values = vec![1, 2, 3];
        assert!(matches!(
            grid_from_pb(&garbage),
            Err(ConversionError::Decompress { .. })
        ));
        let mut version = good.clone();
        version.format_version = 9;
        assert!(matches!(
            grid_from_pb(&version),
            Err(ConversionError::UnsupportedFormatVersion { got: 9, .. })
        ));
        let mut encoding = good;
        encoding.encoding = 77;
        assert!(matches!(
            grid_from_pb(&encoding),
            Err(ConversionError::OutOfRange { .. })
        ));
    }

    #[test]
    fn values_that_do_not_decompress_keep_the_decompressor_error_as_source() {
        let mut garbage = grid_to_pb(&sample_grid(4, 3, 1));
        garbage.values = vec![1, 2, 3];
        let err = grid_from_pb(&garbage).unwrap_err();
        let source = std::error::Error::source(&err).expect("the decompressor's error");
        // The message is the one the `reason` string gave.
        assert_eq!(
            err.to_string(),
            format!("Grid.values cannot be decompressed: {source}")
        );
    }

    #[test]
    fn a_zlib_bomb_is_cut_off() {
        let mut grid = grid_to_pb(&sample_grid(2, 2, 0));
        let mut encoder = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
        encoder.write_all(&vec![0_u8; 10 << 20]).unwrap();
        grid.values = encoder.finish().unwrap();
        assert!(matches!(
            grid_from_pb(&grid),
            Err(ConversionError::BadSize {
                expected: 8,
                got: 9,
                ..
            })
        ));
    }
}
