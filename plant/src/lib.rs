//! The differential-drive robot of the paper (docs/model.md §4): unicycle kinematics
//! (eq. 3), torque-driven velocity dynamics with the centre of mass on the
//! wheel axle (eq. 4, C̄ = 0), a bounded disturbance (Assumption 2) and the
//! discrete process and measurement noise of eq. 55–56; and a
//! velocity-commanded robot (docs/model.md §15), a mobile base that takes
//! (v, ω) commands and reports odometry, as ROS 2 robots do.
//!
//! Everything here is pure: the noise comes from a generator the caller
//! seeds, so the same (seed, follower id) draws the same numbers whether the
//! robot runs in the simulator or alone in its own process.
//!
//! # Examples
//!
//! A velocity-commanded base told to drive at 1 m/s, one step of 10 ms: its
//! velocity follows the command through its first-order lag, and its pose
//! moves by eq. 3.
//!
//! ```
//! use formation_plant::{NoiseDraw, Pose, Velocity, VelocityRobot};
//!
//! let mut robot = VelocityRobot::new(0.1, Pose::new(0.0, 0.0, 0.0), Velocity::new(0.0, 0.0));
//! robot.advance(Velocity::new(1.0, 0.0), 0.01, NoiseDraw::default());
//! let (pose, velocity) = robot.odometry();
//! assert!(velocity.v > 0.0 && velocity.v < 1.0, "lagging the command: {velocity:?}");
//! assert_eq!((pose.y, pose.theta), (0.0, 0.0), "straight ahead");
//! ```

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// Planar pose P = (x, y, θ), metres and radians.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub x: f64,
    pub y: f64,
    pub theta: f64,
}

impl Pose {
    pub const fn new(x: f64, y: f64, theta: f64) -> Self {
        Self { x, y, theta }
    }

    pub fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.theta.is_finite()
    }

    /// One forward-Euler step of the unicycle (eq. 3, docs/model.md §9 step 4):
    /// the pose moves with ξ for Δt, `(s, c) = θ.sin_cos()` given. Both
    /// robots move their pose with this.
    #[inline]
    pub fn advance(&mut self, velocity: Velocity, (s, c): (f64, f64), dt_s: f64) {
        let Velocity { v, w } = velocity;
        self.x += dt_s * v * c;
        self.y += dt_s * v * s;
        self.theta += dt_s * w;
    }

    /// `local`, a pose in the frame whose origin is `self` (a robot's
    /// odometry frame placed in the world), in the world: the rigid motion
    /// `self ⊕ local`.
    pub fn compose(&self, local: &Pose) -> Pose {
        let (s, c) = self.theta.sin_cos();
        Pose::new(self.x + c * local.x - s * local.y, self.y + s * local.x + c * local.y, self.theta + local.theta)
    }

    /// `world` in the frame whose origin is `self`: the inverse of
    /// [`Pose::compose`] (`self.compose(&self.relative(w))` is `w` up to rounding).
    pub fn relative(&self, world: &Pose) -> Pose {
        let (s, c) = self.theta.sin_cos();
        let (dx, dy) = (world.x - self.x, world.y - self.y);
        Pose::new(c * dx + s * dy, -s * dx + c * dy, world.theta - self.theta)
    }
}

/// Body velocity ξ = (v, ω), m/s and rad/s.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Velocity {
    pub v: f64,
    pub w: f64,
}

impl Velocity {
    pub const fn new(v: f64, w: f64) -> Self {
        Self { v, w }
    }

    pub fn is_finite(&self) -> bool {
        self.v.is_finite() && self.w.is_finite()
    }
}

/// Wheel torques τ = (τ_L, τ_R), N m.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Torque {
    pub left: f64,
    pub right: f64,
}

impl Torque {
    pub fn is_finite(&self) -> bool {
        self.left.is_finite() && self.right.is_finite()
    }
}

/// Physical parameters of one robot (docs/model.md §4, §10).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RobotParams {
    /// m, kg.
    pub mass_kg: f64,
    /// I, yaw inertia, kg m².
    pub inertia_kgm2: f64,
    /// r, wheel radius, m.
    pub wheel_radius_m: f64,
    /// c, half the distance between the wheels, m.
    pub half_axle_m: f64,
}

impl RobotParams {
    /// The accelerations (v̇, ω̇) that the torques produce, without
    /// disturbance (eq. 4 with C̄ = 0):
    /// v̇ = (τ_R + τ_L) / (m r), ω̇ = c (τ_R − τ_L) / (I r).
    /// This is M̄⁻¹ B̄ τ, the input matrix the filters use too.
    pub fn torque_to_acceleration(&self, tau: Torque) -> Velocity {
        Velocity {
            v: (tau.right + tau.left) / (self.mass_kg * self.wheel_radius_m),
            w: self.half_axle_m * (tau.right - tau.left) / (self.inertia_kgm2 * self.wheel_radius_m),
        }
    }

    /// The inverse of [`RobotParams::torque_to_acceleration`] (eq. 37–38's
    /// torque mapping): τ_L = (m r / 2) a_v − (I r / (2c)) a_ω,
    /// τ_R = (m r / 2) a_v + (I r / (2c)) a_ω.
    pub fn acceleration_to_torque(&self, a_v: f64, a_w: f64) -> Torque {
        let linear = 0.5 * self.mass_kg * self.wheel_radius_m * a_v;
        let angular = self.inertia_kgm2 * self.wheel_radius_m / (2.0 * self.half_axle_m) * a_w;
        Torque { left: linear - angular, right: linear + angular }
    }
}

/// Bounded disturbance d_1 = D_v sin t (N), d_2 = D_ω cos t (N m)
/// (Assumption 2; the form is decided in docs/model.md §4).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Disturbance {
    pub linear_n: f64,
    pub angular_nm: f64,
}

impl Disturbance {
    /// (d_1, d_2) at time t.
    pub fn at(&self, t_s: f64) -> (f64, f64) {
        let (sin_t, cos_t) = t_s.sin_cos();
        (self.linear_n * sin_t, self.angular_nm * cos_t)
    }
}

/// Diagonal covariances Q (process) and R (measurement) per step, for the
/// (v, ω) channels (docs/model.md §10). Diagonal by construction, so every filter
/// decouples into one scalar filter per channel.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct NoiseCov {
    pub q: [f64; 2],
    pub r: [f64; 2],
}

/// One step's noise draw: α_k (process) and β_k (measurement) of eq. 55–56.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct NoiseDraw {
    pub process: Velocity,
    pub measurement: Velocity,
}

/// A follower's own noise generator, seeded from (scenario seed, follower id)
/// so that a follower draws the same sequence wherever it runs. ChaCha8 is
/// portable and its stream is fixed by its seed.
#[derive(Clone, Debug)]
pub struct NoiseSource {
    rng: ChaCha8Rng,
    std_q: [f64; 2],
    std_r: [f64; 2],
    enabled: bool,
}

impl NoiseSource {
    pub fn new(cov: NoiseCov, enabled: bool, seed: u64, follower_id: u32) -> Self {
        Self {
            rng: ChaCha8Rng::seed_from_u64(stream_seed(seed, follower_id)),
            std_q: [cov.q[0].sqrt(), cov.q[1].sqrt()],
            std_r: [cov.r[0].sqrt(), cov.r[1].sqrt()],
            enabled,
        }
    }

    /// Draws α_k then β_k, in the order (α_v, α_ω, β_v, β_ω). With noise
    /// disabled both are zero and the generator is not touched.
    pub fn draw(&mut self) -> NoiseDraw {
        if !self.enabled {
            return NoiseDraw::default();
        }
        let mut n = || -> f64 { StandardNormal.sample(&mut self.rng) };
        let (av, aw, bv, bw) = (n(), n(), n(), n());
        NoiseDraw {
            process: Velocity::new(self.std_q[0] * av, self.std_q[1] * aw),
            measurement: Velocity::new(self.std_r[0] * bv, self.std_r[1] * bw),
        }
    }
}

/// Mixes the scenario seed and follower id into one 64-bit stream seed
/// (SplitMix64 finaliser, so neighbouring ids get unrelated streams).
pub fn stream_seed(seed: u64, follower_id: u32) -> u64 {
    let mut z = seed ^ (u64::from(follower_id)).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The robot: its true pose and velocity, advanced by forward Euler.
#[derive(Clone, Debug)]
pub struct Robot {
    pub params: RobotParams,
    pub disturbance: Disturbance,
    pub pose: Pose,
    pub velocity: Velocity,
}

impl Robot {
    pub fn new(params: RobotParams, disturbance: Disturbance, pose: Pose, velocity: Velocity) -> Self {
        Self { params, disturbance, pose, velocity }
    }

    /// The true accelerations under torque τ at time t (eq. 4):
    /// v̇ = (τ_R + τ_L)/(m r) + d_1/m, ω̇ = c (τ_R − τ_L)/(I r) + d_2/I.
    pub fn acceleration(&self, tau: Torque, t_s: f64) -> Velocity {
        self.acceleration_with(tau, self.disturbance.at(t_s))
    }

    /// [`Robot::acceleration`] with the disturbance (d_1, d_2) at t given.
    pub fn acceleration_with(&self, tau: Torque, (d1, d2): (f64, f64)) -> Velocity {
        let a = self.params.torque_to_acceleration(tau);
        Velocity::new(a.v + d1 / self.params.mass_kg, a.w + d2 / self.params.inertia_kgm2)
    }

    /// One forward-Euler step from k to k+1 (docs/model.md §9, step 4): the pose moves
    /// with ξ(k) (eq. 3), then ξ(k+1) = ξ(k) + Δt·(accelerations at k) + α_k
    /// (eq. 55). Returns the measurement z(k+1) = ξ(k+1) + β (eq. 56).
    pub fn advance(&mut self, tau: Torque, t_s: f64, dt_s: f64, noise: NoiseDraw) -> Velocity {
        self.advance_with(tau, self.pose.theta.sin_cos(), self.disturbance.at(t_s), dt_s, noise)
    }

    /// [`Robot::advance`] with `heading = self.pose.theta.sin_cos()` and the
    /// disturbance `self.disturbance.at(t)` already computed (a simulator
    /// computes the disturbance once per step for all robots and shares the
    /// heading with the controller's body-frame error): the same numbers.
    pub fn advance_with(
        &mut self,
        tau: Torque,
        (s, c): (f64, f64),
        disturbance: (f64, f64),
        dt_s: f64,
        noise: NoiseDraw,
    ) -> Velocity {
        let Velocity { v, w } = self.velocity;
        let acc = self.acceleration_with(tau, disturbance);
        self.pose.advance(self.velocity, (s, c), dt_s);
        self.velocity.v = v + dt_s * acc.v + noise.process.v;
        self.velocity.w = w + dt_s * acc.w + noise.process.w;
        self.measure(noise)
    }

    /// z = ξ + β (eq. 56).
    pub fn measure(&self, noise: NoiseDraw) -> Velocity {
        measure(self.velocity, noise)
    }
}

/// The velocity sensor: z = ξ + β (eq. 56), for both robots.
#[inline]
fn measure(velocity: Velocity, noise: NoiseDraw) -> Velocity {
    Velocity::new(velocity.v + noise.measurement.v, velocity.w + noise.measurement.w)
}

/// How a follower drives its robot (docs/model.md §15): the brain and the
/// robot agree on it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub enum Drive {
    /// Wheel torques: the paper's robot ([`Robot`], eq. 4), driven by the
    /// dynamic controller.
    #[default]
    Torque,
    /// Body velocities (v_c, ω_c), followed by the robot's own low-level
    /// velocity loop with time constant `lag_s`, s ([`VelocityRobot`]).
    Velocity { lag_s: f64 },
}

/// Maps an angle into [−π, π) (docs/model.md §1): the one wrap of every
/// crate (the controllers', the estimator's, the leader's route).
pub fn wrap(a: f64) -> f64 {
    use std::f64::consts::PI;
    let w = a - 2.0 * PI * ((a + PI) / (2.0 * PI)).floor();
    // Rounding can land exactly on π for inputs just below it.
    if w >= PI {
        w - 2.0 * PI
    } else {
        w
    }
}

/// The heading as a ROS odometry message carries it and a receiver reads it
/// back: the quaternion (0, 0, sin(θ/2), cos(θ/2)) and yaw = 2 atan2(z, w).
/// The ROS 2 node computes exactly this, so the simulator sees the heading
/// an agent reading odometry sees, bit for bit. The result equals θ modulo
/// 2π and lies in (−2π, 2π] (the quaternion is not brought to w ≥ 0, so
/// this is θ modulo 4π, not a wrap into (−π, π]); every use of θ in the
/// brain is through sin, cos or a wrapped difference (docs/model.md §1, §6).
#[inline]
pub fn odometry_heading(theta: f64) -> f64 {
    let (s, c) = (theta * 0.5).sin_cos();
    2.0 * s.atan2(c)
}

/// A velocity-commanded robot (docs/model.md §15, eq. V1): a mobile base
/// (TurtleBot, Gazebo's diff-drive, most ROS 2 bases) that takes velocity
/// commands u = (v_c, ω_c) and follows them through its own low-level
/// velocity loop, modelled as a first-order lag of time constant T; it
/// reports odometry: its pose, the heading through a quaternion
/// ([`odometry_heading`]), and its measured body velocity z.
///
/// It has no disturbance: the robot's own velocity loop rejects the
/// disturbance of Assumption 2 (what is left of it is in the process noise).
///
/// A stand-in robot process runs exactly this with
/// `NoiseSource::new(scenario.covariance, scenario.noise, scenario.seed, id)`:
/// at each step k it publishes [`VelocityRobot::odometry`], receives the
/// command of step k and calls [`VelocityRobot::advance`] with it and the
/// next draw of its noise source.
#[derive(Clone, Debug, PartialEq)]
pub struct VelocityRobot {
    /// T, s: the time constant of the robot's velocity loop.
    pub lag_s: f64,
    /// The true pose (θ not wrapped).
    pub pose: Pose,
    /// The true velocity ξ.
    pub velocity: Velocity,
    /// z(k) = ξ(k) + β: the velocity the robot measures and reports
    /// (z(0) = ξ(0), as for the torque robot).
    pub measurement: Velocity,
}

impl VelocityRobot {
    /// A robot at `pose` moving with ξ(0) = `velocity`, measuring z(0) = ξ(0).
    pub fn new(lag_s: f64, pose: Pose, velocity: Velocity) -> Self {
        Self { lag_s, pose, velocity, measurement: velocity }
    }

    /// a = 1 − exp(−Δt/T) of eq. V1 (computed as −expm1(−Δt/T), which keeps
    /// its digits when Δt ≪ T).
    #[inline]
    pub fn lag_gain(&self, dt_s: f64) -> f64 {
        -(-dt_s / self.lag_s).exp_m1()
    }

    /// One step from k to k+1 under the command u(k) = `command`
    /// (docs/model.md §15): the pose moves with ξ(k) exactly as the torque
    /// robot's does ([`Pose::advance`]), then (eq. V1)
    /// ξ(k+1) = ξ(k) + a (u(k) − ξ(k)) + α_k, a = 1 − exp(−Δt/T), the exact
    /// discretisation of the lag T ξ̇ = u − ξ with u held over the step.
    /// Returns (and keeps) the measurement z(k+1) = ξ(k+1) + β_k (eq. 56).
    /// `noise` is one [`NoiseSource::draw`], α then β as for the torque robot.
    pub fn advance(&mut self, command: Velocity, dt_s: f64, noise: NoiseDraw) -> Velocity {
        let a = self.lag_gain(dt_s);
        let Velocity { v, w } = self.velocity;
        self.pose.advance(self.velocity, self.pose.theta.sin_cos(), dt_s);
        self.velocity.v = v + a * (command.v - v) + noise.process.v;
        self.velocity.w = w + a * (command.w - w) + noise.process.w;
        self.measurement = measure(self.velocity, noise);
        self.measurement
    }

    /// What the robot reports at step k (a ROS odometry message): its pose
    /// with x, y exact and θ as [`odometry_heading`] reads it back, and its
    /// measured velocity z(k).
    pub fn odometry(&self) -> (Pose, Velocity) {
        let p = self.pose;
        (Pose::new(p.x, p.y, odometry_heading(p.theta)), self.measurement)
    }

    /// A robot stopped (ξ = z = 0) at `pose`: a restarted agent's (docs/model.md §14).
    pub fn stop_at(&mut self, pose: Pose) {
        self.pose = pose;
        self.velocity = Velocity::default();
        self.measurement = Velocity::default();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pose_in_an_offset_frame_maps_to_the_world_and_back() {
        let origin = Pose::new(1.0, -2.0, std::f64::consts::FRAC_PI_2);
        let w = origin.compose(&Pose::new(0.5, 0.0, 0.25));
        assert!((w.x - 1.0).abs() < 1e-15 && (w.y + 1.5).abs() < 1e-15, "{w:?}");
        assert!((w.theta - (std::f64::consts::FRAC_PI_2 + 0.25)).abs() < 1e-15);
        assert_eq!(origin.compose(&Pose::default()), origin, "odometry (0, 0, 0) is the origin");
        let back = origin.compose(&origin.relative(&Pose::new(3.0, 4.0, -1.0)));
        assert!((back.x - 3.0).abs() < 1e-12 && (back.y - 4.0).abs() < 1e-12 && (back.theta + 1.0).abs() < 1e-12);
    }

    const PAPER: RobotParams = RobotParams { mass_kg: 10.0, inertia_kgm2: 5.0, wheel_radius_m: 0.05, half_axle_m: 0.2 };

    #[test]
    fn torque_mapping_inverts_the_dynamics() {
        for &(av, aw) in &[(1.0, 0.0), (0.0, 1.0), (-2.5, 3.25), (1e3, -1e-3)] {
            let a = PAPER.torque_to_acceleration(PAPER.acceleration_to_torque(av, aw));
            assert!((a.v - av).abs() <= 1e-12 * av.abs().max(1.0), "v̇ {} vs {}", a.v, av);
            assert!((a.w - aw).abs() <= 1e-12 * aw.abs().max(1.0), "ω̇ {} vs {}", a.w, aw);
        }
    }

    #[test]
    fn robot_without_noise_or_disturbance_reaches_the_demanded_velocity() {
        let mut robot = Robot::new(PAPER, Disturbance::default(), Pose::default(), Velocity::default());
        let tau = PAPER.acceleration_to_torque(0.5, -0.25);
        for k in 0..1000 {
            robot.advance(tau, k as f64 * 1e-3, 1e-3, NoiseDraw::default());
        }
        assert!((robot.velocity.v - 0.5).abs() < 1e-12, "v = {}", robot.velocity.v);
        assert!((robot.velocity.w + 0.25).abs() < 1e-12, "ω = {}", robot.velocity.w);
    }

    #[test]
    fn advance_with_precomputed_trig_is_advance() {
        let d = Disturbance { linear_n: 0.5, angular_nm: -0.25 };
        let start = Robot::new(PAPER, d, Pose::new(1.0, -2.0, 0.7), Velocity::new(0.3, -0.1));
        let noise = NoiseDraw { process: Velocity::new(1e-3, -2e-3), measurement: Velocity::new(3e-3, 4e-3) };
        let tau = Torque { left: 0.4, right: -0.2 };
        let (mut a, mut b) = (start.clone(), start);
        for k in 0..100 {
            let t = k as f64 * 1e-3;
            let za = a.advance(tau, t, 1e-3, noise);
            let zb = b.advance_with(tau, b.pose.theta.sin_cos(), d.at(t), 1e-3, noise);
            assert_eq!((za, a.pose, a.velocity), (zb, b.pose, b.velocity));
        }
    }

    #[test]
    fn the_velocity_robot_follows_a_step_as_a_first_order_lag() {
        // A step of u = (1, −0.5) from rest: after T = n Δt the velocity is
        // (1 − e^(−1)) of the step, the exact lag's value, for any Δt ≤ T
        // (eq. V1 is the exact discretisation).
        for (lag_s, dt_s) in [(0.1, 1e-3), (0.1, 0.01), (0.25, 0.05), (2.0, 1e-3), (0.1, 0.1)] {
            let mut robot = VelocityRobot::new(lag_s, Pose::default(), Velocity::default());
            let steps = (lag_s / dt_s).round() as u64;
            for _ in 0..steps {
                robot.advance(Velocity::new(1.0, -0.5), dt_s, NoiseDraw::default());
            }
            let want = 1.0 - (-1.0f64).exp();
            assert!((robot.velocity.v - want).abs() < 1e-12, "T {lag_s}, Δt {dt_s}: v = {}", robot.velocity.v);
            assert!((robot.velocity.w + 0.5 * want).abs() < 1e-12, "T {lag_s}, Δt {dt_s}: ω = {}", robot.velocity.w);
            assert_eq!(robot.measurement, robot.velocity, "without noise z = ξ");
        }
        // A lag far below Δt: the command is reached in one step, nothing overflows.
        let mut quick = VelocityRobot::new(1e-300, Pose::default(), Velocity::default());
        assert_eq!(quick.advance(Velocity::new(0.7, 0.2), 1e-3, NoiseDraw::default()), Velocity::new(0.7, 0.2));
    }

    #[test]
    fn both_robots_move_their_pose_with_the_same_euler_step() {
        let pose = Pose::new(1.0, -2.0, 0.7);
        let xi = Velocity::new(0.3, -0.1);
        let mut torque = Robot::new(PAPER, Disturbance::default(), pose, xi);
        let mut velocity = VelocityRobot::new(0.1, pose, xi);
        let noise = NoiseDraw { process: Velocity::new(1e-3, -2e-3), measurement: Velocity::new(3e-3, 4e-3) };
        torque.advance(Torque::default(), 0.0, 1e-3, noise);
        let z = velocity.advance(xi, 1e-3, noise);
        assert_eq!(torque.pose, velocity.pose, "pose(k+1) from ξ(k) alone");
        // u = ξ: the lag adds nothing, only α; z = ξ + β.
        assert_eq!(velocity.velocity, Velocity::new(0.3 + 1e-3, -0.1 - 2e-3));
        assert_eq!(z, Velocity::new(velocity.velocity.v + 3e-3, velocity.velocity.w + 4e-3));
        assert_eq!(velocity.odometry().1, z);
    }

    #[test]
    fn odometry_heading_is_the_heading_modulo_two_pi() {
        use std::f64::consts::{PI, TAU};
        let mut theta = -20.0;
        while theta <= 20.0 {
            let h = odometry_heading(theta);
            assert!(h > -TAU && h <= TAU, "θ = {theta}: {h} outside (−2π, 2π]");
            // h − θ is a multiple of 2π; the difference is at most a few ulp of θ.
            let d = h - theta;
            let off = d - TAU * (d / TAU).round();
            assert!(off.abs() <= 4.0 * f64::EPSILON * theta.abs().max(PI), "θ = {theta}: off by {off:e}");
            theta += 0.01;
        }
        // Within (−π, π) the reading is θ itself, to the last bits.
        for theta in [0.0, 1e-9, -0.3, 1.0, 3.0, -3.1] {
            assert!((odometry_heading(theta) - theta).abs() <= 1e-15, "θ = {theta}");
        }
        assert_eq!(odometry_heading(0.0), 0.0);
        assert!((odometry_heading(PI) - PI).abs() <= 1e-15);
        let robot = VelocityRobot::new(0.1, Pose::new(2.0, -1.0, 7.0), Velocity::default());
        let (pose, _) = robot.odometry();
        assert_eq!((pose.x, pose.y, pose.theta), (2.0, -1.0, odometry_heading(7.0)));
    }

    #[test]
    fn noise_streams_are_reproducible_and_differ_by_seed_and_id() {
        let cov = NoiseCov { q: [1.6e-4, 1e-4], r: [1.6e-4, 1e-4] };
        let seq = |seed, id| {
            let mut n = NoiseSource::new(cov, true, seed, id);
            (0..4).map(|_| n.draw().process.v).collect::<Vec<_>>()
        };
        assert_eq!(seq(1, 1), seq(1, 1));
        assert_ne!(seq(1, 1), seq(1, 2));
        assert_ne!(seq(1, 1), seq(2, 1));
        let mut off = NoiseSource::new(cov, false, 1, 1);
        assert_eq!(off.draw(), NoiseDraw::default());
    }

    #[test]
    fn noise_has_the_requested_variance() {
        let cov = NoiseCov { q: [1.6e-4, 1e-4], r: [4e-4, 9e-4] };
        let mut n = NoiseSource::new(cov, true, 42, 3);
        let k = 200_000;
        let mut acc = [0.0f64; 4];
        for _ in 0..k {
            let d = n.draw();
            for (a, x) in acc.iter_mut().zip([d.process.v, d.process.w, d.measurement.v, d.measurement.w]) {
                *a += x * x;
            }
        }
        for (a, want) in acc.iter().zip([1.6e-4, 1e-4, 4e-4, 9e-4]) {
            let var = a / k as f64;
            // 200k samples: the sample variance is within ±1.5 % at 5 σ.
            assert!((var / want - 1.0).abs() < 0.016, "variance {var} vs {want}");
        }
    }
}
