//! A networked run's record, and the same record again. The monitor node
//! feeds the [`recorder::Recorder`] with telemetry payloads and the time;
//! it writes the run folder, judges the run ([`health`]) and says when it
//! ended ([`watch`]), and whether a real-time run kept its period
//! ([`period`]). `formation replay` runs the hearing record through
//! the same steps ([`replay`]), sets each fault beside its model
//! ([`explain`]) and plays a finished run to the live page or Foxglove
//! ([`playback`]).
//!
//! This crate must never import zenoh, tokio or a node of `formation-net`:
//! an offline command reads a run without a network stack.

pub mod explain;
pub mod health;
pub mod period;
#[cfg(feature = "playback")]
pub mod playback;
pub mod recorder;
pub mod replay;
pub mod watch;
