//! Plain little-endian CDR (XCDR1), the payload format of rmw_zenoh.
//!
//! rmw_zenoh serializes with Fast-CDR in `DDS_CDR` mode and writes the
//! 4-byte encapsulation header first (`type_support.cpp` @2e635f5,
//! `cdr.cpp` @546a1f4, read for issue 32); on x86 and ARM that header is
//! `00 01 00 00` (CDR_LE, options 0). The rules the [`Writer`] follows and
//! the [`Reader`] expects:
//!
//! - every primitive is aligned to its own size (`u32`/`i32` to 4, `f64`
//!   to 8), measured from the first byte *after* the header;
//! - a string is a `u32` length that counts the terminating NUL, the bytes,
//!   then the NUL;
//! - a fixed array (`float64[36]`) is its elements, with no count;
//! - a sequence (`T[]`) is a `u32` count, then its elements;
//! - a message ends after its last field (no padding), though a reader
//!   accepts up to 3 trailing bytes, as rosbags does.
//!
//! The reader never panics and never allocates more than the input could
//! hold: every length is checked against the bytes that remain.

use thiserror::Error;

/// The encapsulation header of a plain little-endian CDR payload.
pub const ENCAPSULATION_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Bytes of the encapsulation header, the origin of every alignment.
const HEADER_LEN: usize = 4;

/// Trailing bytes a reader tolerates after the last field (rosbags'
/// `deserialize_cdr` allows the same: DDS pads payloads to 4 bytes).
const MAX_TRAILING: usize = 3;

/// Bytes of padding that bring body offset `offset` to a multiple of `n`.
fn padding(offset: usize, n: usize) -> usize {
    (n - offset % n) % n
}

/// Why a payload (or an attachment) could not be read. Offsets count from
/// the first byte of the payload, header included.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum DecodeError {
    #[error("payload of {len} bytes has no 4-byte CDR encapsulation header")]
    NoHeader { len: usize },
    #[error("big-endian CDR (encapsulation 00 00) is not supported; rmw_zenoh writes little-endian (00 01)")]
    BigEndian,
    #[error("unsupported CDR encapsulation {0:02x} {1:02x}; only plain little-endian CDR (00 01) is read")]
    Encapsulation(u8, u8),
    #[error("truncated: {what} needs {needed} bytes at offset {offset}, but only {left} remain")]
    Truncated { what: &'static str, offset: usize, needed: usize, left: usize },
    #[error("string length {len} at offset {offset} is larger than the {left} bytes that remain")]
    StringLength { offset: usize, len: u32, left: usize },
    #[error("string at offset {offset} does not end with NUL")]
    NotTerminated { offset: usize },
    #[error("string at offset {offset} is not UTF-8")]
    NotUtf8 { offset: usize },
    #[error("sequence of {count} elements at offset {offset} cannot fit in the {left} bytes that remain")]
    SequenceLength { offset: usize, count: u32, left: usize },
    #[error("{extra} bytes follow the end of the message (at most 3 bytes of padding are allowed)")]
    TrailingBytes { extra: usize },
    #[error("attachment of {len} bytes; rmw_zenoh's is exactly 33 (i64 sequence, i64 timestamp, 0x10, 16-byte GID)")]
    AttachmentLength { len: usize },
    #[error("attachment byte 16 is {found:#04x}, not the GID's length prefix 0x10")]
    AttachmentGidPrefix { found: u8 },
}

/// Writes one payload: the header, then fields in declaration order.
#[derive(Debug, Clone)]
pub struct Writer {
    buf: Vec<u8>,
}

impl Default for Writer {
    fn default() -> Self {
        Self::new()
    }
}

impl Writer {
    /// A payload holding only the little-endian encapsulation header.
    pub fn new() -> Self {
        Self { buf: ENCAPSULATION_LE.to_vec() }
    }

    /// Zero padding up to a multiple of `n` bytes after the header.
    fn align(&mut self, n: usize) {
        let pad = padding(self.buf.len() - HEADER_LEN, n);
        self.buf.resize(self.buf.len() + pad, 0);
    }

    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A string: length with the NUL, bytes, NUL. A string of 4 GiB or
    /// more (beyond what a `u32` length can say) is cut to fit.
    pub fn string(&mut self, s: &str) {
        let n = s.len().min(u32::MAX as usize - 1);
        self.u32(n as u32 + 1);
        self.buf.extend_from_slice(&s.as_bytes()[..n]);
        self.buf.push(0);
    }

    /// A fixed-size array of doubles: no count, just the elements.
    pub fn f64_array(&mut self, v: &[f64]) {
        for &x in v {
            self.f64(x);
        }
    }

    /// A sequence's element count (saturating at `u32::MAX`); the caller
    /// writes the elements next.
    pub fn sequence_len(&mut self, n: usize) {
        self.u32(u32::try_from(n).unwrap_or(u32::MAX));
    }

    /// The payload so far, header included.
    pub fn as_bytes(&self) -> &[u8] {
        &self.buf
    }

    pub fn into_bytes(self) -> Vec<u8> {
        self.buf
    }
}

/// Reads one payload written by a [`Writer`] or by Fast-CDR.
#[derive(Debug, Clone)]
pub struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    /// Checks the encapsulation header: only plain little-endian CDR is
    /// accepted; the two option bytes are ignored, as Fast-CDR does.
    pub fn new(bytes: &'a [u8]) -> Result<Self, DecodeError> {
        match bytes {
            [0x00, 0x01, _, _, ..] => Ok(Self { bytes, pos: HEADER_LEN }),
            [0x00, 0x00, _, _, ..] => Err(DecodeError::BigEndian),
            [a, b, _, _, ..] => Err(DecodeError::Encapsulation(*a, *b)),
            _ => Err(DecodeError::NoHeader { len: bytes.len() }),
        }
    }

    fn left(&self) -> usize {
        self.bytes.len() - self.pos
    }

    /// The next `n` bytes, or the error naming `what` was being read.
    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], DecodeError> {
        if n > self.left() {
            return Err(DecodeError::Truncated { what, offset: self.pos, needed: n, left: self.left() });
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    /// Skips the padding before a primitive of `n` bytes.
    fn align(&mut self, n: usize, what: &'static str) -> Result<(), DecodeError> {
        self.take(padding(self.pos - HEADER_LEN, n), what).map(|_| ())
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], DecodeError> {
        self.align(N, what)?;
        let mut a = [0; N];
        a.copy_from_slice(self.take(N, what)?);
        Ok(a)
    }

    pub fn u32(&mut self) -> Result<u32, DecodeError> {
        self.array("uint32").map(u32::from_le_bytes)
    }

    pub fn i32(&mut self) -> Result<i32, DecodeError> {
        self.array("int32").map(i32::from_le_bytes)
    }

    pub fn f64(&mut self) -> Result<f64, DecodeError> {
        self.array("float64").map(f64::from_le_bytes)
    }

    /// A NUL-terminated UTF-8 string. A length of 0 (which Fast-CDR also
    /// accepts) reads as the empty string.
    pub fn string(&mut self) -> Result<String, DecodeError> {
        let len = self.u32()?;
        let offset = self.pos;
        if len as usize > self.left() {
            return Err(DecodeError::StringLength { offset, len, left: self.left() });
        }
        let bytes = self.take(len as usize, "string")?;
        let text = match bytes.split_last() {
            None => &[][..],
            Some((0, text)) => text,
            Some(_) => return Err(DecodeError::NotTerminated { offset }),
        };
        String::from_utf8(text.to_vec()).map_err(|_| DecodeError::NotUtf8 { offset })
    }

    /// A fixed-size array of `N` doubles.
    pub fn f64_array<const N: usize>(&mut self) -> Result<[f64; N], DecodeError> {
        let mut a = [0.0; N];
        for x in &mut a {
            *x = self.f64()?;
        }
        Ok(a)
    }

    /// A sequence's element count. Every element takes at least one byte,
    /// so a count larger than the bytes that remain is refused here,
    /// before anyone allocates for it.
    pub fn sequence_len(&mut self) -> Result<usize, DecodeError> {
        let count = self.u32()?;
        if count as usize > self.left() {
            return Err(DecodeError::SequenceLength { offset: self.pos - 4, count, left: self.left() });
        }
        Ok(count as usize)
    }

    /// Ends the payload: at most 3 bytes of padding may follow.
    pub fn finish(self) -> Result<(), DecodeError> {
        match self.left() {
            n if n <= MAX_TRAILING => Ok(()),
            extra => Err(DecodeError::TrailingBytes { extra }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alignment_counts_from_after_the_header() {
        let mut w = Writer::new();
        w.u32(7);
        w.f64(1.0);
        // 4 header + 4 u32 + 4 padding (body offset 4 -> 8) + 8 = 20 bytes;
        // aligning from the buffer's start would have given 16.
        assert_eq!(w.as_bytes().len(), 20, "{:02x?}", w.as_bytes());
        let mut w = Writer::new();
        w.string("ab");
        w.f64(1.0);
        // body: 4 length + "ab\0" = 7, padded to 8, then the double.
        assert_eq!(w.as_bytes().len(), 4 + 8 + 8, "{:02x?}", w.as_bytes());
        assert_eq!(&w.as_bytes()[4..12], &[3, 0, 0, 0, b'a', b'b', 0, 0]);
    }

    #[test]
    fn round_trip_of_every_primitive() {
        let mut w = Writer::new();
        w.i32(-5);
        w.string("héllo");
        w.f64(-0.25);
        w.sequence_len(2);
        w.f64_array(&[1.0, 2.0]);
        w.u32(9);
        let bytes = w.into_bytes();
        let mut r = Reader::new(&bytes).unwrap();
        assert_eq!(r.i32(), Ok(-5));
        assert_eq!(r.string().as_deref(), Ok("héllo"));
        assert_eq!(r.f64(), Ok(-0.25));
        assert_eq!(r.sequence_len(), Ok(2));
        assert_eq!(r.f64_array::<2>(), Ok([1.0, 2.0]));
        assert_eq!(r.u32(), Ok(9));
        assert_eq!(r.finish(), Ok(()));
    }

    #[test]
    fn headers_other_than_little_endian_plain_cdr_are_refused() {
        assert_eq!(Reader::new(&[0, 0, 0, 0, 1, 0, 0, 0]).err(), Some(DecodeError::BigEndian));
        assert_eq!(Reader::new(&[0, 7, 0, 0]).err(), Some(DecodeError::Encapsulation(0, 7)));
        assert_eq!(Reader::new(&[0, 1, 0]).err(), Some(DecodeError::NoHeader { len: 3 }));
        let msg = DecodeError::BigEndian.to_string();
        assert!(msg.contains("big-endian"), "{msg}");
    }

    #[test]
    fn a_huge_string_length_is_an_error_not_an_allocation() {
        let bytes = [0, 1, 0, 0, 0xff, 0xff, 0xff, 0xff, b'a'];
        let err = Reader::new(&bytes).unwrap().string().unwrap_err();
        assert_eq!(err, DecodeError::StringLength { offset: 8, len: u32::MAX, left: 1 });
    }

    #[test]
    fn strings_must_be_terminated_utf8() {
        let unterminated = [0, 1, 0, 0, 2, 0, 0, 0, b'a', b'b'];
        assert_eq!(Reader::new(&unterminated).unwrap().string(), Err(DecodeError::NotTerminated { offset: 8 }));
        let latin1 = [0, 1, 0, 0, 2, 0, 0, 0, 0xe9, 0];
        assert_eq!(Reader::new(&latin1).unwrap().string(), Err(DecodeError::NotUtf8 { offset: 8 }));
        let empty = [0, 1, 0, 0, 0, 0, 0, 0];
        assert_eq!(Reader::new(&empty).unwrap().string().as_deref(), Ok(""));
    }

    #[test]
    fn a_huge_sequence_count_is_refused_before_allocating() {
        let bytes = [0, 1, 0, 0, 0x00, 0x00, 0x00, 0x80];
        let err = Reader::new(&bytes).unwrap().sequence_len().unwrap_err();
        assert_eq!(err, DecodeError::SequenceLength { offset: 4, count: 0x8000_0000, left: 0 });
    }

    #[test]
    fn up_to_three_trailing_bytes_are_padding_four_are_an_error() {
        assert_eq!(Reader::new(&[0, 1, 0, 0, 0, 0, 0]).unwrap().finish(), Ok(()));
        assert_eq!(
            Reader::new(&[0, 1, 0, 0, 0, 0, 0, 0]).unwrap().finish(),
            Err(DecodeError::TrailingBytes { extra: 4 })
        );
    }
}
