//! A formation run's viewers: the live page ([`web`]: one embedded page,
//! the run's frames as server-sent events, a playback's controls) and the
//! Foxglove WebSocket server ([`foxglove`]: run.mcap's channels, fed rows
//! through [`formation_record::LiveSink`]). Both are fed by whoever
//! records or replays a run (the monitor, a playback) and are on no
//! control path: a slow viewer skips frames, it never holds the run.
//!
//! This crate never imports zenoh or a node: it knows a run only as rows,
//! events and JSON frames.

pub mod error;
pub mod foxglove;
pub mod web;

pub use error::ViewError;
