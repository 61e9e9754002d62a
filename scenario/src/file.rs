//! The scenario file as written (TOML), before validation.
//!
//! Every value but the followers and edges has a default: docs/model.md §10's value,
//! so a scenario file states only what differs from the paper. Unknown keys
//! are errors.

use serde::{Deserialize, Deserializer, Serialize};

use formation_control::{DynamicKind, FilterKind, KinematicKind, Shunting};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioFile {
    /// Run name; defaults to the file's stem.
    pub name: Option<String>,
    #[serde(default = "d::seed")]
    pub seed: u64,
    /// Step Δt, s.
    #[serde(default = "d::dt")]
    pub dt: f64,
    /// Duration T, s.
    #[serde(default = "d::duration")]
    pub duration: f64,
    /// Process and measurement noise on or off.
    #[serde(default = "d::yes")]
    pub noise: bool,
    #[serde(default = "d::kinematic")]
    pub kinematic: KinematicKind,
    #[serde(default = "d::dynamic")]
    pub dynamic: DynamicKind,
    #[serde(default = "d::filter")]
    pub filter: FilterKind,
    /// `leader` (P_ir(0) = P_r(0), …) or `zero`.
    #[serde(default = "d::estimate_init")]
    pub estimate_init: String,
    /// `lockstep` or `realtime` (networked runs).
    #[serde(default = "d::timing")]
    pub timing: String,
    #[serde(default)]
    pub leader: LeaderFile,
    pub followers: Vec<FollowerFile>,
    /// Undirected follower edges, by follower id.
    #[serde(deserialize_with = "exact::edges")]
    pub edges: Vec<[u32; 2]>,
    #[serde(default)]
    pub estimator: EstimatorFile,
    #[serde(default)]
    pub backstepping: BacksteppingFile,
    #[serde(default)]
    pub sliding_mode: SlidingModeFile,
    #[serde(default)]
    pub robot: RobotFile,
    #[serde(default)]
    pub disturbance: DisturbanceFile,
    #[serde(default)]
    pub covariance: CovarianceFile,
    #[serde(default)]
    pub asif: AsifFile,
    #[serde(default)]
    pub fault: FaultFile,
    #[serde(default)]
    pub network: NetworkFile,
    /// Link faults (docs/model.md §14): outages and loss over windows of run time.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub faults: Vec<LinkFaultFile>,
    /// The formation on ROS 2's wire (rmw_zenoh; docs/ros2.md).
    #[serde(default, skip_serializing_if = "Ros2File::is_off")]
    pub ros2: Ros2File,
    /// Robots kept apart (docs/model.md §16).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub safety: Option<SafetyFile>,
    /// The frame of the offsets and the shape changes (docs/model.md §17).
    #[serde(default, skip_serializing_if = "FormationFile::is_default")]
    pub formation: FormationFile,
}

/// `[formation]`: the frame the followers' offsets are written in, and the
/// shapes the formation takes during the run (docs/model.md §17).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FormationFile {
    /// `world` (the paper's, the default) or `leader`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<String>,
    /// The distance between neighbouring slots of a named shape, m (default:
    /// twice `safety.distance`, or 1 m without `[safety]`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spacing: Option<f64>,
    /// Shape changes, in time order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub shapes: Vec<ShapeFile>,
}

impl FormationFile {
    fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// One `[[formation.shapes]]`: from `at` s on, a named shape or one offset
/// per follower; the robots are assigned to its slots at the least total
/// squared distance (docs/model.md §17).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShapeFile {
    pub at: f64,
    /// `line`, `column`, `wedge`, `diamond` or `circle`; or give `offsets`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shape: Option<String>,
    /// This shape's spacing, m (default: `formation.spacing`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spacing: Option<f64>,
    /// One (Δx, Δy) per follower, m, in `formation.frame`.
    #[serde(default, deserialize_with = "exact::points", skip_serializing_if = "Vec::is_empty")]
    pub offsets: Vec<[f64; 2]>,
}

/// `[ros2]`: the formation's topics on rmw_zenoh's wire, and robots driven
/// through ROS 2 (docs/ros2.md). Off unless `enabled` (or `robots`) says otherwise.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2File {
    /// Publish every robot's odometry, command, leader estimate and transform
    /// (and `/clock` in lock-step) as ROS 2 topics.
    #[serde(default)]
    pub enabled: bool,
    /// ROS_DOMAIN_ID: the first chunk of every ROS 2 key.
    #[serde(default)]
    pub domain_id: u32,
    /// `simulated` (each agent simulates its robot), `stand-in` (a
    /// `formation robot` process per follower, driven through ROS 2) or
    /// `external` (real robots or Gazebo: `/follower_<i>/odom` in,
    /// `/follower_<i>/cmd_vel` out). Anything but `simulated` turns ROS 2 on.
    #[serde(default = "d::robots")]
    pub robots: String,
    /// A driven robot whose odometry is older than this (s) is sent zero velocity.
    #[serde(default = "d::odom_timeout")]
    pub odom_timeout: f64,
    /// The `frame_id` a driven robot's odometry must carry; `{id}` is the
    /// follower's id (default `follower_{id}/odom`; a bare driver's `odom`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub odom_frame: Option<String>,
}

impl Default for Ros2File {
    fn default() -> Self {
        Self { enabled: false, domain_id: 0, robots: d::robots(), odom_timeout: d::odom_timeout(), odom_frame: None }
    }
}

impl Ros2File {
    fn is_off(&self) -> bool {
        *self == Self::default()
    }
}

/// One row of docs/model.md §14's fault table: one link (both directions; 0 is the
/// leader) or every link of one follower, over [from, to) s of run time,
/// each message lost with probability `loss`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LinkFaultFile {
    /// Every link of this node: a follower, or 0, the leader (silent on
    /// every link: a handover's gap, or without `to` a leader gone).
    pub node: Option<u32>,
    /// One link, by node ids (0 = the leader).
    #[serde(default, deserialize_with = "exact::option")]
    pub link: Option<[u32; 2]>,
    /// Start, s of run time (inclusive).
    pub from: f64,
    /// End, s of run time (exclusive); left out: to the end of the run,
    /// its last step included (a follower absent from the start, or one
    /// that leaves for good: docs/model.md §14).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub to: Option<f64>,
    /// Probability that a message is lost (1: the link is down).
    #[serde(default = "d::loss")]
    pub loss: f64,
    /// A follower that joins late (`node = ID, from = 0, to = T_J`): its
    /// process starts at `to`, taking its estimate from the first source it
    /// hears, as a new process does, whatever `network.rejoin` says
    /// (docs/model.md §14).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub join: bool,
    /// A follower that leaves the run for good at `from` (`node = ID`, no
    /// `to`): its links are cut from then on and its robot stops where it
    /// is, an obstacle there for the others' safety filters (docs/model.md
    /// §14, §16). Without it, such a row is a follower cut off but running.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub leave: bool,
    /// A follower whose process is killed (SIGKILL, a crash) at `from`
    /// (`node = ID`, no `to`): a leave without the last word. As a leave,
    /// no estimate of step k = ⌈from/Δt⌉ or later comes from it; unlike
    /// one, no last pose does: its robot stands at the last pose it sent,
    /// of step k − 2 (docs/model.md §14). `leave` may be left out.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub died: bool,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LeaderFile {
    /// Where the leader's motion comes from (docs/model.md §18):
    /// `trajectory` (the default), `cmd_vel`, `path`, `robot` or `recorded`.
    #[serde(default = "d::source", skip_serializing_if = "d::is_trajectory")]
    pub source: String,
    /// `recorded`: a run folder (its `leader.csv`) or such a CSV; a relative
    /// path is the working directory's, on every host that loads the scenario.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recorded: Option<String>,
    /// `cmd_vel`, `robot`: the leader stops once its input has been silent
    /// this long, s (default 0.5).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub timeout: Option<f64>,
    /// `paper`, `line`, `circle`, `figure-eight` or `waypoints`.
    #[serde(default = "d::trajectory")]
    pub trajectory: String,
    /// P_r(0) = (x, y, θ).
    #[serde(default = "d::leader_pose", deserialize_with = "exact::array")]
    pub pose: [f64; 3],
    /// Start-up ramp time constant, s (0: none).
    #[serde(default = "d::ramp")]
    pub ramp: f64,
    /// Speed of line, circle and figure eight, m/s.
    #[serde(default = "d::speed")]
    pub speed: f64,
    /// Radius of circle and figure eight, m.
    #[serde(default = "d::radius")]
    pub radius: f64,
    /// `waypoints`: the route's points (x, y), m, driven in order at `speed`.
    #[serde(default, deserialize_with = "exact::points", skip_serializing_if = "Vec::is_empty")]
    pub waypoints: Vec<[f64; 2]>,
    /// `waypoints` and `cmd_vel`: the leader's greatest turn rate, rad/s (default 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub turn_rate: Option<f64>,
    /// `waypoints`: k_θ, the turn rate per radian of bearing, 1/s (default 2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub turn_gain: Option<f64>,
    /// `waypoints`: a point is passed within this distance, m (default 0.1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reach: Option<f64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FollowerFile {
    pub id: u32,
    /// (Δx, Δy), m.
    #[serde(deserialize_with = "exact::array")]
    pub offset: [f64; 2],
    /// Initial pose (x, y, θ); give this or `body_error`.
    #[serde(default, deserialize_with = "exact::option")]
    pub pose: Option<[f64; 3]>,
    /// Initial body-frame error (x̂, ŷ, θ̂) against the leader's initial pose
    /// plus the offset; give this or `pose`.
    #[serde(default, deserialize_with = "exact::option")]
    pub body_error: Option<[f64; 3]>,
    /// Initial velocity (v, ω).
    #[serde(default, deserialize_with = "exact::array")]
    pub velocity: [f64; 2],
    /// a_i0.
    #[serde(default)]
    pub leader_link: bool,
    /// Where this robot's odometry frame sits in the world (x, y, θ): its
    /// odometry (0, 0, 0) is this pose (docs/ros2.md). Overrides
    /// `robot.odom_origin`.
    #[serde(default, deserialize_with = "exact::option", skip_serializing_if = "Option::is_none")]
    pub odom_origin: Option<[f64; 3]>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EstimatorFile {
    #[serde(default = "d::k", deserialize_with = "exact::array")]
    pub k: [f64; 3],
    #[serde(default = "d::ka", deserialize_with = "exact::array")]
    pub ka: [f64; 2],
    #[serde(default = "d::kb", deserialize_with = "exact::array")]
    pub kb: [f64; 2],
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BacksteppingFile {
    #[serde(default = "d::c1")]
    pub c1: f64,
    #[serde(default = "d::c2")]
    pub c2: f64,
    #[serde(default = "d::c3")]
    pub c3: f64,
    #[serde(default = "d::kin_shunting")]
    pub shunting: Shunting,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SlidingModeFile {
    #[serde(default = "d::c_ab")]
    pub ca: f64,
    #[serde(default = "d::c_ab")]
    pub cb: f64,
    #[serde(default = "d::dyn_shunting")]
    pub shunting_v: Shunting,
    #[serde(default = "d::dyn_shunting")]
    pub shunting_w: Shunting,
    /// Super-twisting k_1, k_2.
    #[serde(default = "d::st_k")]
    pub k1: f64,
    #[serde(default = "d::st_k")]
    pub k2: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotFile {
    /// `torque` (the paper's robot) or `velocity` (a velocity-commanded
    /// base, docs/model.md §15). Left out when written if `torque`, so a file
    /// written before the key existed reads back the same.
    #[serde(default, skip_serializing_if = "RobotModel::is_torque")]
    pub model: RobotModel,
    /// With `model = "velocity"`: T, the time constant of the robot's own
    /// velocity loop, s (default [`DEFAULT_LAG_S`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lag: Option<f64>,
    #[serde(default = "d::mass")]
    pub mass: f64,
    #[serde(default = "d::inertia")]
    pub inertia: f64,
    #[serde(default = "d::wheel_radius")]
    pub wheel_radius: f64,
    #[serde(default = "d::half_axle")]
    pub half_axle: f64,
    /// The base's top speed, m/s: no command beyond it (docs/model.md §16).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub v_max: Option<f64>,
    /// The base's top turn rate, rad/s (with `v_max`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub w_max: Option<f64>,
    /// A `formation robot` stand-in stops when no command came for this
    /// long, s (default [`DEFAULT_CMD_TIMEOUT_S`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cmd_timeout: Option<f64>,
    /// Where a driven robot's odometry starts: `world` (default: it reports
    /// its pose in the scenario's world frame) or `start` (it reports
    /// (0, 0, 0) where it was switched on, at its scenario pose).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub odom_origin: Option<String>,
}

/// `[robot] cmd_timeout` when none is given, s: a driver's usual command time-out.
/// `leader.timeout`'s default, s: a live leader's input silent this long stops it.
pub const DEFAULT_LEADER_TIMEOUT_S: f64 = 0.5;
pub const DEFAULT_CMD_TIMEOUT_S: f64 = 0.5;

/// `[safety]`: the closest two robots may come, and the filter that keeps
/// them apart (docs/model.md §16). Absent: no safety figures, no filter.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SafetyFile {
    /// The closest two robots' centres may come, m: a run that comes closer is degraded.
    pub distance: f64,
    /// The barrier-certificate filter on (`true`) or only the figures (`false`).
    #[serde(default = "d::yes")]
    pub filter: bool,
    /// γ of the barrier certificates.
    #[serde(default = "d::gamma")]
    pub gamma: f64,
    /// How far ahead of the axle the filtered point lies, m.
    #[serde(default = "d::projection")]
    pub projection: f64,
    /// Other robots farther than this are left out of a robot's filter, m.
    #[serde(default = "d::safety_radius")]
    pub radius: f64,
    /// [x_min, x_max, y_min, y_max], m: the robots stay inside.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arena: Option<[f64; 4]>,
    /// Held by the filter short of its slot this long, s, a robot is in a
    /// deadlock and sidesteps to the right (0: never).
    #[serde(default = "d::deadlock_after")]
    pub deadlock_after: f64,
    /// How long a sidestep lasts, s.
    #[serde(default = "d::sidestep")]
    pub sidestep: f64,
    /// A sidestep's direction: the direction to the robots near turned
    /// right by this much, rad (π/2: sideways).
    #[serde(default = "d::sidestep_angle")]
    pub sidestep_angle: f64,
    /// The barrier's radius adds `robot.lag` × the point's top speed (eq.
    /// G3d): for a velocity-commanded base slow to take its commands.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub lag_margin: bool,
}

/// How the robot takes its commands (`[robot] model`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RobotModel {
    /// Wheel torques (eq. 4): the paper's robot.
    #[default]
    Torque,
    /// Velocity commands (v_c, ω_c) through a first-order lag (docs/model.md §15).
    Velocity,
}

impl RobotModel {
    pub fn is_torque(&self) -> bool {
        *self == RobotModel::Torque
    }
}

/// `[robot] lag` when `model = "velocity"` gives none, s (docs/model.md §15, decided).
pub const DEFAULT_LAG_S: f64 = 0.1;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DisturbanceFile {
    /// D_v, N.
    #[serde(default = "d::dv")]
    pub dv: f64,
    /// D_ω, N m.
    #[serde(default = "d::dw")]
    pub dw: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CovarianceFile {
    #[serde(default = "d::cov", deserialize_with = "exact::array")]
    pub q: [f64; 2],
    #[serde(default = "d::cov", deserialize_with = "exact::array")]
    pub r: [f64; 2],
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AsifFile {
    #[serde(default = "d::rho", deserialize_with = "exact::array")]
    pub rho_max: [f64; 2],
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaultFile {
    /// t_fault, s; absent: no fault.
    pub time: Option<f64>,
    #[serde(default = "d::mass_factor")]
    pub mass_factor: f64,
    #[serde(default = "d::inertia_factor")]
    pub inertia_factor: f64,
}

/// Settings of networked runs (ignored by the in-process simulator).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetworkFile {
    /// Real-time mode: a neighbour silent this long (s, run time) is left out
    /// of the estimator's sums until it speaks again.
    #[serde(default = "d::silence_timeout")]
    pub silence_timeout: f64,
    /// Real-time mode: run time per wall-clock second (1: real time).
    #[serde(default = "d::time_scale")]
    pub time_scale: f64,
    /// Steps per telemetry message to the monitor; every step is recorded (batches keep
    /// the message rate low).
    #[serde(default = "d::telemetry_batch")]
    pub telemetry_batch: u32,
    /// Followers record which step's message they used of each source at
    /// each step (`hearing.bin`, for `formation replay`).
    #[serde(default = "d::hearing_record")]
    pub hearing_record: bool,
    /// After isolation: `consensus` (the paper's law) or `adopt` (docs/model.md §14).
    #[serde(default = "d::rejoin")]
    pub rejoin: String,
    /// Seconds without any source before hearing one again is a rejoin.
    #[serde(default = "d::rejoin_after")]
    pub rejoin_after: f64,
    /// Communication delay in steps (docs/model.md §14's addition): at step k a
    /// follower uses its sources' messages of step k − d. 0: the paper's
    /// model. A real-time run with 1 uses only messages that had a whole
    /// period to arrive, and `formation sim` with 1 predicts it.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub delay_steps: u64,
    /// A follower whose telemetry has been silent this long (s, wall clock)
    /// is taken for gone: the monitor records it as having left the run
    /// where its record ends, and no longer waits for it (docs/model.md
    /// §14). Not given: it is waited for until the monitor's idle timeout.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gone_after: Option<f64>,
}

fn is_zero(x: &u64) -> bool {
    *x == 0
}

/// Fixed-length arrays read exactly. toml fills a `[T; N]` from the first N
/// elements of a longer array and drops the rest without a word, so every
/// fixed-length field goes through here: a length mismatch is an error
/// (`expected 2 numbers, got 3`) at the array's span.
pub(crate) mod exact {
    use serde::de::{Error, SeqAccess, Visitor};

    use super::{Deserialize, Deserializer};

    /// An array of exactly N elements.
    struct Exact<T, const N: usize>([T; N]);

    /// What the elements are called in the message.
    pub trait Element {
        const NOUN: &'static str;
    }
    impl Element for f64 {
        const NOUN: &'static str = "numbers";
    }
    impl Element for u32 {
        const NOUN: &'static str = "follower ids";
    }

    impl<'de, T: Deserialize<'de> + Element, const N: usize> Deserialize<'de> for Exact<T, N> {
        fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
            d.deserialize_seq(ExactVisitor::<T, N>(std::marker::PhantomData))
        }
    }

    /// Checks the length inside the visit, so that the error carries the
    /// span of this array (an element of `edges`), not of the one around it.
    struct ExactVisitor<T, const N: usize>(std::marker::PhantomData<T>);

    impl<'de, T: Deserialize<'de> + Element, const N: usize> Visitor<'de> for ExactVisitor<T, N> {
        type Value = Exact<T, N>;

        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            write!(f, "an array of {N} {}", T::NOUN)
        }

        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
            let mut items = Vec::with_capacity(N);
            while let Some(item) = seq.next_element::<T>()? {
                items.push(item);
            }
            let got = items.len();
            items.try_into().map(Exact).map_err(|_| A::Error::custom(message(N, T::NOUN, got)))
        }
    }

    fn message(expected: usize, noun: &str, got: usize) -> String {
        format!("expected {expected} {noun}, got {got}")
    }

    /// Whether a deserialization message is a length mismatch from here.
    pub(crate) fn is_length_error(message: &str) -> bool {
        let Some(rest) = message.strip_prefix("expected ") else { return false };
        let Some((expected, got)) = rest.split_once(", got ") else { return false };
        let mut words = expected.splitn(2, ' ');
        let (Some(n), Some(noun)) = (words.next(), words.next()) else { return false };
        [<f64 as Element>::NOUN, <u32 as Element>::NOUN].contains(&noun)
            && n.parse::<usize>().is_ok()
            && got.parse::<usize>().is_ok()
    }

    pub fn array<'de, D: Deserializer<'de>, T: Deserialize<'de> + Element, const N: usize>(
        d: D,
    ) -> Result<[T; N], D::Error> {
        Exact::<T, N>::deserialize(d).map(|e| e.0)
    }

    pub fn option<'de, D: Deserializer<'de>, T: Deserialize<'de> + Element, const N: usize>(
        d: D,
    ) -> Result<Option<[T; N]>, D::Error> {
        Option::<Exact<T, N>>::deserialize(d).map(|o| o.map(|e| e.0))
    }

    pub fn edges<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<[u32; 2]>, D::Error> {
        Vec::<Exact<u32, 2>>::deserialize(d).map(|v| v.into_iter().map(|e| e.0).collect())
    }

    pub fn points<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<[f64; 2]>, D::Error> {
        Vec::<Exact<f64, 2>>::deserialize(d).map(|v| v.into_iter().map(|e| e.0).collect())
    }
}

macro_rules! default_impl {
    ($t:ty { $($f:ident: $v:expr),* $(,)? }) => {
        impl Default for $t {
            fn default() -> Self { Self { $($f: $v),* } }
        }
    };
}
default_impl!(LeaderFile {
    source: d::source(),
    recorded: None,
    timeout: None,
    trajectory: d::trajectory(),
    pose: d::leader_pose(),
    ramp: d::ramp(),
    speed: d::speed(),
    radius: d::radius(),
    waypoints: Vec::new(),
    turn_rate: None,
    turn_gain: None,
    reach: None
});
default_impl!(EstimatorFile { k: d::k(), ka: d::ka(), kb: d::kb() });
default_impl!(BacksteppingFile { c1: d::c1(), c2: d::c2(), c3: d::c3(), shunting: d::kin_shunting() });
default_impl!(SlidingModeFile {
    ca: d::c_ab(),
    cb: d::c_ab(),
    shunting_v: d::dyn_shunting(),
    shunting_w: d::dyn_shunting(),
    k1: d::st_k(),
    k2: d::st_k()
});
default_impl!(RobotFile {
    model: RobotModel::Torque,
    lag: None,
    mass: d::mass(),
    inertia: d::inertia(),
    wheel_radius: d::wheel_radius(),
    half_axle: d::half_axle(),
    v_max: None,
    w_max: None,
    cmd_timeout: None,
    odom_origin: None
});
default_impl!(DisturbanceFile { dv: d::dv(), dw: d::dw() });
default_impl!(CovarianceFile { q: d::cov(), r: d::cov() });
default_impl!(AsifFile { rho_max: d::rho() });
default_impl!(FaultFile { time: None, mass_factor: d::mass_factor(), inertia_factor: d::inertia_factor() });
default_impl!(NetworkFile {
    silence_timeout: d::silence_timeout(),
    time_scale: d::time_scale(),
    telemetry_batch: d::telemetry_batch(),
    hearing_record: d::hearing_record(),
    rejoin: d::rejoin(),
    rejoin_after: d::rejoin_after(),
    delay_steps: 0,
    gone_after: None
});

/// docs/model.md §10's values, the defaults of every key.
mod d {
    use super::*;
    pub fn gamma() -> f64 {
        100.0
    }
    pub fn projection() -> f64 {
        0.05
    }
    pub fn safety_radius() -> f64 {
        1.0
    }
    pub fn deadlock_after() -> f64 {
        1.0
    }
    pub fn sidestep() -> f64 {
        2.0
    }
    pub fn sidestep_angle() -> f64 {
        std::f64::consts::FRAC_PI_2
    }
    pub fn robots() -> String {
        "simulated".into()
    }
    pub fn odom_timeout() -> f64 {
        0.5
    }
    pub fn seed() -> u64 {
        1
    }
    pub fn dt() -> f64 {
        1e-3
    }
    pub fn duration() -> f64 {
        30.0
    }
    pub fn yes() -> bool {
        true
    }
    pub fn kinematic() -> KinematicKind {
        KinematicKind::Bio
    }
    pub fn dynamic() -> DynamicKind {
        DynamicKind::Bio
    }
    pub fn filter() -> FilterKind {
        FilterKind::Asif
    }
    pub fn estimate_init() -> String {
        "leader".into()
    }
    pub fn timing() -> String {
        "lockstep".into()
    }
    pub fn source() -> String {
        "trajectory".into()
    }
    pub fn is_trajectory(s: &str) -> bool {
        s == "trajectory"
    }
    pub fn trajectory() -> String {
        "paper".into()
    }
    pub fn leader_pose() -> [f64; 3] {
        [0.0, 3.0, 0.0]
    }
    pub fn ramp() -> f64 {
        0.5
    }
    pub fn speed() -> f64 {
        1.0
    }
    pub fn radius() -> f64 {
        5.0
    }
    pub fn k() -> [f64; 3] {
        [1.0; 3]
    }
    pub fn ka() -> [f64; 2] {
        [20.0; 2]
    }
    pub fn kb() -> [f64; 2] {
        [5.0; 2]
    }
    pub fn c1() -> f64 {
        3.0
    }
    pub fn c2() -> f64 {
        2.0
    }
    pub fn c3() -> f64 {
        1.0
    }
    pub fn kin_shunting() -> Shunting {
        Shunting { a: 4.0, b: 2.0, d: 2.0 }
    }
    pub fn c_ab() -> f64 {
        3.0
    }
    pub fn dyn_shunting() -> Shunting {
        Shunting { a: 4.0, b: 6.0, d: 6.0 }
    }
    pub fn st_k() -> f64 {
        3.0
    }
    pub fn mass() -> f64 {
        10.0
    }
    pub fn inertia() -> f64 {
        5.0
    }
    pub fn wheel_radius() -> f64 {
        0.05
    }
    pub fn half_axle() -> f64 {
        0.2
    }
    pub fn dv() -> f64 {
        0.5
    }
    pub fn dw() -> f64 {
        0.2
    }
    pub fn cov() -> [f64; 2] {
        [1.6e-4, 1.0e-4]
    }
    pub fn rho() -> [f64; 2] {
        [0.08, 0.08]
    }
    pub fn mass_factor() -> f64 {
        0.01
    }
    pub fn inertia_factor() -> f64 {
        0.1
    }
    pub fn silence_timeout() -> f64 {
        0.05
    }
    pub fn time_scale() -> f64 {
        1.0
    }
    pub fn telemetry_batch() -> u32 {
        50
    }
    pub fn hearing_record() -> bool {
        true
    }
    pub fn rejoin() -> String {
        "consensus".into()
    }
    pub fn rejoin_after() -> f64 {
        0.1
    }
    pub fn loss() -> f64 {
        1.0
    }
}
