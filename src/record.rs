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
            formation_error: norm(p.x - leader.pose.x - offset[0], p.y - leader.pose.y - offset[1]),
            heading_error: wrap(p.theta - leader.pose.theta).abs(),
            estimator_error: norm(e.pose.x - leader.pose.x, e.pose.y - leader.pose.y),
            estimator_v_error: (e.v - leader.v).abs(),
            estimator_w_error: (e.w - leader.w).abs(),
        }
    }
}

/// ‖(a, b)‖. Plain sqrt(a² + b²): `hypot`'s overflow guard costs a third of
/// a row and positions here are far from 1e154 m.
fn norm(a: f64, b: f64) -> f64 {
    (a * a + b * b).sqrt()
}

/// The SPEC §11 metrics of one follower (SI units; RMSE not scaled).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FollowerMetrics {
    /// RMS of the formation error over the samples with t ≥ T − 10, m.
    pub formation_rms_last10: f64,
    /// Formation error at t = T, m.
    pub formation_final: f64,
    /// Heading error at t = T, rad.
    pub heading_final: f64,
    /// Estimator position error at t = T, m.
    pub estimator_error_final: f64,
    /// Estimator |v_ir − v_r| at t = T, m/s.
    pub estimator_v_error_final: f64,
    /// Estimator |ω_ir − ω_r| at t = T, rad/s.
    pub estimator_w_error_final: f64,
    /// Peak |v_c|, m/s (speed jump).
    pub vc_peak: f64,
    /// Σ_k (|Δτ_L| + |Δτ_R|) / T, N m/s (chattering).
    pub torque_tv: f64,
    /// Peak |τ| over both wheels, N m.
    pub torque_peak: f64,
    /// sqrt(mean((v̂ − v)²)) over all samples, m/s.
    pub rmse_v: f64,
    /// sqrt(mean((ω̂ − ω)²)) over all samples, rad/s.
    pub rmse_w: f64,
    /// Number of samples the metrics were computed from.
    pub samples: u64,
}

/// Streaming accumulator of [`FollowerMetrics`] (O(1) memory per follower).
#[derive(Clone, Debug, Default)]
pub struct MetricsAccumulator {
    last10_from_k: u64,
    duration_s: f64,
    sum_formation_sq_last10: f64,
    n_last10: u64,
    sum_v_sq: f64,
    sum_w_sq: f64,
    prev_torque: Option<(f64, f64)>,
    tv: f64,
    last: Row,
    m: FollowerMetrics,
}

impl MetricsAccumulator {
    /// For a run of `steps` steps of Δt: "the last 10 s" are the samples
    /// with k ≥ (T − 10)/Δt (all samples when T ≤ 10).
    pub fn new(steps: u64, dt_s: f64) -> Self {
        let duration_s = steps as f64 * dt_s;
        // The first k with k Δt ≥ T − 10 (the 1e-9 absorbs rounding of a
        // quotient that is whole on paper).
        let last10_from_k = if duration_s > 10.0 { ((duration_s - 10.0) / dt_s - 1e-9).ceil() as u64 } else { 0 };
        Self { last10_from_k, duration_s, ..Default::default() }
    }

    /// Adds the sample of step k (samples must come in step order).
    pub fn push(&mut self, k: u64, r: &Row) {
        let m = &mut self.m;
        if k >= self.last10_from_k {
            self.sum_formation_sq_last10 += r.formation_error * r.formation_error;
            self.n_last10 += 1;
        }
        self.sum_v_sq += (r.v_hat - r.v) * (r.v_hat - r.v);
        self.sum_w_sq += (r.w_hat - r.w) * (r.w_hat - r.w);
        m.vc_peak = m.vc_peak.max(r.v_c.abs());
        m.torque_peak = m.torque_peak.max(r.tau_l.abs()).max(r.tau_r.abs());
        if let Some((l, rr)) = self.prev_torque {
            self.tv += (r.tau_l - l).abs() + (r.tau_r - rr).abs();
        }
        self.prev_torque = Some((r.tau_l, r.tau_r));
        m.samples += 1;
        self.last = *r;
    }

    pub fn finish(&self) -> FollowerMetrics {
        let n = self.m.samples.max(1) as f64;
        FollowerMetrics {
            formation_rms_last10: (self.sum_formation_sq_last10 / self.n_last10.max(1) as f64).sqrt(),
            formation_final: self.last.formation_error,
            heading_final: self.last.heading_error,
            estimator_error_final: self.last.estimator_error,
            estimator_v_error_final: self.last.estimator_v_error,
            estimator_w_error_final: self.last.estimator_w_error,
            torque_tv: if self.duration_s > 0.0 { self.tv / self.duration_s } else { 0.0 },
            rmse_v: (self.sum_v_sq / n).sqrt(),
            rmse_w: (self.sum_w_sq / n).sqrt(),
            ..self.m
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
    pub followers: BTreeMap<u32, FollowerMetrics>,
}

impl Summary {
    pub fn new(s: &Scenario, followers: BTreeMap<u32, FollowerMetrics>) -> Self {
        Self {
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
            followers,
        }
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_default() + "\n"
    }

    /// A compact, aligned table of the metrics.
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
        for (id, m) in &self.followers {
            out += &format!(
                "{:>8} {:>11.4} {:>10.4} {:>9.4} {:>10.2e} {:>9.3} {:>10.3} {:>9.3} {:>9.2e} {:>9.2e}\n",
                id,
                m.formation_rms_last10,
                m.formation_final,
                m.heading_final,
                m.estimator_error_final,
                m.vc_peak,
                m.torque_tv,
                m.torque_peak,
                m.rmse_v,
                m.rmse_w
            );
        }
        out
    }
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
    ids: Vec<u32>,
    buffers: Vec<Vec<u8>>,
    leader_buffer: Vec<u8>,
    flush_at: usize,
}

const FOLLOWER_HEADER: &str = "t,x,y,theta,v,w,v_hat,w_hat,x_ir,y_ir,theta_ir,v_ir,w_ir,v_c,w_c,tau_l,tau_r,formation_error,heading_error,estimator_error,estimator_v_error,estimator_w_error\n";
const LEADER_HEADER: &str = "t,x,y,theta,v,w\n";

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
        refuse_foreign_folder(&self.final_dir)?;
        if self.final_dir.exists() {
            fs::remove_dir_all(&self.final_dir).map_err(at_path(&self.final_dir, "cannot replace the old run"))?;
        }
        let what = format!("cannot move {} here", self.dir.display());
        fs::rename(&self.dir, &self.final_dir).map_err(at_path(&self.final_dir, &what))?;
        Ok(self.final_dir.clone())
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
