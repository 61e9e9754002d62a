//! The 33-byte attachment rmw_zenoh puts on every sample.
//!
//! rmw_zenoh's subscriptions drop a sample without an attachment ("Unable
//! to obtain attachment", `rmw_subscription_data.cpp` @a72659a). Current
//! rmw_zenoh (`attachment_helpers.cpp` @534747d) writes it with zenoh-ext's
//! serializer:
//!
//! | bytes  | meaning |
//! |--------|---------|
//! | 0..8   | sequence number, i64 LE, 1 for a publisher's first sample |
//! | 8..16  | source timestamp, i64 LE, ns since the Unix epoch |
//! | 16     | `0x10`: zenoh-ext's LEB128 length of the 16-byte array |
//! | 17..33 | the publisher's GID |
//!
//! Older rmw_zenoh releases named each field in the attachment; only this
//! form is read by current Jazzy, Kilted and Rolling builds.

use crate::cdr::DecodeError;
use sha2::{Digest, Sha256};

/// Bytes in an attachment.
pub const LEN: usize = 33;

/// zenoh-ext's length prefix of a 16-byte array (LEB128 of 16).
const GID_PREFIX: u8 = 0x10;

/// One sample's attachment.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Attachment {
    pub sequence: i64,
    pub source_timestamp_ns: i64,
    pub gid: [u8; 16],
}

/// The attachment of a sample: sequence number, source time and the
/// publisher's GID.
pub fn encode(seq: i64, source_timestamp_ns: i64, gid: [u8; 16]) -> [u8; LEN] {
    let mut a = [0; LEN];
    a[0..8].copy_from_slice(&seq.to_le_bytes());
    a[8..16].copy_from_slice(&source_timestamp_ns.to_le_bytes());
    a[16] = GID_PREFIX;
    a[17..].copy_from_slice(&gid);
    a
}

/// Reads an attachment: exactly 33 bytes with `0x10` at byte 16.
pub fn decode(bytes: &[u8]) -> Result<Attachment, DecodeError> {
    let a: &[u8; LEN] = bytes.try_into().map_err(|_| DecodeError::AttachmentLength { len: bytes.len() })?;
    if a[16] != GID_PREFIX {
        return Err(DecodeError::AttachmentGidPrefix { found: a[16] });
    }
    let i64_at = |i: usize| {
        let mut b = [0; 8];
        b.copy_from_slice(&a[i..i + 8]);
        i64::from_le_bytes(b)
    };
    let mut gid = [0; 16];
    gid.copy_from_slice(&a[17..]);
    Ok(Attachment { sequence: i64_at(0), source_timestamp_ns: i64_at(8), gid })
}

/// A publisher's GID: the first 16 bytes of SHA-256 of its liveliness
/// token. rmw_zenoh uses XXH3-128 of the same key; receivers only pass the
/// GID on in `rmw_message_info_t`, so any stable 16 bytes per publisher
/// serve (only `ros2 topic info -v` would show the difference).
pub fn gid_of(token_key: &str) -> [u8; 16] {
    let digest = Sha256::digest(token_key.as_bytes());
    let mut gid = [0; 16];
    gid.copy_from_slice(&digest[..16]);
    gid
}

/// A publisher's sequence numbers: 1, 2, 3, … as rmw_zenoh counts them.
#[derive(Debug, Clone)]
pub struct Sequence {
    next: i64,
}

impl Default for Sequence {
    fn default() -> Self {
        Self::new()
    }
}

impl Sequence {
    pub fn new() -> Self {
        Self { next: 1 }
    }

    /// The number for the next sample (wrapping after `i64::MAX`, which no
    /// run reaches).
    pub fn next_number(&mut self) -> i64 {
        let n = self.next;
        self.next = n.wrapping_add(1);
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `attachment_helpers.cpp`: sequence 1, then the timestamp, 0x10, the GID.
    #[test]
    fn golden_bytes() {
        let gid: [u8; 16] = core::array::from_fn(|i| 0xa0 + i as u8);
        let a = encode(1, 0x0102_0304_0506_0708, gid);
        let mut want = vec![1, 0, 0, 0, 0, 0, 0, 0, 8, 7, 6, 5, 4, 3, 2, 1, 0x10];
        want.extend_from_slice(&gid);
        assert_eq!(a.to_vec(), want);
        assert_eq!(decode(&a), Ok(Attachment { sequence: 1, source_timestamp_ns: 0x0102_0304_0506_0708, gid }));
        let neg = encode(-2, -3, [0; 16]);
        assert_eq!(decode(&neg).map(|x| (x.sequence, x.source_timestamp_ns)), Ok((-2, -3)));
    }

    #[test]
    fn wrong_lengths_and_prefixes_are_refused() {
        let a = encode(5, 6, [9; 16]);
        for len in [0, 1, 16, 17, 32] {
            assert_eq!(decode(&a[..len]), Err(DecodeError::AttachmentLength { len }));
        }
        let mut long = a.to_vec();
        long.push(0);
        assert_eq!(decode(&long), Err(DecodeError::AttachmentLength { len: 34 }));
        let mut bad = a;
        bad[16] = 0x0f;
        assert_eq!(decode(&bad), Err(DecodeError::AttachmentGidPrefix { found: 0x0f }));
    }

    #[test]
    fn gid_is_the_head_of_sha256() {
        // SHA-256("abc") = ba7816bf 8f01cfea 414140de 5dae2223 b00361a3 ...
        let want = [0xba, 0x78, 0x16, 0xbf, 0x8f, 0x01, 0xcf, 0xea, 0x41, 0x41, 0x40, 0xde, 0x5d, 0xae, 0x22, 0x23];
        assert_eq!(gid_of("abc"), want);
    }

    #[test]
    fn sequence_starts_at_one() {
        let mut s = Sequence::new();
        assert_eq!([s.next_number(), s.next_number(), s.next_number()], [1, 2, 3]);
    }
}
