//! `network.json`: how the network carried the run, per node (telemetry
//! figures, message counters, loop timing, clocks, links, a timeline of
//! what happened) and for the run (how it ended, what was refused, its
//! health).

use serde_json::{json, Map, Value};

use super::stream::Stream;
use super::{NodeStats, Recorder};
use crate::health::Health;
use crate::watch::Ending;
use formation_protocol::barrier;

impl Recorder {
    /// `network.json`: per-node message counts and loop timing.
    pub fn network_json(&self, ending: Ending) -> String {
        self.network_json_with(ending, None)
    }

    /// `network.json` with the run's health (written by the monitor node).
    pub(super) fn network_json_with(&self, ending: Ending, health: Option<&Health>) -> String {
        let nodes: Map<String, Value> = self
            .nodes
            .iter()
            .map(|(&id, n)| {
                let name = if id == 0 { "leader".to_string() } else { id.to_string() };
                (name, self.node_json(id, n))
            })
            .collect();
        let lost = self.lost_steps();
        let v = json!({
            "scenario": self.scenario.name,
            // The scenario as the nodes loaded it (hearing.bin carries the same).
            "fingerprint": format!("{:016x}", barrier::fingerprint(&self.scenario)),
            "timing": formation_record::name(&self.scenario.timing),
            // Real time: the wall-clock period (dt / time scale), and whether
            // the robots are driven over ROS 2, their motion on wall time
            // (a late step is then a late command, crate::period).
            "period_s": (self.scenario.timing == formation_scenario::Timing::Realtime)
                .then(|| self.scenario.dt_s / barrier::positive_scale(self.scenario.network.time_scale)),
            "robots_driven": self.scenario.ros2.is_some_and(|r| r.robots.driven()),
            // Every step of every node recorded, none lost.
            "complete": ending == Ending::Complete && lost == 0,
            // Both signals interrupt the run; `signal` says which.
            "ending": match ending {
                Ending::Complete if lost > 0 => "finished with gaps",
                Ending::Complete => "complete",
                Ending::Interrupted | Ending::Terminated => "interrupted",
                Ending::Idle => "idle",
            },
            "signal": match ending {
                Ending::Interrupted => Some("SIGINT"),
                Ending::Terminated => Some("SIGTERM"),
                _ => None,
            },
            "steps": self.scenario.steps(),
            "recorded_steps": self.recorded_steps(),
            "lost_steps": lost,
            "malformed_telemetry": self.malformed,
            "malformed_telemetry_by_key": self.malformed_by_key.iter().map(|(k, n)| {
                let key = k.map_or("telemetry/(not a node of the run)".to_string(), |id| format!("telemetry/{id}"));
                (key, json!(n))
            }).collect::<Map<_, _>>(),
            // Puts from other processes on the run's control keys: per key, how
            // many and how many were refused (foreign fingerprint, garbage).
            "control_puts": self.control.keys.iter().map(|(k, (n, bad))| {
                (k.clone(), json!({"puts": n, "refused": bad}))
            }).collect::<Map<_, _>>(),
            // How healthy the run was (crate::health): written by the monitor node.
            "health": health,
            // Telemetry dropped on arrival: more than MAX_QUEUED_BYTES waited to be filed.
            "telemetry_dropped_queue_full": self.queue_dropped,
            // Followers whose key carried a second sender (another process
            // with the same identity), as their neighbours saw it.
            "twins": self.twins(),
            // Followers a quorum start went without (also in "left", at step 0).
            "absent": self.absent_at_start,
            // Followers absent at the start that joined later (real time):
            // the first step each took, and its time.
            "joined": self.joined.iter().map(|&(id, k)| json!({
                "follower": id, "step": k, "t_s": k as f64 * self.scenario.dt_s,
            })).collect::<Vec<_>>(),
            // Followers that left the run for good: the first step each did
            // not take, its time, and why (its process was told to stop).
            "left": self.left().iter().map(|(id, k, why)| json!({
                "follower": id, "step": k, "t_s": *k as f64 * self.scenario.dt_s, "why": why,
            })).collect::<Vec<_>>(),
            // Standby leaders that took the run over: the newest step heard
            // from the leader before, and the first the standby published.
            "handovers": self.handovers.iter().map(|h| json!({
                "heard_step": h.heard, "step": h.at_k, "t_s": h.at_k as f64 * self.scenario.dt_s,
                "said": crate::health::handover_line(h.heard, h.at_k, self.scenario.dt_s),
            })).collect::<Vec<_>>(),
            // The leaders' terms (docs/model.md §14): who led each, over
            // which steps, and where one stood down for a higher term.
            "terms": self.terms.iter().map(|t| json!({
                "term": t.number,
                "led_by": match t.handover { None => "the leader", Some(_) => "a standby" },
                "from_step": t.handover.map_or(t.first_k, |h| h.at_k.max(t.first_k)),
                "to_step": t.end_k.saturating_sub(1),
                "stood_down_at_step": t.stood_down_at,
            })).collect::<Vec<_>>(),
            // Messages zenoh's access control refused, by the node that refused them.
            "access_denied": self.denied.rows(),
            // Start-up (every node ready, from the monitor's start) and the
            // run itself, wall clock.
            "wall": {
                "startup_s": self.startup_s,
                "run_s": self.run_s,
                "steps_per_s": self.run_s.filter(|&r| r > 0.0).map(|r| self.recorded_steps() as f64 / r),
            },
            "nodes": nodes,
        });
        serde_json::to_string_pretty(&v).unwrap_or_default() + "\n"
    }

    /// One node's entry of `network.json` (0: the leader).
    fn node_json(&self, id: u32, n: &NodeStats) -> Value {
        let c = &n.counters;
        let follower = self.scenario.index_of(id).filter(|_| id != 0).map(|i| &self.followers[i]);
        let (stream, timeline) = match follower {
            Some(f) => (Figures::of(&f.stream), self.timeline(n, &f.stream, Vec::new(), |_| RESTARTED)),
            None => {
                let took = "a standby leader took the run over";
                let handovers = self.handovers.iter().map(|h| (h.at_k, took.to_string())).collect();
                // A standby's record begins before its takeover (it resends
                // the leader's last states): the newest restart at or before it.
                let restarts = &self.leader_stream.restarts;
                let standbys = |at_k: u64| restarts.iter().copied().filter(|&r| r <= at_k).max();
                let resent = |k: u64| self.handovers.iter().any(|h| standbys(h.at_k) == Some(k));
                let why = |k: u64| if resent(k) { STANDBYS_RECORD } else { RESTARTED };
                (Figures::of(&self.leader_stream), self.timeline(n, &self.leader_stream, handovers, why))
            }
        };
        let d = &n.delivery;
        json!({
            "telemetry_messages": n.messages,
            "telemetry_bytes": n.bytes,
            "telemetry_samples": n.samples,
            "telemetry_reordered": stream.reordered,
            "telemetry_duplicates": stream.duplicates,
            "telemetry_resent": d.courier.resent,
            "telemetry_dropped_by_sender": d.courier.lost_steps,
            "telemetry_peak_unacknowledged_bytes": d.courier.peak_held_bytes,
            "gaps": stream.gaps,
            "recovered": stream.recovered,
            "timeline": timeline,
            "unpaired": follower.map(|f| f.unpaired),
            "done": n.done,
            // Steps this follower's record has reached (followers can be ahead of the slowest one).
            "recorded_steps": follower.map(|f| f.next_k),
            "estimates_sent": c.sent,
            "republished": c.republished,
            "received": c.received,
            "late": c.late,
            "silent": c.silent,
            "older": c.older,
            "fault_lost": c.fault_lost,
            "rejected": c.rejected,
            "rejected_invalid": c.rejected.invalid(),
            // (The leader) questions on control/time, and the most in one second.
            "time_queries": (id == 0).then_some(c.time_queries),
            "time_queries_peak_per_s": (id == 0).then_some(c.time_queries_peak_per_s),
            "loop": n.loop_stats,
            "clock": n.clock,
            "links": n.links,
        })
    }

    /// A node's timeline: its own events, and the monitor's (telemetry
    /// that came late and filled a hole, steps lost for good, restarts), in
    /// step order.
    fn timeline<T>(
        &self,
        n: &NodeStats,
        stream: &Stream<T>,
        extra: Vec<(u64, String)>,
        restart: impl Fn(u64) -> &'static str,
    ) -> Vec<Value> {
        let dt = self.scenario.dt_s;
        let span = |a: u64, b: u64| format!("t = {:.3}–{:.3} s", a as f64 * dt, b as f64 * dt);
        let mut timeline: Vec<(u64, String)> = n.timeline.iter().map(|e| (e.k, e.what.describe())).collect();
        timeline
            .extend(stream.recovered.iter().map(|&(a, b)| (a, format!("telemetry for {} recovered late", span(a, b)))));
        timeline.extend(
            stream.gaps.iter().map(|g| (g.from, format!("telemetry for {} lost ({})", span(g.from, g.to), g.why))),
        );
        timeline.extend(stream.restarts.iter().map(|&k| (k, restart(k).to_string())));
        timeline.extend(extra);
        timeline.sort_by_key(|e| e.0);
        timeline.iter().map(|(k, what)| json!({"t": *k as f64 * dt, "event": what})).collect()
    }
}

/// A new process's telemetry, in a node's timeline.
const RESTARTED: &str = "a new process took over (restarted)";
/// The same for a standby leader's, resending the leader's states before its takeover.
const STANDBYS_RECORD: &str = "the standby's record begins (the leader's states before its takeover, resent)";

/// A node's stream figures as `network.json` gives them.
struct Figures<'a> {
    gaps: &'a [super::Gap],
    reordered: u64,
    duplicates: u64,
    recovered: Vec<Value>,
}

impl<'a> Figures<'a> {
    fn of<T>(s: &'a Stream<T>) -> Self {
        Self {
            gaps: &s.gaps,
            reordered: s.reordered,
            duplicates: s.duplicates,
            recovered: s.recovered.iter().map(|&(from, to)| json!({"from": from, "to": to})).collect(),
        }
    }
}
