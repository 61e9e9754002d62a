//! The monitor (the `monitor` binary): subscribes to every node's
//! telemetry, shows a live line of the formation error per follower and the
//! worst one, and writes the same run folder as `formation sim` (through
//! [`formation_record::RunWriter`], [`formation_record::MetricsAccumulator`]
//! and [`formation_record::Summary`], so a lock-step run gives a
//! byte-identical `summary.json`) plus `network.json` with each node's
//! message counters. When its shutdown future resolves (the binaries':
//! Ctrl-C or SIGTERM) it writes everything received so far, and
//! `network.json` names the signal (the binary then exits with status 130
//! for SIGINT or 143 for SIGTERM).
//!
//! What it records is [`formation_recorder::Recorder`]'s job (the same
//! recorder replays and playbacks use); this module is the node around
//! it: its arguments ([`args`]), and the zenoh side ([`run`] and its loop,
//! in `node`).

mod args;
mod deaths;
mod node;

pub use args::{MonitorArgs, WebArgs};
pub use node::{model_errors, run};
