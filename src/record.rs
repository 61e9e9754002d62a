//! What a run records: one [`Row`] per follower and step, the SPEC §11
//! metrics computed from the rows, and the run folder (a CSV per follower,
//! `leader.csv`, `summary.json`). The simulator and the monitor both record
//! through this module, so their folders have the same shape and, for the
//! same rows, the same numbers.

use std::collections::BTreeMap;
use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use formation_agent::math::wrap;
use formation_agent::{LeaderState, StepOutput};
use formation_plant::{Pose, Velocity};
use formation_topology::Scenario;
use serde::{Deserialize, Serialize};

/// What a follower reports about one step: everything on the robot side.
/// (This is also the monitor's telemetry payload.)
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FollowerSample {
    pub k: u64,
    pub pose: Pose,
    pub velocity: Velocity,
    pub velocity_estimate: Velocity,
    pub estimate: LeaderState,
    pub command: Velocity,
    pub torque_l: f64,
    pub torque_r: f64,
}

impl FollowerSample {
    pub fn new(out: &StepOutput, pose: Pose, velocity: Velocity) -> Self {
        Self {
            k: out.k,
            pose,
            velocity,
            velocity_estimate: out.velocity_estimate,
            estimate: out.estimate,
            command: out.command,
            torque_l: out.torque.left,
            torque_r: out.torque.right,
        }
    }

    pub fn is_finite(&self) -> bool {
        self.pose.is_finite()
            && self.velocity.is_finite()
            && self.velocity_estimate.is_finite()
            && self.estimate.is_finite()
            && self.command.is_finite()
            && self.torque_l.is_finite()
            && self.torque_r.is_finite()
    }
}

/// One CSV row: the sample plus the errors against the true leader (SPEC §11).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Row {
    pub t: f64,
    pub x: f64,
    pub y: f64,
    pub theta: f64,
    pub v: f64,
    pub w: f64,
    pub v_hat: f64,
    pub w_hat: f64,
    pub x_ir: f64,
    pub y_ir: f64,
    pub theta_ir: f64,
    pub v_ir: f64,
    pub w_ir: f64,
    pub v_c: f64,
    pub w_c: f64,
    pub tau_l: f64,
    pub tau_r: f64,
    /// ‖(x − x_r − Δx, y − y_r − Δy)‖, m.
    pub formation_error: f64,
    /// |wrap(θ − θ_r)|, rad.
    pub heading_error: f64,
    /// ‖(x_ir, y_ir) − (x_r, y_r)‖, m.
    pub estimator_error: f64,
    /// |v_ir − v_r|, m/s.
    pub estimator_v_error: f64,
    /// |ω_ir − ω_r|, rad/s.
    pub estimator_w_error: f64,
}

impl Row {
    /// The row of a sample against the true leader state at the same step.
    pub fn new(s: &FollowerSample, leader: &LeaderState, offset: [f64; 2], dt_s: f64) -> Self {
        let p = &s.pose;
        let e = &s.estimate;
        Self {
            t: s.k as f64 * dt_s,
            x: p.x,
            y: p.y,
            theta: p.theta,
            v: s.velocity.v,
            w: s.velocity.w,
            v_hat: s.velocity_estimate.v,
            w_hat: s.velocity_estimate.w,
            x_ir: e.pose.x,
            y_ir: e.pose.y,
            theta_ir: e.pose.theta,
            v_ir: e.v,
            w_ir: e.w,
            v_c: s.command.v,
            w_c: s.command.w,
            tau_l: s.torque_l,
            tau_r: s.torque_r,
            formation_error: formation_error(p, leader, offset),
            heading_error: wrap(p.theta - leader.pose.theta).abs(),
            estimator_error: norm(e.pose.x - leader.pose.x, e.pose.y - leader.pose.y),
            estimator_v_error: (e.v - leader.v).abs(),
            estimator_w_error: (e.w - leader.w).abs(),
        }
    }
}

/// [`Row::formation_error`].
fn formation_error(p: &Pose, leader: &LeaderState, offset: [f64; 2]) -> f64 {
    norm(p.x - leader.pose.x - offset[0], p.y - leader.pose.y - offset[1])
}

/// ‖(a, b)‖. Plain sqrt(a² + b²): `hypot`'s overflow guard costs a third of
/// a row and positions here are far from 1e154 m.
fn norm(a: f64, b: f64) -> f64 {
    (a * a + b * b).sqrt()
}

/// The SPEC §11 metrics of one follower (SI units; RMSE not scaled). A
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
}

impl FollowerMetrics {
    /// Nulls the metrics whose window `samples` (steps 0, 1, … in order)
    /// does not reach in a run of `steps` steps of Δt. A no-op for metrics
    /// from [`MetricsAccumulator`]; older `summary.json` files wrote 0 there.
    pub fn null_unreached(&mut self, steps: u64, dt_s: f64) {
        // How far the record reached: its samples and the gaps between them.
        let reached = self.samples + self.gap_steps;
        if reached <= last10_from_k(steps, dt_s) {
            self.formation_rms_last10 = None;
        }
        if reached <= steps {
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
        formation_agent::math::step_at(duration_s - 10.0, dt_s)
    } else {
        0
    }
}

/// One sample's formation error (read in the last 10 s only) and its
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
    /// One per fault window of the scenario (SPEC §14's metrics under faults).
    outages: Vec<crate::outage::OutageAccumulator>,
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
        a.outages = crate::outage::Window::all(s)
            .into_iter()
            .map(|w| crate::outage::OutageAccumulator::new(w, s.dt_s))
            .collect();
        a
    }

    /// The metrics around each fault window, in table order.
    pub fn outages(&self) -> Vec<crate::outage::OutageMetrics> {
        self.outages.iter().map(|o| o.finish()).collect()
    }

    /// Adds the sample of step k (samples must come in step order).
    pub fn push(&mut self, k: u64, r: &Row) {
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

    /// [`MetricsAccumulator::push`] of `Row::new(s, leader, offset, dt_s)`,
    /// the same numbers, but computing only what the metrics read when no
    /// one else needs the row (the simulator without an observer).
    pub fn push_sample(&mut self, k: u64, s: &FollowerSample, leader: &LeaderState, offset: [f64; 2], dt_s: f64) {
        if k == self.steps || !self.outages.is_empty() {
            return self.push(k, &Row::new(s, leader, offset, dt_s));
        }
        // Row::new's formation error, needed only in the last 10 s.
        let formation = if k >= self.last10_from_k { formation_error(&s.pose, leader, offset) } else { 0.0 };
        let errors =
            Errors { formation, v: [s.velocity_estimate.v, s.velocity.v], w: [s.velocity_estimate.w, s.velocity.w] };
        self.accumulate(k, &errors, s.command.v, s.torque_l, s.torque_r);
    }

    /// What every sample adds (in this order: the same sums whichever way in).
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
        self.samples += 1;
        self.next_k = k + 1;
        self.reached_final = k == self.steps;
    }

    /// Bytes this holds on the heap (one accumulator per fault window).
    pub fn heap_bytes(&self) -> usize {
        self.outages.capacity() * std::mem::size_of::<crate::outage::OutageAccumulator>()
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
        }
    }
}

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
    /// Every follower recorded all steps + 1 samples (t = 0 to T, SPEC §9).
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
    /// SPEC §14's metrics under faults, per fault window and follower.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub faults: Vec<crate::outage::FaultSummary>,
}

/// How many samples a follower of an incomplete run recorded, of how many.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shortfall {
    pub recorded: u64,
    /// steps + 1.
    pub expected: u64,
    /// Of the missing ones, steps missing between recorded ones.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub in_gaps: u64,
}

impl Shortfall {
    /// "follower 3 recorded 8150 of 20001 samples (to t = 8.149 s of T = 20 s)".
    pub fn describe(&self, id: u32, dt_s: f64, duration_s: f64) -> String {
        let reached = match self.recorded {
            0 => String::new(),
            // To the microsecond: 1499 × 0.001 prints as 1.499, not 1.4990000000000001.
            n => format!(" (to t = {} s of T = {duration_s} s)", ((n - 1) as f64 * dt_s * 1e6).round() / 1e6),
        };
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
        let mut summary = Self {
            scenario: s.name.clone(),
            seed: s.seed,
            dt: s.dt_s,
            duration: s.duration_s,
            steps: s.steps(),
            noise: s.noise,
            kinematic: name(&s.control.kinematic),
            dynamic: name(&s.control.dynamic),
            filter: name(&s.control.filter.kind),
            estimate_init: name(&s.estimate_init),
            fault_time: s.control.fault.map(|f| f.time_s),
            lambda_min_h: s.graph.lambda_min_h(),
            complete: true,
            incomplete: BTreeMap::new(),
            followers,
            rejoin: (!s.faults.is_empty()).then(|| name(&s.control.rejoin.policy)),
            faults: Vec::new(),
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
            m.null_unreached(self.steps, self.dt);
        }
        self.incomplete = self
            .followers
            .iter()
            .filter(|(_, m)| m.samples < expected)
            .map(|(&id, m)| (id, Shortfall { recorded: m.samples, expected, in_gaps: m.gap_steps }))
            .collect();
        self.complete = self.incomplete.is_empty();
    }

    /// What the run is missing, a clause for each of the first three short
    /// followers (`incomplete` lists them all); `None` when complete.
    pub fn shortfall_text(&self) -> Option<String> {
        let mut parts: Vec<String> =
            self.incomplete.iter().take(3).map(|(&id, s)| s.describe(id, self.dt, self.duration)).collect();
        if self.incomplete.len() > 3 {
            parts.push(format!("and {} more followers", self.incomplete.len() - 3));
        }
        (!parts.is_empty()).then(|| parts.join("; "))
    }

    /// Adds the metrics under faults (by follower id, one per fault window).
    pub fn with_outages(
        mut self,
        s: &Scenario,
        per_follower: &BTreeMap<u32, Vec<crate::outage::OutageMetrics>>,
    ) -> Self {
        self.faults = crate::outage::FaultSummary::all(s, per_follower);
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
        out += &crate::outage::table(&self.faults);
        out
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

/// Where and how densely a run folder is written.
#[derive(Clone, Debug)]
pub struct RecordOptions {
    pub dir: PathBuf,
    /// Write every N-th sample to the CSVs (metrics use every sample).
    pub every: u64,
    /// Write CSVs at all.
    pub csv: bool,
    /// Also write run.mcap from the CSVs ([`crate::mcap_file`]).
    pub mcap: bool,
}

/// Writes a run folder. Rows are buffered per follower and appended to the
/// follower's CSV when the buffer fills, so any number of followers works
/// with a bounded number of open files and bounded memory. The folder is
/// built under `<dir>.partial` and renamed into place by [`RunWriter::finish`].
pub struct RunWriter {
    final_dir: PathBuf,
    dir: PathBuf,
    every: u64,
    csv: bool,
    mcap: bool,
    ids: Vec<u32>,
    buffers: Vec<Vec<u8>>,
    leader_buffer: Vec<u8>,
    flush_at: usize,
}

pub(crate) const FOLLOWER_HEADER: &str = "t,x,y,theta,v,w,v_hat,w_hat,x_ir,y_ir,theta_ir,v_ir,w_ir,v_c,w_c,tau_l,tau_r,formation_error,heading_error,estimator_error,estimator_v_error,estimator_w_error\n";
pub(crate) const LEADER_HEADER: &str = "t,x,y,theta,v,w\n";

impl RunWriter {
    pub fn create(opts: &RecordOptions, ids: &[u32]) -> std::io::Result<Self> {
        refuse_foreign_folder(&opts.dir)?;
        let mut partial = opts.dir.clone().into_os_string();
        partial.push(".partial");
        let dir = PathBuf::from(partial);
        if dir.exists() {
            fs::remove_dir_all(&dir).map_err(at_path(&dir, "cannot remove the old folder"))?;
        }
        fs::create_dir_all(&dir).map_err(at_path(&dir, "cannot create the folder"))?;
        let flush_at = (64 << 20) / ids.len().max(1);
        let flush_at = flush_at.clamp(4 << 10, 1 << 20);
        let mut w = Self {
            final_dir: opts.dir.clone(),
            dir,
            every: opts.every.max(1),
            csv: opts.csv,
            mcap: opts.mcap,
            ids: ids.to_vec(),
            buffers: vec![FOLLOWER_HEADER.as_bytes().to_vec(); ids.len()],
            leader_buffer: LEADER_HEADER.as_bytes().to_vec(),
            flush_at,
        };
        if w.csv {
            for i in 0..ids.len() {
                let path = w.follower_path(i);
                File::create(&path).map_err(at_path(&path, "cannot create"))?;
            }
            let path = w.dir.join("leader.csv");
            File::create(&path).map_err(at_path(&path, "cannot create"))?;
        }
        w.flush_all()?;
        Ok(w)
    }

    fn follower_path(&self, index: usize) -> PathBuf {
        self.dir.join(format!("follower_{}.csv", self.ids[index]))
    }

    /// Whether sample k goes into the CSVs.
    pub fn wants(&self, k: u64, last: bool) -> bool {
        self.csv && (k % self.every == 0 || last)
    }

    pub fn follower_row(&mut self, index: usize, r: &Row) -> std::io::Result<()> {
        let b = &mut self.buffers[index];
        let fields = [
            r.t,
            r.x,
            r.y,
            r.theta,
            r.v,
            r.w,
            r.v_hat,
            r.w_hat,
            r.x_ir,
            r.y_ir,
            r.theta_ir,
            r.v_ir,
            r.w_ir,
            r.v_c,
            r.w_c,
            r.tau_l,
            r.tau_r,
            r.formation_error,
            r.heading_error,
            r.estimator_error,
            r.estimator_v_error,
            r.estimator_w_error,
        ];
        write_fields(b, &fields);
        if b.len() >= self.flush_at {
            let path = self.follower_path(index);
            append(&path, &mut self.buffers[index])?;
        }
        Ok(())
    }

    pub fn leader_row(&mut self, t: f64, l: &LeaderState) -> std::io::Result<()> {
        write_fields(&mut self.leader_buffer, &[t, l.pose.x, l.pose.y, l.pose.theta, l.v, l.w]);
        if self.leader_buffer.len() >= self.flush_at {
            append(&self.dir.join("leader.csv"), &mut self.leader_buffer)?;
        }
        Ok(())
    }

    fn flush_all(&mut self) -> std::io::Result<()> {
        if !self.csv {
            return Ok(());
        }
        for i in 0..self.ids.len() {
            let path = self.follower_path(i);
            append(&path, &mut self.buffers[i])?;
        }
        append(&self.dir.join("leader.csv"), &mut self.leader_buffer)
    }

    /// Writes an extra file into the run folder.
    pub fn write_file(&self, name: &str, contents: &str) -> std::io::Result<()> {
        let path = self.dir.join(name);
        fs::write(&path, contents).map_err(at_path(&path, "cannot write"))
    }

    /// Flushes the CSVs and writes what has been recorded so far, without
    /// finishing (for a partial run that stops with an error).
    pub fn flush(&mut self) -> std::io::Result<()> {
        self.flush_all()
    }

    /// Flushes everything, writes `summary.json` and moves the folder into place.
    pub fn finish(mut self, summary: &Summary) -> std::io::Result<PathBuf> {
        self.flush_all()?;
        self.write_file("summary.json", &summary.to_json())?;
        if self.csv && self.mcap {
            crate::mcap_file::write(&self.dir, &self.ids)?;
        }
        refuse_foreign_folder(&self.final_dir)?;
        if self.final_dir.exists() {
            fs::remove_dir_all(&self.final_dir).map_err(at_path(&self.final_dir, "cannot replace the old run"))?;
        }
        let what = format!("cannot move {} here", self.dir.display());
        fs::rename(&self.dir, &self.final_dir).map_err(at_path(&self.final_dir, &what))?;
        Ok(self.final_dir.clone())
    }

    /// Removes the `<dir>.partial` folder: nothing of it is worth keeping.
    pub fn discard(self) {
        let _ = fs::remove_dir_all(&self.dir);
    }

    /// The folder being written (`<dir>.partial` until finished).
    pub fn partial_dir(&self) -> &Path {
        &self.dir
    }
}

/// A run folder is replaced by a new run only if it is one: empty, or
/// holding a `summary.json` or `network.json`. Anything else (`--out .`,
/// `--out ~`, a folder of the user's, a file) is refused rather than deleted.
pub fn refuse_foreign_folder(dir: &Path) -> std::io::Result<()> {
    if fs::metadata(dir).is_ok_and(|m| !m.is_dir()) {
        return Err(std::io::Error::new(
            std::io::ErrorKind::AlreadyExists,
            format!("{} exists and is not a folder: refusing to replace it", dir.display()),
        ));
    }
    let Ok(mut entries) = fs::read_dir(dir) else { return Ok(()) };
    let is_run = dir.join("summary.json").is_file() || dir.join("network.json").is_file();
    if is_run || entries.next().is_none() {
        return Ok(());
    }
    Err(std::io::Error::new(
        std::io::ErrorKind::AlreadyExists,
        format!("{} exists and is not a run folder (no summary.json): refusing to replace it", dir.display()),
    ))
}

fn write_fields(b: &mut Vec<u8>, fields: &[f64]) {
    let mut buf = ryu::Buffer::new();
    for (i, f) in fields.iter().enumerate() {
        if i > 0 {
            b.push(b',');
        }
        b.extend_from_slice(buf.format(*f).as_bytes());
    }
    b.push(b'\n');
}

fn append(path: &Path, buffer: &mut Vec<u8>) -> std::io::Result<()> {
    if buffer.is_empty() {
        return Ok(());
    }
    let mut f = OpenOptions::new().append(true).create(true).open(path).map_err(at_path(path, "cannot open"))?;
    f.write_all(buffer).map_err(at_path(path, "cannot write"))?;
    buffer.clear();
    Ok(())
}

/// An IO error that names the path it is about (the OS message alone does
/// not: "File name too long (os error 36)"), of the same kind.
pub fn at_path<'a>(path: &'a Path, what: &'a str) -> impl FnOnce(std::io::Error) -> std::io::Error + 'a {
    move |e| std::io::Error::new(e.kind(), format!("{}: {what}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// T = 20 s at Δt = 0.01 s: 2000 steps, 2001 samples, the last 10 s from k = 1000.
    const STEPS: u64 = 2000;
    const DT: f64 = 0.01;

    fn row(k: u64) -> Row {
        let x = k as f64 * 1e-3;
        Row {
            t: k as f64 * DT,
            v: 1.0,
            v_hat: 1.0 + x,
            v_c: 2.0 - x,
            tau_l: x,
            tau_r: -x,
            formation_error: x,
            heading_error: 0.5 * x,
            estimator_error: 0.25 * x,
            ..Default::default()
        }
    }

    /// The metrics of the samples of steps 0..n.
    fn metrics_of(n: u64) -> FollowerMetrics {
        let mut acc = MetricsAccumulator::new(STEPS, DT);
        for k in 0..n {
            acc.push(k, &row(k));
        }
        acc.finish()
    }

    fn scenario() -> Scenario {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenarios/paper.toml");
        Scenario::load(&path, &["dt=0.01".to_string(), "duration=20".to_string()]).expect("scenario")
    }

    #[test]
    fn a_run_cut_before_the_last_10_s_has_null_windows_not_zeros() {
        assert_eq!(last10_from_k(STEPS, DT), 1000, "T − 10 = 10 s is step 1000");
        // Samples k = 0..=799: t ≤ 7.99 s < T − 10.
        let m = metrics_of(800);
        assert_eq!(m.samples, 800);
        assert_eq!(m.formation_rms_last10, None, "no sample with t ≥ 10 s, got {:?}", m.formation_rms_last10);
        for (name, x) in [
            ("formation_final", m.formation_final),
            ("heading_final", m.heading_final),
            ("estimator_error_final", m.estimator_error_final),
            ("estimator_v_error_final", m.estimator_v_error_final),
            ("estimator_w_error_final", m.estimator_w_error_final),
        ] {
            assert_eq!(x, None, "{name}: the sample at t = T was not recorded, got {x:?}");
        }
        // Whole-run metrics are measured over what was recorded.
        let rmse_v = (0..800).map(|k| (k as f64 * 1e-3).powi(2)).sum::<f64>() / 800.0;
        assert!((m.rmse_v.unwrap() - rmse_v.sqrt()).abs() < 1e-12, "rmse_v {:?} vs {}", m.rmse_v, rmse_v.sqrt());
        assert_eq!(m.vc_peak, Some(2.0), "peak |v_c| at k = 0: {:?}", m.vc_peak);
        // Σ|Δτ| = 2 · 799 · 1e-3 over the recorded 7.99 s, not over T = 20 s.
        let tv = m.torque_tv.unwrap();
        assert!((tv - 2.0 * 799.0 * 1e-3 / 7.99).abs() < 1e-9, "torque_tv {tv}");
        let json = serde_json::to_value(m).unwrap();
        assert!(json["formation_rms_last10"].is_null() && json["formation_final"].is_null(), "{json}");
    }

    #[test]
    fn a_run_cut_inside_the_last_10_s_has_its_rms_but_no_final_values() {
        // Samples k = 0..=1499: 500 of them in the last 10 s, none at t = T.
        let m = metrics_of(1500);
        let want = ((1000..1500).map(|k| (k as f64 * 1e-3).powi(2)).sum::<f64>() / 500.0).sqrt();
        let rms = m.formation_rms_last10.expect("500 samples with t ≥ 10 s");
        assert!((rms - want).abs() < 1e-12, "formation RMS over the recorded last 10 s {rms} vs {want}");
        assert_eq!(m.formation_final, None, "formation_final {:?} without the sample at t = T", m.formation_final);
        assert_eq!(m.estimator_error_final, None, "estimator_error_final {:?}", m.estimator_error_final);
    }

    #[test]
    fn a_complete_run_measures_everything_and_no_samples_measure_nothing() {
        let m = metrics_of(STEPS + 1);
        assert_eq!(m.formation_final, Some(2.0), "final formation error = row(2000).formation_error");
        assert_eq!(m.heading_final, Some(1.0));
        assert_eq!(m.estimator_error_final, Some(0.5));
        let tv = m.torque_tv.unwrap();
        assert!((tv - 2.0 * 2000.0 * 1e-3 / 20.0).abs() < 1e-9, "torque_tv {tv} = Σ|Δτ| / T");
        assert!(m.formation_rms_last10.is_some());
        assert_eq!(metrics_of(0), FollowerMetrics::default(), "no samples: every metric null");
    }

    #[test]
    fn summary_says_which_followers_are_short_and_older_zeros_become_null() {
        let s = scenario();
        let full = Summary::new(&s, s.followers.iter().map(|f| (f.id, metrics_of(STEPS + 1))).collect());
        assert!(full.complete && full.incomplete.is_empty());
        let json = full.to_json();
        // Complete: no key at all, so the file is what it was before the key existed.
        assert!(!json.contains("complete"), "{json}");
        let v: serde_json::Value = serde_json::from_str(&json).unwrap();
        let mut metrics = v["followers"].as_object().unwrap().values().flat_map(|m| m.as_object().unwrap().values());
        assert!(metrics.all(serde_json::Value::is_number), "a complete run has no null metric: {json}");

        let mut followers = full.followers.clone();
        followers.insert(3, metrics_of(800));
        let cut = Summary::new(&s, followers);
        assert!(!cut.complete);
        assert_eq!(cut.incomplete.len(), 1, "{:?}", cut.incomplete);
        assert_eq!(cut.incomplete[&3], Shortfall { recorded: 800, expected: 2001, in_gaps: 0 });
        let v: serde_json::Value = serde_json::from_str(&cut.to_json()).unwrap();
        assert_eq!(v["complete"], false);
        assert_eq!(v["incomplete"]["3"], serde_json::json!({ "recorded": 800, "expected": 2001 }));
        assert!(v["followers"]["3"]["formation_rms_last10"].is_null(), "{}", v["followers"]["3"]);
        assert_eq!(
            cut.shortfall_text().as_deref(),
            Some("follower 3 recorded 800 of 2001 samples (to t = 7.99 s of T = 20 s)")
        );
        assert!(cut.table().contains("incomplete run: follower 3 recorded 800 of 2001"), "{}", cut.table());

        // An older file: no `complete`, zeros for the windows not reached.
        let mut old = v.clone();
        old.as_object_mut().unwrap().remove("complete");
        old.as_object_mut().unwrap().remove("incomplete");
        for key in ["formation_rms_last10", "formation_final", "heading_final", "estimator_error_final"] {
            old["followers"]["3"][key] = 0.0.into();
        }
        let mut read: Summary = serde_json::from_value(old).expect("older summary.json loads");
        assert_eq!(read.followers[&3].formation_rms_last10, Some(0.0), "as written");
        read.mark_unreached();
        let cut: Summary = serde_json::from_value(v).unwrap();
        assert_eq!(read, cut, "an older file reads as the same incomplete run");
    }
}
