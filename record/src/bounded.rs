//! Decoding bytes from the network or a file with an allocation bound, and
//! encoding what it decodes (bincode 2, standard configuration, through
//! serde). Every decoder of the project's network messages and files goes
//! through [`decode_bounded`].
//!
//! # Examples
//!
//! ```
//! use formation_record::bounded::{decode_bounded, encode_value};
//!
//! let bytes = encode_value(&(7u32, String::from("follower")));
//! assert_eq!(decode_bounded::<(u32, String)>(&bytes), Some((7, "follower".to_string())));
//! // A string that claims more bytes than its input could hold is refused unread.
//! assert_eq!(decode_bounded::<String>(&[0xfc, 0xff, 0xff, 0xff, 0x7f]), None);
//! ```

use serde::Serialize;

pub(crate) fn config() -> bincode::config::Configuration {
    bincode::config::standard()
}

/// Every decoder's allocation bound, as a multiple of the input's length:
/// bincode claims a value's size in memory (a varint `u64` of one byte
/// claims 8, a `u128` 16), and a string or byte buffer its declared length,
/// before allocating it. A declared length beyond this is refused unread.
pub const ALLOCATION_FACTOR: usize = 16;

/// The largest input [`decode_bounded`] takes (64 MiB: a hearing record
/// holds about 0.2 B per follower-step, so this is some 300 million
/// follower-steps; the bound times [`ALLOCATION_FACTOR`] fits a 32-bit
/// robot computer's address space).
pub const MAX_INPUT: usize = 1 << 26;

/// Decodes a whole bincode value (standard configuration) from `bytes`,
/// however its length fields lie: strings and byte buffers claim their
/// declared length against a limit of at most 2 × [`ALLOCATION_FACTOR`] ×
/// `bytes.len()` (4 KiB for the smallest inputs) before anything is
/// allocated, and a sequence's first allocation is capped by serde (1 MiB)
/// and grows only with elements actually read. The claims count an empty
/// string or list as 8 bytes where it takes 24 in memory, so an input made
/// of empty elements can take up to 48 × its length in one allocation and
/// 72 × at the peak (measured by `tests/it/fuzz_decoders.rs`): bounded, but
/// for a 64 MiB file that is 3 GiB. bincode's limit is a type
/// parameter, so the input's length picks the smallest power-of-two limit
/// above it. None if it does not decode, leaves bytes over, or is
/// longer than [`MAX_INPUT`]. Every decoder of the project's network
/// messages and files goes through this one.
pub fn decode_bounded<T: serde::de::DeserializeOwned>(bytes: &[u8]) -> Option<T> {
    use bincode::config::standard;
    macro_rules! limited {
        ($limit:expr) => {
            bincode::serde::decode_from_slice::<T, _>(bytes, standard().with_limit::<{ $limit }>())
        };
    }
    if bytes.len() > MAX_INPUT {
        return None;
    }
    let need = bytes.len().saturating_mul(ALLOCATION_FACTOR);
    let result = match need {
        n if n <= 1 << 12 => limited!(1 << 12),
        n if n <= 1 << 14 => limited!(1 << 14),
        n if n <= 1 << 16 => limited!(1 << 16),
        n if n <= 1 << 18 => limited!(1 << 18),
        n if n <= 1 << 20 => limited!(1 << 20),
        n if n <= 1 << 22 => limited!(1 << 22),
        n if n <= 1 << 24 => limited!(1 << 24),
        n if n <= 1 << 26 => limited!(1 << 26),
        n if n <= 1 << 28 => limited!(1 << 28),
        n if n <= 1 << 30 => limited!(1 << 30),
        _ => return None,
    };
    match result {
        Ok((v, used)) if used == bytes.len() => Some(v),
        _ => None,
    }
}

/// Encodes any value as [`decode_bounded`] decodes it (bincode 2, standard
/// configuration; encoding into a Vec cannot fail for the project's types).
pub fn encode_value<T: Serialize>(v: &T) -> Vec<u8> {
    bincode::serde::encode_to_vec(v, config()).unwrap_or_default()
}
