//! One follower's step as recorded: the [`FollowerSample`] a follower
//! reports and the CSV [`Row`] made of it against the true leader
//! (docs/model.md §11).

use formation_control::slot::{formation_error, Frame};
use formation_control::StepOutput;
use formation_leader::LeaderState;
use formation_plant::wrap;
use formation_plant::{Pose, Velocity};
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
    /// What the limits and the safety filter did (docs/model.md §16);
    /// None where the scenario has neither.
    pub guard: Option<formation_control::GuardStep>,
}

impl FollowerSample {
    #[inline]
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
            guard: out.guard,
        }
    }

    #[inline]
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

/// One CSV row: the sample plus the errors against the true leader (docs/model.md §11).
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
    /// The row's fields in [`FOLLOWER_HEADER`]'s order: what the CSV holds.
    #[inline]
    pub fn csv_fields(&self) -> [f64; 22] {
        [
            self.t,
            self.x,
            self.y,
            self.theta,
            self.v,
            self.w,
            self.v_hat,
            self.w_hat,
            self.x_ir,
            self.y_ir,
            self.theta_ir,
            self.v_ir,
            self.w_ir,
            self.v_c,
            self.w_c,
            self.tau_l,
            self.tau_r,
            self.formation_error,
            self.heading_error,
            self.estimator_error,
            self.estimator_v_error,
            self.estimator_w_error,
        ]
    }

    /// The row of a sample against the true leader state at the same step.
    #[inline]
    pub fn new(s: &FollowerSample, leader: &LeaderState, frame: Frame, offset: [f64; 2], dt_s: f64) -> Self {
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
            formation_error: formation_error(frame, p, &leader.pose, offset),
            heading_error: wrap(p.theta - leader.pose.theta).abs(),
            estimator_error: norm(e.pose.x - leader.pose.x, e.pose.y - leader.pose.y),
            estimator_v_error: (e.v - leader.v).abs(),
            estimator_w_error: (e.w - leader.w).abs(),
        }
    }
}

/// ‖(a, b)‖. Plain sqrt(a² + b²): `hypot`'s overflow guard costs a third of
/// a row and positions here are far from 1e154 m.
#[inline]
fn norm(a: f64, b: f64) -> f64 {
    (a * a + b * b).sqrt()
}

/// The header of every `follower_<id>.csv`: [`Row`]'s fields in order.
pub const FOLLOWER_HEADER: &str = "t,x,y,theta,v,w,v_hat,w_hat,x_ir,y_ir,theta_ir,v_ir,w_ir,v_c,w_c,tau_l,tau_r,formation_error,heading_error,estimator_error,estimator_v_error,estimator_w_error\n";
/// The fields of a `leader.csv` row at time `t`, in [`LEADER_HEADER`]'s order.
#[inline]
pub fn leader_csv_fields(t: f64, l: &LeaderState) -> [f64; 6] {
    [t, l.pose.x, l.pose.y, l.pose.theta, l.v, l.w]
}

/// The header of `leader.csv`.
pub const LEADER_HEADER: &str = "t,x,y,theta,v,w\n";
