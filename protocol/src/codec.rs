//! The encoding of control and telemetry payloads (bincode 2, standard
//! configuration; decoded with the allocation bound of
//! `formation_record::bounded::decode_bounded`); estimate messages have their
//! own format (docs/model.md §13, `crate::wire`).

use serde::{Deserialize, Serialize};

/// Encodes a control or telemetry payload.
pub fn encode<T: Serialize>(v: &T) -> Vec<u8> {
    formation_record::bounded::encode_value(v)
}

/// Decodes a control or telemetry payload (None if malformed, has bytes
/// over, or declares more than its length could hold).
pub fn decode<T: for<'de> Deserialize<'de>>(bytes: &[u8]) -> Option<T> {
    formation_record::bounded::decode_bounded(bytes)
}
