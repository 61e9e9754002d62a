//! The per-follower metrics of docs/model.md §11, accumulated sample by
//! sample in O(1) memory (and, per fault window, those of §14).

use formation_control::{GuardStep, GuardTally};
use formation_leader::LeaderState;
use formation_scenario::Scenario;
use serde::{Deserialize, Serialize};

use crate::outage::{OutageAccumulator, OutageMetrics, Window};
use crate::row::{FollowerSample, Row};
use formation_control::slot::{formation_error, Frame};

/// The docs/model.md §11 metrics of one follower (SI units; RMSE not scaled). A
/// metric is `None` (`null` in `summary.json`) when the samples it needs
/// were not recorded: the last 10 s, the sample at t = T, or any sample.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FollowerMetrics {
    /// RMS of the formation error over the samples with t ≥ T − 10, m.
    pub formation_rms_last10: Option<f64>,
    /// Formation error at t = T, m.
    pub formation_final: Option<f64>,
    /// Heading error at t = T, rad.
    pub heading_final: Option<f64>,
    /// Estimator position error at t = T, m.
    pub estimator_error_final: Option<f64>,
    /// Estimator |v_ir − v_r| at t = T, m/s.
    pub estimator_v_error_final: Option<f64>,
    /// Estimator |ω_ir − ω_r| at t = T, rad/s.
    pub estimator_w_error_final: Option<f64>,
    /// Peak |v_c|, m/s (speed jump).
    pub vc_peak: Option<f64>,
    /// Σ_k (|Δτ_L| + |Δτ_R|) / T, N m/s (chattering); over the recorded
    /// span instead of T when the run is incomplete.
    pub torque_tv: Option<f64>,
    /// Peak |τ| over both wheels, N m.
    pub torque_peak: Option<f64>,
    /// sqrt(mean((v̂ − v)²)) over all samples, m/s.
    pub rmse_v: Option<f64>,
    /// sqrt(mean((ω̂ − ω)²)) over all samples, rad/s.
    pub rmse_w: Option<f64>,
    /// Number of samples the metrics were computed from.
    pub samples: u64,
    /// Steps missing between recorded ones (an agent that was down,
    /// telemetry lost for good; `network.json` lists the gaps). Written only
    /// when not 0.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub gap_steps: u64,
    /// What the limits and the safety filter did to the commands
    /// (docs/model.md §16); absent when the scenario has neither.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub guard: Option<formation_control::GuardTally>,
}

/// The formation error, m, within which a follower counts as in its new
/// slot after a shape change.
pub const SETTLED_M: f64 = 0.1;

/// One shape change's window [from_k, until_k) and the first step of the
/// run of steps within [`SETTLED_M`] that the window's samples end on.
#[derive(Clone, Copy, Debug, Default)]
struct Settling {
    from_k: u64,
    until_k: u64,
    within_from: Option<u64>,
}

impl FollowerMetrics {
    /// Nulls the metrics whose window `samples` (steps 0, 1, … in order)
    /// does not cover to its end in a run of `steps` steps. Older
    /// `summary.json` files wrote 0 there.
    pub fn null_unreached(&mut self, steps: u64) {
        // How far the record reached: its samples and the gaps between them.
        let reached = self.samples + self.gap_steps;
        // A window the record does not cover to its end has no value: the
        // last 10 s of a follower that stopped at 5 s of 12 was its RMS
        // over 2–5 s, called the last 10 s.
        if reached <= steps {
            self.formation_rms_last10 = None;
            for m in [
                &mut self.formation_final,
                &mut self.heading_final,
                &mut self.estimator_error_final,
                &mut self.estimator_v_error_final,
                &mut self.estimator_w_error_final,
            ] {
                *m = None;
            }
        }
        if self.samples == 0 {
            *self = Self::default();
        }
    }
}

/// The first step k of "the last 10 s" of a run of `steps` steps of Δt: the
/// first k with k Δt ≥ T − 10 (0 when T ≤ 10).
pub fn last10_from_k(steps: u64, dt_s: f64) -> u64 {
    let duration_s = steps as f64 * dt_s;
    if duration_s > 10.0 {
        formation_control::math::step_at(duration_s - 10.0, dt_s)
    } else {
        0
    }
}

/// One sample's formation error (read in the last 10 s and after shape
/// changes only) and its
/// (estimate, true) velocities.
struct Errors {
    formation: f64,
    v: [f64; 2],
    w: [f64; 2],
}

/// Streaming accumulator of [`FollowerMetrics`] (O(1) memory per follower).
#[derive(Clone, Debug, Default)]
pub struct MetricsAccumulator {
    steps: u64,
    dt_s: f64,
    last10_from_k: u64,
    sum_formation_sq_last10: f64,
    n_last10: u64,
    sum_v_sq: f64,
    sum_w_sq: f64,
    /// The torques of the previous sample, and its step.
    prev_torque: Option<(u64, f64, f64)>,
    tv: f64,
    vc_peak: f64,
    torque_peak: f64,
    samples: u64,
    /// The sample of step `steps` (t = T) was pushed.
    reached_final: bool,
    /// The step after the last one pushed.
    next_k: u64,
    /// The errors at t = T (formation, heading, estimator position, v, ω):
    /// the sample of step `steps`, valid when `reached_final`.
    finals: [f64; 5],
    /// One per fault window of the scenario (docs/model.md §14's metrics under faults).
    outages: Vec<OutageAccumulator>,
    /// What the guard did, where the scenario has one.
    guard: Option<GuardTally>,
    /// One per shape change of the scenario.
    settling: Vec<Settling>,
}

impl MetricsAccumulator {
    /// For a run of `steps` steps of Δt: "the last 10 s" are the samples
    /// with k ≥ (T − 10)/Δt (all samples when T ≤ 10).
    pub fn new(steps: u64, dt_s: f64) -> Self {
        Self { steps, dt_s, last10_from_k: last10_from_k(steps, dt_s), ..Default::default() }
    }

    /// For a scenario, with its fault windows.
    pub fn for_scenario(s: &Scenario) -> Self {
        let mut a = Self::new(s.steps(), s.dt_s);
        a.guard = (!s.control.guard.is_off()).then(GuardTally::default);
        a.outages = Window::all(s).into_iter().map(|w| OutageAccumulator::new(w, s.dt_s)).collect();
        let starts: Vec<u64> = s.shapes.iter().map(|c| c.from_k).collect();
        let ends = starts.iter().skip(1).copied().chain([s.steps() + 1]);
        a.settling =
            starts.iter().zip(ends).map(|(&from_k, until_k)| Settling { from_k, until_k, within_from: None }).collect();
        a
    }

    /// The metrics around each fault window, in table order.
    pub fn outages(&self) -> Vec<OutageMetrics> {
        self.outages.iter().map(|o| o.finish()).collect()
    }

    /// What the guard did so far (None without limits or a filter).
    pub fn guard(&self) -> Option<&GuardTally> {
        self.guard.as_ref()
    }

    /// What the guard did at a step (docs/model.md §16): the sample's, where
    /// the scenario has a guard.
    #[inline]
    fn push_guard(&mut self, g: Option<&GuardStep>) {
        if let (Some(tally), Some(g)) = (self.guard.as_mut(), g) {
            tally.add(g);
        }
    }

    /// Adds the row of step k (rows must come in step order) and what the
    /// guard did at it (the sample's `guard`).
    #[inline]
    pub fn push(&mut self, k: u64, r: &Row, guard: Option<&GuardStep>) {
        self.push_guard(guard);
        let errors = Errors { formation: r.formation_error, v: [r.v_hat, r.v], w: [r.w_hat, r.w] };
        self.accumulate(k, &errors, r.v_c, r.tau_l, r.tau_r);
        if k == self.steps {
            self.finals =
                [r.formation_error, r.heading_error, r.estimator_error, r.estimator_v_error, r.estimator_w_error];
        }
        for o in &mut self.outages {
            o.push(k, r);
        }
    }

    /// [`MetricsAccumulator::push`] of `Row::new(s, leader, frame, offset, dt_s)`,
    /// the same numbers, but computing only what the metrics read when no
    /// one else needs the row (the simulator without an observer).
    #[inline]
    pub fn push_sample(
        &mut self,
        k: u64,
        s: &FollowerSample,
        leader: &LeaderState,
        frame: Frame,
        offset: [f64; 2],
        dt_s: f64,
    ) {
        if k == self.steps || !self.outages.is_empty() {
            return self.push(k, &Row::new(s, leader, frame, offset, dt_s), s.guard.as_ref());
        }
        self.push_guard(s.guard.as_ref());
        // Row::new's formation error, needed only in the last 10 s.
        let formation =
            if k >= self.last10_from_k { formation_error(frame, &s.pose, &leader.pose, offset) } else { 0.0 };
        let errors =
            Errors { formation, v: [s.velocity_estimate.v, s.velocity.v], w: [s.velocity_estimate.w, s.velocity.w] };
        self.accumulate(k, &errors, s.command.v, s.torque_l, s.torque_r);
    }

    /// What every sample adds (in this order: the same sums whichever way in).
    #[inline]
    fn accumulate(&mut self, k: u64, e: &Errors, v_c: f64, tau_l: f64, tau_r: f64) {
        if k >= self.last10_from_k {
            self.sum_formation_sq_last10 += e.formation * e.formation;
            self.n_last10 += 1;
        }
        self.sum_v_sq += (e.v[0] - e.v[1]) * (e.v[0] - e.v[1]);
        self.sum_w_sq += (e.w[0] - e.w[1]) * (e.w[0] - e.w[1]);
        self.vc_peak = self.vc_peak.max(v_c.abs());
        self.torque_peak = self.torque_peak.max(tau_l.abs()).max(tau_r.abs());
        // Across a gap in the record (a node that was down) there is no Δτ to add.
        if let Some((_, l, rr)) = self.prev_torque.filter(|p| p.0 + 1 == k) {
            self.tv += (tau_l - l).abs() + (tau_r - rr).abs();
        }
        self.prev_torque = Some((k, tau_l, tau_r));
        for w in self.settling.iter_mut().filter(|w| (w.from_k..w.until_k).contains(&k)) {
            w.within_from = if e.formation < SETTLED_M { w.within_from.or(Some(k)) } else { None };
        }
        self.samples += 1;
        self.next_k = self.next_k.max(k + 1);
        self.reached_final = k == self.steps;
    }

    /// Every step below `k` not pushed by now never will be (a follower
    /// killed, its last telemetry lost with its process): counted as steps
    /// in gaps, as a hole in the middle is.
    pub fn gap_to(&mut self, k: u64) {
        self.next_k = self.next_k.max(k);
    }

    /// Bytes this holds on the heap (one accumulator per fault window).
    pub fn heap_bytes(&self) -> usize {
        self.outages.capacity() * std::mem::size_of::<OutageAccumulator>()
    }

    /// The metrics of the samples pushed so far; `None` for a metric whose
    /// window they do not reach (never 0).
    pub fn finish(&self) -> FollowerMetrics {
        let n = self.samples;
        let any = n > 0;
        let at_t = |x: f64| self.reached_final.then_some(x);
        // T for a complete run: samples 0..=steps span steps Δt (gaps included).
        let span_s = self.next_k.saturating_sub(1) as f64 * self.dt_s;
        FollowerMetrics {
            formation_rms_last10: (self.n_last10 > 0)
                .then(|| (self.sum_formation_sq_last10 / self.n_last10 as f64).sqrt()),
            formation_final: at_t(self.finals[0]),
            heading_final: at_t(self.finals[1]),
            estimator_error_final: at_t(self.finals[2]),
            estimator_v_error_final: at_t(self.finals[3]),
            estimator_w_error_final: at_t(self.finals[4]),
            vc_peak: any.then_some(self.vc_peak),
            torque_tv: any.then(|| if span_s > 0.0 { self.tv / span_s } else { 0.0 }),
            torque_peak: any.then_some(self.torque_peak),
            rmse_v: any.then(|| (self.sum_v_sq / n as f64).sqrt()),
            rmse_w: any.then(|| (self.sum_w_sq / n as f64).sqrt()),
            samples: n,
            gap_steps: self.next_k.saturating_sub(n),
            guard: self.guard,
        }
    }

    /// Per shape change (docs/model.md §17): how long after it, s, the
    /// formation error came within [`SETTLED_M`] and stayed there until the
    /// next change or the last sample pushed (None: it did not).
    pub fn settled_after(&self) -> Vec<Option<f64>> {
        self.settling.iter().map(|w| w.within_from.map(|k| (k - w.from_k) as f64 * self.dt_s)).collect()
    }
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}
