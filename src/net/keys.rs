//! The key expressions of a run, and the names nodes go by in them.
//!
//! | key | who publishes | payload |
//! | --- | --- | --- |
//! | `estimate/<id>` | leader (id 0), follower id | [`formation_topology::wire::EstimateMsg`] (SPEC §13) |
//! | `telemetry/<id>` | leader (id 0), follower id | [`crate::net::telemetry::Telemetry`] |
//! | `control/hello/<node>` | every node, until the start | empty |
//! | `control/ready/<node>` | agents and monitor, until the start | [`crate::net::barrier::Ready`] |
//! | `control/start` | leader, every 100 ms during the run | [`crate::net::barrier::Start`] |
//! | `control/ack` | monitor, every 100 ms during the run | [`crate::net::telemetry::Ack`] |
//!
//! `<node>` is `0` for the leader, the follower id, or `monitor`.

use crate::net::session;

/// The key expressions of one run.
#[derive(Clone, Debug)]
pub struct Keys {
    pub run: String,
}

impl Keys {
    pub fn new(run: &str) -> Self {
        Self { run: run.to_string() }
    }
    pub fn estimate(&self, id: u32) -> String {
        session::key(&self.run, &format!("estimate/{id}"))
    }
    pub fn telemetry(&self, id: u32) -> String {
        session::key(&self.run, &format!("telemetry/{id}"))
    }
    pub fn telemetry_all(&self) -> String {
        session::key(&self.run, "telemetry/*")
    }
    pub fn hello(&self, node: &str) -> String {
        session::key(&self.run, &format!("control/hello/{node}"))
    }
    pub fn ready(&self, node: &str) -> String {
        session::key(&self.run, &format!("control/ready/{node}"))
    }
    pub fn ready_all(&self) -> String {
        session::key(&self.run, "control/ready/*")
    }
    pub fn ack(&self) -> String {
        session::key(&self.run, "control/ack")
    }
    pub fn start(&self) -> String {
        session::key(&self.run, "control/start")
    }
    /// The leader refuses the run before its start (the reason, UTF-8).
    pub fn abort(&self) -> String {
        session::key(&self.run, "control/abort")
    }
}

/// The last chunk of a key expression (`…/estimate/3` → `3`).
pub fn last_chunk(key: &str) -> &str {
    key.rsplit('/').next().unwrap_or("")
}

/// Node name of the monitor in control keys.
pub const MONITOR: &str = "monitor";
/// Node name of the leader in control keys (its wire id).
pub const LEADER_NODE: &str = "0";
