//! A bounds-checked reader of OMG CDR (XCDR1, "plain CDR"), the serialization ROS 2 uses for every
//! message it records or sends (rmw_fastrtps, rmw_cyclonedds and rmw_zenoh alike).
//!
//! A payload starts with a 4-byte encapsulation header: `00 00` (CDR, big endian) or `00 01` (CDR,
//! little endian), then two option bytes. Every primitive of size `n` (1, 2, 4 or 8 bytes) is aligned to a
//! multiple of `n` **counted from the first byte after that header**, not from the start of the buffer;
//! strings are a `u32` length that counts the terminating NUL, then the bytes and the NUL; sequences are a
//! `u32` element count, then the elements; fixed-size arrays have no count. Nested structures add no
//! alignment of their own: each of their fields is aligned as usual.
//!
//! Why hand-written and not the `cdr` crate: that crate (0.2.4) has had no release since 2021, and it
//! deserializes whole structs through serde, so every message would need a full mirror of its ROS
//! definition (covariances, twist, intensities) only to read a few fields. The few rules above fit in
//! this file; the readers in `ros2_messages` skip what they do not need, and every read is bounds-checked,
//! so a truncated or corrupt payload is an error and never a panic. The `mcap_cdr_test` and
//! `sqlite3_cdr_test` recordings of rosbag2's own test suite check the alignment rules (see the tests of
//! `rosbag2`).

use super::ros_messages::DecodeError;

/// Reads one CDR payload front to back.
pub struct CdrReader<'a> {
    /// The bytes after the encapsulation header: alignment is relative to their start.
    body: &'a [u8],
    pos: usize,
    little_endian: bool,
}

impl<'a> CdrReader<'a> {
    /// Starts reading a payload, checking its encapsulation header.
    pub fn new(payload: &'a [u8]) -> Result<Self, DecodeError> {
        let Some((header, body)) = payload.split_at_checked(4) else {
            return Err(DecodeError(format!(
                "CDR payload of {} bytes has no 4-byte encapsulation header",
                payload.len()
            )));
        };
        let little_endian = match (header[0], header[1]) {
            (0x00, 0x00) => false,
            (0x00, 0x01) => true,
            (a, b) => {
                return Err(DecodeError(format!(
                    "CDR encapsulation {a:02x} {b:02x} is not plain CDR (00 00 big endian or 00 01 little \
                     endian); parameter lists and XCDR2 are not read"
                )));
            }
        };
        Ok(Self {
            body,
            pos: 0,
            little_endian,
        })
    }

    /// Whether the payload is little endian.
    pub fn is_little_endian(&self) -> bool {
        self.little_endian
    }

    /// Bytes of the body not read yet (trailing padding included).
    pub fn remaining(&self) -> usize {
        self.body.len() - self.pos
    }

    fn truncated(&self, what: &str) -> DecodeError {
        DecodeError(format!(
            "truncated CDR at byte {} of {} reading {what}",
            self.pos,
            self.body.len()
        ))
    }

    /// Skips the padding before a primitive of `size` bytes.
    fn align(&mut self, size: usize, what: &str) -> Result<(), DecodeError> {
        let padded = self.pos.next_multiple_of(size);
        if padded > self.body.len() {
            return Err(self.truncated(what));
        }
        self.pos = padded;
        Ok(())
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], DecodeError> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.body.len())
            .ok_or_else(|| self.truncated(what))?;
        let bytes = &self.body[self.pos..end];
        self.pos = end;
        Ok(bytes)
    }

    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], DecodeError> {
        self.align(N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N, what)?);
        Ok(a)
    }

    /// `uint8`, `byte`, `char`.
    pub fn u8(&mut self, what: &str) -> Result<u8, DecodeError> {
        Ok(self.take(1, what)?[0])
    }

    /// `bool` (any non-zero byte is true).
    pub fn bool(&mut self, what: &str) -> Result<bool, DecodeError> {
        Ok(self.u8(what)? != 0)
    }

    /// `int8`.
    pub fn i8(&mut self, what: &str) -> Result<i8, DecodeError> {
        Ok(i8::from_ne_bytes([self.u8(what)?]))
    }

    /// `uint16`.
    pub fn u16(&mut self, what: &str) -> Result<u16, DecodeError> {
        let b = self.array::<2>(what)?;
        Ok(if self.little_endian {
            u16::from_le_bytes(b)
        } else {
            u16::from_be_bytes(b)
        })
    }

    /// `int16`.
    pub fn i16(&mut self, what: &str) -> Result<i16, DecodeError> {
        Ok(self.u16(what)?.cast_signed())
    }

    /// `uint32`.
    pub fn u32(&mut self, what: &str) -> Result<u32, DecodeError> {
        let b = self.array::<4>(what)?;
        Ok(if self.little_endian {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }

    /// `int32`.
    pub fn i32(&mut self, what: &str) -> Result<i32, DecodeError> {
        Ok(self.u32(what)?.cast_signed())
    }

    /// `uint64`.
    pub fn u64(&mut self, what: &str) -> Result<u64, DecodeError> {
        let b = self.array::<8>(what)?;
        Ok(if self.little_endian {
            u64::from_le_bytes(b)
        } else {
            u64::from_be_bytes(b)
        })
    }

    /// `int64`.
    pub fn i64(&mut self, what: &str) -> Result<i64, DecodeError> {
        Ok(self.u64(what)?.cast_signed())
    }

    /// `float32`.
    pub fn f32(&mut self, what: &str) -> Result<f32, DecodeError> {
        Ok(f32::from_bits(self.u32(what)?))
    }

    /// `float64`.
    pub fn f64(&mut self, what: &str) -> Result<f64, DecodeError> {
        Ok(f64::from_bits(self.u64(what)?))
    }

    /// `string`: a `u32` length counting the terminating NUL, the bytes, the NUL. Invalid UTF-8 is
    /// replaced, not an error (frame ids are only compared).
    pub fn string(&mut self, what: &str) -> Result<String, DecodeError> {
        let n = self.u32(what)? as usize;
        let bytes = self.take(n, what)?;
        let text = match bytes.split_last() {
            None => &[][..],
            Some((0, text)) => text,
            Some(_) => {
                return Err(DecodeError(format!(
                    "{what}: CDR string of {n} bytes is not NUL-terminated"
                )));
            }
        };
        Ok(String::from_utf8_lossy(text).into_owned())
    }

    /// A sequence's element count, checked against the bytes left (each element takes at least
    /// `min_element_bytes`), so a corrupt count cannot make the caller allocate gigabytes.
    pub fn sequence_len(
        &mut self,
        min_element_bytes: usize,
        what: &str,
    ) -> Result<usize, DecodeError> {
        let n = self.u32(what)? as usize;
        if n.saturating_mul(min_element_bytes.max(1)) > self.remaining() {
            return Err(DecodeError(format!(
                "{what}: sequence of {n} elements does not fit in the {} bytes left",
                self.remaining()
            )));
        }
        Ok(n)
    }

    /// `sequence<float32>` (`float32[]`).
    pub fn f32_sequence(&mut self, what: &str) -> Result<Vec<f32>, DecodeError> {
        let n = self.sequence_len(4, what)?;
        if n == 0 {
            return Ok(Vec::new());
        }
        self.align(4, what)?;
        let bytes = self.take(4 * n, what)?;
        let le = self.little_endian;
        Ok(bytes
            .chunks_exact(4)
            .map(|b| {
                let b = [b[0], b[1], b[2], b[3]];
                f32::from_bits(if le {
                    u32::from_le_bytes(b)
                } else {
                    u32::from_be_bytes(b)
                })
            })
            .collect())
    }

    /// Skips `n` values of `size` bytes each (a fixed-size array or the elements of a sequence).
    pub fn skip(&mut self, size: usize, n: usize, what: &str) -> Result<(), DecodeError> {
        if n == 0 {
            return Ok(());
        }
        self.align(size, what)?;
        self.take(size.saturating_mul(n), what).map(|_| ())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn aligns_relative_to_the_body_and_honours_endianness() {
        // u8 1, pad 3, u32 0x01020304, then f64 1.5 at body offset 8; header 00 01 (little endian).
        let mut le = vec![0x00, 0x01, 0x00, 0x00, 1, 0xee, 0xee, 0xee];
        le.extend_from_slice(&0x0102_0304u32.to_le_bytes());
        le.extend_from_slice(&1.5f64.to_le_bytes());
        let mut r = CdrReader::new(&le).unwrap();
        assert!(r.is_little_endian());
        assert_eq!(r.u8("a").unwrap(), 1);
        assert_eq!(r.u32("b").unwrap(), 0x0102_0304);
        assert_eq!(r.f64("c").unwrap().to_bits(), 1.5f64.to_bits());
        assert_eq!(r.remaining(), 0);

        let mut be = vec![0x00, 0x00, 0x00, 0x00, 1, 0, 0, 0];
        be.extend_from_slice(&0x0102_0304u32.to_be_bytes());
        be.extend_from_slice(&1.5f64.to_be_bytes());
        let mut r = CdrReader::new(&be).unwrap();
        assert!(!r.is_little_endian());
        assert_eq!(r.u8("a").unwrap(), 1);
        assert_eq!(r.u32("b").unwrap(), 0x0102_0304);
        assert_eq!(r.f64("c").unwrap().to_bits(), 1.5f64.to_bits());
    }

    #[test]
    fn strings_sequences_and_bad_input_are_checked() {
        let mut b = vec![0x00, 0x01, 0x00, 0x00];
        b.extend_from_slice(&6u32.to_le_bytes());
        b.extend_from_slice(b"laser\0");
        b.extend_from_slice(&[0, 0]); // pad to 4
        b.extend_from_slice(&2u32.to_le_bytes());
        b.extend_from_slice(&1.0f32.to_le_bytes());
        b.extend_from_slice(&2.0f32.to_le_bytes());
        let mut r = CdrReader::new(&b).unwrap();
        assert_eq!(r.string("frame").unwrap(), "laser");
        assert_eq!(r.f32_sequence("ranges").unwrap(), vec![1.0, 2.0]);
        for cut in 0..b.len() {
            let outcome = CdrReader::new(&b[..cut]).and_then(|mut r| {
                r.string("frame")?;
                r.f32_sequence("ranges")
            });
            assert!(outcome.is_err(), "cut at {cut}");
        }
        // A huge count is refused before any allocation.
        let mut huge = vec![0x00, 0x01, 0x00, 0x00];
        huge.extend_from_slice(&u32::MAX.to_le_bytes());
        let error = CdrReader::new(&huge)
            .unwrap()
            .f32_sequence("ranges")
            .unwrap_err();
        assert!(error.0.contains("does not fit"), "{error:?}");
        // Not plain CDR.
        assert!(CdrReader::new(&[0x00, 0x03, 0, 0]).is_err());
        // A string without its NUL.
        let mut s = vec![0x00, 0x01, 0x00, 0x00];
        s.extend_from_slice(&2u32.to_le_bytes());
        s.extend_from_slice(b"ab");
        assert!(CdrReader::new(&s).unwrap().string("x").is_err());
    }
}
