//! `summary.json`: a run's settings and every follower's metrics, and
//! what an incomplete run is missing.

use std::collections::BTreeMap;

use formation_scenario::Scenario;
use serde::{Deserialize, Serialize};

use crate::metrics::FollowerMetrics;
use crate::outage::{self, FaultSummary, OutageMetrics};
use crate::proximity::Proximity;

/// `summary.json`: the run's settings and every follower's metrics, keyed by id.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub scenario: String,
    pub seed: u64,
    pub dt: f64,
    pub duration: f64,
    pub steps: u64,
    pub noise: bool,
    pub kinematic: String,
    pub dynamic: String,
    pub filter: String,
    pub estimate_init: String,
    pub fault_time: Option<f64>,
    pub lambda_min_h: Option<f64>,
    /// Every follower recorded all steps + 1 samples (t = 0 to T, docs/model.md §9).
    /// Written only when false (`"complete": false` with `incomplete`), so a
    /// complete run's summary.json is what it was before the key existed;
    /// [`Summary::mark_unreached`] recomputes it on load.
    #[serde(default = "yes", skip_serializing_if = "is_true")]
    pub complete: bool,
    /// The followers that recorded fewer samples, by id (absent when complete).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub incomplete: BTreeMap<u32, Shortfall>,
    pub followers: BTreeMap<u32, FollowerMetrics>,
    /// `network.rejoin`, when the scenario has link faults.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rejoin: Option<String>,
    /// docs/model.md §14's metrics under faults, per fault window and follower.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub faults: Vec<FaultSummary>,
    /// How close the robots came, with `[safety]` (docs/model.md §16).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub safety: Option<Proximity>,
    /// `formation.frame` when it is the leader's (docs/model.md §17).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<String>,
    /// The shape changes and the slot each follower was assigned (eq. 17.4).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub shapes: Vec<ShapeAssigned>,
}

/// One shape change as run: when, which shape, each follower's new slot
/// and the assignment's total squared distance from the slots before.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShapeAssigned {
    pub at: f64,
    pub shape: String,
    /// m², Σ_i |Δ_i(before) − Δ_i(after)|².
    pub cost: f64,
    pub offsets: BTreeMap<u32, [f64; 2]>,
    /// How long after the change, s, each follower's formation error came
    /// within `SETTLED_M` (0.1 m) and stayed there until the next change or
    /// the end (null: it did not, or its record stops before then, so that
    /// it is not known to have stayed).
    #[serde(default)]
    pub settled_after: BTreeMap<u32, Option<f64>>,
    /// The step it took effect at.
    #[serde(skip)]
    pub from_k: u64,
}

/// How many samples a follower of an incomplete run recorded, of how many.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shortfall {
    pub recorded: u64,
    /// steps + 1.
    pub expected: u64,
    /// Of the missing ones, steps missing between recorded ones.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub in_gaps: u64,
    /// It left the run for good (or was absent from a quorum start), and
    /// why: its samples end there by design, not by loss.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub left: Option<String>,
    /// Absent at the start, it joined the run at this step: its samples
    /// begin there by design.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub joined_at_k: Option<u64>,
}

impl Shortfall {
    /// "follower 3 recorded 8150 of 20001 samples (to t = 8.149 s of T = 20 s)".
    pub fn describe(&self, id: u32, dt_s: f64, duration_s: f64) -> String {
        let reached = match self.recorded {
            0 => String::new(),
            // To the microsecond: 1499 × 0.001 prints as 1.499, not 1.4990000000000001.
            n => format!(" (to t = {} s of T = {duration_s} s)", ((n - 1) as f64 * dt_s * 1e6).round() / 1e6),
        };
        if let Some(k) = self.joined_at_k {
            return format!(
                "follower {id} joined at t = {} s (absent at the start): {} of {} steps",
                (k as f64 * dt_s * 1e6).round() / 1e6,
                self.recorded,
                self.expected
            );
        }
        match (&self.left, self.recorded) {
            (Some(why), 0) => return format!("follower {id} took no step ({why})"),
            (Some(why), n) => {
                return format!("follower {id} left after {n} of {} steps{reached} ({why})", self.expected)
            }
            (None, _) => {}
        }
        if self.in_gaps > 0 && self.recorded + self.in_gaps == self.expected {
            return format!(
                "follower {id} recorded {} of {} samples ({} missing in gaps: an agent that was down or telemetry \
                 lost for good; network.json lists them)",
                self.recorded, self.expected, self.in_gaps
            );
        }
        format!("follower {id} recorded {} of {} samples{reached}", self.recorded, self.expected)
    }
}

impl Summary {
    pub fn new(s: &Scenario, followers: BTreeMap<u32, FollowerMetrics>) -> Self {
        // A velocity-commanded robot runs neither (docs/model.md §15): it was
        // written "bio" and "asif", and `formation report` put its zero
        // filter RMSE beside the paper's Table I.
        let (dynamic, filter) = match s.control.drive {
            formation_plant::Drive::Torque => (name(&s.control.dynamic), name(&s.control.filter.kind)),
            formation_plant::Drive::Velocity { .. } => ("none (velocity-commanded robot)".into(), "none".into()),
        };
        let mut summary = Self {
            scenario: s.name.clone(),
            seed: s.seed,
            dt: s.dt_s,
            duration: s.duration_s,
            steps: s.steps(),
            noise: s.noise,
            kinematic: name(&s.control.kinematic),
            dynamic,
            filter,
            estimate_init: name(&s.estimate_init),
            fault_time: s.control.fault.map(|f| f.time_s),
            lambda_min_h: s.graph.lambda_min_h(),
            complete: true,
            incomplete: BTreeMap::new(),
            followers,
            rejoin: (!s.faults.is_empty()).then(|| name(&s.control.rejoin.policy)),
            faults: Vec::new(),
            safety: None,
            frame: (s.control.frame == formation_control::Frame::Leader).then(|| "leader".to_string()),
            shapes: shapes(s),
        };
        summary.mark_unreached();
        summary
    }

    /// Marks what the recorded samples do not cover: `complete`,
    /// `incomplete`, and null metrics whose window was not reached (older
    /// `summary.json` files wrote 0 for them). Idempotent.
    pub fn mark_unreached(&mut self) {
        let expected = self.steps + 1;
        for m in self.followers.values_mut() {
            m.null_unreached(self.steps);
        }
        let was = std::mem::take(&mut self.incomplete);
        self.incomplete = self
            .followers
            .iter()
            .filter(|(_, m)| m.samples < expected)
            .map(|(&id, m)| {
                let left = was.get(&id).and_then(|s| s.left.clone());
                let joined_at_k = was.get(&id).and_then(|s| s.joined_at_k);
                (id, Shortfall { recorded: m.samples, expected, in_gaps: m.gap_steps, left, joined_at_k })
            })
            .collect();
        self.complete = self.incomplete.is_empty();
    }

    /// Follower `id` left the run for good before it ended (`why`: "SIGTERM",
    /// "absent at the start", …): its shortfall says so.
    /// Follower `id`, absent at the start, joined the run at step `k`: its
    /// shortfall says so.
    pub fn mark_joined(&mut self, id: u32, k: u64) {
        if let Some(s) = self.incomplete.get_mut(&id) {
            s.joined_at_k = Some(k);
        }
    }

    /// Follower `id` left the run for good before it ended (`why`: "SIGTERM",
    /// "absent at the start", …): its shortfall says so.
    pub fn mark_left(&mut self, id: u32, why: &str) {
        if let Some(s) = self.incomplete.get_mut(&id) {
            s.left = Some(why.to_string());
        }
    }

    /// What the run is missing, a clause for each of the first three short
    /// followers (`incomplete` lists them all); `None` when complete.
    pub fn shortfall_text(&self) -> Option<String> {
        let mut parts: Vec<String> =
            self.incomplete.iter().take(3).map(|(&id, s)| s.describe(id, self.dt, self.duration)).collect();
        if self.incomplete.len() > 3 {
            let more = self.incomplete.len() - 3;
            parts.push(format!("and {more} more follower{}", if more == 1 { "" } else { "s" }));
        }
        (!parts.is_empty()).then(|| parts.join("; "))
    }

    /// Adds the metrics under faults (by follower id, one per fault window).
    pub fn with_outages(mut self, s: &Scenario, per_follower: &BTreeMap<u32, Vec<OutageMetrics>>) -> Self {
        self.faults = FaultSummary::all(s, per_follower);
        self
    }

    /// [`ShapeAssigned::settled_after`] from each follower's accumulator;
    /// null for a follower whose record stops before the change's window
    /// (to the next change, or the end) does.
    pub fn with_settling(mut self, per_follower: &BTreeMap<u32, Vec<Option<f64>>>) -> Self {
        let ends: Vec<u64> =
            self.shapes.iter().skip(1).map(|c| c.from_k).chain(std::iter::once(self.steps + 1)).collect();
        for (i, change) in self.shapes.iter_mut().enumerate() {
            change.settled_after = per_follower
                .iter()
                .map(|(&id, s)| {
                    // One past the follower's last sample: samples and the gaps between them.
                    let seen = self.followers.get(&id).map_or(0, |m| m.samples + m.gap_steps);
                    (id, s.get(i).copied().flatten().filter(|_| seen >= ends[i]))
                })
                .collect();
        }
        self
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_default() + "\n"
    }

    /// A compact, aligned table of the metrics ("—": window not reached),
    /// and a line saying so when the run is incomplete.
    pub fn table(&self) -> String {
        let mut out = format!(
            "{:>8} {:>11} {:>10} {:>9} {:>10} {:>9} {:>10} {:>9} {:>9} {:>9}\n",
            "follower",
            "form_rms10",
            "form_fin",
            "head_fin",
            "est_fin",
            "vc_peak",
            "torque_tv",
            "tau_peak",
            "rmse_v",
            "rmse_w"
        );
        let c = |x: Option<f64>, f: fn(f64) -> String| x.map_or_else(|| "—".to_string(), f);
        for (id, m) in &self.followers {
            out += &format!(
                "{:>8} {:>11} {:>10} {:>9} {:>10} {:>9} {:>10} {:>9} {:>9} {:>9}\n",
                id,
                c(m.formation_rms_last10, |x| format!("{x:.4}")),
                c(m.formation_final, |x| format!("{x:.4}")),
                c(m.heading_final, |x| format!("{x:.4}")),
                c(m.estimator_error_final, |x| format!("{x:.2e}")),
                c(m.vc_peak, |x| format!("{x:.3}")),
                c(m.torque_tv, |x| format!("{x:.3}")),
                c(m.torque_peak, |x| format!("{x:.3}")),
                c(m.rmse_v, |x| format!("{x:.2e}")),
                c(m.rmse_w, |x| format!("{x:.2e}"))
            );
        }
        if let Some(short) = self.shortfall_text() {
            out += &format!("incomplete run: {short}; — marks a metric whose window was not reached\n");
        }
        out += &outage::table(&self.faults, self.recorded_until());
        out += &self.guard_lines();
        out
    }

    /// The limits' and the filter's figures, and how close the robots came
    /// (docs/model.md §16); empty without either.
    pub fn guard_lines(&self) -> String {
        let mut out = String::new();
        if let Some(t) = self.guard_total() {
            let pct = |n: u64| 100.0 * n as f64 / t.steps.max(1) as f64;
            out += &format!(
                "commands: a limit clipped {} of {} ({:.1} %); the safety filter changed {} ({:.1} %, by up to \
                 {:.3} m/s){}{}\n",
                t.saturated,
                t.steps,
                pct(t.saturated),
                t.filtered,
                pct(t.filtered),
                t.change_max,
                match t.infeasible {
                    0 => String::new(),
                    n => format!("; {n} had no safe command and stopped the robot"),
                },
                match t.blind {
                    0 => String::new(),
                    n => format!("; {n} stopped the robot beside one whose pose was stale"),
                }
            );
            if t.deadlocks > 0 {
                out += &format!(
                    "deadlocks: {} found (a robot held short of its slot), {:.2} s of sidestepping to the right\n",
                    t.deadlocks,
                    t.sidestep as f64 * self.dt
                );
            }
        }
        if let Some(p) = &self.safety {
            out += &p.line();
        }
        out += &self.shape_lines();
        out
    }

    /// One line per shape change: when every follower was in its new slot
    /// (within `SETTLED_M`) and the closest two robots after it.
    fn shape_lines(&self) -> String {
        let after = self.safety.as_ref().map_or(&[][..], |p| &p.after_shapes[..]);
        let mut out = String::new();
        for (i, c) in self.shapes.iter().enumerate() {
            let slowest = c
                .settled_after
                .iter()
                .map(|(&id, t)| (id, t.unwrap_or(f64::INFINITY)))
                .max_by(|a, b| a.1.total_cmp(&b.1));
            let settled = match slowest {
                Some((_, t)) if t.is_finite() => format!("every robot within 0.1 m of its slot {t:.2} s after"),
                Some((id, _)) => format!("follower {id} not within 0.1 m of its slot by the next change or the end"),
                None => "no follower recorded".to_string(),
            };
            let closest = match after.get(i).and_then(|w| w.closest) {
                Some(p) => format!(", closest robots {} and {} at {:.3} m", p.pair[0], p.pair[1], p.distance),
                None => String::new(),
            };
            out += &format!("shape at t = {} s, {} ({:.3} m² moved): {settled}{closest}\n", c.at, c.shape, c.cost);
        }
        out
    }
}

impl Summary {
    /// Every follower's guard tally summed (the largest change the
    /// largest); None without limits or a filter.
    pub fn guard_total(&self) -> Option<formation_control::GuardTally> {
        let mut tallies = self.followers.values().filter_map(|m| m.guard).peekable();
        tallies.peek()?;
        Some(tallies.fold(formation_control::GuardTally::default(), |mut a, t| {
            a.merge(&t);
            a
        }))
    }

    /// Where the record ends (s): the run's duration, or for an incomplete
    /// run the last sample of its shortest follower that ended early (one
    /// with gaps ran to the end).
    pub fn recorded_until(&self) -> f64 {
        self.incomplete
            .values()
            .filter(|s| s.recorded + s.in_gaps < s.expected)
            .map(|s| (s.recorded + s.in_gaps).saturating_sub(1) as f64 * self.dt)
            .fold(self.duration, f64::min)
    }
}

fn yes() -> bool {
    true
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

fn is_true(b: &bool) -> bool {
    *b
}

/// The name of an enum choice as scenario files write it (`super-twisting`).
pub fn name<T: Serialize>(v: &T) -> String {
    serde_json::to_value(v).ok().and_then(|v| v.as_str().map(str::to_string)).unwrap_or_default()
}

/// [`Summary::shapes`] of a scenario.
fn shapes(s: &Scenario) -> Vec<ShapeAssigned> {
    s.shapes
        .iter()
        .map(|c| {
            let offsets = s.followers.iter().zip(&c.offsets).map(|(f, &o)| (f.id, o)).collect();
            ShapeAssigned {
                at: c.at_s,
                shape: c.name.clone(),
                cost: c.cost,
                offsets,
                settled_after: BTreeMap::new(),
                from_k: c.from_k,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::FollowerMetrics;

    /// doorway's changes at 20 s (step 1000) and 60 s (step 3000) of 4250
    /// steps: a follower whose record stops at 70 s is not known to have
    /// stayed in its wedge slot, so its second `settled_after` is null; the
    /// first, whose window closed at 60 s, is kept, as is every one of a
    /// follower recorded to the end.
    #[test]
    fn settling_is_null_where_the_record_stops_before_the_window_ends() {
        let s = Scenario::load(std::path::Path::new("doorway"), &[]).expect("built in");
        let full = FollowerMetrics { samples: s.steps() + 1, ..FollowerMetrics::default() };
        let short = FollowerMetrics { samples: 3500, ..FollowerMetrics::default() };
        let metrics = [(1, full), (2, full), (3, short), (4, full)].into_iter().collect();
        let settled: BTreeMap<u32, Vec<Option<f64>>> = (1..=4).map(|id| (id, vec![Some(5.0), Some(7.0)])).collect();
        let summary = Summary::new(&s, metrics).with_settling(&settled);
        assert_eq!(summary.shapes[0].settled_after[&3], Some(5.0), "its first window closed before its record did");
        assert_eq!(summary.shapes[1].settled_after[&3], None, "its record stops at 70 s, the window at the end");
        assert_eq!(summary.shapes[1].settled_after[&1], Some(7.0));
    }
}
