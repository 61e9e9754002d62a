//! The formation on a network: the protocol's rules as plain types that
//! own no socket and no clock (start barrier, lock-step gate, inbox,
//! courier), and the zenoh nodes that drive them: the leader, an agent per
//! follower, the monitor that records the run, and the router.
//!
//! Layers, each module using only those of the layers below it:
//!
//! | layer | modules |
//! | --- | --- |
//! | names and wire | [`names`], [`codec`], [`counters`], [`error`] |
//! | protocol rules (no IO, no clock) | [`barrier`], [`latency`], [`inbox`], [`gate`], [`hearing`], [`courier`], [`watch`], [`timebase`], [`clockguard`], [`health`] |
//! | the wall clock, pacing, files | [`clock`], [`timing`], [`checkpoint`] |
//! | zenoh session | [`identity`], [`session`], [`node`] |
//! | shared node parts | [`startup`], [`timesync`], [`telemetry`] |
//! | a run's record (no zenoh) | [`recorder`] (its viewers: `formation_view`'s live page and Foxglove server) |
//! | nodes | [`agent`], [`leader`], [`monitor`] (on the recorder), [`router`] |
//! | a run again | [`replay`] (on the recorder), [`explain`], [`playback`] |

pub mod agent;
pub mod checkpoint;
pub mod clock;
pub mod courier;
pub mod denials;
pub mod identity;
pub mod leader;
pub mod limits;
pub mod monitor;
pub mod node;
pub mod router;
pub mod session;
pub mod startup;
pub mod telemetry;
pub mod timesync;
pub mod timing;

pub use error::Error;

// A run's record and its replay live in formation-replay.
pub use formation_replay::{explain, health, playback, recorder, replay, watch};

// The protocol's rules live in formation-protocol; the nodes here reach them
// by their old paths.
pub use formation_protocol::{
    barrier, clockguard, codec, counters, error, gate, hearing, inbox, latency, names, timebase,
};
