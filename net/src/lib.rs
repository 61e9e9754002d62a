//! The formation on zenoh: the nodes. Each node is a translation between
//! zenoh and the rules of `formation-protocol` (the follower's machine, the
//! start barrier, the lock-step gate): subscriber callbacks feed the rules,
//! a loop asks them what to send and when to wake, and performs it. The
//! leader, an agent per follower, the monitor (recording through
//! `formation-replay`'s `Recorder`, viewed through `formation-view`) and
//! the router.
//!
//! This crate holds what needs zenoh, tokio, a thread or a clock, and
//! nothing else: a rule that can be decided from what arrived and the time
//! belongs in `formation-protocol`, where tests run it on virtual time.
//!
//! | part | modules |
//! | --- | --- |
//! | the one clock of a node, and the run's timebase | [`clock`] (the node's clock, which a test can mock, and the timebase), [`clock_sync`] (asks and answers the leader's clock on zenoh), [`timer`] (a precise sleep for a loop that is a task) |
//! | zenoh session | [`identity`] (the topology's access policy), [`session`], [`limits`], [`node`] |
//! | shared node parts | [`startup`] (the barrier on zenoh), [`telemetry`] (delivery and acknowledgements), [`courier`] (its thread), [`checkpoint`], [`denials`] |
//! | nodes | [`agent`], [`leader`], [`monitor`], [`router`] |
//! | ROS 2 (rmw_zenoh's wire) | [`ros2`]: the formation's topics, robots driven through `cmd_vel` and `odom`, the stand-in robot |
//!
//! # Examples
//!
//! A node's one clock ([`clock::Clock`]), mocked as a test of a node's loop
//! does: an hour passes in no wall time, to the nanosecond.
//!
//! ```
//! use std::time::Duration;
//! use formation_net::clock::Clock;
//!
//! let clock = Clock::mock(1_700_000_000_000_000_000);
//! let began = std::time::Instant::now();
//! clock.sleep_until_mono(Duration::from_secs(3600));
//! assert_eq!(clock.mono(), Duration::from_secs(3600));
//! assert_eq!(clock.unix_ns(), 1_700_003_600_000_000_000);
//! assert!(began.elapsed() < Duration::from_secs(60), "the hour took no wall time");
//! ```

pub mod agent;
pub mod checkpoint;
pub mod clock;
pub mod clock_sync;
pub mod courier;
pub mod denials;
pub mod died;
pub mod identity;
pub mod lead_loop;
pub mod leader;
pub mod leave;
pub mod limits;
pub mod monitor;
pub mod node;
pub mod ros2;
pub mod router;
pub mod session;
pub mod standby;
pub mod startup;
pub mod telemetry;
pub mod timer;
