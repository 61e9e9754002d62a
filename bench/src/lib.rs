//! The formation's benchmarks, a crate of their own so that the shipped
//! nodes carry none of them: the simulator's speed ([`sim`], `formation
//! bench`) and the network's ([`net`], `formation bench-net`), with the
//! floor of plain zenoh ([`floor`]: its processes are the command line's
//! hidden `formation bench-floor`), the hearing record's cost ([`hearing`]),
//! the stand-in robots' ([`ros2`]) and round trips between namespaces
//! ([`netns`]), and the networked formation at nominal timing against its
//! model ([`verify`], `formation verify`). Every figure is measured here,
//! never by timing a test.
//!
//! # Examples
//!
//! The simulator's speed, as `formation bench` measures it, for a short
//! run of the paper's formation (the figure itself belongs to the command,
//! never to a test):
//!
//! ```
//! use std::path::Path;
//! use formation_scenario::Scenario;
//!
//! let paper = Scenario::load(Path::new("paper"), &[]).expect("scenario");
//! let m = formation_bench::sim::measure(&paper, 200, false, 1, 1).expect("measured");
//! assert_eq!((m.followers, m.threads), (4, 1));
//! assert!(m.follower_steps_per_second() > 0.0);
//! ```

pub mod floor;
pub mod hearing;
pub mod net;
pub mod netns;
pub mod ros2;
pub mod sim;
pub mod verify;
