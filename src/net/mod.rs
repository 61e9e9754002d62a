//! The networked nodes (agent, leader, monitor, router) and what they share.
pub mod agent;
pub mod barrier;
pub mod bench;
pub mod checkpoint;
pub mod codec;
pub mod counters;
pub mod courier;
pub mod inbox;
pub mod keys;
pub mod leader;
pub mod monitor;
pub mod node;
pub mod session;
pub mod telemetry;
pub mod timing;
