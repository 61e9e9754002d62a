//! What a formation's traffic is, enforced by zenoh on every link a node
//! receives from: no certified node can make others wait, fill their
//! memory or their CPU using only the keys it may publish on.
//!
//! Every node's and the router's session gets, on ingress, unless its
//! `--config` file sets the section itself:
//!
//! - `low_pass_filter`: a size limit per key (an estimate is about 83
//!   bytes: 1 KiB; a telemetry batch of `network.telemetry_batch` steps
//!   from a follower with the scenario's most sources: [`telemetry_limit`];
//!   control messages 64 KiB). Larger puts are dropped before they are
//!   decoded or forwarded, silently: a limit below what a node legitimately
//!   sends loses that message and every resend of it.
//! - Real-time runs only (lock-step estimates are needed, every one, and
//!   the loops wait for them by design):
//!   - `qos/network` overwrites every put under `formation/**` to
//!     `congestion_control: drop`, so a client that publishes with `Block`
//!     cannot make a router (or a peer) wait for a slow link;
//!   - `downsampling`, on routers only: each node's estimate key at most
//!     [`RATE_FACTOR`] times the run's step rate, one rule per key (zenoh
//!     keeps one clock per rule and transport). Without it a certified agent that flooded
//!     its own key (25,000 puts/s) left its neighbours isolated and every
//!     follower's error over the last 10 s at 3.9–4.1 m instead of
//!     0.08–0.16 m; with it, within 2 %. Its cost: of two messages of one
//!     key that arrive together the newer is dropped (the receiver uses the
//!     older for that step): 0.5 % of estimates in a real-time client-mode
//!     run of the paper scenario on the 2-core VM (89,516 and 89,519 of
//!     90,009 arrived), every follower's error unchanged to 4 digits.
//!
//! A router that forwards real-time traffic runs two worker threads
//! ([`crate::session::ROUTER_RUNTIME`]): one client cannot hold the only one.

use serde_json::{json, Value};

use formation_scenario::{Scenario, Timing};

/// Largest estimate put, bytes (one is about 83).
pub const ESTIMATE_BYTES: u64 = 1024;
/// Largest control put (hello, ready, start, abort, ack, time), bytes.
pub const CONTROL_BYTES: u64 = 64 * 1024;
/// Telemetry of one step is about 155 bytes; this much room per step.
pub const TELEMETRY_STEP_BYTES: u64 = 512;
/// Room for a batch's events, link figures and framing, bytes.
pub const TELEMETRY_EXTRA_BYTES: u64 = 64 * 1024;
/// An estimate key may carry at most this many times the run's step rate.
pub const RATE_FACTOR: f64 = 5.0;

/// Sources per follower a node that does not know the scenario allows for.
pub const UNKNOWN_SOURCES: usize = 32;

/// Largest telemetry put of a run whose batches hold `batch` steps and
/// whose followers have at most `sources` sources (neighbours and the
/// leader): the steps, the last batch's rescued messages
/// ([`formation_protocol::follower::most_rescued_bytes`]; 14 KB a source
/// at 50-step batches, which a follower with 7 sources took past a limit
/// without them, and lost its last batch for good) and room for the rest.
pub fn telemetry_limit(batch: u32, sources: usize) -> u64 {
    u64::from(batch.max(1)) * TELEMETRY_STEP_BYTES
        + formation_protocol::follower::most_rescued_bytes(sources, batch)
        + TELEMETRY_EXTRA_BYTES
}

/// What a run's traffic is, as far as the limits need it.
#[derive(Clone, Debug, PartialEq)]
pub struct Traffic {
    /// Real time (droppable, rate known) or lock-step.
    pub realtime: bool,
    /// Steps per second at the run's time scale (`network.time_scale`,
    /// which `launch --time-scale` sets for every node).
    pub step_hz: f64,
    /// Largest telemetry put, bytes.
    pub telemetry_bytes: u64,
    /// Every node that publishes an estimate (0 is the leader).
    pub estimate_ids: Vec<u32>,
    /// A router: only routers cap rates (see [`Traffic::sections`]).
    pub router: bool,
}

impl Traffic {
    pub fn of(scenario: &Scenario) -> Self {
        let mut estimate_ids = vec![0];
        estimate_ids.extend(scenario.graph.ids().iter().copied());
        Traffic {
            realtime: scenario.timing == Timing::Realtime,
            step_hz: scenario.network.time_scale / scenario.dt_s,
            telemetry_bytes: telemetry_limit(
                scenario.network.telemetry_batch,
                (0..scenario.graph.len()).map(|i| scenario.sources_of(i).len()).max().unwrap_or(0),
            ),
            estimate_ids,
            router: false,
        }
    }

    /// A node that does not know the scenario (a router started by hand):
    /// size limits only, for batches of up to 1,000 steps from followers
    /// of up to [`UNKNOWN_SOURCES`] sources.
    pub fn unknown() -> Self {
        Traffic {
            realtime: false,
            step_hz: 0.0,
            telemetry_bytes: telemetry_limit(1000, UNKNOWN_SOURCES),
            estimate_ids: Vec::new(),
            router: true,
        }
    }

    /// The zenoh configuration sections, by key.
    pub fn sections(&self) -> Vec<(&'static str, Value)> {
        let mut out = vec![(
            "low_pass_filter",
            json!([
                { "id": "formation-estimate-size", "flows": ["ingress"], "messages": ["put"],
                  "key_exprs": ["formation/*/estimate/**", "formation/*/pose/**"], "size_limit": ESTIMATE_BYTES },
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
            // Routers only: a router multiplies a flood to every node behind
            // it, and its clients' links carry one sender's key each. Peers
            // and clients keep every message (a real-time run in peer mode
            // with a delay of 2 steps once missed the simulator's torque
            // variation by 22 % with the cap on every node).
            if self.router && self.step_hz > 0.0 && !self.estimate_ids.is_empty() {
                let freq = RATE_FACTOR * self.step_hz;
                let rules: Vec<Value> = self
                    .estimate_ids
                    .iter()
                    .map(|id| json!({ "key_expr": format!("formation/*/estimate/{id}"), "freq": freq }))
                    .collect();
                out.push((
                    "downsampling",
                    json!([{ "id": "formation-estimate-rate", "flows": ["ingress"], "messages": ["put"],
                             "rules": rules }]),
                ));
            }
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
    fn a_realtime_run_limits_sizes_rates_and_never_blocks() {
        let node = Traffic::of(&paper("realtime"));
        let keys: Vec<&str> = node.sections().into_iter().map(|(k, _)| k).collect();
        assert_eq!(keys, ["low_pass_filter", "qos/network"], "a node does not cap rates");
        let t = Traffic { router: true, ..node };
        // The paper's followers have at most 3 sources.
        assert_eq!(t.telemetry_bytes, 50 * 512 + 3 * 4 * 50 * 80 + 65_536);
        assert_eq!(t.estimate_ids, vec![0, 1, 2, 3, 4]);
        let s = t.sections();
        let keys: Vec<&str> = s.iter().map(|(k, _)| *k).collect();
        assert_eq!(keys, ["low_pass_filter", "qos/network", "downsampling"]);
        let rules = &s[2].1[0]["rules"];
        assert_eq!(rules.as_array().map(Vec::len), Some(5), "{rules}");
        assert_eq!(rules[2]["key_expr"], "formation/*/estimate/2", "{rules}");
        assert_eq!(rules[2]["freq"], 5_000.0, "{rules}");
        assert_eq!(s[1].1[0]["overwrite"]["congestion_control"], "drop", "{}", s[1].1);
        assert_eq!(s[0].1[1]["size_limit"], 50 * 512 + 3 * 4 * 50 * 80 + 65_536, "{}", s[0].1);
    }

    #[test]
    fn a_lockstep_run_limits_sizes_only() {
        let s = Traffic::of(&paper("lockstep")).sections();
        assert_eq!(s.iter().map(|(k, _)| *k).collect::<Vec<_>>(), ["low_pass_filter"]);
    }

    /// The last batch of a follower with many sources, every rescued
    /// message at its largest encoding, fits under the limit the scenario
    /// gives (the constant behind it is checked against the real encoding).
    #[test]
    fn the_limit_holds_a_last_batch_that_rescues_every_source() {
        use formation_protocol::follower::{RESCUED_BYTES, RESCUE_BATCHES};
        use formation_protocol::telemetry::Telemetry;
        use formation_record::hearing::{HeardRuns, Rescued};
        let worst = Rescued { source: u32::MAX, stamp: u64::MAX, state: Default::default(), fresh: true };
        assert!(
            formation_protocol::codec::encode(&worst).len() as u64 <= RESCUED_BYTES,
            "a rescued message takes {} bytes",
            formation_protocol::codec::encode(&worst).len()
        );
        let (batch, sources) = (50u32, 12usize);
        let keep = RESCUE_BATCHES * batch as usize;
        let last = Telemetry::Follower {
            id: 1,
            first_k: 0,
            samples: vec![Default::default(); batch as usize],
            counters: Default::default(),
            done: true,
            loop_stats: None,
            delivery: Default::default(),
            events: Vec::new(),
            clock: None,
            links: Vec::new(),
            heard: HeardRuns::with_slots(sources, 8),
            rescued: vec![worst; sources * keep],
            resumed: None,
            diverged: None,
            left: None,
        };
        let bytes = formation_protocol::codec::encode(&last).len() as u64;
        let limit = telemetry_limit(batch, sources);
        assert!(bytes <= limit, "the last batch takes {bytes} bytes, the limit is {limit}");
        assert!(bytes > telemetry_limit(batch, 0), "{bytes} bytes: the old limit would have dropped it");
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
