//! What a formation's traffic is, enforced by zenoh on every link a node
//! receives from: no certified node can make others wait, fill their
//! memory or their CPU using only the keys it may publish on.
//!
//! Every node's and the router's session gets, on ingress, unless its
//! `--config` file sets the section itself:
//!
//! - `low_pass_filter`: a size limit per key (an estimate is about 83
//!   bytes: 1 KiB; a telemetry batch of `network.telemetry_batch` steps:
//!   [`telemetry_limit`]; control messages 64 KiB). Larger puts are dropped
//!   before they are decoded or forwarded.
//! - Real-time runs only (lock-step estimates are needed, every one, and
//!   the loops wait for them by design): `qos/network` overwrites every put
//!   under `formation/**` to `congestion_control: drop`, so a client that
//!   publishes with `Block` cannot make a router (or a peer) wait for a
//!   slow link.
//!
//! No `downsampling`: zenoh keeps one clock per rule and transport and lets
//! through the first of two messages that arrive together, so batched
//! estimates lose their newest. Measured (paper scenario, real time, client
//! mode, 10 s, 2-core VM, two runs each): one rule per estimate key at ten
//! times the step rate dropped 337 and 737 of 90,009 estimates; none without.
//! A flood is held by the rest: dropped when a queue is full, never waited
//! for, never larger than its key allows.
//!
//! A router that forwards real-time traffic runs two worker threads
//! ([`crate::session::ROUTER_RUNTIME`]): one client cannot hold the only one.

use serde_json::{json, Value};

use formation_topology::{Scenario, Timing};

/// Largest estimate put, bytes (one is about 83).
pub const ESTIMATE_BYTES: u64 = 1024;
/// Largest control put (hello, ready, start, abort, ack, time), bytes.
pub const CONTROL_BYTES: u64 = 64 * 1024;
/// Telemetry of one step is about 155 bytes; this much room per step.
pub const TELEMETRY_STEP_BYTES: u64 = 512;
/// Room for a batch's events, link figures and framing, bytes.
pub const TELEMETRY_EXTRA_BYTES: u64 = 64 * 1024;

/// Largest telemetry put of a run whose batches hold `batch` steps.
pub fn telemetry_limit(batch: u32) -> u64 {
    u64::from(batch.max(1)) * TELEMETRY_STEP_BYTES + TELEMETRY_EXTRA_BYTES
}

/// What a run's traffic is, as far as the limits need it.
#[derive(Clone, Debug, PartialEq)]
pub struct Traffic {
    /// Real time (droppable) or lock-step.
    pub realtime: bool,
    /// Largest telemetry put, bytes.
    pub telemetry_bytes: u64,
}

impl Traffic {
    pub fn of(scenario: &Scenario) -> Self {
        Traffic {
            realtime: scenario.timing == Timing::Realtime,
            telemetry_bytes: telemetry_limit(scenario.network.telemetry_batch),
        }
    }

    /// A node that does not know the scenario (a router started by hand):
    /// size limits only, for batches of up to 1,000 steps.
    pub fn unknown() -> Self {
        Traffic { realtime: false, telemetry_bytes: telemetry_limit(1000) }
    }

    /// The zenoh configuration sections, by key.
    pub fn sections(&self) -> Vec<(&'static str, Value)> {
        let mut out = vec![(
            "low_pass_filter",
            json!([
                { "id": "formation-estimate-size", "flows": ["ingress"], "messages": ["put"],
                  "key_exprs": ["formation/*/estimate/**"], "size_limit": ESTIMATE_BYTES },
                { "id": "formation-telemetry-size", "flows": ["ingress"], "messages": ["put"],
                  "key_exprs": ["formation/*/telemetry/**"], "size_limit": self.telemetry_bytes },
                { "id": "formation-control-size", "flows": ["ingress"], "messages": ["put", "query", "reply"],
                  "key_exprs": ["formation/*/control/**"], "size_limit": CONTROL_BYTES },
            ]),
        )];
        if self.realtime {
            out.push((
                "qos/network",
                json!([{ "id": "formation-never-block", "flows": ["ingress"], "messages": ["put"],
                         "key_exprs": ["formation/**"], "overwrite": { "congestion_control": "drop" } }]),
            ));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper(timing: &str) -> Scenario {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        Scenario::load(&path, &[format!("timing={timing}")]).unwrap()
    }

    #[test]
    fn a_realtime_run_limits_sizes_and_never_blocks() {
        let t = Traffic::of(&paper("realtime"));
        assert_eq!(t.telemetry_bytes, 50 * 512 + 65_536);
        let s = t.sections();
        let keys: Vec<&str> = s.iter().map(|(k, _)| *k).collect();
        assert_eq!(keys, ["low_pass_filter", "qos/network"]);
        assert_eq!(s[1].1[0]["overwrite"]["congestion_control"], "drop", "{}", s[1].1);
        assert_eq!(s[0].1[1]["size_limit"], 50 * 512 + 65_536, "{}", s[0].1);
    }

    #[test]
    fn a_lockstep_run_limits_sizes_only() {
        let s = Traffic::of(&paper("lockstep")).sections();
        assert_eq!(s.iter().map(|(k, _)| *k).collect::<Vec<_>>(), ["low_pass_filter"]);
    }

    #[test]
    fn zenoh_takes_the_sections() {
        for t in [Traffic::of(&paper("realtime")), Traffic::unknown()] {
            let mut c = zenoh::Config::default();
            for (k, v) in t.sections() {
                c.insert_json5(k, &v.to_string()).unwrap_or_else(|e| panic!("{k} = {v}: {e}"));
            }
        }
    }
}
