//! Velocity filters (docs/model.md §8): the Kalman filter baseline and the adaptive
//! sliding innovation filter (ASIF, eq. 57–65).
//!
//! State ζ = (v, ω), A_h = I, H = I, B_h = M̄⁻¹ B̄ Δt. Q, R and P(0) = R are
//! diagonal and so are A_h and H, so P and K stay diagonal and the filter
//! decouples into one scalar filter per channel; that is how it is written.

use serde::{Deserialize, Serialize};

use crate::math::sat;
use formation_plant::{RobotParams, Torque, Velocity};

/// Which velocity filter a follower runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FilterKind {
    Asif,
    Kf,
    /// No filter: the controller uses the raw measurement z.
    None,
}

/// Q, R (per step, diagonal) and the ASIF limit ρ_max.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FilterParams {
    pub kind: FilterKind,
    pub q: [f64; 2],
    pub r: [f64; 2],
    pub rho_max: [f64; 2],
}

/// The gain of one channel (eq. 63–65 and the fixed-boundary switch).
///
/// KF: K = P⁻ / S. ASIF: δ = S (S − R)⁻¹ |z̃| (eq. 65); while δ ≤ ρ_max the
/// gain is (S − R)/S = P⁻/S, the Kalman gain (eq. 63–65 reduce to it); once
/// δ > ρ_max it is the fixed-boundary SIF gain sat(|z̃| / ρ_max) (eq. 60).
/// The comparison δ ≤ ρ_max is made as S |z̃| ≤ ρ_max P⁻, which needs no
/// division and stays defined when P⁻ = 0.
pub fn channel_gain(kind: FilterKind, p_minus: f64, s: f64, innovation: f64, rho_max: f64) -> f64 {
    let kalman = if s > 0.0 { p_minus / s } else { 0.0 };
    match kind {
        FilterKind::Kf => kalman,
        FilterKind::Asif => {
            if s * innovation.abs() <= rho_max * p_minus {
                kalman
            } else {
                sat(innovation.abs() / rho_max)
            }
        }
        FilterKind::None => 1.0,
    }
}

/// A velocity filter's state: ζ̂ and the diagonal of P. Its parameters are
/// not copied in: every follower of a scenario shares them
/// ([`crate::ControlParams::filter`]) and passes them to each update.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VelocityFilter {
    pub estimate: [f64; 2],
    pub p: [f64; 2],
    /// The gain of the last update, per channel (telemetry).
    pub gain: [f64; 2],
}

impl VelocityFilter {
    /// ζ̂(0) = ξ(0), P(0) = R (docs/model.md §8).
    pub fn new(params: &FilterParams, initial: Velocity) -> Self {
        Self { estimate: [initial.v, initial.w], p: params.r, gain: [0.0; 2] }
    }

    pub fn estimate(&self) -> Velocity {
        Velocity::new(self.estimate[0], self.estimate[1])
    }

    /// One predict-update cycle, with the filter's `params`, the torque τ(k), the filter's model at
    /// t_k and the measurement z(k+1):
    ///
    /// predict  ζ⁻ = ζ̂ + B_h τ, P⁻ = P + Q                      (eq. 57–58)
    ///          z̃ = z − ζ⁻, S = P⁻ + R                         (eq. 59, 64)
    /// update   ζ̂ = ζ⁻ + K z̃                                    (eq. 61)
    ///          P = (I − K) P⁻ (I − K)ᵀ + K R Kᵀ                 (eq. 62)
    ///
    /// With the filter `none`, ζ̂ = z.
    pub fn update(&mut self, params: &FilterParams, model: &RobotParams, tau: Torque, dt_s: f64, z: Velocity) {
        let z = [z.v, z.w];
        if params.kind == FilterKind::None {
            self.estimate = z;
            self.gain = [1.0; 2];
            return;
        }
        let a = model.torque_to_acceleration(tau);
        let b_tau = [a.v * dt_s, a.w * dt_s];
        for i in 0..2 {
            let prior = self.estimate[i] + b_tau[i];
            let p_minus = self.p[i] + params.q[i];
            let innovation = z[i] - prior;
            let s = p_minus + params.r[i];
            let k = channel_gain(params.kind, p_minus, s, innovation, params.rho_max[i]);
            self.estimate[i] = prior + k * innovation;
            self.p[i] = (1.0 - k) * p_minus * (1.0 - k) + k * params.r[i] * k;
            self.gain[i] = k;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn asif_gain_is_kalman_below_the_limit_and_sif_beyond(
            p_minus in 1e-8f64..1.0, r in 1e-8f64..1.0, innovation in -10f64..10.0, rho in 1e-4f64..1.0,
        ) {
            let s = p_minus + r;
            let delta = s / (s - r) * innovation.abs();
            let asif = channel_gain(FilterKind::Asif, p_minus, s, innovation, rho);
            let kf = channel_gain(FilterKind::Kf, p_minus, s, innovation, rho);
            prop_assert!((kf - p_minus / s).abs() < 1e-15);
            if delta <= rho * (1.0 - 1e-12) {
                prop_assert_eq!(asif, kf);
            } else if delta > rho * (1.0 + 1e-12) {
                prop_assert_eq!(asif, sat(innovation.abs() / rho));
                prop_assert!((0.0..=1.0).contains(&asif));
            }
        }
    }

    #[test]
    fn asif_saturates_to_one_for_a_large_innovation() {
        assert_eq!(channel_gain(FilterKind::Asif, 1e-4, 2e-4, 5.0, 0.08), 1.0);
    }

    fn params(kind: FilterKind) -> FilterParams {
        FilterParams { kind, q: [1.6e-4, 1e-4], r: [1.6e-4, 1e-4], rho_max: [0.08, 0.08] }
    }

    #[test]
    fn kalman_covariance_reaches_the_riccati_fixed_point() {
        // With Q = R = q the steady state solves P² + qP − q² = 0: P = q (√5 − 1)/2.
        let model = RobotParams { mass_kg: 10.0, inertia_kgm2: 5.0, wheel_radius_m: 0.05, half_axle_m: 0.2 };
        let mut f = VelocityFilter::new(&params(FilterKind::Kf), Velocity::default());
        for _ in 0..200 {
            f.update(&params(FilterKind::Kf), &model, Torque::default(), 1e-3, Velocity::default());
        }
        let golden = (5f64.sqrt() - 1.0) / 2.0;
        assert!((f.p[0] / 1.6e-4 - golden).abs() < 1e-9, "P_v = {}", f.p[0]);
        assert!((f.p[1] / 1e-4 - golden).abs() < 1e-9, "P_ω = {}", f.p[1]);
    }

    #[test]
    fn none_passes_the_measurement_through() {
        let model = RobotParams { mass_kg: 10.0, inertia_kgm2: 5.0, wheel_radius_m: 0.05, half_axle_m: 0.2 };
        let mut f = VelocityFilter::new(&params(FilterKind::None), Velocity::default());
        f.update(&params(FilterKind::None), &model, Torque { left: 3.0, right: 1.0 }, 1e-3, Velocity::new(0.25, -0.5));
        assert_eq!(f.estimate(), Velocity::new(0.25, -0.5));
    }

    #[test]
    fn prediction_uses_the_model_input_matrix() {
        // No noise in the model's eyes is impossible (S > 0), but with a
        // measurement equal to the prediction the update keeps the prediction.
        let model = RobotParams { mass_kg: 10.0, inertia_kgm2: 5.0, wheel_radius_m: 0.05, half_axle_m: 0.2 };
        let tau = model.acceleration_to_torque(2.0, -1.0);
        let mut f = VelocityFilter::new(&params(FilterKind::Asif), Velocity::new(1.0, 0.5));
        let predicted = Velocity::new(1.0 + 2.0e-3, 0.5 - 1.0e-3);
        f.update(&params(FilterKind::Asif), &model, tau, 1e-3, predicted);
        assert!((f.estimate[0] - predicted.v).abs() < 1e-15 && (f.estimate[1] - predicted.w).abs() < 1e-15);
    }
}
