//! The virtual leader (node 0): unicycle kinematics (eq. 6) driven by a
//! velocity profile (v_r(t), ω_r(t)); the pose is integrated by forward Euler
//! like every other state (docs/model.md §3, §9).
//!
//! # Examples
//!
//! The paper's leader (section IV) with its start-up ramp, stepped for one
//! second at Δt = 10 ms:
//!
//! ```
//! use formation_leader::{Leader, Profile, Trajectory};
//! use formation_plant::Pose;
//!
//! let mut leader = Leader::new(Profile { trajectory: Trajectory::Paper, ramp_s: 0.5 }, Pose::new(0.0, 3.0, 0.0));
//! let dt = 0.01;
//! for k in 0..100 {
//!     let state = leader.state(k as f64 * dt);
//!     leader.advance(&state, dt);
//! }
//! let after = leader.state(1.0);
//! assert!(after.pose.x > 0.5 && after.pose.x < 1.0, "x = {} m after the ramp", after.pose.x);
//! assert!(after.v < std::f64::consts::SQRT_2, "v_r ≤ √2 (eq. 6's bound)");
//! ```

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use formation_plant::{wrap, Pose, Velocity};

/// The leader's velocity profile.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum Trajectory {
    /// The paper's reference x_d = t, y_d = 2 + sin(π/2 + t), hence
    /// v_d = sqrt(1 + sin² t), ω_d = −cos t / (1 + sin² t) (section IV).
    Paper,
    /// Straight line at constant speed.
    Line { speed_mps: f64 },
    /// Circle of the given radius at constant speed (counter-clockwise for a
    /// positive radius).
    Circle { speed_mps: f64, radius_m: f64 },
    /// Figure eight: two circles of the given radius, one turning left and
    /// then one turning right, repeated (ω = ±speed / radius, switching
    /// every 2π radius / speed); the path closes after both loops.
    FigureEight { speed_mps: f64, radius_m: f64 },
    /// Through the leader's route, point after point (docs/model.md §17,
    /// eq. 17.6): it turns toward the next point at ω = k_θ α within
    /// ±`turn_rate` (α the bearing of the point from its heading), drives at
    /// `speed` cos α (none while the point is behind it), takes the next
    /// point within `reach_m` of this one, and stops at the last.
    Waypoints { speed_mps: f64, turn_rate: f64, turn_gain: f64, reach_m: f64 },
    /// Steered from outside (`leader.source = "cmd_vel"`, docs/model.md
    /// §18): the unicycle (eq. 6) integrates the newest command
    /// ([`Leader::steer`]), each clipped to |v| ≤ `speed_mps`, |ω| ≤
    /// `turn_rate` ([`Profile::clip`]); silent input stops it.
    Commanded { speed_mps: f64, turn_rate: f64 },
    /// Through the newest route a planner sent (`leader.source = "path"`,
    /// a nav_msgs/Path on `/leader/path`), by eq. 17.6 as
    /// [`Trajectory::Waypoints`]; it stands until the first, and at the
    /// last point of each.
    Routed { speed_mps: f64, turn_rate: f64, turn_gain: f64, reach_m: f64 },
    /// An external robot (`leader.source = "robot"`): pose and velocities
    /// are its odometry's ([`Leader::steer`] with [`Input::Odometry`]), not
    /// integrated here; silent odometry holds the last pose at rest.
    External,
    /// A run's leader played again (`leader.source = "recorded"`): step k's
    /// state is the recording's row k, bit for bit ([`Leader::recorded`]).
    Recorded,
}

/// What steers a leader that is not scripted, at one step.
#[derive(Clone, Debug, PartialEq)]
pub enum Input {
    /// A new route ([`Trajectory::Routed`]): driven from its first point
    /// (the same route again changes nothing).
    Route(Arc<[[f64; 2]]>),
    /// A velocity command (v, ω), already clipped ([`Profile::clip`]).
    Command(Velocity),
    /// The leader robot's odometry: its pose in the world and its twist.
    Odometry { pose: Pose, twist: Velocity },
    /// Nothing fresh within the source's time-out: the leader stops.
    Silent,
}

/// A trajectory with the paper's start-up ramp v_r = v_d (1 − e^(−t/τ)).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Profile {
    pub trajectory: Trajectory,
    /// τ of the start-up ramp, s; 0 turns the ramp off. The paper uses 0.5.
    pub ramp_s: f64,
}

impl Profile {
    /// The start-up ramp's factor 1 − e^(−t/τ) at t (1 without a ramp).
    pub fn ramp(&self, t_s: f64) -> f64 {
        if self.ramp_s > 0.0 {
            1.0 - (-t_s / self.ramp_s).exp()
        } else {
            1.0
        }
    }

    /// (v_r(t), ω_r(t)) (eq. 6's inputs, with the start-up ramp on v).
    pub fn velocity(&self, t_s: f64) -> Velocity {
        let (v, w) = match self.trajectory {
            Trajectory::Paper => {
                let s = t_s.sin();
                let d = 1.0 + s * s;
                (d.sqrt(), -t_s.cos() / d)
            }
            Trajectory::Line { speed_mps } => (speed_mps, 0.0),
            Trajectory::Circle { speed_mps, radius_m } => (speed_mps, speed_mps / radius_m),
            // The route's law needs the pose, a steered leader its input: `Leader::state`.
            Trajectory::Waypoints { speed_mps, .. } => (speed_mps, 0.0),
            Trajectory::Commanded { .. } | Trajectory::Routed { .. } | Trajectory::External | Trajectory::Recorded => {
                (0.0, 0.0)
            }
            Trajectory::FigureEight { speed_mps, radius_m } => {
                let loop_s = 2.0 * std::f64::consts::PI * radius_m.abs() / speed_mps.abs();
                let turn = if (t_s / loop_s).floor() as i64 % 2 == 0 { 1.0 } else { -1.0 };
                (speed_mps, turn * speed_mps / radius_m)
            }
        };
        Velocity::new(v * self.ramp(t_s), w)
    }

    /// An upper bound of v_r over all time (used for docs/model.md §12's speed bound).
    pub fn max_speed(&self) -> f64 {
        match self.trajectory {
            Trajectory::Paper => std::f64::consts::SQRT_2,
            Trajectory::Line { speed_mps }
            | Trajectory::Circle { speed_mps, .. }
            | Trajectory::FigureEight { speed_mps, .. }
            | Trajectory::Waypoints { speed_mps, .. }
            | Trajectory::Commanded { speed_mps, .. }
            | Trajectory::Routed { speed_mps, .. } => speed_mps.abs(),
            // What a robot or a recording did is not bounded by the scenario
            // (a record's own: `Scenario::leader_max_speed`).
            Trajectory::External | Trajectory::Recorded => f64::INFINITY,
        }
    }

    /// A command within the leader's limits (|v| ≤ speed, |ω| ≤ turn
    /// rate), and whether it had to be clipped; None for a command that is
    /// not finite. Only a [`Trajectory::Commanded`] leader has limits.
    pub fn clip(&self, command: Velocity) -> Option<(Velocity, bool)> {
        if !command.is_finite() {
            return None;
        }
        let Trajectory::Commanded { speed_mps, turn_rate } = self.trajectory else { return Some((command, false)) };
        let v = command.v.clamp(-speed_mps, speed_mps);
        let w = command.w.clamp(-turn_rate, turn_rate);
        Some((Velocity::new(v, w), v != command.v || w != command.w))
    }

    /// Whether the leader is steered from outside while the run goes (a
    /// command or a robot): such a run is simulated again from its record.
    pub fn is_live(&self) -> bool {
        matches!(self.trajectory, Trajectory::Commanded { .. } | Trajectory::Routed { .. } | Trajectory::External)
    }
}

/// What the leader tells the followers that hear it (docs/model.md §13):
/// P_r, Ṗ_r, v_r, ω_r at one step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LeaderState {
    pub pose: Pose,
    pub pose_rate: Pose,
    pub v: f64,
    pub w: f64,
}

impl LeaderState {
    pub fn is_finite(&self) -> bool {
        self.pose.is_finite() && self.pose_rate.is_finite() && self.v.is_finite() && self.w.is_finite()
    }
}

/// The virtual leader: a profile and the pose integrated from it; for
/// [`Trajectory::Waypoints`], its route and the point it drives to; for a
/// steered leader, its input; for [`Trajectory::Recorded`], the recording
/// and the row it is at.
#[derive(Clone, Debug)]
pub struct Leader {
    pub profile: Profile,
    pub pose: Pose,
    route: Arc<[[f64; 2]]>,
    /// The route's point driven to, or the recording's row.
    next: usize,
    /// A steered leader's velocity: the newest command, or the robot's twist.
    steered: Velocity,
    recording: Arc<[LeaderState]>,
}

impl Leader {
    pub fn new(profile: Profile, pose: Pose) -> Self {
        Self::with_route(profile, pose, Arc::from([]))
    }

    /// A leader that follows `route` (with [`Trajectory::Waypoints`]).
    pub fn with_route(profile: Profile, pose: Pose, route: Arc<[[f64; 2]]>) -> Self {
        Self { profile, pose, route, next: 0, steered: Velocity::new(0.0, 0.0), recording: Arc::from([]) }
    }

    /// A leader that plays `recording` again, row k at step k (the last row
    /// from then on, at rest, should the run outlast it).
    pub fn recorded(recording: Arc<[LeaderState]>) -> Self {
        let pose = recording.first().map_or(Pose::default(), |s| s.pose);
        let profile = Profile { trajectory: Trajectory::Recorded, ramp_s: 0.0 };
        Self { recording, ..Self::new(profile, pose) }
    }

    /// The input of a steered leader for the step to come (ignored by a
    /// scripted one): a command is driven from this pose, a robot's
    /// odometry taken as the leader's pose and velocities, and silence
    /// stops the leader where it is.
    pub fn steer(&mut self, input: Input) {
        match (self.profile.trajectory, input) {
            (Trajectory::Commanded { .. }, Input::Command(c)) => self.steered = c,
            (Trajectory::Routed { .. }, Input::Route(r)) if r != self.route => (self.route, self.next) = (r, 0),
            (Trajectory::External, Input::Odometry { pose, twist }) => (self.pose, self.steered) = (pose, twist),
            (Trajectory::Commanded { .. } | Trajectory::External, Input::Silent) => {
                self.steered = Velocity::new(0.0, 0.0)
            }
            _ => {}
        }
    }

    /// The route's point the leader drives to (None: it has arrived, or has no route).
    pub fn heading_for(&self) -> Option<[f64; 2]> {
        self.route.get(self.next).copied()
    }

    /// The leader's outputs at time t from its pose at step k (docs/model.md §9,
    /// step 1): Ṗ_r = (v_r cos θ_r, v_r sin θ_r, ω_r) (eq. 6).
    pub fn state(&self, t_s: f64) -> LeaderState {
        let Velocity { v, w } = match self.profile.trajectory {
            Trajectory::Waypoints { speed_mps, turn_rate, turn_gain, .. } => {
                self.route_velocity(speed_mps, turn_rate, turn_gain, t_s)
            }
            // A planner's route: no start-up ramp (it comes while the run goes).
            Trajectory::Routed { speed_mps, turn_rate, turn_gain, .. } => {
                self.route_velocity(speed_mps, turn_rate, turn_gain, f64::INFINITY)
            }
            Trajectory::Commanded { .. } | Trajectory::External => self.steered,
            Trajectory::Recorded => return self.recording_at(self.next),
            _ => self.profile.velocity(t_s),
        };
        let (s, c) = self.pose.theta.sin_cos();
        LeaderState { pose: self.pose, pose_rate: Pose::new(v * c, v * s, w), v, w }
    }

    /// eq. 17.6: toward the next point, slowing into the last (v ≤ k_θ d).
    fn route_velocity(&self, speed: f64, turn_rate: f64, gain: f64, t_s: f64) -> Velocity {
        let Some([gx, gy]) = self.heading_for() else { return Velocity::new(0.0, 0.0) };
        let (dx, dy) = (gx - self.pose.x, gy - self.pose.y);
        let bearing = wrap(dy.atan2(dx) - self.pose.theta);
        let w = (gain * bearing).clamp(-turn_rate, turn_rate);
        let mut v = speed * bearing.cos().max(0.0) * self.profile.ramp(t_s);
        if self.next + 1 == self.route.len() {
            v = v.min(gain * dx.hypot(dy));
        }
        Velocity::new(v, w)
    }

    /// Advances the pose to k+1 with the rate of `state` (forward Euler),
    /// and a route to its next point once this one is within reach.
    pub fn advance(&mut self, state: &LeaderState, dt_s: f64) {
        match self.profile.trajectory {
            // The robot moves itself: its next odometry says where to.
            Trajectory::External => return,
            Trajectory::Recorded => {
                self.next += 1;
                self.pose = self.recording_at(self.next).pose;
                return;
            }
            _ => {}
        }
        self.pose.x += dt_s * state.pose_rate.x;
        self.pose.y += dt_s * state.pose_rate.y;
        self.pose.theta += dt_s * state.pose_rate.theta;
        let reach = match self.profile.trajectory {
            Trajectory::Waypoints { reach_m, .. } | Trajectory::Routed { reach_m, .. } => Some(reach_m),
            _ => None,
        };
        if let (Some(reach_m), Some([gx, gy])) = (reach, self.heading_for()) {
            if (gx - self.pose.x).hypot(gy - self.pose.y) < reach_m {
                self.next += 1;
            }
        }
    }
}

impl Leader {
    /// The recording's row k, or past its end the last row at rest.
    fn recording_at(&self, k: usize) -> LeaderState {
        match (self.recording.get(k), self.recording.last()) {
            (Some(s), _) => *s,
            (None, Some(last)) => LeaderState { pose: last.pose, ..LeaderState::default() },
            (None, None) => LeaderState { pose: self.pose, ..LeaderState::default() },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_profile_is_the_derivative_of_the_reference_path() {
        // x_d = t, y_d = 2 + sin(π/2 + t) = 2 + cos t: v_d = |(1, −sin t)|,
        // and ω_d is the rate of atan2(−sin t, 1).
        let p = Profile { trajectory: Trajectory::Paper, ramp_s: 0.0 };
        for &t in &[0.0, 0.3, 1.0, 2.5, 7.0] {
            let vel = p.velocity(t);
            assert!((vel.v - (1.0 + t.sin().powi(2)).sqrt()).abs() < 1e-12);
            let h = 1e-6;
            let heading = |t: f64| (-t.sin()).atan2(1.0);
            let rate = (heading(t + h) - heading(t - h)) / (2.0 * h);
            assert!((vel.w - rate).abs() < 1e-6, "t={t}: ω {} vs {}", vel.w, rate);
        }
    }

    #[test]
    fn ramp_starts_at_zero_and_approaches_one() {
        let p = Profile { trajectory: Trajectory::Line { speed_mps: 2.0 }, ramp_s: 0.5 };
        assert_eq!(p.velocity(0.0).v, 0.0);
        assert!((p.velocity(0.5).v - 2.0 * (1.0 - (-1.0f64).exp())).abs() < 1e-12);
        assert!((p.velocity(10.0).v - 2.0).abs() < 1e-8);
    }

    #[test]
    fn integrated_paper_leader_follows_the_reference_path() {
        // From (0, 3, 0) the integrated pose follows (t, 2 + cos t) up to the
        // ramp's lag (about 0.5 m of arc) and Euler's O(Δt) error.
        let profile = Profile { trajectory: Trajectory::Paper, ramp_s: 0.0 };
        let mut leader = Leader::new(profile, Pose::new(0.0, 3.0, 0.0));
        let dt = 1e-3;
        for k in 0..10_000 {
            let s = leader.state(k as f64 * dt);
            leader.advance(&s, dt);
        }
        let t = 10.0f64;
        assert!((leader.pose.x - t).abs() < 0.02, "x = {}", leader.pose.x);
        assert!((leader.pose.y - (2.0 + t.cos())).abs() < 0.02, "y = {}", leader.pose.y);
    }

    #[test]
    fn figure_eight_closes_after_two_loops() {
        let profile = Profile { trajectory: Trajectory::FigureEight { speed_mps: 1.0, radius_m: 2.0 }, ramp_s: 0.0 };
        let mut leader = Leader::new(profile, Pose::default());
        let dt = 1e-4;
        let steps = (2.0 * 2.0 * std::f64::consts::PI * 2.0 / dt).round() as usize;
        let mut farthest = 0.0f64;
        for k in 0..steps {
            let s = leader.state(k as f64 * dt);
            leader.advance(&s, dt);
            farthest = farthest.max(leader.pose.x.hypot(leader.pose.y));
        }
        assert!(leader.pose.x.hypot(leader.pose.y) < 5e-3, "end {:?}", leader.pose);
        assert!((farthest - 4.0).abs() < 1e-2, "each loop is 2 radii across: {farthest}");
    }

    #[test]
    fn a_route_is_driven_point_after_point_and_ends_standing_at_the_last() {
        let profile = Profile {
            trajectory: Trajectory::Waypoints { speed_mps: 0.2, turn_rate: 1.0, turn_gain: 2.0, reach_m: 0.1 },
            ramp_s: 1.0,
        };
        let route: Arc<[[f64; 2]]> = Arc::from([[1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]);
        let mut leader = Leader::with_route(profile, Pose::default(), route);
        let (dt, mut passed, mut fastest, mut sharpest) = (0.01, Vec::new(), 0.0f64, 0.0f64);
        for k in 0..6000 {
            let s = leader.state(k as f64 * dt);
            (fastest, sharpest) = (fastest.max(s.v), sharpest.max(s.w.abs()));
            let before = leader.heading_for();
            leader.advance(&s, dt);
            if leader.heading_for() != before {
                passed.push((k, leader.pose));
            }
        }
        assert_eq!(passed.len(), 3, "three points, each reached once: {passed:?}");
        for ((_, at), goal) in passed.iter().zip([[1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]) {
            assert!((at.x - goal[0]).hypot(at.y - goal[1]) < 0.1, "reached {goal:?} at {at:?}");
        }
        assert!(fastest <= 0.2 && sharpest <= 1.0, "limits: {fastest} m/s, {sharpest} rad/s");
        let end = leader.state(60.0);
        assert_eq!((end.v, end.w), (0.0, 0.0), "it stands at the last point");
    }

    #[test]
    fn circle_closes_on_itself() {
        let profile = Profile { trajectory: Trajectory::Circle { speed_mps: 1.0, radius_m: 2.0 }, ramp_s: 0.0 };
        let mut leader = Leader::new(profile, Pose::default());
        let dt = 1e-4;
        let steps = (2.0 * std::f64::consts::PI * 2.0 / dt).round() as usize;
        for k in 0..steps {
            let s = leader.state(k as f64 * dt);
            leader.advance(&s, dt);
        }
        assert!(leader.pose.x.hypot(leader.pose.y) < 2e-3, "end {:?}", leader.pose);
    }

    #[test]
    fn a_commanded_leader_drives_the_clipped_command_and_stops_when_silent() {
        let profile = Profile { trajectory: Trajectory::Commanded { speed_mps: 0.2, turn_rate: 1.0 }, ramp_s: 0.0 };
        let (clipped, was) = profile.clip(Velocity::new(0.5, -3.0)).expect("finite");
        assert_eq!((clipped.v, clipped.w, was), (0.2, -1.0, true), "clipped to ±0.2 m/s, ±1 rad/s");
        assert_eq!(profile.clip(Velocity::new(0.1, 0.5)), Some((Velocity::new(0.1, 0.5), false)));
        assert_eq!(profile.clip(Velocity::new(f64::NAN, 0.0)), None, "a command that is not finite is refused");
        let mut leader = Leader::new(profile, Pose::default());
        let dt = 0.01;
        for k in 0..100 {
            leader.steer(Input::Command(clipped));
            let s = leader.state(k as f64 * dt);
            leader.advance(&s, dt);
        }
        // ω = −1 rad/s for 1 s at 0.2 m/s: an arc of radius 0.2 m.
        let (x, y) = (0.2 * 1.0f64.sin(), -0.2 * (1.0 - 1.0f64.cos()));
        assert!((leader.pose.x - x).hypot(leader.pose.y - y) < 2e-3, "{:?} against ({x}, {y})", leader.pose);
        leader.steer(Input::Silent);
        let at = leader.pose;
        let s = leader.state(1.0);
        leader.advance(&s, dt);
        assert_eq!((s.v, s.w, leader.pose), (0.0, 0.0, at), "silence stops it where it is");
        assert!(profile.is_live() && !Profile { trajectory: Trajectory::Paper, ramp_s: 0.5 }.is_live());
    }

    #[test]
    fn an_external_leader_is_its_robots_odometry_and_rests_when_it_falls_silent() {
        let mut leader = Leader::new(Profile { trajectory: Trajectory::External, ramp_s: 0.0 }, Pose::default());
        let pose = Pose::new(1.0, 2.0, 0.5);
        leader.steer(Input::Odometry { pose, twist: Velocity::new(0.3, 0.1) });
        let s = leader.state(0.0);
        assert_eq!((s.pose, s.v, s.w), (pose, 0.3, 0.1));
        assert_eq!(s.pose_rate, Pose::new(0.3 * 0.5f64.cos(), 0.3 * 0.5f64.sin(), 0.1), "eq. 6 from its twist");
        leader.advance(&s, 0.01);
        assert_eq!(leader.pose, pose, "not integrated: the next odometry says where it is");
        leader.steer(Input::Silent);
        let s = leader.state(0.01);
        assert_eq!((s.pose, s.v, s.w), (pose, 0.0, 0.0));
    }

    #[test]
    fn a_recorded_leader_plays_its_rows_bit_for_bit_and_rests_past_the_end() {
        let profile = Profile { trajectory: Trajectory::Paper, ramp_s: 0.5 };
        let mut original = Leader::new(profile, Pose::new(0.0, 3.0, 0.0));
        let dt = 0.01;
        let rows: Vec<LeaderState> = (0..50)
            .map(|k| {
                let s = original.state(k as f64 * dt);
                original.advance(&s, dt);
                s
            })
            .collect();
        let mut again = Leader::recorded(rows.clone().into());
        for (k, row) in rows.iter().enumerate() {
            let s = again.state(k as f64 * dt);
            assert_eq!(&s, row, "row {k}");
            again.advance(&s, dt);
        }
        let past = again.state(1.0);
        assert_eq!((past.pose, past.v, past.w), (rows[49].pose, 0.0, 0.0));
    }

    #[test]
    fn a_routed_leader_stands_until_a_route_comes_and_takes_a_new_one_from_its_start() {
        let profile = Profile {
            trajectory: Trajectory::Routed { speed_mps: 0.2, turn_rate: 1.0, turn_gain: 2.0, reach_m: 0.1 },
            ramp_s: 0.5,
        };
        assert!(profile.is_live());
        let mut leader = Leader::new(profile, Pose::default());
        let s = leader.state(0.0);
        assert_eq!((s.v, s.w), (0.0, 0.0), "no route yet: it stands");
        let route: Arc<[[f64; 2]]> = Arc::from([[1.0, 0.0], [1.0, 1.0]]);
        leader.steer(Input::Route(route.clone()));
        let dt = 0.01;
        for k in 0..600 {
            leader.steer(Input::Silent);
            let s = leader.state(k as f64 * dt);
            assert!(s.v <= 0.2 && s.w.abs() <= 1.0);
            leader.advance(&s, dt);
        }
        assert_eq!(leader.heading_for(), Some([1.0, 1.0]), "past the first point after 6 s at 0.2 m/s");
        leader.steer(Input::Route(route));
        assert_eq!(leader.heading_for(), Some([1.0, 1.0]), "the same route again changes nothing");
        leader.steer(Input::Route(Arc::from([[0.0, 0.0]])));
        assert_eq!(leader.heading_for(), Some([0.0, 0.0]), "a new route is driven from its start");
        leader.steer(Input::Route(Arc::from([])));
        assert_eq!(leader.state(4.0).v, 0.0, "an empty route stops it");
    }
}
