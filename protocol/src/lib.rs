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
//! | names and encodings | [`names`], [`wire`] (the estimate's and the pose's messages, docs/model.md §13), [`codec`] (control and telemetry), [`counters`], [`denied`] (access-control reports) |
//! | start-up | [`barrier`] (the start barrier), [`claim`] (which of two processes started for one node keeps it), [`clock_estimate`] (the leader's clock as another node estimates it) and [`clockguard`] (which answers are the leader's) |
//! | receiving | [`inbox`] (checks, the fault table, freshness), [`latency`], [`hearing`] (what was heard, for the record) |
//! | lock-step | [`gate`] (look-ahead, repeats, stalls), [`patience`] (waits that take slow for slow, not gone) |
//! | telemetry | [`telemetry`] (the messages), [`courier`] (what is kept until acknowledged), [`loop_timing`] (how late each step woke) |
//! | safety | [`poses`] (the other robots' poses, for the safety filter) |
//! | one follower | [`follower`]: all of the above for one agent, as one machine |
//!
//! # Examples
//!
//! The paper's four follower machines and the leader's in lock-step, on
//! virtual time over a network of queues (`testing::World`): a fifth of a
//! second of the run, every step of every follower recorded, in no wall
//! time at all.
//!
//! ```
//! use std::path::Path;
//! use std::time::Duration;
//! use formation_protocol::testing::{Faults, World};
//! use formation_scenario::Scenario;
//!
//! let set = ["duration=0.2".to_string(), "timing=lockstep".to_string()];
//! let scenario = Scenario::load(Path::new("paper"), &set).expect("scenario");
//! let mut world = World::new(scenario.clone(), Faults::default());
//! world.start_all();
//! world.drive(Duration::from_secs(60));
//! for i in 0..4 {
//!     assert_eq!(world.samples(i).len() as u64, scenario.steps() + 1, "follower {}", world.id(i));
//! }
//! ```

pub mod barrier;
pub mod claim;
pub mod clock_estimate;
pub mod clockguard;
pub mod codec;
pub mod counters;
pub mod courier;
pub mod denied;
pub mod died;
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
pub mod steering;
pub mod telemetry;
pub mod testing;
pub mod wire;

/// A reading of the caller's clock: the time since an origin it chooses
/// (its monotonic clock's first reading, the run's epoch on the leader's
/// timebase, or a test's zero). Only differences and order matter to the
/// machines here, so a test's virtual time is as good as a clock's.
pub type Now = std::time::Duration;
