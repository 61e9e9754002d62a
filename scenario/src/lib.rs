//! Scenario files and the communication graph.
//!
//! A scenario is parsed from TOML ([`file`]), then validated once into typed
//! values ([`Scenario`]). Past validation nothing re-checks and nothing
//! panics on user input. The graph ([`graph`]) gives each follower its
//! neighbours, L, H = L + diag(a_i0) and λ_min(H), and enforces Lemma 1.
//!
//! # Examples
//!
//! The paper's scenario (built into the binary), shortened and with a
//! delay, as `--set` changes it; a value out of range is refused with the
//! key it is about.
//!
//! ```
//! use std::path::Path;
//! use formation_scenario::Scenario;
//!
//! let set = ["duration=2".to_string(), "network.delay_steps=3".to_string()];
//! let scenario = Scenario::load(Path::new("paper"), &set).expect("the paper's scenario");
//! assert_eq!((scenario.steps(), scenario.network.delay_steps), (2000, 3), "Δt = 1 ms");
//! assert_eq!(scenario.graph.len(), 4, "four followers");
//!
//! let refused = Scenario::load(Path::new("paper"), &["dt=-0.01".to_string()]).unwrap_err();
//! assert!(refused.to_string().contains("dt"), "{refused}");
//! ```

pub mod args;
pub mod error;
pub mod file;
pub mod generate;
pub mod graph;
pub mod load;
mod overrides;
pub mod recorded;
pub mod scenario;
pub mod shape;
mod syntax;
mod validate;

pub use error::ScenarioError;
pub use graph::Graph;
pub use scenario::{EstimateInit, FaultTarget, FollowerSpec, LinkFault, RobotSource, Ros2Settings, Scenario, Timing};
