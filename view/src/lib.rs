//! A formation run's viewers: the live page ([`web`]: one embedded page,
//! the run's frames as server-sent events, a playback's controls) and the
//! Foxglove WebSocket server ([`foxglove`]: run.mcap's channels, fed rows
//! through [`formation_record::LiveSink`]). Both are fed by whoever
//! records or replays a run (the monitor, a playback) and are on no
//! control path: a slow viewer skips frames, it never holds the run.
//!
//! This crate never imports zenoh or a node: it knows a run only as rows,
//! events and JSON frames.
//!
//! # Examples
//!
//! The live page's state ([`web::Live`]): the scene once, then a frame per
//! update; no viewer is connected until a browser opens the page.
//!
//! ```
//! use formation_view::web::Live;
//!
//! let live = Live::new(r#"{"followers":[1,2,3,4]}"#.to_string());
//! live.publish(r#"{"k":0}"#.to_string(), String::new());
//! assert_eq!(live.viewers(), 0);
//! ```

pub mod foxglove;
pub mod web;
