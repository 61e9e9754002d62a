//! What crosses the network (docs/model.md §13): a small header and the estimate
//! payload, encoded with bincode 2 (standard config) through serde.
//!
//! Decoding checks what can be checked from the bytes alone: the format
//! version, that the message decodes completely and that every number is
//! finite. Whether the sender is a neighbour, matches its key, or is stale
//! is for the receiving node to decide ([`Reject`] names those too).

use formation_leader::LeaderState;
use formation_record::bounded::{decode_bounded, encode_value};
use serde::{Deserialize, Serialize};

/// Bumped on any change of the encoding.
pub const FORMAT_VERSION: u16 = 5;

/// Leader id on the wire.
pub const LEADER_ID: u32 = 0;

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub version: u16,
    /// 0 for the leader, else the follower id.
    pub sender: u32,
    /// The step k the payload belongs to.
    pub step: u64,
    /// t = k Δt, s.
    pub time_s: f64,
    /// When the sender published it, on the run's timebase (the leader's
    /// clock), ns; 0 where not known. For measuring one-way latency only:
    /// control never reads it.
    pub sent_ns: i64,
}

/// An estimate message: from the leader, its true state; from follower i,
/// (P_ir, Ṗ_ir, v_ir, ω_ir) and whether that estimate is fresh (docs/model.md §14:
/// not held through an isolation since it last came from the leader; the
/// leader's is always fresh). Format 2 added `fresh`, format 5 `term`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EstimateMsg {
    pub header: Header,
    pub state: LeaderState,
    pub fresh: bool,
    /// The leader's term (docs/model.md §14): from the leader, its own (1
    /// for the leader the run started with, one more for each standby that
    /// took it over); from a follower, the highest it has heard from the
    /// leader (0: none yet). A follower uses the leader's messages of the
    /// highest term it has heard only.
    pub term: u32,
}

/// Why a received message was not used.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Reject {
    /// Not decodable, trailing bytes, or too short.
    Malformed,
    /// Another format version.
    Version,
    /// A non-finite number.
    NonFinite,
    /// The header names another sender than the key it came on.
    WrongSender,
    /// The sender is not a neighbour (or the leader, for one that does not hear it).
    NotNeighbour,
    /// Older than a step already used from that sender.
    Stale,
    /// A step further ahead of the receiver's than any genuine sender can be.
    Future,
    /// From a leader of an older term than one already heard: a leader
    /// that a standby took the run over from (docs/model.md §14).
    OldTerm,
}

/// Encodes an estimate message.
pub fn encode(msg: &EstimateMsg) -> Vec<u8> {
    encode_value(msg)
}

/// Decodes and checks version and finiteness.
///
/// ```
/// use formation_leader::LeaderState;
/// use formation_plant::Pose;
/// use formation_protocol::wire::{decode, encode, EstimateMsg, Header, Reject, FORMAT_VERSION};
///
/// let header = Header { version: FORMAT_VERSION, sender: 3, step: 42, time_s: 0.042, sent_ns: 0 };
/// let state = LeaderState { pose: Pose::new(1.0, 2.0, 0.5), pose_rate: Pose::new(0.1, 0.2, 0.3), v: 1.0, w: -0.5 };
/// let msg = EstimateMsg { header, state, fresh: true, term: 1 };
/// let bytes = encode(&msg);
/// assert_eq!(decode(&bytes), Ok(msg));
/// assert_eq!(decode(&bytes[..bytes.len() - 1]), Err(Reject::Malformed));
/// ```
pub fn decode(bytes: &[u8]) -> Result<EstimateMsg, Reject> {
    let msg: EstimateMsg = decode_bounded(bytes).ok_or(Reject::Malformed)?;
    if msg.header.version != FORMAT_VERSION {
        return Err(Reject::Version);
    }
    if !msg.header.time_s.is_finite() || !msg.state.is_finite() {
        return Err(Reject::NonFinite);
    }
    Ok(msg)
}

/// A robot's pose message (docs/model.md §16), published only where the
/// scenario turns the safety filter on: follower `sender`'s robot's pose
/// [x, y, θ] at step k, the one its step k ran on (odometry for a velocity
/// robot). Its header's version is [`FORMAT_VERSION`]. `left`: the
/// robot's last pose, where it stopped, from a follower that leaves the run
/// before step k (format 4).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseMsg {
    pub header: Header,
    pub pose: [f64; 3],
    pub left: bool,
}

pub fn encode_pose(msg: &PoseMsg) -> Vec<u8> {
    encode_value(msg)
}

/// Decodes a pose message and checks its version and finiteness.
pub fn decode_pose(bytes: &[u8]) -> Result<PoseMsg, Reject> {
    let msg: PoseMsg = decode_bounded(bytes).ok_or(Reject::Malformed)?;
    if msg.header.version != FORMAT_VERSION {
        return Err(Reject::Version);
    }
    if !msg.header.time_s.is_finite() || !msg.pose.iter().all(|v| v.is_finite()) {
        return Err(Reject::NonFinite);
    }
    Ok(msg)
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_plant::Pose;

    fn msg() -> EstimateMsg {
        EstimateMsg {
            header: Header { version: FORMAT_VERSION, sender: 3, step: 42, time_s: 0.042, sent_ns: 0 },
            state: LeaderState { pose: Pose::new(1.0, 2.0, 0.5), pose_rate: Pose::new(0.1, 0.2, 0.3), v: 1.0, w: -0.5 },
            fresh: false,
            term: 2,
        }
    }

    #[test]
    fn round_trip() {
        assert_eq!(decode(&encode(&msg())), Ok(msg()));
        let pose = PoseMsg { header: msg().header, pose: [1.0, -2.0, 3.0], left: true };
        assert_eq!(decode_pose(&encode_pose(&pose)), Ok(pose));
    }

    #[test]
    fn bad_pose_messages_are_refused() {
        let pose = PoseMsg { header: msg().header, pose: [1.0, f64::INFINITY, 3.0], left: false };
        assert_eq!(decode_pose(&encode_pose(&pose)), Err(Reject::NonFinite));
        let bytes = encode_pose(&PoseMsg { header: msg().header, pose: [0.0; 3], left: false });
        assert_eq!(decode_pose(&bytes[..bytes.len() - 1]), Err(Reject::Malformed));
        assert_eq!(decode_pose(&encode(&msg())), Err(Reject::Malformed), "an estimate is not a pose");
        let mut old = PoseMsg { header: msg().header, pose: [0.0; 3], left: false };
        old.header.version = 2;
        assert_eq!(decode_pose(&encode_pose(&old)), Err(Reject::Version));
    }

    #[test]
    fn garbage_truncation_and_trailing_bytes_are_malformed() {
        let bytes = encode(&msg());
        assert_eq!(decode(&bytes[..bytes.len() - 1]), Err(Reject::Malformed));
        let mut long = bytes.clone();
        long.push(0);
        assert_eq!(decode(&long), Err(Reject::Malformed));
        assert_eq!(decode(b""), Err(Reject::Malformed));
        assert!(decode(b"hello, formation").is_err());
    }

    #[test]
    fn non_finite_and_foreign_versions_are_rejected() {
        let mut m = msg();
        m.state.v = f64::NAN;
        assert_eq!(decode(&encode(&m)), Err(Reject::NonFinite));
        let mut m = msg();
        m.header.version = 99;
        assert_eq!(decode(&encode(&m)), Err(Reject::Version));
    }
}
