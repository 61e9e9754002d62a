//! The distributed leader estimator (eq. 11–15, docs/model.md §5).
//!
//! Every follower keeps an estimate (P_ir, v_ir, ω_ir) of the leader's pose
//! and velocities and drives it by consensus with its neighbours' estimates
//! and, if it hears the leader, the leader's own state.

use serde::{Deserialize, Serialize};

use crate::math::sat;
use formation_leader::LeaderState;
use formation_plant::wrap;
use formation_plant::Pose;

/// k_i (diagonal of a 3×3 gain), k_a1, k_a2, k_b1, k_b2 (docs/model.md §10).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EstimatorGains {
    /// Diagonal of k_i, for (x, y, θ).
    pub k: [f64; 3],
    /// (k_a1, k_a2).
    pub ka: [f64; 2],
    /// (k_b1, k_b2).
    pub kb: [f64; 2],
}

/// The rates of one estimator step.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EstimatorRates {
    /// Ṗ_ir (eq. 12).
    pub pose_rate: Pose,
    /// v̇_ir (eq. 14).
    pub v_rate: f64,
    /// ω̇_ir (eq. 15).
    pub w_rate: f64,
    /// How many sources entered the sums: ξ_i of docs/model.md §2 restricted to the
    /// neighbours (and leader) actually heard at this step.
    pub sources: u32,
}

/// The estimator's rates at one step.
///
/// `own` is this follower's estimate, whose `pose_rate` is its own latest
/// Ṗ_ir. `leader` is `Some` only for a follower with a_i0 = 1 that holds the
/// leader's state; `neighbours` yields the neighbours' latest estimates in
/// ascending id (docs/model.md §1), each with the Ṗ_jr its sender computed last.
///
/// e_ip = a_i0 (P_ir − P_r) + Σ_j a_ij (P_ir − P_jr)                (eq. 11)
/// Ṗ_ir = ( −k_i e_ip + Σ_j a_ij Ṗ_jr + a_i0 Ṗ_r ) / ξ_i            (eq. 12)
/// e_iv = a_i0 (v_ir − v_r) + Σ_j a_ij (v_ir − v_jr)                (eq. 13)
/// v̇_ir = −k_a1 e_iv − k_b1 sat(e_iv), ω̇_ir likewise            (eq. 14–15)
///
/// θ differences are wrapped. A neighbour that was not heard is simply not
/// yielded, and ξ_i counts only what was: the estimate then keeps consensus
/// with the sources it has. With no source at all, the estimate dead-reckons
/// on its own last Ṗ_ir and holds v_ir, ω_ir.
pub fn rates<'a>(
    gains: &EstimatorGains,
    own: &LeaderState,
    leader: Option<&LeaderState>,
    neighbours: impl IntoIterator<Item = &'a LeaderState>,
) -> EstimatorRates {
    let mut e_p = [0.0f64; 3];
    let mut rate_sum = [0.0f64; 3];
    let mut e_v = 0.0;
    let mut e_w = 0.0;
    let mut sources = 0u32;
    let mut add = |other: &LeaderState| {
        e_p[0] += own.pose.x - other.pose.x;
        e_p[1] += own.pose.y - other.pose.y;
        e_p[2] += wrap(own.pose.theta - other.pose.theta);
        rate_sum[0] += other.pose_rate.x;
        rate_sum[1] += other.pose_rate.y;
        rate_sum[2] += other.pose_rate.theta;
        e_v += own.v - other.v;
        e_w += own.w - other.w;
        sources += 1;
    };
    // docs/model.md §1: the leader term first, then neighbours in ascending id.
    if let Some(l) = leader {
        add(l);
    }
    for n in neighbours {
        add(n);
    }
    if sources == 0 {
        return EstimatorRates { pose_rate: own.pose_rate, v_rate: 0.0, w_rate: 0.0, sources };
    }
    let xi = f64::from(sources);
    let component = |i: usize| (-gains.k[i] * e_p[i] + rate_sum[i]) / xi;
    EstimatorRates {
        pose_rate: Pose::new(component(0), component(1), component(2)),
        v_rate: -gains.ka[0] * e_v - gains.kb[0] * sat(e_v),
        w_rate: -gains.ka[1] * e_w - gains.kb[1] * sat(e_w),
        sources,
    }
}

/// Forward-Euler advance of the estimate with the rates of step k; the new
/// Ṗ_ir becomes the "latest" rate that the next message carries.
pub fn advance(own: &mut LeaderState, r: &EstimatorRates, dt_s: f64) {
    own.pose.x += dt_s * r.pose_rate.x;
    own.pose.y += dt_s * r.pose_rate.y;
    own.pose.theta += dt_s * r.pose_rate.theta;
    own.v += dt_s * r.v_rate;
    own.w += dt_s * r.w_rate;
    own.pose_rate = r.pose_rate;
}

#[cfg(test)]
mod tests {
    use super::*;

    const GAINS: EstimatorGains = EstimatorGains { k: [1.0; 3], ka: [20.0; 2], kb: [5.0; 2] };

    fn state(x: f64, y: f64, th: f64, v: f64, w: f64) -> LeaderState {
        LeaderState { pose: Pose::new(x, y, th), pose_rate: Pose::default(), v, w }
    }

    #[test]
    fn error_contracts_at_rate_k_for_a_static_leader() {
        // A chain leader → 1 → 2: H δ̇ = −k H δ, so every error decays as e^(−k t).
        let leader = state(1.0, -2.0, 0.5, 0.7, -0.3);
        let mut a = state(0.0, 0.0, 0.0, 0.0, 0.0);
        let mut b = state(3.0, 3.0, -2.0, 1.0, 1.0);
        let dt = 1e-3;
        let err = |s: &LeaderState| (s.pose.x - 1.0).hypot(s.pose.y + 2.0);
        let (a0, b0) = (err(&a), err(&b));
        for _ in 0..2000 {
            let ra = rates(&GAINS, &a, Some(&leader), [&b]);
            let rb = rates(&GAINS, &b, None, [&a]);
            advance(&mut a, &ra, dt);
            advance(&mut b, &rb, dt);
        }
        // After 2 s, e^(−2) ≈ 0.135 of the start; allow the one-step delay of Ṗ_jr.
        assert!(err(&a) < 0.15 * a0, "follower 1: {} of {}", err(&a), a0);
        assert!(err(&b) < 0.15 * b0, "follower 2: {} of {}", err(&b), b0);
        assert!((a.v - 0.7).abs() < 1e-6 && (b.v - 0.7).abs() < 1e-6, "v: {} {}", a.v, b.v);
        assert!((a.w + 0.3).abs() < 1e-6 && (b.w + 0.3).abs() < 1e-6, "ω: {} {}", a.w, b.w);
    }

    #[test]
    fn heading_differences_are_wrapped() {
        // 3.1 and −3.1 rad are 0.083 rad apart, not 6.2.
        let leader = state(0.0, 0.0, -3.1, 0.0, 0.0);
        let own = state(0.0, 0.0, 3.1, 0.0, 0.0);
        let r = rates(&GAINS, &own, Some(&leader), []);
        let expected = -wrap(3.1 - -3.1);
        assert!((r.pose_rate.theta - expected).abs() < 1e-12, "{}", r.pose_rate.theta);
        assert!(r.pose_rate.theta.abs() < 0.1);
    }

    #[test]
    fn with_no_source_the_estimate_dead_reckons() {
        let mut own = state(1.0, 2.0, 0.0, 0.5, 0.1);
        own.pose_rate = Pose::new(0.5, 0.0, 0.1);
        let r = rates(&GAINS, &own, None, []);
        assert_eq!(r.sources, 0);
        assert_eq!(r.pose_rate, own.pose_rate);
        assert_eq!((r.v_rate, r.w_rate), (0.0, 0.0));
    }

    #[test]
    fn xi_counts_the_sources() {
        let own = state(0.0, 0.0, 0.0, 0.0, 0.0);
        let n = state(2.0, 0.0, 0.0, 0.0, 0.0);
        let one = rates(&GAINS, &own, None, [&n]);
        let two = rates(&GAINS, &own, None, [&n, &n]);
        // (−k·Σ(P_i − P_j)) / ξ: the same pull whether one or two agree.
        assert_eq!(one.sources, 1);
        assert_eq!(two.sources, 2);
        assert_eq!(one.pose_rate.x, 2.0);
        assert_eq!(two.pose_rate.x, 2.0);
    }
}
