//! Small shared pieces: saturation, sign and the shunting
//! model of bioinspired neural dynamics (eq. 34).

use serde::{Deserialize, Serialize};

/// sat(e) = clamp(e, −1, 1) (docs/model.md §1).
pub fn sat(e: f64) -> f64 {
    e.clamp(-1.0, 1.0)
}

/// sign(e) with sign(0) = 0, as sliding-mode laws use it.
pub fn sign(e: f64) -> f64 {
    if e > 0.0 {
        1.0
    } else if e < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// The shunting model of eq. 34:
/// V̇ = −A V + (B − V) f(u) − (D + V) g(u), f(u) = max(u, 0), g(u) = max(−u, 0).
/// Its state stays in [−D, B] whatever the input.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Shunting {
    /// A, the passive decay rate.
    pub a: f64,
    /// B, the upper bound of the state.
    pub b: f64,
    /// D, the lower bound of the state is −D.
    pub d: f64,
}

impl Shunting {
    /// V̇ of eq. 34.
    pub fn rate(&self, v: f64, u: f64) -> f64 {
        let f = u.max(0.0);
        let g = (-u).max(0.0);
        -self.a * v + (self.b - v) * f - (self.d + v) * g
    }

    /// V(k+1) from V(k) and the input at k.
    ///
    /// Forward Euler (docs/model.md §9) is used whenever it keeps the bound, that is
    /// when Δt (A + |u|) ≤ 1 (it is then a convex combination of V and the
    /// equilibrium V∞). Beyond that, Euler would overshoot [−D, B] (a huge
    /// input in one step), so the step takes the exact solution for an input
    /// held over the step, V∞ + (V − V∞) e^(−(A+|u|)Δt), which never leaves
    /// the bound. The final clamp only absorbs rounding.
    pub fn advance(&self, v: f64, u: f64, dt_s: f64) -> f64 {
        let gain = self.a + u.abs();
        let next = if dt_s * gain <= 1.0 {
            v + dt_s * self.rate(v, u)
        } else {
            let target = (self.b * u.max(0.0) - self.d * (-u).max(0.0)) / gain;
            target + (v - target) * (-gain * dt_s).exp()
        };
        next.clamp(-self.d, self.b)
    }
}

/// The first step k with k Δt ≥ t, decided on step indices: the 1e-9
/// absorbs rounding of a quotient that is whole on paper (0.3 / 0.1 =
/// 2.9999999999999996 is step 3).
pub fn step_at(t_s: f64, dt_s: f64) -> u64 {
    (t_s / dt_s - 1e-9).ceil().max(0.0) as u64
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_plant::wrap;
    use proptest::prelude::*;
    use std::f64::consts::PI;

    #[test]
    fn wrap_maps_into_half_open_interval() {
        assert_eq!(wrap(PI), -PI);
        assert_eq!(wrap(-PI), -PI);
        assert!((wrap(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
        assert!((wrap(-7.0 * PI / 2.0) - PI / 2.0).abs() < 1e-12);
        assert_eq!(wrap(0.25), 0.25);
    }

    proptest! {
        #[test]
        fn wrap_is_in_range_and_congruent(a in -1e6f64..1e6) {
            let w = wrap(a);
            prop_assert!((-PI..PI).contains(&w));
            let turns = (a - w) / (2.0 * PI);
            prop_assert!((turns - turns.round()).abs() < 1e-6);
        }

        #[test]
        fn shunting_state_stays_in_bounds(
            a in 0.1f64..50.0, b in 0.1f64..20.0, d in 0.1f64..20.0,
            inputs in proptest::collection::vec(prop_oneof![-1e12f64..1e12, -10f64..10.0], 1..200),
            dt in prop_oneof![Just(1e-3), 1e-4f64..1.0],
        ) {
            let s = Shunting { a, b, d };
            let mut v = 0.0;
            for u in inputs {
                v = s.advance(v, u, dt);
                prop_assert!(v >= -d && v <= b, "V = {v} outside [-{d}, {b}] after u = {u}");
            }
        }
    }

    #[test]
    fn shunting_settles_at_its_equilibrium() {
        // Constant input u > 0: V∞ = B u / (A + u) (eq. 34 with V̇ = 0).
        let s = Shunting { a: 4.0, b: 2.0, d: 2.0 };
        let mut v = 0.0;
        for _ in 0..20_000 {
            v = s.advance(v, 5.0, 1e-3);
        }
        assert!((v - 2.0 * 5.0 / 9.0).abs() < 1e-9, "V = {v}");
        for _ in 0..20_000 {
            v = s.advance(v, -5.0, 1e-3);
        }
        assert!((v + 2.0 * 5.0 / 9.0).abs() < 1e-9, "V = {v}");
    }

    #[test]
    fn shunting_uses_forward_euler_in_the_normal_regime() {
        let s = Shunting { a: 4.0, b: 6.0, d: 6.0 };
        let (v, u, dt) = (0.3, -0.7, 1e-3);
        assert_eq!(s.advance(v, u, dt), v + dt * s.rate(v, u));
    }
}
