//! Scenario files and the communication graph.
//!
//! A scenario is parsed from TOML ([`file`]), then validated once into typed
//! values ([`Scenario`]). Past validation nothing re-checks and nothing
//! panics on user input. The graph ([`graph`]) gives each follower its
//! neighbours, L, H = L + diag(a_i0) and λ_min(H), and enforces Lemma 1.
//! [`wire`] is the format of the messages of docs/model.md §13.

pub mod args;
pub mod error;
pub mod file;
pub mod generate;
pub mod graph;
pub mod scenario;
pub mod wire;

pub use error::ScenarioError;
pub use graph::Graph;
pub use scenario::{EstimateInit, FaultTarget, FollowerSpec, LinkFault, RobotSource, Ros2Settings, Scenario, Timing};
