//! The differential-drive robot of the paper (docs/model.md §4): unicycle kinematics
//! (eq. 3), torque-driven velocity dynamics with the centre of mass on the
//! wheel axle (eq. 4, C̄ = 0), a bounded disturbance (Assumption 2) and the
//! discrete process and measurement noise of eq. 55–56.
//!
//! Everything here is pure: the noise comes from a generator the caller
//! seeds, so the same (seed, follower id) draws the same numbers whether the
//! robot runs in the simulator or alone in its own process.

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
        self.pose.x += dt_s * v * c;
        self.pose.y += dt_s * v * s;
        self.pose.theta += dt_s * w;
        self.velocity.v = v + dt_s * acc.v + noise.process.v;
        self.velocity.w = w + dt_s * acc.w + noise.process.w;
        self.measure(noise)
    }

    /// z = ξ + β (eq. 56).
    pub fn measure(&self, noise: NoiseDraw) -> Velocity {
        Velocity::new(self.velocity.v + noise.measurement.v, self.velocity.w + noise.measurement.w)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
