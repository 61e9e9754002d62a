//! A formation scenario as typed values ([`Scenario`]), loaded from its
//! file (reading and TOML errors: [`crate::syntax`]; `--set`:
//! [`crate::overrides`]; the checks: [`crate::validate`]), and the
//! scenarios built into the binary.

use std::path::Path;
use std::sync::Arc;

use formation_control::{ControlParams, FollowerConfig, LinkLoss, LossWindow, Slots};
use formation_leader::LeaderState;
use formation_leader::{Leader, Profile, Trajectory};
use formation_plant::{Disturbance, NoiseCov, Pose, RobotParams, Velocity};
use serde::Serialize;

use crate::file::ScenarioFile;
use crate::graph::Graph;

/// How followers initialise their leader estimate.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum EstimateInit {
    /// P_ir(0) = P_r(0), v_ir(0) = v_r(0), ω_ir(0) = ω_r(0) (docs/model.md §10).
    Leader,
    /// Everything zero.
    Zero,
}

/// How networked nodes pace their steps.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Timing {
    /// A node advances from step k once it holds all its inputs for k.
    Lockstep,
    /// Fixed-rate loops on a shared time base, latest values.
    Realtime,
}

/// One follower's initial conditions and place in the formation.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct FollowerSpec {
    pub id: u32,
    pub offset: [f64; 2],
    pub pose: Pose,
    pub velocity: Velocity,
    pub hears_leader: bool,
    /// Where this robot's odometry frame sits in the world (`robot.odom_origin`
    /// or the follower's own): None, the world frame itself.
    pub odom_origin: Option<Pose>,
}

/// Networked-run settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct NetworkSettings {
    pub silence_timeout_s: f64,
    pub time_scale: f64,
    pub telemetry_batch: u32,
    /// Followers record their hearing for `formation replay`.
    pub hearing_record: bool,
    /// At step k a follower uses its sources' messages of step k − d.
    pub delay_steps: u64,
    /// A follower whose telemetry is silent this long (s) is taken for gone.
    pub gone_after_s: Option<f64>,
}

/// Who moves the followers' robots when ROS 2 is on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum RobotSource {
    /// Each agent simulates its own robot and publishes what it does.
    Simulated,
    /// A `formation robot` process per follower, driven through ROS 2.
    StandIn,
    /// Robots this project does not run (a TurtleBot, Gazebo), driven through ROS 2.
    External,
}

impl RobotSource {
    /// Driven through ROS 2's `cmd_vel` and `odom` rather than simulated in the agent.
    pub fn driven(self) -> bool {
        self != RobotSource::Simulated
    }
}

/// `[ros2]`, validated.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Ros2Settings {
    pub domain_id: u32,
    pub robots: RobotSource,
    /// A driven robot's odometry older than this is a stopped robot.
    pub odom_timeout_s: f64,
}

/// `ros2.odom_frame` when none is given: `{id}` is the follower's id.
pub const DEFAULT_ODOM_FRAME: &str = "follower_{id}/odom";

/// Largest ROS_DOMAIN_ID (ROS 2's own limit: 0–232).
pub const MAX_DOMAIN_ID: u32 = 232;

/// Largest `[robot] lag` accepted, s (docs/model.md §15): a mobile base's
/// velocity loop settles within a second or so; a lag above this is more
/// likely milliseconds written as seconds than a robot.
pub const MAX_LAG_S: f64 = 10.0;

/// Largest `network.delay_steps` accepted.
pub const MAX_DELAY_STEPS: u64 = 1000;
/// Largest distance from the origin a follower's offset, pose or body
/// error may give, m.
pub const MAX_DISTANCE_M: f64 = 1e6;
/// Largest initial speed (m/s) or turn rate (rad/s) of a follower.
pub const MAX_SPEED: f64 = 1e3;
/// Most followers in one scenario (a networked run is one process each; the
/// simulator's memory grows with the edges).
pub const MAX_FOLLOWERS: usize = 10_000;
/// Most steps in one run (T/Δt): 1e8 is 27.8 hours at Δt = 1 ms.
pub const MAX_STEPS: f64 = 1e8;
/// Most edges in one scenario (a complete graph of 1,414 followers).
pub const MAX_EDGES: usize = 1_000_000;
/// Most rows of the fault table.
pub const MAX_FAULT_ROWS: usize = 10_000;
/// Largest scenario file read, bytes (a generated scenario of
/// [`MAX_FOLLOWERS`] followers is about 1.5 MB).
pub const MAX_FILE_BYTES: u64 = 16 << 20;

/// The longest run name (a scenario's `name`, `--run`): it names the run's
/// folder and every key of its traffic.
pub const MAX_NAME_CHARS: usize = 100;

/// A number for a message: plain when it reads well, else in exponent form
/// (1e308 is not written with 309 digits).
pub fn num(x: f64) -> String {
    if x != 0.0 && x.is_finite() && !(1e-4..1e6).contains(&x.abs()) {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

/// What a link fault covers (docs/model.md §14).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum FaultTarget {
    /// Every link of this node, both directions: a follower, or 0, the
    /// leader (silent on every link: a handover's gap).
    Node(u32),
    /// One link between two nodes (0 = the leader), both directions.
    Link(u32, u32),
}

/// One validated row of the fault table.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct LinkFault {
    pub target: FaultTarget,
    pub from_s: f64,
    pub to_s: f64,
    pub loss: f64,
    /// A late join (`join = true`): the follower's process starts at `to_s`.
    pub join: bool,
    /// A leave (`leave = true`): the follower's process ends at `from_s`,
    /// its robot stopped where it is (docs/model.md §14).
    pub leave: bool,
    /// A leave by death (`died = true`, `leave` then set too): no last
    /// pose, its robot stands at its pose of two steps before `from_s`.
    pub died: bool,
}

impl LinkFault {
    /// Whether the fault covers the directed link sender → receiver.
    pub fn covers(&self, sender: u32, receiver: u32) -> bool {
        match self.target {
            FaultTarget::Node(n) => sender == n || receiver == n,
            FaultTarget::Link(a, b) => (sender, receiver) == (a, b) || (sender, receiver) == (b, a),
        }
    }

    /// The window in steps: [first k with k Δt ≥ from, first k with k Δt ≥ to).
    pub fn steps(&self, dt_s: f64) -> (u64, u64) {
        (step_at(self.from_s, dt_s), step_at(self.to_s, dt_s))
    }

    /// "follower 3" or "link 0–1", for tables and messages.
    pub fn label(&self) -> String {
        let what = match self.target {
            FaultTarget::Node(0) => "the leader".to_string(),
            FaultTarget::Node(n) => format!("follower {n}"),
            FaultTarget::Link(a, b) => format!("link {a}–{b}"),
        };
        if self.loss >= 1.0 {
            format!("{what} down {}–{} s", self.from_s, self.to_s)
        } else {
            format!("{what} {}% loss {}–{} s", self.loss * 100.0, self.from_s, self.to_s)
        }
    }
}

use formation_control::math::step_at;

/// One shape change, validated: from step `from_k` on, the follower at index
/// i holds `offsets[i]` (in the scenario's frame).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ShapeChange {
    pub at_s: f64,
    pub from_k: u64,
    /// The shape's name, or `offsets` for one given slot by slot.
    pub name: String,
    /// eq. 17.4's Σ_i |Δ_i(before) − Δ_i(after)|², m², of the assignment.
    pub cost: f64,
    pub offsets: Vec<[f64; 2]>,
}

/// A validated scenario. Followers are in ascending id, indexed like the graph.
#[derive(Clone, Debug, PartialEq)]
pub struct Scenario {
    pub name: String,
    pub seed: u64,
    pub dt_s: f64,
    pub duration_s: f64,
    pub noise: bool,
    pub covariance: NoiseCov,
    pub estimate_init: EstimateInit,
    pub timing: Timing,
    pub leader_profile: Profile,
    pub leader_pose: Pose,
    /// `leader.waypoints` (empty unless the trajectory is `waypoints`).
    pub leader_route: Arc<[[f64; 2]]>,
    /// `leader.source = "recorded"`: the leader's state at every step of
    /// the run (empty for any other source; docs/model.md §18).
    pub leader_recording: Arc<[LeaderState]>,
    /// `cmd_vel`, `robot`: the leader stops once its input has been silent this long, s.
    pub leader_timeout_s: f64,
    pub followers: Vec<FollowerSpec>,
    /// `[[formation.shapes]]`, each with its assignment (docs/model.md §17).
    pub shapes: Vec<ShapeChange>,
    pub graph: Graph,
    /// Controllers, filter, the model they assume, the fault: shared by
    /// every follower.
    pub control: Arc<ControlParams>,
    /// The true robot (the plant); `control.model` is what the controllers
    /// assume, the same values unless a study changes one of them.
    pub robot: RobotParams,
    pub disturbance: Disturbance,
    pub network: NetworkSettings,
    /// docs/model.md §14's fault table (empty: perfect links).
    pub faults: Vec<LinkFault>,
    /// The formation on ROS 2's wire (None: off).
    pub ros2: Option<Ros2Settings>,
    /// `[safety] distance`: the closest two robots may come, m (None: no
    /// `[safety]`, no proximity figures). The filter itself is `control.guard.safety`.
    pub safety_distance: Option<f64>,
    /// A stand-in robot stops when no command came for this long, s (`robot.cmd_timeout`).
    pub cmd_timeout_s: f64,
    /// The `frame_id` driven robots' odometry carries (`ros2.odom_frame`), `{id}` for the id.
    pub odom_frame: String,
    /// The file as it was read and overridden, for the record of a run.
    pub source: ScenarioFile,
}

impl Scenario {
    /// Followers above which [`Scenario::estimator_stability_warning`] does
    /// not look (its cost grows with the graph: about a second at this size).
    pub const STABILITY_CHECK_LIMIT: usize = 20_000;

    /// A warning when the position estimator (eq. 11–12), as the followers
    /// step it on this graph at this Δt, gain k_i and `network.delay_steps`,
    /// is unstable: its disagreement grows by more than 5 % a second of the
    /// run ([`Graph::estimator_growth`]). On the generated rings at Δt =
    /// 10 ms, one step of delay is enough (docs/performance.md); at 1 ms it
    /// is not. None for a stable setting or a graph above
    /// [`Scenario::STABILITY_CHECK_LIMIT`].
    pub fn estimator_stability_warning(&self) -> Option<String> {
        if self.graph.len() > Self::STABILITY_CHECK_LIMIT || self.dt_s.is_nan() || self.dt_s <= 0.0 {
            return None;
        }
        let d = usize::try_from(self.network.delay_steps).ok()?;
        let mut ks = self.control.estimator.k.to_vec();
        ks.sort_by(f64::total_cmp);
        ks.dedup();
        let (k, growth) = ks
            .into_iter()
            .map(|k| (k, self.graph.estimator_growth(k, self.dt_s, d)))
            .max_by(|a, b| a.1.total_cmp(&b.1))?;
        let per_second = growth.powf(1.0 / self.dt_s);
        if per_second <= 1.05 {
            return None;
        }
        // What each change by itself does here: the advice names only those
        // that help (a larger delay can, and a smaller one may not).
        let dt = self.dt_s;
        let at = |k: f64, dt: f64, d: usize| self.graph.estimator_growth(k, dt, d).powf(1.0 / dt);
        let mut changes = vec![
            (format!("k_i = {} (estimator.k)", k / 2.0), at(k / 2.0, dt, d)),
            (format!("Δt = {} ms", dt * 500.0), at(k, dt / 2.0, d)),
            (format!("network.delay_steps = {}", d + 1), at(k, dt, d + 1)),
        ];
        if d > 0 {
            changes.push((format!("network.delay_steps = {}", d - 1), at(k, dt, d - 1)));
        }
        changes.retain(|(_, g)| *g < per_second);
        changes.sort_by(|a, b| a.1.total_cmp(&b.1));
        let advice = if changes.is_empty() {
            "halving k_i or Δt, or a step more or less of delay, does not slow it".to_string()
        } else {
            let each: Vec<String> = changes
                .iter()
                .map(|(what, g)| if *g <= 1.0 { format!("{what}: stable") } else { format!("{what}: ×{g:.2}") })
                .collect();
            format!("each change alone: {}", each.join("; "))
        };
        Some(format!(
            "warning: the leader estimator (eq. 11–12) is unstable here: at Δt = {} ms with network.delay_steps = {d} \
             and k_i = {k}, the followers' estimates oscillate with an amplitude that grows ×{per_second:.2} a second \
             of the run, and so do the torques ({advice}; docs/performance.md, \"Fewer wake-ups per step\")",
            dt * 1e3
        ))
    }

    /// Number of steps T/Δt; the run has steps + 1 samples (docs/model.md §9).
    pub fn steps(&self) -> u64 {
        (self.duration_s / self.dt_s).round() as u64
    }

    pub fn leader(&self) -> Leader {
        if self.leader_profile.trajectory == Trajectory::Recorded {
            return Leader::recorded(Arc::clone(&self.leader_recording));
        }
        Leader::with_route(self.leader_profile, self.leader_pose, Arc::clone(&self.leader_route))
    }

    /// Every follower's initial leader estimate.
    pub fn initial_estimate(&self) -> LeaderState {
        match self.estimate_init {
            EstimateInit::Leader => self.leader().state(0.0),
            EstimateInit::Zero => LeaderState::default(),
        }
    }

    /// The brain configuration of the follower at `index`.
    pub fn follower_config(&self, index: usize) -> FollowerConfig {
        let f = &self.followers[index];
        FollowerConfig {
            id: f.id,
            slots: self.slots(index),
            hears_leader: f.hears_leader,
            control: Arc::clone(&self.control),
        }
    }

    /// The offsets the follower at `index` holds over the run (in
    /// `control.frame`): its own, then each shape change's.
    pub fn slots(&self, index: usize) -> Slots {
        let first = self.followers[index].offset;
        match self.shapes.is_empty() {
            true => Slots::fixed(first),
            false => Slots::changing(first, self.shapes.iter().map(|c| (c.from_k, c.offsets[index])).collect()),
        }
    }

    pub fn index_of(&self, id: u32) -> Option<usize> {
        self.graph.index_of(id)
    }

    /// `network.silence_timeout` in steps, rounded to the nearest (docs/model.md §14).
    pub fn silence_steps(&self) -> u64 {
        (self.network.silence_timeout_s / self.dt_s).round() as u64
    }

    /// The fault windows, in steps, on the directed link sender → receiver.
    pub fn link_windows(&self, sender: u32, receiver: u32) -> Vec<LossWindow> {
        self.faults
            .iter()
            .filter(|f| f.covers(sender, receiver))
            .map(|f| {
                let (from_k, mut to_k) = f.steps(self.dt_s);
                // A joiner's new process publishes nothing before its first
                // step: its message of the join step is not sent either.
                if f.join && f.target == FaultTarget::Node(sender) {
                    to_k += 1;
                }
                LossWindow { from_k, to_k, loss: f.loss }
            })
            .collect()
    }

    /// This scenario with the followers that left the run for good cut off
    /// from then on: (id, the first step whose message it did not send).
    /// The model of a leave (docs/model.md §14): the fault row `node = id`
    /// from that step to T + Δt, which covers the last step.
    pub fn with_leaves(&self, leaves: &[(u32, u64)]) -> Scenario {
        let mut s = self.clone();
        for &(id, at_k) in leaves {
            s.faults.push(LinkFault {
                target: FaultTarget::Node(id),
                from_s: at_k as f64 * s.dt_s,
                to_s: s.duration_s + s.dt_s,
                loss: 1.0,
                join: false,
                leave: true,
                died: false,
            });
        }
        s
    }

    /// The scenario with each (follower, step L) killed: the died row
    /// `{ node = id, from = L Δt, died = true }` (docs/model.md §14).
    pub fn with_died(&self, died: &[(u32, u64)]) -> Scenario {
        let mut s = self.with_leaves(died);
        let rows = s.faults.len() - died.len();
        for f in &mut s.faults[rows..] {
            f.died = true;
        }
        s
    }

    /// The model of handovers (docs/model.md §14): for each, the leader
    /// silent on every link over steps [from_k, to_k), the row `node = 0`
    /// (real time; in lock-step the followers wait for the standby and the
    /// model has no gap).
    pub fn with_handovers(mut self, gaps: &[(u64, u64)]) -> Scenario {
        if self.timing == Timing::Lockstep {
            return self;
        }
        for &(from_k, to_k) in gaps.iter().filter(|g| g.0 < g.1) {
            let to_s = (to_k as f64 * self.dt_s).min(self.duration_s + self.dt_s);
            self.faults.push(LinkFault {
                target: FaultTarget::Node(0),
                from_s: from_k as f64 * self.dt_s,
                to_s,
                loss: 1.0,
                join: false,
                leave: false,
                died: false,
            });
        }
        self
    }

    /// The model of joins (docs/model.md §14): each follower absent at the
    /// start that joined at step k has its links cut over [0, k) and takes
    /// its estimate from the first source it hears, the row `{ node = id,
    /// from = 0, to = k Δt, join = true }`.
    pub fn with_joins(mut self, joins: &[(u32, u64)]) -> Scenario {
        for &(id, k) in joins.iter().filter(|j| j.1 > 0) {
            let to_s = (k as f64 * self.dt_s).min(self.duration_s + self.dt_s);
            self.faults.push(LinkFault {
                target: FaultTarget::Node(id),
                from_s: 0.0,
                to_s,
                loss: 1.0,
                join: true,
                leave: false,
                died: false,
            });
        }
        self
    }

    /// The step at which follower `id` joins late (a `join = true` row,
    /// docs/model.md §14): its process starts then, its robot at its
    /// initial pose, its estimate taken from the first source it hears.
    pub fn join_step(&self, id: u32) -> Option<u64> {
        self.faults.iter().find(|f| f.join && f.target == FaultTarget::Node(id)).map(|f| f.steps(self.dt_s).1)
    }

    /// The step before which follower `id` leaves the run for good (a
    /// `leave = true` row, docs/model.md §14): its robot stops at its pose
    /// of that step.
    pub fn leave_step(&self, id: u32) -> Option<u64> {
        self.faults.iter().filter(|f| f.leave && f.target == FaultTarget::Node(id)).map(|f| f.steps(self.dt_s).0).min()
    }

    /// Whether follower `id`'s leave is a death (`died = true`, docs/model.md
    /// §14): its robot then stands at its pose of [`Scenario::leave_step`]
    /// − 2, the last it sent, from the step after that on.
    pub fn died(&self, id: u32) -> bool {
        let first = self.faults.iter().filter(|f| f.leave && f.target == FaultTarget::Node(id));
        first.min_by_key(|f| f.steps(self.dt_s).0).is_some_and(|f| f.died)
    }

    /// The receiver's loss decisions for the link sender → receiver.
    pub fn link_loss(&self, sender: u32, receiver: u32) -> LinkLoss {
        let windows = self.link_windows(sender, receiver);
        if windows.is_empty() {
            LinkLoss::none()
        } else {
            LinkLoss::new(self.seed, sender, receiver, &windows)
        }
    }

    /// The sources of the follower at `index` in inbox order: its neighbours'
    /// ids in ascending order, then the leader (0) if it hears it.
    pub fn sources_of(&self, index: usize) -> Vec<u32> {
        let mut ids: Vec<u32> = self.graph.neighbours(index).iter().map(|&j| self.graph.id(j)).collect();
        if self.graph.hears_leader(index) {
            ids.push(0);
        }
        ids
    }

    /// The `frame_id` follower `id`'s odometry carries (`ros2.odom_frame`).
    pub fn odom_frame_of(&self, id: u32) -> String {
        self.odom_frame.replace("{id}", &id.to_string())
    }

    /// The frame a leader robot's odometry must carry (`leader.source =
    /// "robot"`): `ros2.odom_frame` with the follower's prefix made the
    /// leader's (`leader/odom` by default; a bare `odom` stays `odom`).
    pub fn leader_odom_frame(&self) -> String {
        self.odom_frame.replace("follower_{id}", "leader").replace("{id}", "0")
    }

    /// Where a leader robot's odometry frame sits in the world: at the
    /// leader's pose with `robot.odom_origin = "start"`, else the world's.
    pub fn leader_odom_origin(&self) -> Option<Pose> {
        (self.source.robot.odom_origin.as_deref() == Some("start")).then_some(self.leader_pose)
    }

    /// This scenario with its leader played from a record (`leader.source =
    /// "recorded"`): a run folder or its `leader.csv`, checked against `dt`
    /// and the run's length (docs/model.md §18). A run steered live is
    /// replayed and explained this way.
    pub fn with_recorded_leader(self, path: &Path) -> Result<Self, String> {
        let states = crate::recorded::read(path, self.dt_s, self.steps())?;
        Ok(self.with_leader_states(states.into()))
    }

    /// This scenario with its leader's state at every step given (row k at step k).
    pub fn with_leader_states(mut self, states: Arc<[LeaderState]>) -> Self {
        self.leader_recording = states;
        self.leader_profile = Profile { trajectory: Trajectory::Recorded, ramp_s: 0.0 };
        self
    }

    /// Whether this scenario can be simulated in one process: not with a
    /// leader steered live (what steers it is not known in advance); the
    /// line says how to play such a run again.
    pub fn simulable(&self) -> Result<(), String> {
        match self.live_leader() {
            Some(source) => Err(format!(
                "leader.source = \"{source}\" steers the leader while a networked run goes (formation launch); a \
                 simulation plays such a run again from its record: --leader runs/NAME (leader.source = \
                 \"recorded\", leader.recorded = \"runs/NAME\")"
            )),
            None => Ok(()),
        }
    }

    /// The largest |v_r| of the leader (for docs/model.md §12's speed
    /// bound): a record's own; infinite for a leader steered live.
    pub fn leader_max_speed(&self) -> f64 {
        match self.leader_profile.trajectory {
            Trajectory::Recorded => self.leader_recording.iter().map(|s| s.v.abs()).fold(0.0, f64::max),
            _ => self.leader_profile.max_speed(),
        }
    }

    /// `leader.source` when it steers the leader while the run goes
    /// (`cmd_vel`, `robot`), for the commands that cannot take one.
    pub fn live_leader(&self) -> Option<&str> {
        self.leader_profile.is_live().then_some(self.source.leader.source.as_str())
    }

    /// The followers the one at `index` exchanges messages with, by index:
    /// its neighbours, and with the safety filter on every other follower
    /// (their robots' poses, docs/model.md §16). Who dials whom follows it.
    pub fn peers_of(&self, index: usize) -> Vec<usize> {
        match self.control.guard.safety.is_some() {
            true => (0..self.followers.len()).filter(|&j| j != index).collect(),
            false => self.graph.neighbours(index).to_vec(),
        }
    }
}

/// The pose whose body-frame error against the leader's pose plus the offset
/// is (x̂, ŷ, θ̂): θ = θ_r − θ̂, and (e_x, e_y) is (x̂, ŷ) rotated back into
/// the world frame by θ (the inverse of eq. 29).
pub fn pose_from_body_error(leader: Pose, offset: [f64; 2], e: [f64; 3]) -> Pose {
    let theta = leader.theta - e[2];
    let (s, c) = theta.sin_cos();
    let ex = c * e[0] - s * e[1];
    let ey = s * e[0] + c * e[1];
    Pose::new(leader.x + offset[0] - ex, leader.y + offset[1] - ey, theta)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::ScenarioError;
    use crate::file::DEFAULT_CMD_TIMEOUT_S;
    use crate::file::DEFAULT_LAG_S;
    use crate::syntax::find_line;
    use formation_control::{DeadlockRule, Limits, RejoinPolicy, RejoinRule};
    use formation_plant::Drive;

    /// The warning names what helps here, measured: on the 50-ring at
    /// 10 ms a delay of one step grows ×1.30 a second, no delay is stable
    /// and two steps still grow (it advised "a smaller … delay" even with
    /// none, where only a larger one helped).
    #[test]
    fn the_stability_warning_names_the_changes_that_help() {
        let spec =
            crate::generate::Spec { chords: 10, ..crate::generate::Spec::new(50, crate::generate::GraphKind::Ring) };
        let mut s = crate::generate::scenario(&spec).expect("ring");
        s.dt_s = 0.01;
        s.network.delay_steps = 1;
        let w = s.estimator_stability_warning().expect("a warning");
        for part in ["grows ×1.30 a second", "network.delay_steps = 0: stable", "network.delay_steps = 2: ×1.19"] {
            assert!(w.contains(part), "{part:?} not in: {w}");
        }
        s.network.delay_steps = 0;
        assert_eq!(s.estimator_stability_warning(), None);
    }

    #[test]
    fn body_error_round_trips_through_eq_29() {
        let leader = Pose::new(0.3, 3.0, 0.4);
        let e = [-1.0, 2.0, 0.25];
        let p = pose_from_body_error(leader, [4.0, -4.0], e);
        let back = formation_control::kinematic::body_error(&leader, [4.0, -4.0], &p);
        assert!((back.x - e[0]).abs() < 1e-12 && (back.y - e[1]).abs() < 1e-12 && (back.theta - e[2]).abs() < 1e-12);
    }

    const PAPER: &str = "duration = 20\nedges = [[1, 2], [1, 3], [2, 4], [3, 4]]\n\
        [[followers]]\nid = 1\noffset = [4, -4]\nbody_error = [-1, 0, 0]\nleader_link = true\n\
        [[followers]]\nid = 2\noffset = [4, 4]\nbody_error = [2, 0, 0]\n\
        [[followers]]\nid = 3\noffset = [7, -7]\nbody_error = [2, 0, 0]\n\
        [[followers]]\nid = 4\noffset = [7, 7]\nbody_error = [5, 0, 0]\n";

    fn with_faults(faults: &str) -> Result<Scenario, ScenarioError> {
        Scenario::from_toml(&format!("{PAPER}{faults}"), "t.toml", "t", &[])
    }

    #[test]
    fn fault_table_rows_cover_their_links_in_steps() {
        let s = with_faults(
            "[[faults]]\nnode = 3\nfrom = 10\nto = 13\n[[faults]]\nlink = [0, 1]\nfrom = 1\nto = 2\nloss = 0.3\n",
        )
        .expect("valid fault table");
        assert_eq!(s.faults.len(), 2);
        // Follower 3's links, both directions: 1–3 and 3–4; not 1–2.
        assert_eq!(s.link_windows(1, 3), vec![LossWindow { from_k: 10_000, to_k: 13_000, loss: 1.0 }]);
        assert_eq!(s.link_windows(3, 4).len(), 1);
        assert!(s.link_windows(1, 2).is_empty());
        assert_eq!(s.link_windows(0, 1), vec![LossWindow { from_k: 1000, to_k: 2000, loss: 0.3 }]);
        assert_eq!(s.sources_of(0), vec![2, 3, 0]);
        assert_eq!(s.silence_steps(), 50);
        assert_eq!(s.control.rejoin, RejoinRule { policy: RejoinPolicy::Consensus, after_steps: 100 });
    }

    /// `node = 0` is the leader silent on every link (a handover's gap):
    /// it covers the leader's link to each follower that hears it, and no
    /// link between followers.
    #[test]
    fn node_0_is_the_leader_silent_on_every_link() {
        let s = with_faults("[[faults]]\nnode = 0\nfrom = 10\nto = 10.3\n").expect("the leader's row");
        assert_eq!(s.faults[0].target, FaultTarget::Node(0));
        assert_eq!(s.faults[0].label(), "the leader down 10–10.3 s");
        assert_eq!(s.link_windows(0, 1), vec![LossWindow { from_k: 10_000, to_k: 10_300, loss: 1.0 }]);
        for (a, b) in [(1, 2), (1, 3), (3, 4)] {
            assert!(s.link_windows(a, b).is_empty(), "{a}–{b} is no link of the leader");
        }
    }

    /// A join row (docs/model.md §14): follower 3 joins at 8 s, its step
    /// 8000; its incoming links are down over [0, 8000), its outgoing ones
    /// one step longer (a new process publishes nothing before its first
    /// step); it is written back as given.
    #[test]
    fn a_join_row_names_the_join_step_and_cuts_the_joiners_first_message() {
        let s = with_faults("[[faults]]\nnode = 3\nfrom = 0\nto = 8\njoin = true\n").expect("a join row");
        assert_eq!((s.join_step(3), s.join_step(2)), (Some(8000), None));
        assert_eq!(s.link_windows(1, 3), vec![LossWindow { from_k: 0, to_k: 8000, loss: 1.0 }]);
        assert_eq!(s.link_windows(3, 1), vec![LossWindow { from_k: 0, to_k: 8001, loss: 1.0 }]);
        let plain = with_faults("[[faults]]\nnode = 3\nfrom = 0\nto = 8\n").expect("an outage");
        assert_eq!((plain.join_step(3), plain.link_windows(3, 1)[0].to_k), (None, 8000));
        assert!(toml::to_string(&s.source.faults[0]).expect("toml").contains("join = true"));
        assert!(!toml::to_string(&plain.source.faults[0]).expect("toml").contains("join"));
    }

    /// A leave row: follower 3 leaves at 5 s, its step 5000, for the rest
    /// of the run; anything else written as a leave is refused in one line
    /// naming the key.
    #[test]
    fn a_leave_row_names_the_leave_step_and_bad_ones_are_refused_with_the_key() {
        let s = with_faults("[[faults]]\nnode = 3\nfrom = 5\nleave = true\n").expect("a leave row");
        assert_eq!((s.leave_step(3), s.leave_step(2), s.join_step(3)), (Some(5000), None, None));
        assert!(toml::to_string(&s.source.faults[0]).expect("toml").contains("leave = true"));
        assert!(!s.died(3), "a leave is not a death");
        // A death is a leave without the last word; `leave` may be left out.
        for row in ["died = true", "died = true\nleave = true"] {
            let d = with_faults(&format!("[[faults]]\nnode = 3\nfrom = 5\n{row}\n")).expect("a died row");
            assert_eq!((d.leave_step(3), d.died(3), d.died(2)), (Some(5000), true, false), "{row}");
        }
        let plain = with_faults("[[faults]]\nnode = 3\nfrom = 5\n").expect("cut off for good");
        assert_eq!(plain.leave_step(3), None, "a row without leave cuts a follower off that still runs");
        for (row, key, says) in [
            ("node = 0\nfrom = 5\nleave = true", "node", "the leader does not leave"),
            ("link = [1, 2]\nfrom = 5\nleave = true", "link", "a leave is a follower's"),
            ("node = 3\nfrom = 5\nto = 6\nleave = true", "to", "does not come back"),
            ("node = 3\nfrom = 5\nloss = 0.5\nleave = true", "loss", "sends nothing"),
            ("node = 3\nfrom = 0\nto = 5\njoin = true\nleave = true", "join", "a join or a leave"),
            ("node = 3\nfrom = 0\ndied = true", "from", "is absent"),
            ("node = 0\nfrom = 5\ndied = true", "node", "the leader does not leave"),
            ("node = 3\nfrom = 5\nto = 6\ndied = true", "to", "does not come back"),
        ] {
            let e = with_faults(&format!("[[faults]]\n{row}\n")).expect_err(row).to_string();
            assert!(e.contains(&format!("faults[0].{key}")) && e.contains(says), "{row}: {e}");
            assert_eq!(e.lines().count(), 1, "{e}");
        }
    }

    /// A window may end one step after the run's end, T + Δt, and then
    /// covers its last step (t = T): the model of a follower that leaves
    /// for good; a step further is refused with that end named.
    #[test]
    fn a_window_may_cover_the_last_step_and_no_further() {
        let set = |to: &str| vec![format!("faults=[{{node=3, from=1, to={to}}}]"), "duration=2".to_string()];
        let s = Scenario::from_toml(PAPER, "t.toml", "t", &set("2.001")).expect("T + dt");
        assert_eq!(s.faults[0].steps(s.dt_s), (1000, 2001), "the window covers steps 1000..=2000");
        let e = Scenario::from_toml(PAPER, "t.toml", "t", &set("2.002")).expect_err("T + 2 dt").to_string();
        assert!(e.contains("leave `to` out for the rest of the run, its last step (t = T) included"), "{e}");
        // Without `to`: the rest of the run (a follower absent from the
        // start, from = 0, or one that leaves for good).
        for (from, first) in [("0", 0), ("1", 1000)] {
            let rest = vec![format!("faults=[{{node=3, from={from}}}]"), "duration=2".to_string()];
            let s = Scenario::from_toml(PAPER, "t.toml", "t", &rest).expect("no to");
            assert_eq!(s.faults[0].steps(s.dt_s), (first, 2001), "from = {from}: to the last step");
        }
    }

    #[test]
    fn bad_fault_rows_are_refused_naming_the_field() {
        let cases = [
            ("node = 9\nfrom = 1\nto = 2", "faults[0].node", "follower 9 is not in the scenario"),
            ("link = [1, 4]\nfrom = 1\nto = 2", "faults[0].link", "1–4 is not a link"),
            ("link = [0, 2]\nfrom = 1\nto = 2", "faults[0].link", "0–2 is not a link"),
            ("link = [1, 7]\nfrom = 1\nto = 2", "faults[0].link", "node 7 is not in the scenario"),
            ("node = 3\nlink = [1, 3]\nfrom = 1\nto = 2", "faults[0].node", "not both"),
            ("from = 1\nto = 2", "faults[0]", "missing"),
            ("node = 3\nfrom = 5\nto = 5", "faults[0].to", "empty"),
            ("node = 3\nfrom = -1\nto = 5", "faults[0].from", "before the run"),
            ("node = 3\nfrom = 5\nto = 25", "faults[0].to", "after the end of the run"),
            ("node = 3\nfrom = 1\nto = 2\nloss = 1.5", "faults[0].loss", "not a probability"),
            ("node = 3\nfrom = 1\nto = 2\nloss = -0.1", "faults[0].loss", "not a probability"),
        ];
        for (row, field, says) in cases {
            let e = with_faults(&format!("[[faults]]\n{row}\n")).expect_err(row).to_string();
            assert!(e.contains(&format!("{field}:")) && e.contains(says), "{row}: {e}");
            assert!(e.starts_with("t.toml:"), "names the file and line: {e}");
        }
        let e = with_faults("[network]\nrejoin = \"maybe\"\n").expect_err("rejoin").to_string();
        assert!(e.contains("network.rejoin:") && e.contains("consensus, adopt"), "{e}");
        let e = with_faults("[network]\nrejoin_after = 0.0001\n").expect_err("rejoin_after").to_string();
        assert!(e.contains("network.rejoin_after:"), "{e}");
    }

    #[test]
    fn an_outage_can_be_appended_from_the_command_line() {
        let set =
            ["faults+={node=3, from=10, to=13}".to_string(), "faults+={link=[0,1], from=1, to=2, loss=0.5}".into()];
        let s = Scenario::from_toml(PAPER, "t.toml", "t", &set).expect("appended");
        assert_eq!(s.faults.len(), 2);
        assert_eq!(s.faults[0].target, FaultTarget::Node(3));
        assert_eq!(s.faults[1].loss, 0.5);
        let replaced = Scenario::from_toml(PAPER, "t.toml", "t", &["faults=[{node=2, from=1, to=2}]".into()]).unwrap();
        assert_eq!(replaced.faults[0].target, FaultTarget::Node(2));
        // An error in an appended row names the --set, not the file.
        let file_row = format!("{PAPER}[[faults]]\nnode = 2\nfrom = 1\nto = 2\n");
        let e = Scenario::from_toml(&file_row, "t.toml", "t", &["faults+={node=9, from=1, to=2}".into()])
            .expect_err("unknown node")
            .to_string();
        assert!(e.starts_with("--set faults+={node=9") && e.contains("faults[1].node"), "{e}");
    }

    #[test]
    fn find_line_locates_keys_in_tables_and_arrays_of_tables() {
        let src = "name = \"x\"\nedges = [[1, 2]]\n[robot]\nmass = -1\n[[followers]]\nid = 1\n[[followers]]\nid = 2\noffset = [0, 0]\n";
        assert_eq!(find_line(src, "robot.mass"), Some(4));
        assert_eq!(find_line(src, "followers[1].offset"), Some(9));
        assert_eq!(find_line(src, "followers[0].id"), Some(6));
        assert_eq!(find_line(src, "edges[0]"), Some(2));
        assert_eq!(find_line(src, "fault.time"), None);
    }

    /// Every fixed-length array of the file, written out, on two followers.
    const ARRAYS: &str = "edges = [[1, 2]]\n[leader]\npose = [0.0, 3.0, 0.0]\n\
        [[followers]]\nid = 1\noffset = [1.0, 0.0]\npose = [0.0, 0.0, 0.0]\nvelocity = [0.0, 0.0]\nleader_link = true\n\
        [[followers]]\nid = 2\noffset = [2.0, 0.0]\nbody_error = [0.0, 0.0, 0.0]\n\
        [estimator]\nk = [1.0, 1.0, 1.0]\nka = [20.0, 20.0]\nkb = [5.0, 5.0]\n\
        [covariance]\nq = [1.6e-4, 1.0e-4]\nr = [1.6e-4, 1.0e-4]\n[asif]\nrho_max = [0.08, 0.08]\n";

    fn load(text: &str, overrides: &[&str]) -> Result<Scenario, ScenarioError> {
        let overrides: Vec<String> = overrides.iter().map(|s| s.to_string()).collect();
        Scenario::from_toml(text, "s.toml", "s", &overrides)
    }

    fn message(text: &str, overrides: &[&str]) -> String {
        load(text, overrides).expect_err("must be rejected").to_string()
    }

    #[test]
    fn every_fixed_length_array_must_have_exactly_its_length() {
        load(ARRAYS, &[]).expect("the arrays as written load");
        for (from, to, want) in [
            ("[[1, 2]]", "[[1, 2], [2, 1, 3]]", "edges[1]: expected 2 follower ids, got 3"),
            ("[[1, 2]]", "[[1]]", "edges[0]: expected 2 follower ids, got 1"),
            ("[0.0, 3.0, 0.0]", "[0.0, 3.0, 0.0, 1.0]", "leader.pose: expected 3 numbers, got 4"),
            ("[1.0, 0.0]", "[1.0, 0.0, 5.0]", "followers[0].offset: expected 2 numbers, got 3"),
            ("[0.0, 0.0, 0.0]\nvel", "[0.0, 0.0, 0.0, 0.0]\nvel", "followers[0].pose: expected 3 numbers, got 4"),
            ("velocity = [0.0, 0.0]", "velocity = [0.0]", "followers[0].velocity: expected 2 numbers, got 1"),
            ("[2.0, 0.0]", "[2.0, 0.0, 0.0]", "followers[1].offset: expected 2 numbers, got 3"),
            (
                "body_error = [0.0, 0.0, 0.0]",
                "body_error = [0.0, 0.0]",
                "followers[1].body_error: expected 3 numbers, got 2",
            ),
            ("[1.0, 1.0, 1.0]", "[1.0, 1.0, 1.0, 1.0]", "estimator.k: expected 3 numbers, got 4"),
            ("[20.0, 20.0]", "[20.0, 20.0, 20.0]", "estimator.ka: expected 2 numbers, got 3"),
            ("[5.0, 5.0]", "[5.0, 5.0, 5.0]", "estimator.kb: expected 2 numbers, got 3"),
            ("q = [1.6e-4, 1.0e-4]", "q = [1.6e-4, 1.0e-4, 1.0]", "covariance.q: expected 2 numbers, got 3"),
            ("r = [1.6e-4, 1.0e-4]", "r = [1.6e-4, 1.0e-4, 1.0]", "covariance.r: expected 2 numbers, got 3"),
            ("[0.08, 0.08]", "[0.08, 0.08, 0.08]", "asif.rho_max: expected 2 numbers, got 3"),
        ] {
            assert_eq!(ARRAYS.matches(from).count(), 1, "{from:?} is not unique");
            let text = ARRAYS.replace(from, to);
            let line = text[..text.find(to).unwrap()].matches('\n').count() + 1;
            let want = format!("s.toml:{line}: {want}");
            assert_eq!(message(&text, &[]), want);
            // A --set elsewhere does not take the blame for the file.
            assert_eq!(message(&text, &["duration=1"]), want, "with --set duration=1");
        }
    }

    #[test]
    fn a_set_table_over_an_earlier_set_key_is_refused() {
        let text = format!("{ARRAYS}[robot]\nmass = 10.0\ninertia = 5.0\n");
        assert_eq!(
            message(&text, &["robot.mass=1", "robot={inertia=2}"]),
            "--set robot={inertia=2}: conflicts with --set robot.mass=1: a table replaces all of `robot`, so \
             robot.mass would be dropped (give every key in the one table, or each as robot.KEY=VALUE)"
        );
        // The other order sets a key inside the table: nothing is dropped.
        let m = message(&text, &["robot={inertia=2, mass=3}", "robot.mass=-1"]);
        assert_eq!(m, "--set robot.mass=-1: robot.mass: must be positive, got -1");
    }

    #[test]
    fn a_set_array_must_have_exactly_its_length() {
        assert_eq!(
            message(ARRAYS, &["estimator.ka=[1, 2, 3]"]),
            "--set estimator.ka=[1, 2, 3]: `estimator.ka`: expected 2 numbers, got 3"
        );
    }

    #[test]
    fn an_error_in_a_set_value_names_the_set_not_a_file_line() {
        let text = format!("{ARRAYS}[robot]\nmass = 10.0\n");
        assert_eq!(message(&text, &["robot.mass=-1"]), "--set robot.mass=-1: robot.mass: must be positive, got -1");
        // The last assignment of a key is the one that counts.
        assert_eq!(
            message(&text, &["robot.mass=-1", "robot.mass=-2"]),
            "--set robot.mass=-2: robot.mass: must be positive, got -2"
        );
        // A table set as a whole.
        assert_eq!(
            message(&text, &["backstepping.shunting={a = 1.0, b = -1.0, d = 1.0}"]),
            "--set backstepping.shunting={a = 1.0, b = -1.0, d = 1.0}: backstepping.shunting.b: must be positive, got -1"
        );
        // A file value made invalid by a --set of another field.
        let m = message(&text, &["dt=0.007"]);
        assert!(m.starts_with("--set dt=0.007: duration: 30 s is not a whole number of steps"), "{m}");
        let m = message(&text, &["edges=[]"]);
        assert!(m.starts_with("--set edges=[]: graph: H is not positive definite"), "{m}");
        // The file's own errors still cite the file's line.
        let text = format!("{ARRAYS}[robot]\nmass = -1.0\n");
        let line = text.lines().count();
        assert_eq!(message(&text, &["duration=1"]), format!("s.toml:{line}: robot.mass: must be positive, got -1"));
    }

    #[test]
    fn a_velocity_commanded_robot_parses_with_its_lag() {
        assert_eq!(load(ARRAYS, &[]).unwrap().control.drive, Drive::Torque, "the default is the paper's robot");
        let with = |robot: &str| format!("{ARRAYS}[robot]\n{robot}\n");
        let s = load(&with("model = \"velocity\""), &[]).unwrap();
        assert_eq!(s.control.drive, Drive::Velocity { lag_s: DEFAULT_LAG_S });
        let s = load(&with("model = \"velocity\"\nlag = 0.25"), &[]).unwrap();
        assert_eq!(s.control.drive, Drive::Velocity { lag_s: 0.25 });
        let s = load(ARRAYS, &["robot.model=velocity", "robot.lag=0.05"]).unwrap();
        assert_eq!(s.control.drive, Drive::Velocity { lag_s: 0.05 });
        // The bounds are (0, 10] s.
        assert_eq!(
            load(ARRAYS, &["robot.model=velocity", "robot.lag=10"]).unwrap().control.drive,
            Drive::Velocity { lag_s: 10.0 }
        );
        // A torque scenario is written as before the key existed; a velocity one says so.
        let written = toml::to_string(&load(ARRAYS, &[]).unwrap().source).unwrap();
        assert!(!written.contains("model") && !written.contains("lag"), "{written}");
        let written = toml::to_string(&s.source).unwrap();
        assert!(written.contains("model = \"velocity\"") && written.contains("lag = 0.05"), "{written}");
    }

    #[test]
    fn a_bad_lag_or_a_lag_without_the_velocity_model_is_refused() {
        let with = |robot: &str| format!("{ARRAYS}[robot]\n{robot}\n");
        // The line of `lag`, right after `[robot]`.
        let line = with("").lines().count();
        for (lag, says) in [
            ("-1.0", "must be positive, got -1"),
            ("0.0", "must be positive, got 0"),
            ("inf", "must be a finite number, got inf"),
            ("nan", "must be a finite number, got NaN"),
            ("100.0", "must be at most 10 s (the time constant of the robot's velocity loop, in seconds), got 100"),
        ] {
            let text = with(&format!("lag = {lag}\nmodel = \"velocity\""));
            assert_eq!(message(&text, &[]), format!("s.toml:{line}: robot.lag: {says}"));
        }
        assert_eq!(
            message(&with("lag = 0.1"), &[]),
            format!(
                "s.toml:{line}: robot.lag: only a velocity-commanded robot has a lag: set robot.model = \"velocity\" \
                 or remove lag"
            )
        );
        // From the command line, the assignment at fault is named.
        assert_eq!(
            message(ARRAYS, &["robot.model=velocity", "robot.lag=-0.1"]),
            "--set robot.lag=-0.1: robot.lag: must be positive, got -0.1"
        );
        assert_eq!(
            message(&with("model = \"velocity\"\nlag = 0.2"), &["robot.model=torque"]),
            "--set robot.model=torque: robot.lag: only a velocity-commanded robot has a lag: set robot.model = \
             \"velocity\" or remove lag"
        );
        let m = message(ARRAYS, &["robot.model=wheels"]);
        assert_eq!(m, "--set robot.model=wheels: `robot.model`: `wheels` is not one of: torque or velocity");
        let m = message(&format!("{ARRAYS}[fault]\ntime = 10.0\n"), &["robot.model=velocity"]);
        assert_eq!(
            m,
            "--set robot.model=velocity: fault.time: the fault changes the velocity filter's model, and a \
             velocity-commanded robot (robot.model = \"velocity\") runs no filter"
        );
    }

    #[test]
    fn fault_time_must_lie_within_the_run() {
        let with_fault = |t: &str| format!("{ARRAYS}[fault]\ntime = {t}\n");
        let line = with_fault("0").lines().count();
        assert_eq!(load(&with_fault("30.0"), &[]).unwrap().control.fault.unwrap().time_s, 30.0);
        assert_eq!(load(&with_fault("0.0"), &[]).unwrap().control.fault.unwrap().time_s, 0.0);
        assert_eq!(
            message(&with_fault("30.5"), &[]),
            format!("s.toml:{line}: fault.time: must lie within [0, duration] = [0, 30] s, got 30.5")
        );
        assert_eq!(
            message(&with_fault("10.0"), &["duration=5"]),
            "--set duration=5: fault.time: must lie within [0, duration] = [0, 5] s, got 10"
        );
        assert_eq!(
            message(ARRAYS, &["fault.time=31"]),
            "--set fault.time=31: fault.time: must lie within [0, duration] = [0, 30] s, got 31"
        );
    }

    #[test]
    fn limits_and_the_safety_filter_parse_and_default() {
        let s = load(ARRAYS, &["robot.v_max=0.22", "robot.w_max=2.84"]).unwrap();
        assert_eq!(s.control.guard.limits, Some(Limits { v_max: 0.22, w_max: 2.84 }));
        assert!(s.control.guard.safety.is_none() && s.safety_distance.is_none());
        assert_eq!(s.cmd_timeout_s, DEFAULT_CMD_TIMEOUT_S);
        let s = load(ARRAYS, &["safety.distance=0.3"]).unwrap();
        let f = s.control.guard.safety.expect("the filter is on by default");
        assert_eq!((f.distance, f.gamma, f.projection, f.radius, f.arena), (0.3, 100.0, 0.05, 1.0, None));
        assert_eq!(s.safety_distance, Some(0.3));
        // The deadlock rule (eq. G6) on by default: 1 s held, 2 s sidestep, sideways; in steps of dt.
        let steps = |t: f64| (t / s.dt_s).round() as u64;
        let rule = DeadlockRule {
            after_steps: steps(1.0),
            sidestep_steps: steps(2.0),
            angle_rad: std::f64::consts::FRAC_PI_2,
        };
        assert_eq!(f.deadlock, Some(rule));
        let s = load(ARRAYS, &["safety={distance=0.3,deadlock_after=0}"]).unwrap();
        assert_eq!(s.control.guard.safety.unwrap().deadlock, None, "deadlock_after = 0: off");
        let s = load(ARRAYS, &["safety.distance=0.3", "safety.filter=false"]).unwrap();
        assert!(s.control.guard.is_off() && s.safety_distance == Some(0.3), "figures without the filter");
    }

    #[test]
    fn bad_limits_and_safety_settings_are_refused_in_one_line() {
        for (set, want) in [
            ("robot.v_max=0", "--set robot.v_max=0: robot.v_max: must be positive, got 0"),
            ("robot.w_max=-1", "--set robot.w_max=-1: robot.w_max: must be positive, got -1"),
            ("robot.v_max=inf", "--set robot.v_max=inf: robot.v_max: must be a finite number, got inf"),
            ("robot.w_max=nan", "--set robot.w_max=nan: robot.w_max: must be a finite number, got NaN"),
            ("robot.cmd_timeout=0", "--set robot.cmd_timeout=0: robot.cmd_timeout: must be positive, got 0"),
            ("safety.distance=0", "--set safety.distance=0: safety.distance: must be positive, got 0"),
            (
                "safety.distance=4",
                "--set safety.distance=4: safety.distance: followers 1 and 2 start 3.605551 m apart, closer than \
                 the safety distance 4 m",
            ),
            (
                "safety={distance=0.3,arena=[-1.0,1.0,-1.0,1.0]}",
                "--set safety={distance=0.3,arena=[-1.0,1.0,-1.0,1.0]}: safety.arena: follower 2 starts at (2, 3), \
                 outside the arena x ∈ [-1, 1], y ∈ [-1, 1]",
            ),
            (
                "safety={distance=0.3,arena=[1.0,-1.0,-1.0,1.0]}",
                "--set safety={distance=0.3,arena=[1.0,-1.0,-1.0,1.0]}: safety.arena: [x_min, x_max, y_min, y_max] = \
                 [1.0, -1.0, -1.0, 1.0]: each min must be below its max",
            ),
            (
                "safety={distance=0.3,radius=0.35}",
                "--set safety={distance=0.3,radius=0.35}: safety.radius: 0.35 m must exceed the barrier's radius, \
                 distance + 2 × projection = 0.4 m, or no robot is ever seen in time",
            ),
            (
                "safety={distance=3.58,radius=5.0}",
                "--set safety={distance=3.58,radius=5.0}: safety.distance: followers 1 and 2 start with their filtered points \
                 (0.05 m ahead of the axle) 3.605551 m apart, closer than the barrier's radius, distance + 2 × \
                 projection = 3.68 m: they would start outside the set the filter keeps them in",
            ),
            (
                "safety={distance=0.3,arena=[-0.1,3.0,-1.0,4.0]}",
                "--set safety={distance=0.3,arena=[-0.1,3.0,-1.0,4.0]}: safety.arena: follower 1's filtered point \
                 starts 0.15 m from the wall x = -0.1, within the filter's margin r / 2 = 0.2 m: it would start \
                 outside the set the filter keeps it in",
            ),
            (
                "safety={distance=0.3,deadlock_after=-1}",
                "--set safety={distance=0.3,deadlock_after=-1}: safety.deadlock_after: must not be negative, got -1",
            ),
            (
                "safety={distance=0.3,sidestep=0}",
                "--set safety={distance=0.3,sidestep=0}: safety.sidestep: must be positive, got 0",
            ),
            (
                "safety={distance=0.3,sidestep_angle=4}",
                "--set safety={distance=0.3,sidestep_angle=4}: safety.sidestep_angle: 4 rad must be in (0, π): a \
                 turn to the right",
            ),
            (
                "safety={distance=0.3,lag_margin=true}",
                "--set safety={distance=0.3,lag_margin=true}: safety.lag_margin: is for a velocity-commanded robot's \
                 lag (robot.model = \"velocity\"); a torque robot has none",
            ),
        ] {
            assert_eq!(message(ARRAYS, &[set]), want);
        }
        let velocity = ["robot.model=\"velocity\"", "robot.lag=0.2", "safety={distance=0.3,lag_margin=true}"];
        assert!(
            message(ARRAYS, &velocity).ends_with(
                "safety.lag_margin: robot.lag (0.2 s) × the point's top speed needs robot.v_max and robot.w_max \
                 (without them the margin has no bound)"
            ),
            "{}",
            message(ARRAYS, &velocity)
        );
        // Eq. G3d: r = distance + 2 l + lag √(v_max² + (w_max l)²).
        let s = load(ARRAYS, &[&velocity[..], &["robot.v_max=0.3", "robot.w_max=2"]].concat()).unwrap();
        let safety = s.control.guard.safety.expect("the filter");
        assert!((safety.lag_margin - 0.2 * 0.3f64.hypot(0.1)).abs() < 1e-15, "{}", safety.lag_margin);
        assert!((safety.barrier_radius() - (0.3 + 0.1 + safety.lag_margin)).abs() < 1e-15);
        let s = load(ARRAYS, &["robot.model=\"velocity\"", "safety.distance=0.3"]).unwrap();
        assert_eq!(s.control.guard.safety.map(|g| g.lag_margin), Some(0.0), "no margin unless asked for");
    }

    /// docs/ros2.md: where each robot's odometry frame sits, and the frame it names.
    #[test]
    fn odometry_origins_and_frames_parse_and_bad_ones_are_refused_in_one_line() {
        let s = load(ARRAYS, &[]).unwrap();
        assert!(s.followers.iter().all(|f| f.odom_origin.is_none()), "the world frame by default");
        assert_eq!(s.odom_frame_of(7), "follower_7/odom");
        let s = load(ARRAYS, &["robot.odom_origin=\"start\"", "ros2.odom_frame=\"odom\""]).unwrap();
        assert!(s.followers.iter().all(|f| f.odom_origin == Some(f.pose)), "each at its scenario pose");
        assert_eq!(s.odom_frame_of(7), "odom");
        let own = ARRAYS.replacen("leader_link = true\n", "leader_link = true\nodom_origin = [1.0, 2.0, 0.5]\n", 1);
        let s = load(&own, &["robot.odom_origin=\"start\""]).unwrap();
        assert_eq!(s.followers[0].odom_origin, Some(Pose::new(1.0, 2.0, 0.5)), "a follower's own origin wins");
        assert_eq!(s.followers[1].odom_origin, Some(s.followers[1].pose));
        assert_eq!(
            message(ARRAYS, &["robot.odom_origin=\"here\""]),
            "--set robot.odom_origin=\"here\": robot.odom_origin: `here` is not one of: world, start (or give a \
             follower its own odom_origin = [x, y, θ])"
        );
        assert!(message(ARRAYS, &["ros2.odom_frame=\"\""]).contains("ros2.odom_frame: a frame name of 1 to 256"));
        let bad = ARRAYS.replacen("leader_link = true\n", "leader_link = true\nodom_origin = [1.0, inf, 0.0]\n", 1);
        assert!(load(&bad, &[]).unwrap_err().to_string().contains("followers[0].odom_origin"), "a non-finite origin");
    }

    #[test]
    fn ros2_is_off_by_default_and_turned_on_by_enabled_or_driven_robots() {
        assert_eq!(load(ARRAYS, &[]).unwrap().ros2, None);
        let on = load(ARRAYS, &["ros2.enabled=true", "ros2.domain_id=7"]).unwrap().ros2.unwrap();
        assert_eq!((on.domain_id, on.robots, on.odom_timeout_s), (7, RobotSource::Simulated, 0.5));
        let driven = load(ARRAYS, &["ros2.robots=\"external\"", "robot.model=\"velocity\""]).unwrap().ros2.unwrap();
        assert_eq!(driven.robots, RobotSource::External);
        assert_eq!(
            message(ARRAYS, &["ros2.robots=\"stand-in\""]),
            "--set ros2.robots=\"stand-in\": ros2.robots: `stand-in`: a robot driven through ROS 2 takes velocity \
             commands on cmd_vel; set robot.model = \"velocity\""
        );
        assert_eq!(
            message(ARRAYS, &["ros2.robots=\"turtle\""]),
            "--set ros2.robots=\"turtle\": ros2.robots: `turtle` is not one of: simulated, stand-in, external"
        );
        assert_eq!(
            message(ARRAYS, &["ros2.domain_id=233"]),
            "--set ros2.domain_id=233: ros2.domain_id: 233 is above ROS 2's largest domain id, 232"
        );
        assert_eq!(
            message(ARRAYS, &["ros2.odom_timeout=0"]),
            "--set ros2.odom_timeout=0: ros2.odom_timeout: must be positive, got 0"
        );
    }

    #[test]
    fn the_paper_scenarios_are_built_in_and_a_file_of_that_name_comes_first() {
        let dir = std::env::temp_dir().join(format!("formation-built-in-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let inside = dir.join("scenarios/paper.toml");
        for name in ["paper", "paper.toml"] {
            let s = Scenario::load(Path::new(name), &[]).expect("built in");
            assert_eq!((s.name.as_str(), s.followers.len()), ("paper", 4), "{name}");
        }
        // From any folder, the checkout's path names the built-in copy.
        let s = Scenario::load(&inside, &[]);
        assert!(matches!(s, Err(ScenarioError::Io { .. })), "an absolute path that is no file is an error");
        let v = Scenario::load(Path::new("scenarios/paper-velocity.toml"), &["duration=1".into()]).expect("built in");
        assert_eq!((v.name.as_str(), v.steps()), ("paper-velocity", 1000));
        // A file of that name is read, not the built-in one.
        let own = dir.join("paper");
        std::fs::write(&own, "name = \"mine\"\nedges = [[1, 2]]\n[[followers]]\nid = 1\noffset = [1.0, 0.0]\npose = [0.0, 0.0, 0.0]\nleader_link = true\n[[followers]]\nid = 2\noffset = [2.0, 0.0]\npose = [0.0, 0.0, 0.0]\n").unwrap();
        assert_eq!(Scenario::load(&own, &[]).expect("the file").name, "mine");
        assert!(Scenario::load(Path::new("no-such-scenario.toml"), &[]).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
