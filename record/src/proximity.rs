//! How close the robots came (docs/model.md §16): the closest two robots'
//! centres over a run, which pair and when, and the steps at which a pair
//! was closer than `safety.distance`. Fed one step of every robot's pose at
//! a time (the simulator; a monitor once it holds a whole step).

use formation_plant::Pose;
use serde::{Deserialize, Serialize};

/// Two robots at one step.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairAt {
    /// Their centres' distance, m.
    pub distance: f64,
    /// Follower ids, ascending.
    pub pair: [u32; 2],
    /// s.
    pub t: f64,
}

/// `summary.json`'s `safety`: the scenario's distance and what the run did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Proximity {
    /// `safety.distance`, m.
    pub distance: f64,
    /// The safety filter was on.
    pub filter: bool,
    /// The closest two robots came (none before the first step).
    pub closest: Option<PairAt>,
    /// Steps at which some pair was closer than `distance`.
    pub steps_below: u64,
    /// The first such step's closest pair.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub first_below: Option<PairAt>,
    /// Per shape change (docs/model.md §17), the closest two robots came
    /// from it to the next change or the end. Absent without changes.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub after_shapes: Vec<ShapeClosest>,
}

/// The closest pair after one shape change.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShapeClosest {
    /// The change's time, s.
    pub at: f64,
    pub closest: Option<PairAt>,
}

impl Proximity {
    pub fn new(distance: f64, filter: bool) -> Self {
        Self { distance, filter, closest: None, steps_below: 0, first_below: None, after_shapes: Vec::new() }
    }

    /// Measuring also the closest pair after each shape change (times in s,
    /// ascending; a step counts from `at − Δt/2` on, the change's own step).
    pub fn with_shape_changes(mut self, at: impl IntoIterator<Item = f64>) -> Self {
        self.after_shapes = at.into_iter().map(|at| ShapeClosest { at, closest: None }).collect();
        self
    }

    /// One step: every robot's pose at t, by index, and their ids. O(n²).
    pub fn push(&mut self, t: f64, ids: &[u32], poses: &[Pose]) {
        let mut step: Option<PairAt> = None;
        for (i, a) in poses.iter().enumerate() {
            for (j, b) in poses.iter().enumerate().skip(i + 1) {
                let d = (a.x - b.x).hypot(a.y - b.y);
                if step.is_none_or(|s| d < s.distance) {
                    step = Some(PairAt { distance: d, pair: [ids[i].min(ids[j]), ids[i].max(ids[j])], t });
                }
            }
        }
        let Some(step) = step else { return };
        if self.closest.is_none_or(|c| step.distance < c.distance) {
            self.closest = Some(step);
        }
        // The last change at or before t (the step grid's: `at` is on it or rounds up to it).
        if let Some(w) = self.after_shapes.iter_mut().rev().find(|w| w.at <= t + 1e-9) {
            if w.closest.is_none_or(|c| step.distance < c.distance) {
                w.closest = Some(step);
            }
        }
        if step.distance < self.distance {
            self.steps_below += 1;
            self.first_below.get_or_insert(step);
        }
    }

    /// Two robots came closer than the safety distance.
    pub fn violated(&self) -> bool {
        self.steps_below > 0
    }

    /// "robots 2 and 3 came 0.21 m apart at t = 4.3 s, closer than the safety distance 0.3 m (37 steps)".
    pub fn violation_text(&self) -> Option<String> {
        let first = self.first_below?;
        let closest = self.closest?;
        Some(format!(
            "robots {} and {} came {:.3} m apart at t = {} s (closest: {} and {}, {:.3} m at t = {} s), closer than \
             the safety distance {} m at {} step{}",
            first.pair[0],
            first.pair[1],
            first.distance,
            round_us(first.t),
            closest.pair[0],
            closest.pair[1],
            closest.distance,
            round_us(closest.t),
            self.distance,
            self.steps_below,
            if self.steps_below == 1 { "" } else { "s" }
        ))
    }

    /// The end-of-run line.
    pub fn line(&self) -> String {
        match (self.closest, self.violation_text()) {
            (_, Some(v)) => format!("safety: {v}\n"),
            (Some(c), None) => format!(
                "safety: closest robots {} and {}, {:.3} m apart at t = {} s (safety distance {} m{})\n",
                c.pair[0],
                c.pair[1],
                c.distance,
                round_us(c.t),
                self.distance,
                if self.filter { ", filter on" } else { ", filter off" }
            ),
            (None, None) => String::new(),
        }
    }
}

fn round_us(t: f64) -> f64 {
    (t * 1e6).round() / 1e6
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_closest_pair_and_the_steps_below_are_kept() {
        let mut p = Proximity::new(0.3, true);
        p.push(0.0, &[1, 2, 3], &[Pose::new(0.0, 0.0, 0.0), Pose::new(1.0, 0.0, 0.0), Pose::new(0.0, 0.5, 0.0)]);
        assert!(!p.violated());
        assert_eq!(p.closest, Some(PairAt { distance: 0.5, pair: [1, 3], t: 0.0 }));
        p.push(0.1, &[1, 2, 3], &[Pose::new(0.0, 0.0, 0.0), Pose::new(0.2, 0.0, 0.0), Pose::new(0.0, 0.5, 0.0)]);
        p.push(0.2, &[1, 2, 3], &[Pose::new(0.0, 0.0, 0.0), Pose::new(0.1, 0.0, 0.0), Pose::new(0.0, 0.5, 0.0)]);
        assert_eq!(p.steps_below, 2);
        assert_eq!(p.first_below.map(|f| (f.pair, f.t)), Some(([1, 2], 0.1)));
        assert_eq!(p.closest.map(|c| c.t), Some(0.2));
        let text = p.violation_text().expect("violated");
        assert!(text.starts_with("robots 1 and 2 came 0.200 m apart at t = 0.1 s"), "{text}");
    }
}
