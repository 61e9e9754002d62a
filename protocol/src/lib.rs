//! The formation's network protocol as plain state machines, in the style
//! of quinn-proto: each is fed what arrived and the time, and answers what
//! to send, what to record and when it next wants to be woken. The zenoh
//! nodes (`formation-net`) own the sockets, the threads and the clocks, and
//! only translate.
//!
//! This crate must never import zenoh, tokio or any other runtime, and no
//! source file of it reads a clock: time is always an argument ([`Now`]).
//! So every rule here runs in a test on virtual time, in microseconds.
//!
//! | part | modules |
//! | --- | --- |
//! | names and encodings | [`names`], [`codec`], [`counters`], [`error`], [`denied`] (access-control reports) |
//! | start-up | [`barrier`] (the start barrier), [`claim`] (which of two processes started for one node keeps it), [`clock_estimate`] (the leader's clock as another node estimates it) and [`clockguard`] (which answers are the leader's) |
//! | receiving | [`inbox`] (checks, the fault table, freshness), [`latency`], [`hearing`] (what was heard, for the record) |
//! | lock-step | [`gate`] (look-ahead, repeats, stalls), [`patience`] (waits that take slow for slow, not gone) |
//! | telemetry | [`telemetry`] (the messages), [`courier`] (what is kept until acknowledged), [`loop_timing`] (how late each step woke) |
//! | safety | [`poses`] (the other robots' poses, for the safety filter) |
//! | one follower | [`follower`]: all of the above for one agent, as one machine |

pub mod barrier;
pub mod claim;
pub mod clock_estimate;
pub mod clockguard;
pub mod codec;
pub mod counters;
pub mod courier;
pub mod denied;
pub mod died;
pub mod error;
pub mod follower;
pub mod gate;
pub mod hearing;
pub mod inbox;
pub mod latency;
pub mod leader;
pub mod loop_timing;
pub mod names;
pub mod patience;
pub mod poses;
pub mod telemetry;
pub mod testing;

pub use error::Error;

/// A reading of the caller's clock: the time since an origin it chooses
/// (its monotonic clock's first reading, the run's epoch on the leader's
/// timebase, or a test's zero). Only differences and order matter to the
/// machines here, so a test's virtual time is as good as a clock's.
pub type Now = std::time::Duration;
