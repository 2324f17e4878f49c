//! A writer of OMG CDR (XCDR1, "plain CDR"), little endian: the encoding ROS 2 nodes send and expect on
//! every rmw, rmw_zenoh included. The rules are those [`super::CdrReader`] documents: a 4-byte
//! encapsulation header (`00 01 00 00`: CDR, little endian), each primitive of `n` bytes aligned to a
//! multiple of `n` counted from the first byte after that header, strings as a `u32` length counting the
//! terminating NUL, then the bytes and the NUL, sequences as a `u32` element count then the elements.
//!
//! Hand-written for the reason the reader is (see its module docs): the few messages the agent sends
//! (`nav_msgs/msg/OccupancyGrid`, `tf2_msgs/msg/TFMessage`, `geometry_msgs/msg/PoseWithCovarianceStamped`,
//! in `ros2_nav_messages`) need only these rules, and every output is read back by [`super::CdrReader`]
//! in the tests and decoded by an independent implementation (Python `rosbags`) in the live test.

/// Builds one CDR payload front to back. Writing never fails.
pub struct CdrWriter {
    bytes: Vec<u8>,
}

/// Bytes of the encapsulation header.
const HEADER: usize = 4;

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    /// A payload with its encapsulation header (CDR, little endian) and nothing else yet.
    pub fn new() -> Self {
        Self::with_capacity(64)
    }

    /// As [`Self::new`], with room for `capacity` bytes.
    pub fn with_capacity(capacity: usize) -> Self {
        let mut bytes = Vec::with_capacity(capacity.max(HEADER));
        bytes.extend_from_slice(&[0x00, 0x01, 0x00, 0x00]);
        Self { bytes }
    }

    /// Pads with zeros to a multiple of `size` counted from the end of the header.
    fn align(&mut self, size: usize) {
        let body = self.bytes.len() - HEADER;
        let padded = body.next_multiple_of(size);
        self.bytes.resize(HEADER + padded, 0);
    }

    /// An `octet`/`uint8`.
    pub fn u8(&mut self, v: u8) {
        self.bytes.push(v);
    }

    /// An `int8`.
    pub fn i8(&mut self, v: i8) {
        self.bytes.push(v.to_le_bytes()[0]);
    }

    /// A `uint32`.
    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }

    /// An `int32`.
    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }

    /// A `float32`.
    pub fn f32(&mut self, v: f32) {
        self.align(4);
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }

    /// A `float64`.
    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.bytes.extend_from_slice(&v.to_le_bytes());
    }

    /// A `string`. CDR strings cannot hold NUL: anything from the first NUL on is left out.
    pub fn string(&mut self, s: &str) {
        let s = s.split('\0').next().unwrap_or_default();
        self.sequence_len(s.len() + 1);
        self.bytes.extend_from_slice(s.as_bytes());
        self.bytes.push(0);
    }

    /// The element count of a sequence that follows.
    ///
    /// # Panics
    /// Never in practice: a sequence longer than `u32::MAX` elements cannot be in memory as a message
    /// here; it is clamped (and so written wrong) rather than panicking.
    pub fn sequence_len(&mut self, n: usize) {
        self.u32(u32::try_from(n).unwrap_or(u32::MAX));
    }

    /// A `sequence<int8>` (an occupancy grid's cells): the count, then the bytes.
    pub fn i8_sequence(&mut self, values: &[i8]) {
        self.sequence_len(values.len());
        self.bytes.extend(values.iter().map(|v| v.to_le_bytes()[0]));
    }

    /// The payload.
    pub fn finish(self) -> Vec<u8> {
        self.bytes
    }
}

#[cfg(test)]
mod tests {
    use super::super::CdrReader;
    use super::*;

    #[test]
    fn written_payloads_read_back_with_the_alignment_rules() {
        let mut w = CdrWriter::new();
        w.i32(-7);
        w.string("map"); // 4 + 4 bytes: the f64 after it needs no padding ...
        w.u8(3); // ... but after this byte it does (7 bytes of padding).
        w.f64(1.25);
        w.f32(0.5);
        w.i8_sequence(&[-1, 0, 100]);
        w.string("with\0nul");
        let bytes = w.finish();
        assert_eq!(&bytes[..4], &[0, 1, 0, 0]);
        // The f64 starts at body offset 16: 4 (i32) + 8 (string) + 1 (u8) + 3 padding ... to 16.
        assert_eq!(&bytes[4 + 16..4 + 24], &1.25f64.to_le_bytes());
        let mut r = CdrReader::new(&bytes).unwrap();
        assert_eq!(r.i32("a").unwrap(), -7);
        assert_eq!(r.string("b").unwrap(), "map");
        assert_eq!(r.u8("c").unwrap(), 3);
        assert_eq!(r.f64("d").unwrap().to_bits(), 1.25f64.to_bits());
        assert_eq!(r.f32("e").unwrap().to_bits(), 0.5f32.to_bits());
        assert_eq!(r.sequence_len(1, "f").unwrap(), 3);
        assert_eq!(
            [r.i8("g").unwrap(), r.i8("g").unwrap(), r.i8("g").unwrap()],
            [-1, 0, 100]
        );
        assert_eq!(r.string("h").unwrap(), "with");
        assert_eq!(r.remaining(), 0);
    }
}
