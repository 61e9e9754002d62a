//! The monitor (the `monitor` binary): subscribes to every node's
//! telemetry, shows a live line of the formation error per follower and the
//! worst one, and writes the same run folder as `formation sim` (through
//! [`formation_record::RunWriter`], [`formation_record::MetricsAccumulator`]
//! and [`formation_record::Summary`], so a lock-step run gives a
//! byte-identical `summary.json`) plus `network.json` with each node's
//! message counters. Ctrl-C or SIGTERM: writes everything received so far
//! and exits with status 130 (SIGINT) or 143 (SIGTERM).
//!
//! | module | its job |
//! | --- | --- |
//! | [`args`] | the command line ([`MonitorArgs`], [`WebArgs`]) |
//! | `stream` | one node's batches put back in step order, and checked |
//! | `recorder` | the [`Recorder`]: telemetry in, the run folder out |
//! | `network_json` | `network.json` |
//! | `live` | the live line and the live page's JSON |
//! | `node` | the zenoh side: [`run`] and its loop |

mod args;
mod live;
mod network_json;
mod node;
mod recorder;
mod stream;

pub use crate::watch::Ending;
pub use args::{MonitorArgs, WebArgs};
pub use node::run;
pub use recorder::{model_errors, Recorder};
pub use stream::Gap;
