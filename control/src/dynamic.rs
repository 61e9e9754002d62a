//! Dynamic (torque) controllers (docs/model.md §7): bioinspired sliding mode
//! (eq. 37–43), conventional sliding mode and super-twisting (the baselines).
//! Each returns the demanded accelerations (a_v, a_ω); the torque mapping
//! that realises them is [`formation_plant::RobotParams::acceleration_to_torque`].

use serde::{Deserialize, Serialize};

use crate::math::{sign, Shunting};

/// Which dynamic controller a follower runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DynamicKind {
    /// Bioinspired sliding mode: a = v̇_c + C V_s, V_s a shunting state driven
    /// by the velocity error (eq. 39–43).
    Bio,
    /// Conventional sliding mode: a = v̇_c + C sign(e_η).
    Smc,
    /// Second-order sliding mode, decided here as the super-twisting
    /// algorithm: a = v̇_c + k_1 |e|^½ sign(e) + w, ẇ = k_2 sign(e).
    SuperTwisting,
}

/// C_a, C_b, the two shunting models and the super-twisting gains (docs/model.md §10).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DynamicGains {
    pub ca: f64,
    pub cb: f64,
    /// (A_1, B_1, D_1), driven by e_η1.
    pub shunting_v: Shunting,
    /// (A_2, B_2, D_2), driven by e_η2.
    pub shunting_w: Shunting,
    /// Super-twisting k_1.
    pub k1: f64,
    /// Super-twisting k_2.
    pub k2: f64,
}

/// The controller's own states: V_s1, V_s2 (bioinspired) and w_1, w_2
/// (super-twisting). Unused ones stay at zero.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DynamicState {
    pub vs: [f64; 2],
    pub w: [f64; 2],
}

impl DynamicState {
    pub fn is_finite(&self) -> bool {
        self.vs.iter().chain(&self.w).all(|x| x.is_finite())
    }
}

/// The demanded accelerations (a_v, a_ω) at step k from the state at k,
/// the velocity errors e_η = (v_c − v̂, ω_c − ω̂) and the command rates
/// (v̇_c, ω̇_c):
///
/// - bioinspired (eq. 42–43): a_v = v̇_c + C_a V_s1, a_ω = ω̇_c + C_b V_s2;
/// - conventional: a_v = v̇_c + C_a sign(e_η1), a_ω = ω̇_c + C_b sign(e_η2);
/// - super-twisting: a = v̇_c + k_1 |e_η|^½ sign(e_η) + w.
pub fn accelerations(
    kind: DynamicKind,
    g: &DynamicGains,
    s: &DynamicState,
    e_eta: [f64; 2],
    rate: [f64; 2],
) -> [f64; 2] {
    let c = [g.ca, g.cb];
    std::array::from_fn(|i| {
        rate[i]
            + match kind {
                DynamicKind::Bio => c[i] * s.vs[i],
                DynamicKind::Smc => c[i] * sign(e_eta[i]),
                DynamicKind::SuperTwisting => g.k1 * e_eta[i].abs().sqrt() * sign(e_eta[i]) + s.w[i],
            }
    })
}

/// Advances the controller's state from k to k+1 with the errors at k:
/// the shunting models of eq. 40–41 (V_s1 by e_η1, V_s2 by e_η2; the paper
/// drops the V of −A V there, a typo) or ẇ = k_2 sign(e_η).
pub fn advance(kind: DynamicKind, g: &DynamicGains, s: &mut DynamicState, e_eta: [f64; 2], dt_s: f64) {
    match kind {
        DynamicKind::Bio => {
            s.vs[0] = g.shunting_v.advance(s.vs[0], e_eta[0], dt_s);
            s.vs[1] = g.shunting_w.advance(s.vs[1], e_eta[1], dt_s);
        }
        DynamicKind::SuperTwisting => {
            for (w, e) in s.w.iter_mut().zip(e_eta) {
                *w += dt_s * g.k2 * sign(e);
            }
        }
        DynamicKind::Smc => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const G: DynamicGains = DynamicGains {
        ca: 3.0,
        cb: 3.0,
        shunting_v: Shunting { a: 4.0, b: 6.0, d: 6.0 },
        shunting_w: Shunting { a: 4.0, b: 6.0, d: 6.0 },
        k1: 3.0,
        k2: 3.0,
    };

    /// Closes the loop v̇ = a on a velocity error and returns |e| after 3 s.
    fn track(kind: DynamicKind) -> f64 {
        let (mut v, mut s, dt) = ([0.0f64; 2], DynamicState::default(), 1e-3);
        let target = [1.0, -0.5];
        for _ in 0..3000 {
            let e = [target[0] - v[0], target[1] - v[1]];
            let a = accelerations(kind, &G, &s, e, [0.0; 2]);
            advance(kind, &G, &mut s, e, dt);
            v = [v[0] + dt * a[0], v[1] + dt * a[1]];
        }
        (target[0] - v[0]).abs().max((target[1] - v[1]).abs())
    }

    #[test]
    fn every_controller_drives_the_velocity_error_to_zero() {
        for kind in [DynamicKind::Bio, DynamicKind::Smc, DynamicKind::SuperTwisting] {
            let e = track(kind);
            // Sliding modes chatter within a band of about C·Δt around zero.
            assert!(e < 0.02, "{kind:?}: |e| = {e}");
        }
    }

    #[test]
    fn bioinspired_demand_is_bounded_by_c_times_b() {
        let mut s = DynamicState::default();
        for _ in 0..10_000 {
            advance(DynamicKind::Bio, &G, &mut s, [1e9, -1e9], 1e-3);
            let a = accelerations(DynamicKind::Bio, &G, &s, [1e9, -1e9], [0.0; 2]);
            assert!(a[0].abs() <= G.ca * G.shunting_v.b && a[1].abs() <= G.cb * G.shunting_w.d, "{a:?}");
        }
    }
}
