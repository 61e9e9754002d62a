//! What the monitor shows while it records: the terminal's live line and
//! the live page's JSON (its scene, and one frame per publication; see
//! [`formation_view::web`]).

use std::collections::BTreeSet;
use std::time::Instant;

use formation_scenario::Scenario;
use serde_json::{json, Value};

use super::{NodeStats, Recorder};
use formation_protocol::telemetry::EventKind;

/// The live page names a node whose telemetry stopped this long ago (s).
const SILENT_NODE_S: f64 = 2.0;

/// Network events the live page lists.
const RECENT_EVENTS: usize = 50;

/// How the live page names node `id` (0: the leader).
fn node_name(id: u32) -> String {
    if id == 0 {
        "leader".to_string()
    } else {
        format!("follower {id}")
    }
}

impl Recorder {
    /// The live line: latest formation error per follower and the worst.
    pub fn status_line(&self) -> String {
        let k = self.recorded_steps();
        let mut line = format!("t = {:>7.3} s |", k as f64 * self.scenario.dt_s);
        let mut worst: Option<(u32, f64)> = None;
        for f in &self.followers {
            if self.followers.len() <= 8 {
                line += &format!(" F{} {:.4}", f.id, f.formation_error);
            }
            if f.formation_error.is_finite() && worst.is_none_or(|(_, w)| f.formation_error > w) {
                worst = Some((f.id, f.formation_error));
            }
        }
        match worst {
            Some((id, w)) => line += &format!(" | worst F{id} {w:.4} m"),
            None => line += " | waiting for telemetry",
        }
        line
    }

    /// The live page's scene: what does not change during the run.
    pub fn scene_json(s: &Scenario, run: &str) -> String {
        let g = &s.graph;
        let mut edges = Vec::new();
        for i in 0..g.len() {
            for &j in g.neighbours(i) {
                if i < j {
                    edges.push([g.id(i), g.id(j)]);
                }
            }
        }
        let leader_links: Vec<u32> = (0..g.len()).filter(|&i| g.hears_leader(i)).map(|i| g.id(i)).collect();
        let mode = match s.timing {
            formation_scenario::Timing::Lockstep => "lockstep",
            formation_scenario::Timing::Realtime => "realtime",
        };
        json!({
            "run": run,
            "scenario": s.name,
            "dt": s.dt_s,
            "steps": s.steps(),
            "duration": s.duration_s,
            "mode": mode,
            "followers": s.followers.iter().map(|f| json!({"id": f.id, "offset": f.offset})).collect::<Vec<_>>(),
            "edges": edges,
            "leader_links": leader_links,
        })
        .to_string()
    }

    /// One frame of the live page (see [`formation_view::web`]): every follower's
    /// newest row, the nodes' counters and what the network did; and the
    /// same frame for the history, without the nodes and events (a late
    /// viewer needs those only from the newest frame).
    pub fn live_frame(&self, now: Instant, seq: u64, wall_s: f64, state: &str, viewers: usize) -> (String, String) {
        let dt = self.scenario.dt_s;
        let k = self.recorded_steps();
        // Nodes whose telemetry stopped, while the run goes on.
        let mut gone = Vec::new();
        let nodes: Vec<Value> = self
            .nodes
            .iter()
            .map(|(&id, n)| {
                let heard_s = n.heard.map(|h| now.duration_since(h).as_secs_f64());
                if state == "running" && !n.done && heard_s.is_none_or(|h| h > SILENT_NODE_S) {
                    gone.push(match heard_s {
                        Some(h) => format!("no telemetry from {} for {h:.1} s", node_name(id)),
                        None => format!("no telemetry from {} yet", node_name(id)),
                    });
                }
                node_json(id, n, heard_s)
            })
            .collect();
        let message = match gone.len() {
            0 => None,
            1..=3 => Some(gone.join("; ")),
            n => Some(format!("{}; and {} more nodes", gone[..3].join("; "), n - 3)),
        };
        let mut frame = json!({
            "seq": seq, "wall": wall_s, "k": k, "t": k.saturating_sub(1) as f64 * dt,
            "progress": k as f64 / (self.scenario.steps() + 1) as f64,
            "state": state, "viewers": viewers,
            "leader": self.frame_leader(), "followers": self.frame_followers(), "nodes": nodes,
            "events": self.nodes.values().map(|n| n.timeline.len()).sum::<usize>(),
            "recent_events": self.recent_events(), "message": message,
            "alerts": self.alerts(),
            "safety": self.frame_safety(),
            // Who came and went (null while everyone runs): left, joined, handed over.
            "members": self.membership_line(),
            // The same per node, for the page's rows.
            "membership": self.membership_marks(),
        });
        let full = frame.to_string();
        if let Some(f) = frame.as_object_mut() {
            f.insert("nodes".into(), json!([]));
            f.insert("recent_events".into(), json!([]));
        }
        (full, frame.to_string())
    }

    /// Who came and went, by node id (0: the leader), for the live page's
    /// rows: "joined at 8.594 s", "left at 5.000 s (SIGTERM)", "absent at
    /// the start", "a standby leads from 10.503 s"; empty while everyone runs.
    fn membership_marks(&self) -> Value {
        let dt = self.scenario.dt_s;
        let mut marks: std::collections::BTreeMap<u32, Vec<String>> = Default::default();
        for &(id, k) in &self.joined {
            marks.entry(id).or_default().push(format!("joined at {:.3} s", k as f64 * dt));
        }
        for (id, k, why) in self.left() {
            marks.entry(id).or_default().push(match k {
                0 => why,
                k => format!("left at {:.3} s ({why})", k as f64 * dt),
            });
        }
        if let Some(h) = self.handovers.last() {
            marks.entry(0).or_default().push(format!("a standby leads from {:.3} s", h.at_k as f64 * dt));
        }
        Value::Object(marks.into_iter().map(|(id, m)| (id.to_string(), json!(m.join("; ")))).collect())
    }

    /// How close the robots came so far (docs/model.md §16); null without
    /// `safety.distance`.
    fn frame_safety(&self) -> Value {
        let Some(p) = &self.proximity else { return Value::Null };
        // Deadlocks found and the time spent sidestepping (eq. G6), over every follower.
        let mut g = formation_control::GuardTally::default();
        self.followers.iter().filter_map(|f| f.metrics.guard()).for_each(|t| g.merge(t));
        json!({
            "distance": p.distance, "filter": p.filter, "steps_below": p.steps_below,
            "closest": p.closest.map(|c| json!({"d": c.distance, "pair": c.pair, "t": c.t})),
            "violation": p.violation_text(),
            "deadlocks": g.deadlocks, "sidestep_s": g.sidestep as f64 * self.scenario.dt_s,
        })
    }

    /// The leader as the least advanced follower saw it (the frame's t).
    fn frame_leader(&self) -> Option<Value> {
        self.followers
            .iter()
            .filter_map(|f| f.latest.as_ref())
            .min_by(|a, b| a.0.t.total_cmp(&b.0.t))
            .map(|(_, l)| json!([l.pose.x, l.pose.y, l.pose.theta]))
    }

    /// Every follower's newest row (nulls before its first).
    fn frame_followers(&self) -> Vec<Value> {
        let dt = self.scenario.dt_s;
        let finite = |x: f64| if x.is_finite() { json!(x) } else { Value::Null };
        self.followers
            .iter()
            .map(|f| match &f.latest {
                Some((r, _)) => json!({
                    "id": f.id, "k": (r.t / dt).round() as u64, "t": r.t,
                    "pose": [r.x, r.y, r.theta], "estimate": [r.x_ir, r.y_ir],
                    "ef": finite(r.formation_error), "ee": finite(r.estimator_error),
                }),
                None => {
                    json!({"id": f.id, "k": null, "t": null, "pose": null, "estimate": null, "ef": null, "ee": null})
                }
            })
            .collect()
    }

    /// The newest [`RECENT_EVENTS`] network events of all nodes, in step order.
    fn recent_events(&self) -> Vec<Value> {
        let dt = self.scenario.dt_s;
        let mut recent: Vec<(u64, u32, String)> = Vec::new();
        for (&id, n) in &self.nodes {
            recent.extend(n.timeline.iter().rev().take(RECENT_EVENTS).map(|e| (e.k, id, e.what.describe())));
        }
        recent.sort();
        recent[recent.len().saturating_sub(RECENT_EVENTS)..]
            .iter()
            .map(|(k, id, what)| json!({"t": *k as f64 * dt, "node": node_name(*id), "what": what}))
            .collect()
    }

    /// One line per thing the live page must say at once: twinned
    /// followers and access-control denials.
    fn alerts(&self) -> Vec<String> {
        let mut out: Vec<String> = self
            .twins()
            .iter()
            .map(|t| {
                format!(
                    "follower {}: a second sender on its key since t = {:.2} s (seen by {}; {} messages)",
                    t["follower"],
                    t["since_t"].as_f64().unwrap_or(0.0),
                    t["seen_by"],
                    t["messages"]
                )
            })
            .collect();
        out.extend(self.denied.summary());
        // A second clock on control/time, as each follower saw it.
        for (id, n) in &self.nodes {
            if let Some(g) = n.clock.map(|c| c.guard).filter(|g| g.second_clock_since_ns.is_some()) {
                out.push(format!(
                    "follower {id}: a second clock answers on control/time, {:.1} ms from the leader's; \
                     {} answers refused",
                    g.worst_disagreement_ms, g.refused_answers
                ));
            }
        }
        out
    }
}

/// One node's row of the live page's table; `heard_s`: seconds since its
/// last telemetry.
fn node_json(id: u32, n: &NodeStats, heard_s: Option<f64>) -> Value {
    // The sources this node counts as silent now: the newest event about each.
    let mut silent = BTreeSet::new();
    for e in &n.timeline {
        match e.what {
            EventKind::Silent(s) => {
                silent.insert(s);
            }
            EventKind::Heard(s) => {
                silent.remove(&s);
            }
            _ => {}
        }
    }
    let c = &n.counters;
    json!({
        "id": id, "name": node_name(id), "heard_s": heard_s, "done": n.done,
        "sent": c.sent, "received": c.received, "late": c.late, "rejected": c.rejected.invalid(),
        "silent": c.silent, "fault_lost": c.fault_lost, "silent_sources": silent,
        "clock": n.clock,
        "links": n.links,
    })
}
