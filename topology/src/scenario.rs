//! Validation of a [`ScenarioFile`] into a [`Scenario`], and `--set` overrides.

use std::path::Path;
use std::sync::Arc;

use formation_agent::{
    ControlParams, DeadlockRule, DynamicGains, EstimatorGains, Fault, FilterParams, FollowerConfig, Guard,
    KinematicGains, Limits, LinkLoss, LossWindow, RejoinPolicy, RejoinRule, SafetyParams, Shunting,
};
use formation_leader::LeaderState;
use formation_leader::{Leader, Profile, Trajectory};
use formation_plant::{Disturbance, Drive, NoiseCov, Pose, RobotParams, Velocity};
use serde::Serialize;

use crate::error::ScenarioError;
use crate::file::{exact, LeaderFile, RobotModel, SafetyFile, ScenarioFile, DEFAULT_CMD_TIMEOUT_S, DEFAULT_LAG_S};
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

use formation_agent::math::step_at;

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
    pub followers: Vec<FollowerSpec>,
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

    /// Reads, overrides (`KEY=VALUE`, dotted keys) and validates a scenario file.
    ///
    /// A path that names no file but a built-in scenario ([`BUILT_IN`]:
    /// `paper`, `paper-velocity`, `paper-tables`, or their
    /// `scenarios/<name>.toml` as in a checkout) loads the copy inside the binary, so an installed binary
    /// runs the paper's scenario anywhere.
    pub fn load(path: &Path, overrides: &[String]) -> Result<Self, ScenarioError> {
        let (label, text) = Self::source(path)?;
        let stem = match built_in(path).filter(|_| !path.exists()) {
            Some((name, _)) => name,
            None => path.file_stem().and_then(|s| s.to_str()).unwrap_or("scenario"),
        };
        Self::from_toml(&text, &label, stem, overrides)
    }

    /// The text [`Scenario::load`] reads for `path`, and the label it is
    /// known by in errors: the file's, or the built-in copy's (a run's
    /// hearing record carries it, so `formation replay` needs no file).
    pub fn source(path: &Path) -> Result<(String, String), ScenarioError> {
        if !path.exists() {
            if let Some((name, text)) = built_in(path) {
                return Ok((format!("{name} (built in)"), text.to_string()));
            }
        }
        let label = path.display().to_string();
        let text = read_scenario_file(path).map_err(|mut message| {
            if !path.exists() {
                let names: Vec<&str> = BUILT_IN.iter().map(|(n, _)| *n).collect();
                message.push_str(&format!(" (the built-in scenarios are {})", names.join(", ")));
            }
            ScenarioError::Io { file: label.clone(), message }
        })?;
        Ok((label, text))
    }

    /// Like [`Scenario::load`] from text; `label` names it in errors and
    /// `default_name` is the run name when the file gives none.
    pub fn from_toml(text: &str, label: &str, default_name: &str, overrides: &[String]) -> Result<Self, ScenarioError> {
        let line_of = |span: Option<std::ops::Range<usize>>| {
            span.map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1)
        };
        let file: ScenarioFile = toml::from_str(text).map_err(|e| ScenarioError::Syntax {
            file: label.to_string(),
            line: line_of(e.span()),
            message: syntax_message(text, &e),
        })?;
        let (file, overridden) =
            if overrides.is_empty() { (file, Vec::new()) } else { apply_overrides(text, label, overrides)? };
        validate(file, label, default_name, Some(text), &overridden, MAX_FOLLOWERS)
    }

    /// The file [`Scenario::from_toml`] validates: `text` with `overrides`
    /// applied, every key the text leaves out at its default (what the
    /// Python package reads keys from and saves).
    pub fn effective_file(text: &str, label: &str, overrides: &[String]) -> Result<ScenarioFile, ScenarioError> {
        if overrides.is_empty() {
            return toml::from_str(text).map_err(|e| ScenarioError::Syntax {
                file: label.to_string(),
                line: e.span().map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1),
                message: syntax_message(text, &e),
            });
        }
        apply_overrides(text, label, overrides).map(|(file, _)| file)
    }

    /// A scenario text built in code with up to `most_followers` followers
    /// (the benchmarks' rings of 100,000): a file or a `--set` is held to
    /// [`MAX_FOLLOWERS`].
    pub fn from_toml_sized(
        text: &str,
        label: &str,
        default_name: &str,
        most_followers: usize,
    ) -> Result<Self, ScenarioError> {
        let file: ScenarioFile = toml::from_str(text).map_err(|e| ScenarioError::Syntax {
            file: label.to_string(),
            line: None,
            message: syntax_message(text, &e),
        })?;
        validate(file, label, default_name, Some(text), &[], most_followers)
    }

    /// Validates a scenario built in code (no file lines to report).
    pub fn from_file(file: ScenarioFile, name: &str) -> Result<Self, ScenarioError> {
        validate(file, "", name, None, &[], MAX_FOLLOWERS)
    }

    /// Number of steps T/Δt; the run has steps + 1 samples (docs/model.md §9).
    pub fn steps(&self) -> u64 {
        (self.duration_s / self.dt_s).round() as u64
    }

    pub fn leader(&self) -> Leader {
        Leader::new(self.leader_profile, self.leader_pose)
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
        FollowerConfig { id: f.id, offset: f.offset, hears_leader: f.hears_leader, control: Arc::clone(&self.control) }
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

/// The scenarios inside the binary: the files of `scenarios/` that the
/// documentation runs, by name.
pub const BUILT_IN: [(&str, &str); 6] = [
    ("paper", include_str!("../../scenarios/paper.toml")),
    ("paper-velocity", include_str!("../../scenarios/paper-velocity.toml")),
    ("paper-tables", include_str!("../../scenarios/paper-tables.toml")),
    ("turtlebot", include_str!("../../scenarios/turtlebot.toml")),
    ("swap", include_str!("../../scenarios/swap.toml")),
    ("rotation", include_str!("../../scenarios/rotation.toml")),
];

/// The built-in scenario `path` names: `paper`, `paper.toml` or
/// `scenarios/paper.toml` (and the same for every name of [`BUILT_IN`]).
pub fn built_in(path: &Path) -> Option<(&'static str, &'static str)> {
    let text = path.to_str()?;
    let name = text.strip_prefix("scenarios/").unwrap_or(text);
    let name = name.strip_suffix(".toml").unwrap_or(name);
    BUILT_IN.iter().find(|(n, _)| *n == name).copied()
}

/// Reads a scenario file: a regular file (not a FIFO, a device or a
/// folder, which could block or never end) of at most [`MAX_FILE_BYTES`].
fn read_scenario_file(path: &Path) -> Result<String, String> {
    use std::io::Read;
    let meta = std::fs::metadata(path).map_err(|e| format!("cannot read: {e}"))?;
    if meta.is_dir() {
        return Err("is a folder, not a scenario file".into());
    }
    if !meta.is_file() {
        return Err("is not a regular file (a FIFO, a socket or a device): a scenario must be a file".into());
    }
    if meta.len() > MAX_FILE_BYTES {
        return Err(format!("is {} bytes; a scenario file may have at most {MAX_FILE_BYTES}", meta.len()));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_FILE_BYTES + 1).read_to_end(&mut bytes))
        .map_err(|e| format!("cannot read: {e}"))?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(format!("is more than {MAX_FILE_BYTES} bytes, the most a scenario file may have"));
    }
    String::from_utf8(bytes)
        .map_err(|e| format!("is not UTF-8 text (byte {}): a scenario is a TOML file", e.utf8_error().valid_up_to()))
}

/// A deserialization message in plain words, prefixed with the key it is
/// about where the source says (`followers[2].offset: expected 2 numbers,
/// got 3`; `dt: expected a number, found the string "x"`).
fn syntax_message(text: &str, e: &toml::de::Error) -> String {
    let message = plain_message(e.message().trim());
    let field = e.span().and_then(|s| field_at(text, s.start));
    let key = duplicate_key(&message)
        .map(str::to_string)
        .or_else(|| (message == "duplicate key").then(|| key_at(text, e.span()?.start)).flatten());
    let message = match key {
        Some(key) => match first_line_of(text, &key, e.span().map(|s| s.start)) {
            Some(line) if message == "duplicate key" => {
                format!("duplicate key `{key}`: first given on line {line} (a key may be given once)")
            }
            Some(line) => format!("{message} (first given on line {line}; a key may be given once)"),
            None => format!("{message} (a key may be given once)"),
        },
        None => message,
    };
    match field {
        Some(field) if !message.starts_with(&format!("{field}:")) => format!("{field}: {message}"),
        None if message.starts_with("unknown key") => match e.span().and_then(|s| table_before(text, s.start)) {
            Some(table) => format!("[{table}]: {message}"),
            None => message,
        },
        _ => message,
    }
}

/// The `[table]` or `[[array]]` header last opened before byte `at`.
fn table_before(text: &str, at: usize) -> Option<String> {
    text.get(..at)?
        .lines()
        .rev()
        .map(|l| l.split('#').next().unwrap_or("").trim())
        .find(|l| l.starts_with('['))
        .map(|l| l.trim_matches(['[', ']']).trim().to_string())
}

/// The key written at byte `at` of the source (bare or quoted).
fn key_at(text: &str, at: usize) -> Option<String> {
    let rest = text.get(at..)?;
    let key: String = rest
        .trim_start_matches(['[', ' '])
        .chars()
        .take_while(|c| c.is_ascii_alphanumeric() || "_-\"".contains(*c))
        .filter(|&c| c != '"')
        .collect();
    (!key.is_empty()).then_some(key)
}

/// The key of a `duplicate key` message.
fn duplicate_key(message: &str) -> Option<&str> {
    message.strip_prefix("duplicate key `")?.split('`').next()
}

/// The first line, before byte `before`, where `key` is assigned or opens a table.
fn first_line_of(text: &str, key: &str, before: Option<usize>) -> Option<usize> {
    let end = before.unwrap_or(text.len()).min(text.len());
    let mut offset = 0;
    for (n, line) in text.lines().enumerate() {
        if offset >= end {
            break;
        }
        offset += line.len() + 1;
        let t = line.split('#').next().unwrap_or("").trim();
        let head = t.trim_start_matches('[').trim_end_matches(']').trim();
        let assigned = t.split_once('=').map(|(k, _)| k.trim().trim_matches('"'));
        if assigned == Some(key) || (t.starts_with('[') && head == key) {
            return Some(n + 1);
        }
    }
    None
}

/// serde's and toml's words (`invalid type: string "x", expected f64`,
/// `expected struct RobotFile`, `wanted string or table`) in plain ones.
pub(crate) fn plain_message(message: &str) -> String {
    fn expected(what: &str) -> String {
        let what = what.trim();
        match what {
            "f64" | "f32" => "a number".into(),
            "u64" | "usize" => "a whole number ≥ 0".into(),
            "u32" => "a whole number from 0 to 4294967295".into(),
            "a boolean" | "bool" => "true or false".into(),
            "a sequence" => "an array [ ... ]".into(),
            "a string" => "a string in quotes".into(),
            _ if what.starts_with("struct LinkFaultFile") => {
                "a fault row, a table such as { node = 2, from = 10.0, to = 13.0 }".into()
            }
            _ if what.starts_with("struct ") => "a table ([name] or { key = value, ... })".into(),
            _ if what.starts_with("enum ") => "a name in quotes".into(),
            _ => what.to_string(),
        }
    }
    fn found(what: &str) -> String {
        let what = what.trim();
        match what {
            "unit variant" | "unit value" => "nothing (an empty value)".into(),
            "sequence" => "an array".into(),
            "map" => "a table".into(),
            _ => what
                .strip_prefix("integer ")
                .map(|v| format!("the whole number {}", v.trim_matches('`')))
                .or_else(|| what.strip_prefix("floating point ").map(|v| format!("the number {}", v.trim_matches('`'))))
                .or_else(|| what.strip_prefix("boolean ").map(|v| v.trim_matches('`').to_string()))
                .or_else(|| what.strip_prefix("string ").map(|v| format!("the string {v}")))
                .unwrap_or_else(|| what.to_string()),
        }
    }
    let m = message.trim();
    // An enum (kinematic, filter, …) given a table or an array.
    if m.starts_with("wanted exactly 1 element") || m.ends_with("expected string only") {
        return "expected a name in quotes (for example \"bio\" or \"asif\"), found a table or an array".into();
    }
    for prefix in ["invalid type: ", "invalid value: "] {
        if let Some(rest) = m.strip_prefix(prefix) {
            if let Some((what, exp)) = rest.rsplit_once(", expected ") {
                return format!("expected {}, found {}", expected(exp), found(what));
            }
        }
    }
    if m == "wanted string or table" {
        return "expected a name in quotes (for example \"bio\")".into();
    }
    if let Some(rest) = m.strip_prefix("unknown field `") {
        if let Some((key, others)) = rest.split_once("`, expected ") {
            return format!("unknown key `{key}` (the keys here are {})", others.replace("one of ", ""));
        }
        if let Some((key, _)) = rest.split_once("`, there are no fields") {
            return format!("unknown key `{key}` (this table has no keys)");
        }
    }
    if let Some(rest) = m.strip_prefix("missing field `") {
        return format!("missing key `{}`", rest.trim_end_matches('`'));
    }
    if let Some(rest) = m.strip_prefix("unknown variant `") {
        if let Some((v, others)) = rest.split_once("`, expected ") {
            return format!("`{v}` is not one of: {}", others.replace("one of ", "").replace('`', ""));
        }
    }
    if let Some(rest) = m.strip_prefix("expected ") {
        if !exact::is_length_error(m) && !rest.contains(',') {
            return format!("expected {}", expected(rest));
        }
    }
    m.to_string()
}

/// The dotted keys `--set` gave a value, each with its assignment, in order.
type Overridden = Vec<(String, String)>;

/// Applies `KEY=VALUE` overrides to the parsed document, one at a time so
/// that an error names the assignment at fault.
fn apply_overrides(text: &str, label: &str, overrides: &[String]) -> Result<(ScenarioFile, Overridden), ScenarioError> {
    let file_error =
        |message: &str| ScenarioError::Syntax { file: label.to_string(), line: None, message: message.trim().into() };
    let mut table: toml::Table = toml::from_str(text).map_err(|e| file_error(e.message()))?;
    // The file on its own must convert, so that a failure below is the
    // assignment's and never the file's.
    table.clone().try_into::<ScenarioFile>().map_err(|e| file_error(e.message()))?;
    let mut overridden = Vec::with_capacity(overrides.len());
    for assignment in overrides {
        let err = |message: String| ScenarioError::Override { assignment: assignment.clone(), message };
        let (key, value) = assignment.split_once('=').ok_or_else(|| err("expected KEY=VALUE".into()))?;
        let (key, value) = (key.trim(), value.trim());
        if key.is_empty() {
            return Err(err("empty key".into()));
        }
        let value = parse_value(value).map_err(err)?;
        // A table replaces the whole table at `key`: a value an earlier
        // --set gave inside it would be dropped without a word.
        if value.is_table() && !key.ends_with('+') {
            let inside = |given: &str| given.strip_prefix(key).is_some_and(|rest| rest.starts_with(['.', '[']));
            if let Some((given, earlier)) = overridden.iter().find(|(given, _): &&(String, String)| inside(given)) {
                return Err(err(format!(
                    "conflicts with --set {earlier}: a table replaces all of `{key}`, so {given} would be dropped \
                     (give every key in the one table, or each as {key}.KEY=VALUE)"
                )));
            }
        }
        let mut next = table.clone();
        match key.strip_suffix('+') {
            Some(array) => append_path(&mut next, array.trim(), value).map_err(err)?,
            None => set_path(&mut next, key, value).map_err(err)?,
        }
        next.clone().try_into::<ScenarioFile>().map_err(|e| err(override_message(key, e.message())))?;
        // `faults+=…` gave the array's new last element, nothing before it.
        let given = match key.strip_suffix('+').map(str::trim) {
            Some(array) => format!("{array}[{}]", array_len(&next, array).saturating_sub(1)),
            None => key.to_string(),
        };
        table = next;
        overridden.push((given, assignment.clone()));
    }
    let file = table
        .try_into::<ScenarioFile>()
        .map_err(|e| ScenarioError::Override { assignment: overrides.join(" "), message: e.message().to_string() })?;
    Ok((file, overridden))
}

fn override_message(key: &str, message: &str) -> String {
    let message = plain_message(message);
    let key = key.trim_end_matches('+').trim();
    if let Some(rest) = message.strip_prefix("unknown key `") {
        // The message names the last part of the key: name all of it; or a
        // key inside the table or array the value gave (`shunting={…, e=1}`:
        // it named the table, which exists, and listed the table's keys).
        let (name, after) = rest.split_once('`').unwrap_or((rest, ""));
        if key.rsplit('.').next() == Some(name) {
            format!("unknown key `{key}`{after}")
        } else {
            format!("`{key}`: unknown key `{name}`{after}")
        }
    } else if message.starts_with("unknown key") {
        format!("unknown key `{key}` ({message})")
    } else {
        format!("`{key}`: {message}")
    }
}

/// A TOML value if VALUE parses as one (number, bool, array, inline table,
/// quoted string); a bare word (`filter=kf`, `leader.trajectory=figure-eight`)
/// is a string; anything else is an error with TOML's reason (a missing
/// bracket is not taken for a string).
fn parse_value(value: &str) -> Result<toml::Value, String> {
    if value.trim().is_empty() {
        return Err("no value after `=` (write KEY=VALUE, e.g. duration=20 or filter=kf)".into());
    }
    match toml::from_str::<toml::Table>(&format!("v = {value}")) {
        Ok(mut t) => t.remove("v").ok_or_else(|| format!("`{value}` is not a value")),
        // Digits TOML cannot hold were taken for a word ("found the string").
        Err(_)
            if {
                let digits = value.trim_start_matches(['-', '+']);
                !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit())
            } =>
        {
            Err(format!("{value} is beyond the whole numbers a value can hold (±9223372036854775807)"))
        }
        Err(_) if !value.is_empty() && value.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c)) => {
            Ok(toml::Value::String(value.to_string()))
        }
        Err(e) => Err(format!(
            "`{value}` is not a TOML value ({}); write a number, true/false, [array], {{table}} or a quoted \"string\"",
            e.message().trim()
        )),
    }
}

/// The length of the array at dotted `key` (0 if there is none).
fn array_len(table: &toml::Table, key: &str) -> usize {
    let mut parts = key.split('.').peekable();
    let mut current = table;
    while let Some(part) = parts.next() {
        match (current.get(part), parts.peek()) {
            (Some(toml::Value::Array(a)), None) => return a.len(),
            (Some(toml::Value::Table(t)), Some(_)) => current = t,
            _ => return 0,
        }
    }
    0
}

/// `KEY+=VALUE`: appends VALUE to the array at KEY (creating it), e.g.
/// `--set 'faults+={node=3, from=10, to=13}'`.
fn append_path(table: &mut toml::Table, key: &str, value: toml::Value) -> Result<(), String> {
    let mut current = toml::Value::Array(Vec::new());
    let mut cursor: Option<&toml::Table> = Some(table);
    let parts: Vec<&str> = key.split('.').collect();
    for (n, part) in parts.iter().enumerate() {
        let found = cursor.and_then(|t| t.get(*part));
        if n + 1 == parts.len() {
            if let Some(v) = found {
                current = v.clone();
            }
        } else {
            cursor = found.and_then(toml::Value::as_table);
        }
    }
    let toml::Value::Array(mut items) = current else {
        return Err(format!("`{key}` is not an array, cannot append to it"));
    };
    items.push(value);
    set_path(table, key, toml::Value::Array(items))
}

fn set_path(table: &mut toml::Table, key: &str, value: toml::Value) -> Result<(), String> {
    let mut parts = key.split('.').peekable();
    let mut current = table;
    while let Some(part) = parts.next() {
        if parts.peek().is_none() {
            current.insert(part.to_string(), value);
            return Ok(());
        }
        let entry = current.entry(part.to_string()).or_insert_with(|| toml::Value::Table(toml::Table::new()));
        current = match entry {
            toml::Value::Table(t) => t,
            _ => return Err(format!("`{part}` is not a table, cannot set `{key}`")),
        };
    }
    Ok(())
}

/// Collects validation failures of one field.
struct Check<'a> {
    label: &'a str,
    source: Option<&'a str>,
    /// What `--set` gave a value: an error about it names the assignment,
    /// never a line of the file the user did not write.
    overridden: &'a [(String, String)],
    /// [`MAX_FOLLOWERS`], or more for a scenario built in code ([`Scenario::from_toml_sized`]).
    most_followers: usize,
}

impl Check<'_> {
    fn fail(&self, field: &str, message: impl Into<String>) -> ScenarioError {
        self.fail_with(field, &[], message)
    }

    /// A failure of `field` that also depends on the `related` fields: if
    /// any of them came from `--set`, the error names that assignment.
    fn fail_with(&self, field: &str, related: &[&str], message: impl Into<String>) -> ScenarioError {
        let message = message.into();
        // Every `--set` among them, in the command line's order: with
        // `--set dt=0.3 --set duration=1` both are the cause.
        let mut given: Vec<&str> =
            std::iter::once(field).chain(related.iter().copied()).filter_map(|f| self.assignment_of(f)).collect();
        let position = |a: &str| self.overridden.iter().position(|(_, b)| b == a);
        given.sort_by_key(|a| position(a));
        given.dedup();
        match given.is_empty() {
            false => {
                ScenarioError::Override { assignment: given.join(" --set "), message: format!("{field}: {message}") }
            }
            true => ScenarioError::Invalid {
                file: self.label.to_string(),
                line: self.source.and_then(|s| find_line(s, field)),
                field: field.to_string(),
                message,
            },
        }
    }

    /// The last `--set` that gave `field` its value (or the table or array
    /// holding it).
    fn assignment_of(&self, field: &str) -> Option<&str> {
        let covers =
            |key: &str| field.strip_prefix(key).is_some_and(|rest| rest.is_empty() || rest.starts_with(['.', '[']));
        self.overridden.iter().rev().find(|(key, _)| covers(key)).map(|(_, a)| a.as_str())
    }

    fn finite(&self, field: &str, values: &[f64]) -> Result<(), ScenarioError> {
        match values.iter().find(|v| !v.is_finite()) {
            Some(v) => Err(self.fail(field, format!("must be a finite number, got {v}"))),
            None => Ok(()),
        }
    }

    /// Finite and at most `limit` in size (a value beyond any robot's, whose
    /// square overflows the metrics: 1e300 m/s ran to an `inf` formation
    /// error with exit status 0).
    fn bounded(&self, field: &str, values: &[f64], limit: f64, unit: &str) -> Result<(), ScenarioError> {
        self.finite(field, values)?;
        match values.iter().find(|v| v.abs() > limit) {
            Some(v) => Err(self.fail(field, format!("{} is beyond ±{} {unit}", num(*v), num(limit)))),
            None => Ok(()),
        }
    }

    fn positive(&self, field: &str, values: &[f64]) -> Result<(), ScenarioError> {
        self.finite(field, values)?;
        match values.iter().find(|&&v| v <= 0.0) {
            Some(v) => Err(self.fail(field, format!("must be positive, got {v}"))),
            None => Ok(()),
        }
    }

    fn non_negative(&self, field: &str, values: &[f64]) -> Result<(), ScenarioError> {
        self.finite(field, values)?;
        match values.iter().find(|&&v| v < 0.0) {
            Some(v) => Err(self.fail(field, format!("must not be negative, got {v}"))),
            None => Ok(()),
        }
    }

    fn shunting(&self, field: &str, s: &Shunting) -> Result<(), ScenarioError> {
        self.non_negative(&format!("{field}.a"), &[s.a])?;
        self.positive(&format!("{field}.b"), &[s.b])?;
        self.positive(&format!("{field}.d"), &[s.d])
    }
}

/// The longest run name (a scenario's `name`, `--run`): it names the run's
/// folder and every key of its traffic.
pub const MAX_NAME_CHARS: usize = 100;

fn validate(
    file: ScenarioFile,
    label: &str,
    default_name: &str,
    source: Option<&str>,
    overridden: &[(String, String)],
    most_followers: usize,
) -> Result<Scenario, ScenarioError> {
    let c = Check { label, source, overridden, most_followers };
    let name = validate_name(&c, file.name.clone().unwrap_or_else(|| default_name.to_string()))?;
    validate_steps(&c, &file)?;
    let estimate_init = match file.estimate_init.as_str() {
        "leader" => EstimateInit::Leader,
        "zero" => EstimateInit::Zero,
        other => return Err(c.fail("estimate_init", format!("`{other}` is not one of: leader, zero"))),
    };
    let timing = match file.timing.as_str() {
        "lockstep" => Timing::Lockstep,
        "realtime" => Timing::Realtime,
        other => return Err(c.fail("timing", format!("`{other}` is not one of: lockstep, realtime"))),
    };
    let (leader_profile, leader_pose) = validate_leader(&c, &file.leader)?;
    validate_table_sizes(&c, &file)?;
    let followers = validate_followers(&c, &file, leader_pose)?;
    let graph = validate_graph(&c, &file, &followers)?;
    validate_gains(&c, &file)?;
    let fault = validate_fault(&c, &file)?;
    let drive = validate_drive(&c, &file)?;
    let faults = validate_faults(&c, &file, &followers, &graph)?;
    let (network, rejoin) = validate_network(&c, &file)?;
    let ros2 = validate_ros2(&c, &file, drive)?;
    let guard = validate_guard(&c, &file, &followers)?;
    let cmd_timeout_s = file.robot.cmd_timeout.unwrap_or(DEFAULT_CMD_TIMEOUT_S);
    c.positive("robot.cmd_timeout", &[cmd_timeout_s])?;
    let odom_frame = file.ros2.odom_frame.clone().unwrap_or_else(|| DEFAULT_ODOM_FRAME.to_string());
    if odom_frame.trim().is_empty() || odom_frame.len() > 256 {
        return Err(c.fail("ros2.odom_frame", "a frame name of 1 to 256 characters (`{id}` for the follower's id)"));
    }
    let r = &file.robot;
    let robot = RobotParams {
        mass_kg: r.mass,
        inertia_kgm2: r.inertia,
        wheel_radius_m: r.wheel_radius,
        half_axle_m: r.half_axle,
    };
    Ok(Scenario {
        name,
        seed: file.seed,
        dt_s: file.dt,
        duration_s: file.duration,
        noise: file.noise,
        covariance: NoiseCov { q: file.covariance.q, r: file.covariance.r },
        estimate_init,
        timing,
        leader_profile,
        leader_pose,
        followers,
        graph,
        control: Arc::new(ControlParams { guard, ..control_params(&file, robot, fault, rejoin, drive) }),
        robot,
        disturbance: Disturbance { linear_n: file.disturbance.dv, angular_nm: file.disturbance.dw },
        network,
        faults,
        ros2,
        safety_distance: file.safety.as_ref().map(|s| s.distance),
        cmd_timeout_s,
        odom_frame,
        source: file,
    })
}

/// `[robot] v_max`, `w_max` and `[safety]` (docs/model.md §16): limits that
/// are positive and finite; a safety distance the initial poses keep (the
/// pair that does not is named); an arena that holds every initial pose.
fn validate_guard(c: &Check<'_>, file: &ScenarioFile, followers: &[FollowerSpec]) -> Result<Guard, ScenarioError> {
    let r = &file.robot;
    for (field, value) in [("robot.v_max", r.v_max), ("robot.w_max", r.w_max)] {
        if let Some(v) = value {
            c.positive(field, &[v])?;
        }
    }
    let limits = (r.v_max.is_some() || r.w_max.is_some())
        .then(|| Limits { v_max: r.v_max.unwrap_or(f64::INFINITY), w_max: r.w_max.unwrap_or(f64::INFINITY) });
    let Some(sf) = &file.safety else { return Ok(Guard { limits, safety: None }) };
    c.positive("safety.distance", &[sf.distance])?;
    if let Some((a, b, d)) = closest_pair(followers) {
        if d < sf.distance {
            return Err(c.fail_with(
                "safety.distance",
                &["followers"],
                format!(
                    "followers {} and {} start {} m apart, closer than the safety distance {} m",
                    a,
                    b,
                    num((d * 1e6).round() / 1e6),
                    num(sf.distance)
                ),
            ));
        }
    }
    c.positive("safety.gamma", &[sf.gamma])?;
    c.positive("safety.projection", &[sf.projection])?;
    c.positive("safety.radius", &[sf.radius])?;
    let params = SafetyParams {
        distance: sf.distance,
        gamma: sf.gamma,
        projection: sf.projection,
        radius: sf.radius,
        arena: sf.arena,
        deadlock: validate_deadlock(c, sf, file.dt)?,
        lag_margin: lag_margin(c, file, sf)?,
    };
    if sf.radius <= params.barrier_radius() {
        return Err(c.fail_with(
            "safety.radius",
            &["safety.distance", "safety.projection"],
            format!(
                "{} m must exceed the barrier's radius, distance + 2 × projection = {} m, or no robot is ever seen in time",
                num(sf.radius),
                num(params.barrier_radius())
            ),
        ));
    }
    if let Some(a) = sf.arena {
        c.bounded("safety.arena", &a, MAX_DISTANCE_M, "m")?;
        if a[0] >= a[1] || a[2] >= a[3] {
            return Err(c.fail(
                "safety.arena",
                format!("[x_min, x_max, y_min, y_max] = {a:?}: each min must be below its max"),
            ));
        }
        if let Some(f) =
            followers.iter().find(|f| !(a[0]..=a[1]).contains(&f.pose.x) || !(a[2]..=a[3]).contains(&f.pose.y))
        {
            return Err(c.fail_with(
                "safety.arena",
                &["followers"],
                format!(
                    "follower {} starts at ({}, {}), outside the arena x ∈ [{}, {}], y ∈ [{}, {}]",
                    f.id,
                    num(f.pose.x),
                    num(f.pose.y),
                    num(a[0]),
                    num(a[1]),
                    num(a[2]),
                    num(a[3])
                ),
            ));
        }
    }
    if sf.filter {
        check_filter_start(c, followers, &params)?;
    }
    Ok(Guard { limits, safety: sf.filter.then_some(params) })
}

/// Eq. G3d (docs/model.md §16), with `safety.lag_margin = true`: what the
/// barrier's radius adds for a base that takes a velocity command in time,
/// `robot.lag` × the point's top speed √(v_max² + (w_max l)²). It needs a
/// velocity robot (a torque robot has no lag) and both limits (without
/// them the margin has no bound): refused in one line otherwise.
fn lag_margin(c: &Check<'_>, file: &ScenarioFile, sf: &SafetyFile) -> Result<f64, ScenarioError> {
    let r = &file.robot;
    if !sf.lag_margin {
        return Ok(0.0);
    }
    if r.model != RobotModel::Velocity {
        return Err(c.fail(
            "safety.lag_margin",
            "is for a velocity-commanded robot's lag (robot.model = \"velocity\"); a torque robot has none",
        ));
    }
    let lag_s = r.lag.unwrap_or(DEFAULT_LAG_S);
    let (Some(v), Some(w)) = (r.v_max, r.w_max) else {
        return Err(c.fail(
            "safety.lag_margin",
            format!(
                "robot.lag ({} s) × the point's top speed needs robot.v_max and robot.w_max (without them the \
                 margin has no bound)",
                num(lag_s)
            ),
        ));
    };
    Ok(lag_s * v.hypot(w * sf.projection))
}

/// The filter's own geometry at step 0 (docs/model.md §16): every two
/// robots' points l ahead of the axle at least the barrier's radius r apart,
/// and every point at least r / 2 inside each wall: the set the filter
/// keeps the robots in (its guarantee holds from inside it only). The
/// offending pair or wall is named.
fn check_filter_start(c: &Check<'_>, followers: &[FollowerSpec], s: &SafetyParams) -> Result<(), ScenarioError> {
    let r = s.barrier_radius();
    let points: Vec<(u32, [f64; 2])> = followers.iter().map(|f| (f.id, s.point(&f.pose))).collect();
    for (i, (a, p)) in points.iter().enumerate() {
        for (b, q) in &points[i + 1..] {
            let d = (p[0] - q[0]).hypot(p[1] - q[1]);
            if d < r {
                return Err(c.fail_with(
                    "safety.distance",
                    &["followers", "safety.projection"],
                    format!(
                        "followers {a} and {b} start with their filtered points ({} m ahead of the axle) {} m \
                         apart, closer than the barrier's radius, distance + 2 × projection = {} m: they would \
                         start outside the set the filter keeps them in",
                        num(s.projection),
                        num((d * 1e6).round() / 1e6),
                        num(r)
                    ),
                ));
            }
        }
    }
    let Some([x0, x1, y0, y1]) = s.arena else { return Ok(()) };
    for (id, p) in &points {
        let walls = [(p[0] - x0, "x", x0), (x1 - p[0], "x", x1), (p[1] - y0, "y", y0), (y1 - p[1], "y", y1)];
        if let Some((gap, axis, at)) = walls.into_iter().find(|(gap, _, _)| *gap < r / 2.0) {
            return Err(c.fail_with(
                "safety.arena",
                &["followers", "safety.distance", "safety.projection"],
                format!(
                    "follower {id}'s filtered point starts {} m from the wall {axis} = {}, within the filter's \
                     margin r / 2 = {} m: it would start outside the set the filter keeps it in",
                    num((gap * 1e6).round() / 1e6),
                    num(at),
                    num(r / 2.0)
                ),
            ));
        }
    }
    Ok(())
}

/// `[safety] deadlock_after`, `sidestep`, `sidestep_angle` (eq. G6) in
/// steps: none with `deadlock_after = 0`.
fn validate_deadlock(c: &Check<'_>, sf: &SafetyFile, dt: f64) -> Result<Option<DeadlockRule>, ScenarioError> {
    c.non_negative("safety.deadlock_after", &[sf.deadlock_after])?;
    c.bounded("safety.deadlock_after", &[sf.deadlock_after], 1e6, "s")?;
    c.positive("safety.sidestep", &[sf.sidestep])?;
    c.bounded("safety.sidestep", &[sf.sidestep], 1e6, "s")?;
    let angle = sf.sidestep_angle;
    if !(angle > 0.0 && angle < std::f64::consts::PI) {
        return Err(
            c.fail("safety.sidestep_angle", format!("{} rad must be in (0, π): a turn to the right", num(angle)))
        );
    }
    if sf.deadlock_after == 0.0 {
        return Ok(None);
    }
    let steps = |s: f64| ((s / dt).round() as u64).max(1);
    Ok(Some(DeadlockRule {
        after_steps: steps(sf.deadlock_after),
        sidestep_steps: steps(sf.sidestep),
        angle_rad: angle,
    }))
}

/// The two followers whose initial positions are closest, and how far apart.
fn closest_pair(followers: &[FollowerSpec]) -> Option<(u32, u32, f64)> {
    let mut best: Option<(u32, u32, f64)> = None;
    for (i, a) in followers.iter().enumerate() {
        for b in &followers[i + 1..] {
            let d = (a.pose.x - b.pose.x).hypot(a.pose.y - b.pose.y);
            if best.is_none_or(|(_, _, e)| d < e) {
                best = Some((a.id, b.id, d));
            }
        }
    }
    best
}

/// `[ros2]`: off, or the domain and who moves the robots.
fn validate_ros2(c: &Check<'_>, file: &ScenarioFile, drive: Drive) -> Result<Option<Ros2Settings>, ScenarioError> {
    let r = &file.ros2;
    let robots = match r.robots.as_str() {
        "simulated" => RobotSource::Simulated,
        "stand-in" => RobotSource::StandIn,
        "external" => RobotSource::External,
        other => return Err(c.fail("ros2.robots", format!("`{other}` is not one of: simulated, stand-in, external"))),
    };
    if r.domain_id > MAX_DOMAIN_ID {
        return Err(
            c.fail("ros2.domain_id", format!("{} is above ROS 2's largest domain id, {MAX_DOMAIN_ID}", r.domain_id))
        );
    }
    c.positive("ros2.odom_timeout", &[r.odom_timeout])?;
    if robots.driven() && drive == Drive::Torque {
        return Err(c.fail_with(
            "ros2.robots",
            &["robot.model"],
            format!(
                "`{}`: a robot driven through ROS 2 takes velocity commands on cmd_vel; set robot.model = \"velocity\"",
                r.robots
            ),
        ));
    }
    if !(r.enabled || robots.driven()) {
        return Ok(None);
    }
    Ok(Some(Ros2Settings { domain_id: r.domain_id, robots, odom_timeout_s: r.odom_timeout }))
}

/// `name`: the run's folder and every key of its traffic.
fn validate_name(c: &Check<'_>, name: String) -> Result<String, ScenarioError> {
    if name.chars().count() > MAX_NAME_CHARS {
        let start: String = name.chars().take(20).collect();
        return Err(c.fail(
            "name",
            format!("`{start}…` is {} characters long, at most {MAX_NAME_CHARS}", name.chars().count()),
        ));
    }
    if name.is_empty() || !name.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '-' || ch == '_') {
        return Err(c.fail("name", format!("`{name}` must be non-empty and use only letters, digits, '-' and '_'")));
    }
    Ok(name)
}

/// `dt` and `duration`: a whole number of steps, at most [`MAX_STEPS`].
fn validate_steps(c: &Check<'_>, file: &ScenarioFile) -> Result<(), ScenarioError> {
    c.positive("dt", &[file.dt])?;
    c.positive("duration", &[file.duration])?;
    let (dt, duration) = (num(file.dt), num(file.duration));
    if file.dt > file.duration {
        return Err(c.fail_with(
            "dt",
            &["duration"],
            format!("a step of {dt} s is longer than the whole run (duration = {duration} s)"),
        ));
    }
    let ratio = file.duration / file.dt;
    if ratio > MAX_STEPS {
        return Err(c.fail_with(
            "duration",
            &["dt"],
            format!(
                "{duration} s at Δt = {dt} s is {} steps; a run may have at most {} (split it, or raise dt)",
                num(ratio.round()),
                num(MAX_STEPS)
            ),
        ));
    }
    if (ratio - ratio.round()).abs() > 1e-6 * ratio.max(1.0) {
        return Err(c.fail_with(
            "duration",
            &["dt"],
            format!("{duration} s is not a whole number of steps of {dt} s (T/Δt = {ratio})"),
        ));
    }
    Ok(())
}

/// `[leader]`: the trajectory and the leader's initial pose.
fn validate_leader(c: &Check<'_>, l: &LeaderFile) -> Result<(Profile, Pose), ScenarioError> {
    c.finite("leader.pose", &l.pose)?;
    c.non_negative("leader.ramp", &[l.ramp])?;
    c.finite("leader.speed", &[l.speed])?;
    c.finite("leader.radius", &[l.radius])?;
    let trajectory = match l.trajectory.as_str() {
        "paper" => Trajectory::Paper,
        "line" => Trajectory::Line { speed_mps: l.speed },
        "circle" | "figure-eight" if l.radius == 0.0 => return Err(c.fail("leader.radius", "must not be zero")),
        "circle" => Trajectory::Circle { speed_mps: l.speed, radius_m: l.radius },
        "figure-eight" => Trajectory::FigureEight { speed_mps: l.speed, radius_m: l.radius },
        other => {
            return Err(
                c.fail("leader.trajectory", format!("`{other}` is not one of: paper, line, circle, figure-eight"))
            )
        }
    };
    Ok((Profile { trajectory, ramp_s: l.ramp }, Pose::new(l.pose[0], l.pose[1], l.pose[2])))
}

/// The lengths of `followers`, `edges` and `faults`, before any is read.
fn validate_table_sizes(c: &Check<'_>, file: &ScenarioFile) -> Result<(), ScenarioError> {
    if file.followers.is_empty() {
        return Err(c.fail("followers", "at least one follower is needed"));
    }
    if file.followers.len() > c.most_followers {
        return Err(c.fail(
            "followers",
            format!("{} followers; a scenario may have at most {}", file.followers.len(), c.most_followers),
        ));
    }
    if file.edges.len() > MAX_EDGES {
        return Err(c.fail("edges", format!("{} edges; a scenario may have at most {MAX_EDGES}", file.edges.len())));
    }
    if file.faults.len() > MAX_FAULT_ROWS {
        return Err(c.fail(
            "faults",
            format!("{} fault rows; the fault table may have at most {MAX_FAULT_ROWS}", file.faults.len()),
        ));
    }
    Ok(())
}

/// `[[followers]]`, in ascending id (the order of the graph).
fn validate_followers(
    c: &Check<'_>,
    file: &ScenarioFile,
    leader_pose: Pose,
) -> Result<Vec<FollowerSpec>, ScenarioError> {
    let mut order: Vec<usize> = (0..file.followers.len()).collect();
    order.sort_by_key(|&i| file.followers[i].id);
    if let Some(o) = file.robot.odom_origin.as_deref().filter(|o| !matches!(*o, "world" | "start")) {
        return Err(c.fail(
            "robot.odom_origin",
            format!("`{o}` is not one of: world, start (or give a follower its own odom_origin = [x, y, θ])"),
        ));
    }
    let mut followers = Vec::with_capacity(order.len());
    for (pos, &i) in order.iter().enumerate() {
        let f = &file.followers[i];
        let field = |k: &str| format!("followers[{i}].{k}");
        if f.id == 0 {
            return Err(c.fail(&field("id"), "0 is the leader's id; followers are numbered from 1"));
        }
        if pos > 0 && file.followers[order[pos - 1]].id == f.id {
            return Err(c.fail(&field("id"), format!("duplicate follower id {}", f.id)));
        }
        c.bounded(&field("offset"), &f.offset, MAX_DISTANCE_M, "m")?;
        c.bounded(&field("velocity"), &f.velocity, MAX_SPEED, "(m/s, rad/s)")?;
        let pose = match (f.pose, f.body_error) {
            (Some(p), None) => {
                c.bounded(&field("pose"), &p, MAX_DISTANCE_M, "(m, rad)")?;
                Pose::new(p[0], p[1], p[2])
            }
            (None, Some(e)) => {
                c.bounded(&field("body_error"), &e, MAX_DISTANCE_M, "(m, rad)")?;
                pose_from_body_error(leader_pose, f.offset, e)
            }
            (Some(_), Some(_)) => return Err(c.fail(&field("pose"), "give either `pose` or `body_error`, not both")),
            (None, None) => return Err(c.fail(&field("pose"), "missing: give `pose` or `body_error`")),
        };
        let odom_origin = match (f.odom_origin, file.robot.odom_origin.as_deref()) {
            (Some(o), _) => {
                c.bounded(&field("odom_origin"), &o, MAX_DISTANCE_M, "(m, rad)")?;
                Some(Pose::new(o[0], o[1], o[2]))
            }
            (None, Some("start")) => Some(pose),
            (None, _) => None,
        };
        followers.push(FollowerSpec {
            id: f.id,
            offset: f.offset,
            pose,
            velocity: Velocity::new(f.velocity[0], f.velocity[1]),
            hears_leader: f.leader_link,
            odom_origin,
        });
    }
    Ok(followers)
}

/// `edges` and the followers' `leader_link`: a graph the leader reaches
/// whole (Lemma 1).
fn validate_graph(c: &Check<'_>, file: &ScenarioFile, followers: &[FollowerSpec]) -> Result<Graph, ScenarioError> {
    let ids: Vec<u32> = followers.iter().map(|f| f.id).collect();
    let mut edges = Vec::with_capacity(file.edges.len());
    let mut seen = std::collections::HashSet::with_capacity(file.edges.len());
    for (e, &[a, b]) in file.edges.iter().enumerate() {
        let field = format!("edges[{e}]");
        let index = |id: u32| {
            ids.binary_search(&id).map_err(|_| c.fail(&field, format!("edge {a}–{b} names unknown follower {id}")))
        };
        let (ia, ib) = (index(a)?, index(b)?);
        if ia == ib {
            return Err(c.fail(&field, format!("self-loop {a}–{b}: a follower is not its own neighbour")));
        }
        if !seen.insert((ia.min(ib), ia.max(ib))) {
            return Err(c.fail(&field, format!("duplicate edge {a}–{b} (edges are undirected)")));
        }
        edges.push((ia, ib));
    }
    if !followers.iter().any(|f| f.hears_leader) {
        let message = "no follower hears the leader: give at least one follower `leader_link = true` (Lemma 1 needs the leader to reach every follower)";
        return Err(match c.assignment_of("followers") {
            Some(assignment) => ScenarioError::Override { assignment: assignment.to_string(), message: message.into() },
            None => c.fail("followers", message),
        });
    }
    let graph = Graph::new(ids, &edges, followers.iter().map(|f| f.hears_leader).collect());
    let unreachable = graph.unreachable();
    if !unreachable.is_empty() {
        return Err(match c.assignment_of("edges").or_else(|| c.assignment_of("followers")) {
            Some(assignment) => ScenarioError::Override {
                assignment: assignment.to_string(),
                message: ScenarioError::GraphNotConnected { file: String::new(), unreachable }.to_string(),
            },
            None => ScenarioError::GraphNotConnected { file: c.label.to_string(), unreachable },
        });
    }
    Ok(graph)
}

/// `[estimator]`, `[backstepping]`, `[sliding_mode]`, `[robot]`,
/// `[disturbance]`, `[covariance]`, `[asif]`: the gains and models.
fn validate_gains(c: &Check<'_>, file: &ScenarioFile) -> Result<(), ScenarioError> {
    let est = &file.estimator;
    c.positive("estimator.k", &est.k)?;
    c.non_negative("estimator.ka", &est.ka)?;
    c.non_negative("estimator.kb", &est.kb)?;
    let bs = &file.backstepping;
    // The paper's C₁, C₂, C₃ are positive (a negative C₁ ran to a 130 m
    // formation error with exit status 0).
    c.positive("backstepping.c1", &[bs.c1])?;
    c.positive("backstepping.c2", &[bs.c2])?;
    c.positive("backstepping.c3", &[bs.c3])?;
    c.shunting("backstepping.shunting", &bs.shunting)?;
    let sm = &file.sliding_mode;
    c.non_negative("sliding_mode.ca", &[sm.ca])?;
    c.non_negative("sliding_mode.cb", &[sm.cb])?;
    c.shunting("sliding_mode.shunting_v", &sm.shunting_v)?;
    c.shunting("sliding_mode.shunting_w", &sm.shunting_w)?;
    c.non_negative("sliding_mode.k1", &[sm.k1])?;
    c.non_negative("sliding_mode.k2", &[sm.k2])?;
    let r = &file.robot;
    c.positive("robot.mass", &[r.mass])?;
    c.positive("robot.inertia", &[r.inertia])?;
    c.positive("robot.wheel_radius", &[r.wheel_radius])?;
    c.positive("robot.half_axle", &[r.half_axle])?;
    c.finite("disturbance.dv", &[file.disturbance.dv])?;
    c.finite("disturbance.dw", &[file.disturbance.dw])?;
    c.non_negative("covariance.q", &file.covariance.q)?;
    c.positive("covariance.r", &file.covariance.r)?;
    c.positive("asif.rho_max", &file.asif.rho_max)
}

/// `[fault]`: the change of mass and inertia at one time, if any.
fn validate_fault(c: &Check<'_>, file: &ScenarioFile) -> Result<Option<Fault>, ScenarioError> {
    // Checked with or without a time: a -1 was accepted until one was set.
    c.positive("fault.mass_factor", &[file.fault.mass_factor])?;
    c.positive("fault.inertia_factor", &[file.fault.inertia_factor])?;
    let Some(time_s) = file.fault.time else { return Ok(None) };
    c.non_negative("fault.time", &[time_s])?;
    if time_s > file.duration {
        return Err(c.fail_with(
            "fault.time",
            &["duration"],
            format!("must lie within [0, duration] = [0, {}] s, got {time_s}", file.duration),
        ));
    }
    c.positive("fault.mass_factor", &[file.fault.mass_factor])?;
    c.positive("fault.inertia_factor", &[file.fault.inertia_factor])?;
    Ok(Some(Fault { time_s, mass_factor: file.fault.mass_factor, inertia_factor: file.fault.inertia_factor }))
}

/// `[robot] model` and `lag`: how the robot is driven (docs/model.md §15).
/// A lag belongs to a velocity-commanded robot only, and such a robot runs
/// no filter for a `[fault]` to change.
fn validate_drive(c: &Check<'_>, file: &ScenarioFile) -> Result<Drive, ScenarioError> {
    let r = &file.robot;
    match (r.model, r.lag) {
        (RobotModel::Torque, None) => Ok(Drive::Torque),
        (RobotModel::Torque, Some(_)) => Err(c.fail_with(
            "robot.lag",
            &["robot.model"],
            "only a velocity-commanded robot has a lag: set robot.model = \"velocity\" or remove lag",
        )),
        (RobotModel::Velocity, lag) => {
            let lag_s = lag.unwrap_or(DEFAULT_LAG_S);
            c.positive("robot.lag", &[lag_s])?;
            if lag_s > MAX_LAG_S {
                return Err(c.fail(
                    "robot.lag",
                    format!(
                        "must be at most {MAX_LAG_S} s (the time constant of the robot's velocity loop, in seconds), \
                         got {}",
                        num(lag_s)
                    ),
                ));
            }
            if file.fault.time.is_some() {
                return Err(c.fail_with(
                    "fault.time",
                    &["robot.model"],
                    "the fault changes the velocity filter's model, and a velocity-commanded robot \
                     (robot.model = \"velocity\") runs no filter",
                ));
            }
            Ok(Drive::Velocity { lag_s })
        }
    }
}

/// `[network]`: the networked run's settings and the rejoin rule.
fn validate_network(c: &Check<'_>, file: &ScenarioFile) -> Result<(NetworkSettings, RejoinRule), ScenarioError> {
    let n = &file.network;
    let dt = num(file.dt);
    c.positive("network.silence_timeout", &[n.silence_timeout])?;
    let policy = match n.rejoin.as_str() {
        "consensus" => RejoinPolicy::Consensus,
        "adopt" => RejoinPolicy::Adopt,
        other => return Err(c.fail("network.rejoin", format!("`{other}` is not one of: consensus, adopt"))),
    };
    c.positive("network.rejoin_after", &[n.rejoin_after])?;
    if n.rejoin_after / file.dt > MAX_STEPS {
        return Err(c.fail_with(
            "network.rejoin_after",
            &["dt"],
            format!(
                "{} s is {} steps of {dt} s, longer than any run may be ({} steps): a rejoining follower would never rejoin",
                num(n.rejoin_after),
                num((n.rejoin_after / file.dt).round()),
                num(MAX_STEPS)
            ),
        ));
    }
    let after_steps = (n.rejoin_after / file.dt).round() as u64;
    if after_steps == 0 {
        return Err(c.fail_with(
            "network.rejoin_after",
            &["dt"],
            format!(
                "{} s is less than half a step of {dt} s (give it a step or more: --set network.rejoin_after={dt})",
                num(n.rejoin_after)
            ),
        ));
    }
    c.positive("network.time_scale", &[n.time_scale])?;
    if n.telemetry_batch == 0 {
        return Err(c.fail("network.telemetry_batch", "must be at least 1"));
    }
    if n.delay_steps > MAX_DELAY_STEPS {
        return Err(c.fail("network.delay_steps", format!("{} is more than {MAX_DELAY_STEPS}", n.delay_steps)));
    }
    if let Some(g) = n.gone_after {
        c.positive("network.gone_after", &[g])?;
    }
    let settings = NetworkSettings {
        silence_timeout_s: n.silence_timeout,
        time_scale: n.time_scale,
        telemetry_batch: n.telemetry_batch,
        hearing_record: n.hearing_record,
        delay_steps: n.delay_steps,
        gone_after_s: n.gone_after,
    };
    Ok((settings, RejoinRule { policy, after_steps }))
}

/// The controllers, filter and model every follower shares, from a file
/// already validated.
fn control_params(
    file: &ScenarioFile,
    model: RobotParams,
    fault: Option<Fault>,
    rejoin: RejoinRule,
    drive: Drive,
) -> ControlParams {
    let (est, bs, sm) = (&file.estimator, &file.backstepping, &file.sliding_mode);
    ControlParams {
        estimator: EstimatorGains { k: est.k, ka: est.ka, kb: est.kb },
        kinematic: file.kinematic,
        kinematic_gains: KinematicGains { c1: bs.c1, c2: bs.c2, c3: bs.c3, shunting: bs.shunting },
        dynamic: file.dynamic,
        dynamic_gains: DynamicGains {
            ca: sm.ca,
            cb: sm.cb,
            shunting_v: sm.shunting_v,
            shunting_w: sm.shunting_w,
            k1: sm.k1,
            k2: sm.k2,
        },
        filter: FilterParams {
            kind: file.filter,
            q: file.covariance.q,
            r: file.covariance.r,
            rho_max: file.asif.rho_max,
        },
        model,
        fault,
        rejoin,
        dt_s: file.dt,
        drive,
        guard: Guard::default(),
    }
}

/// docs/model.md §14's fault table: each row one link of the graph or one follower,
/// a window inside the run, a probability.
fn validate_faults(
    c: &Check<'_>,
    file: &ScenarioFile,
    followers: &[FollowerSpec],
    graph: &Graph,
) -> Result<Vec<LinkFault>, ScenarioError> {
    let ids = || followers.iter().map(|f| f.id.to_string()).collect::<Vec<_>>().join(", ");
    let mut out = Vec::with_capacity(file.faults.len());
    for (i, f) in file.faults.iter().enumerate() {
        let field = |k: &str| format!("faults[{i}].{k}");
        let target = match (f.node, f.link) {
            (Some(_), Some(_)) => return Err(c.fail(&field("node"), "give either `node` or `link`, not both")),
            (None, None) => {
                return Err(c.fail(
                    &format!("faults[{i}]"),
                    "missing: give `node = ID` (every link of a follower) or `link = [A, B]` (0 = the leader)",
                ))
            }
            // The leader silent on every link: a handover's gap, or, without
            // `to`, a leader gone for good (docs/model.md §14).
            (Some(0), None) => FaultTarget::Node(0),
            (Some(n), None) => {
                if graph.index_of(n).is_none() {
                    return Err(c.fail(&field("node"), format!("follower {n} is not in the scenario (ids: {})", ids())));
                }
                FaultTarget::Node(n)
            }
            (None, Some([a, b])) => {
                for id in [a, b] {
                    if id != 0 && graph.index_of(id).is_none() {
                        return Err(c.fail(
                            &field("link"),
                            format!("node {id} is not in the scenario (0 = the leader; followers: {})", ids()),
                        ));
                    }
                }
                if a == b {
                    return Err(c.fail(&field("link"), format!("{a}–{b} is not a link: both ends are node {a}")));
                }
                if !is_link(graph, a, b) {
                    return Err(c.fail(&field("link"), not_a_link(graph, a, b)));
                }
                FaultTarget::Link(a, b)
            }
        };
        c.finite(&field("from"), &[f.from])?;
        // No `to`: the rest of the run, its last step (t = T) included.
        let to = f.to.unwrap_or(file.duration + file.dt);
        c.finite(&field("to"), &[to])?;
        if f.from < 0.0 {
            return Err(c.fail(&field("from"), format!("{} s is before the run starts (t = 0)", f.from)));
        }
        if f.from >= to {
            return Err(
                c.fail(&field("to"), format!("the window [{}, {}) s is empty: `to` must be after `from`", f.from, to))
            );
        }
        if f.join {
            check_join(c, &field, target, f)?;
        }
        let leave = f.leave || f.died;
        if leave {
            check_leave(c, &field, target, f)?;
        }
        let fault = LinkFault { target, from_s: f.from, to_s: to, loss: f.loss, join: f.join, leave, died: f.died };
        let (from_k, to_k) = fault.steps(file.dt);
        if from_k >= to_k {
            return Err(c.fail(
                &field("to"),
                format!(
                    "the window [{}, {}) s covers no step of Δt = {} s (both ends round to step {from_k}): widen it",
                    f.from,
                    to,
                    num(file.dt)
                ),
            ));
        }
        // The last step is at t = T: a window that covers it ends one step
        // later (the model of a follower that leaves for good).
        if to_k > formation_agent::math::step_at(file.duration, file.dt) + 1 {
            return Err(c.fail(
                &field("to"),
                format!(
                    "{} s is after the end of the run (T = {} s); leave `to` out for the rest of the run, its \
                     last step (t = T) included",
                    to, file.duration
                ),
            ));
        }
        c.finite(&field("loss"), &[f.loss])?;
        if !(0.0..=1.0).contains(&f.loss) {
            return Err(c.fail(&field("loss"), format!("{} is not a probability in [0, 1]", f.loss)));
        }
        out.push(fault);
    }
    Ok(out)
}

/// A join row (`join = true`): a follower, absent from the run's start
/// (`from = 0`, the link down) until `to`, which must be given.
fn check_join(
    c: &Check<'_>,
    field: &dyn Fn(&str) -> String,
    target: FaultTarget,
    f: &crate::file::LinkFaultFile,
) -> Result<(), ScenarioError> {
    let why = match target {
        FaultTarget::Node(0) => Some(("node", "the leader does not join: give a follower's id".to_string())),
        FaultTarget::Link(..) => Some(("link", "a join is a follower's: give `node = ID`, not `link`".to_string())),
        FaultTarget::Node(_) if f.from != 0.0 => {
            Some(("from", format!("a follower that joins is absent from the start: from = 0, not {}", f.from)))
        }
        FaultTarget::Node(_) if f.to.is_none() => Some(("to", "a join needs `to`, the time it joins (s)".to_string())),
        FaultTarget::Node(_) if f.loss != 1.0 => {
            Some(("loss", format!("a follower not yet started sends nothing: loss = 1, not {}", f.loss)))
        }
        FaultTarget::Node(_) => None,
    };
    refuse_row(c, field, why)
}

/// A fault row's one line, naming its key, or Ok.
fn refuse_row(c: &Check<'_>, field: &dyn Fn(&str) -> String, why: Option<(&str, String)>) -> Result<(), ScenarioError> {
    match why {
        Some((key, why)) => Err(c.fail(&field(key), why)),
        None => Ok(()),
    }
}

/// A leave row (`leave = true`): a follower, cut off from `from` to the
/// end of the run (no `to`), not also a join.
fn check_leave(
    c: &Check<'_>,
    field: &dyn Fn(&str) -> String,
    target: FaultTarget,
    f: &crate::file::LinkFaultFile,
) -> Result<(), ScenarioError> {
    let why = match target {
        FaultTarget::Node(0) => {
            Some(("node", "the leader does not leave: a handover is its own row (node = 0)".to_string()))
        }
        FaultTarget::Link(..) => Some(("link", "a leave is a follower's: give `node = ID`, not `link`".to_string())),
        FaultTarget::Node(_) if f.join => Some(("join", "a row is a join or a leave, not both".to_string())),
        FaultTarget::Node(_) if f.died && f.from <= 0.0 => {
            Some(("from", "a follower killed at the start is absent: give `from` after 0 (s)".to_string()))
        }
        FaultTarget::Node(_) if f.to.is_some() => {
            Some(("to", "a follower that leaves does not come back: leave `to` out (the rest of the run)".to_string()))
        }
        FaultTarget::Node(_) if f.loss != 1.0 => {
            Some(("loss", format!("a follower that left sends nothing: loss = 1, not {}", f.loss)))
        }
        FaultTarget::Node(_) => None,
    };
    refuse_row(c, field, why)
}

/// Why a–b is not a fault table's link: whom its follower end talks to.
fn not_a_link(graph: &Graph, a: u32, b: u32) -> String {
    let end = if a == 0 { b } else { a };
    let links = graph.index_of(end).map(|i| {
        let mut l: Vec<String> = graph.neighbours(i).iter().map(|&j| graph.id(j).to_string()).collect();
        if graph.hears_leader(i) {
            l.insert(0, "0".into());
        }
        l.join(", ")
    });
    format!("{a}–{b} is not a link of the scenario's graph (node {end} talks to: {})", links.unwrap_or_default())
}

/// Whether a and b (0 = the leader) talk to each other in the graph.
fn is_link(graph: &Graph, a: u32, b: u32) -> bool {
    match (a, b) {
        (0, f) | (f, 0) => graph.index_of(f).is_some_and(|i| graph.hears_leader(i)),
        (a, b) => match (graph.index_of(a), graph.index_of(b)) {
            (Some(ia), Some(ib)) => graph.neighbours(ia).contains(&ib),
            _ => false,
        },
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

/// The dotted field (`followers[2].offset`, `edges[1]`) of the innermost
/// value that spans byte `at` of the TOML source.
fn field_at(source: &str, at: usize) -> Option<String> {
    fn path_to(value: &toml::Spanned<toml::de::DeValue<'_>>, at: usize, path: &mut String) -> bool {
        let len = path.len();
        let found = match value.get_ref() {
            toml::de::DeValue::Table(t) => t.iter().any(|(key, v)| {
                path.truncate(len);
                path.push_str(&format!(".{}", key.get_ref()));
                path_to(v, at, path)
            }),
            toml::de::DeValue::Array(a) => a.iter().enumerate().any(|(i, v)| {
                path.truncate(len);
                path.push_str(&format!("[{i}]"));
                path_to(v, at, path)
            }),
            _ => false,
        };
        if !found {
            path.truncate(len);
        }
        found || value.span().contains(&at)
    }
    let document = toml::de::DeTable::parse(source).ok()?;
    let mut path = String::new();
    let root = toml::Spanned::new(document.span(), toml::de::DeValue::Table(document.into_inner()));
    (path_to(&root, at, &mut path) && !path.is_empty()).then(|| path.trim_start_matches('.').to_string())
}

/// The 1-based line of a dotted field (`robot.mass`, `followers[2].offset`,
/// `edges[1]`) in the TOML source, when it can be found by its key.
fn find_line(source: &str, field: &str) -> Option<usize> {
    let target = field.split('[').next().unwrap_or(field);
    let index: Option<usize> = field.split_once('[').and_then(|(_, rest)| rest.split(']').next()?.parse().ok());
    let mut context = String::new();
    let mut array_counts = std::collections::HashMap::<String, usize>::new();
    let mut best = None;
    for (n, raw) in source.lines().enumerate() {
        let line = raw.trim();
        if let Some(h) = line.strip_prefix("[[") {
            let name = h.split("]]").next().unwrap_or("").trim().to_string();
            let count = array_counts.entry(name.clone()).or_insert(0);
            context = format!("{name}[{count}]");
            *count += 1;
            if field == context {
                return Some(n + 1);
            }
            continue;
        }
        if let Some(h) = line.strip_prefix('[') {
            context = h.split(']').next().unwrap_or("").trim().to_string();
            if field == context || field.starts_with(&format!("{context}.")) && best.is_none() {
                best = Some(n + 1);
            }
            continue;
        }
        let Some((key, _)) = line.split_once('=') else { continue };
        let key = key.trim().trim_matches('"');
        let full = if context.is_empty() { key.to_string() } else { format!("{context}.{key}") };
        if full == field || (index.is_some() && full == target) {
            return Some(n + 1);
        }
        if field.starts_with(&format!("{full}.")) {
            best = Some(n + 1);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::file::DEFAULT_CMD_TIMEOUT_S;

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
        let back = formation_agent::kinematic::body_error(&leader, [4.0, -4.0], &p);
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
