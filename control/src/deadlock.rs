//! Deadlocks of the safety filter found and resolved (docs/model.md §16,
//! eq. G6): robots that the barriers hold still short of their slots, as
//! two robots meeting head-on or four crossing through one point do
//! (Grover, Liu and Sycara 2016: such equilibria of the filtered
//! dynamics exist wherever the robots' wishes are symmetric).
//!
//! Every robot applies the same rule, on what it alone knows (whether the
//! filter changed its command, and its distance to its slot): held for
//! `after_steps` steps without getting closer, it turns its controller's wish to the right by
//! `angle_rad` for `sidestep_steps` steps, as drivers keep right (the
//! Crazyflie's collision avoidance sidesteps the same way). The
//! turned wish still goes through the filter, so the rule never breaks
//! the safety distance. Pure and allocation-free.

use serde::{Deserialize, Serialize};

/// Held means: the filter took away at least this share of the point's
/// speed the controller asked for (‖u − û‖ ≥ share × ‖û‖, eq. G6a).
pub const HELD_CUT: f64 = 0.5;

/// A robot whose slot comes less than this share of `safety.distance`
/// closer while the filter holds it for `deadlock_after` is in a deadlock
/// (eq. G6a).
pub const PROGRESS_SHARE: f64 = 0.2;

/// `[safety] deadlock_after`, `sidestep`, `sidestep_angle`, in steps.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeadlockRule {
    /// Steps held before a deadlock is declared.
    pub after_steps: u64,
    /// Steps the turned wish lasts.
    pub sidestep_steps: u64,
    /// How far the wish turns to the right, rad.
    pub angle_rad: f64,
}

/// One follower's count of held steps and of the sidestep it is in.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DeadlockState {
    /// Consecutive steps at which the filter changed the command while the
    /// robot was farther from its slot than the safety distance.
    held: u64,
    /// The distance to the slot when that run of steps began, m.
    from_m: f64,
    sidestep_left: u64,
}

impl DeadlockState {
    /// Step k's wish before the guard (eq. G6b): the controller's
    /// command; during a sidestep, the point moving at the wish's speed
    /// (`want`, the point's velocity for the command) in the direction of
    /// `crowd` ([`crate::guard::crowd`]) turned right by `angle_rad`:
    /// sideways, the others passed on the left. The point's velocity to
    /// filter, or None: the controller's command as it is.
    #[inline]
    pub fn wish(&self, rule: &DeadlockRule, want: [f64; 2], crowd: [f64; 2]) -> Option<[f64; 2]> {
        let norm = crowd[0].hypot(crowd[1]);
        if self.sidestep_left == 0 || norm == 0.0 || !norm.is_finite() {
            return None;
        }
        let speed = want[0].hypot(want[1]);
        let (s, c) = rule.angle_rad.sin_cos();
        let d = [crowd[0] / norm, crowd[1] / norm];
        // R(−φ) d: the crowd's direction turned clockwise.
        Some([speed * (c * d[0] + s * d[1]), speed * (-s * d[0] + c * d[1])])
    }

    /// A sidestep is under way.
    pub fn sidestepping(&self) -> bool {
        self.sidestep_left > 0
    }

    /// After the guard at step k (eq. G6a): `to_slot_m` is the robot's
    /// distance to its slot, `distance` the safety distance, `cut` the
    /// share of the asked point velocity relative to the slot's the filter
    /// took away (‖u − û‖ / ‖û − ṡ‖, ṡ the slot's velocity, Ṗ_r: two
    /// robots held side by side while they move level with their slots are
    /// held too),
    /// `stopped` whether the guard stopped the robot for another reason (no
    /// safe command, stale poses), which no sidestep can help. The robot is
    /// held while it is farther from its slot than `distance` and the
    /// filter takes at least [`HELD_CUT`] of its wish at every step; held for `after_steps` with its slot less than
    /// [`PROGRESS_SHARE`] × `distance` closer, it is in a deadlock, and a
    /// sidestep starts at step k + 1 (the return value: one found).
    #[inline]
    pub fn after(&mut self, rule: &DeadlockRule, to_slot_m: f64, distance: f64, cut: f64, stopped: bool) -> bool {
        if self.sidestep_left > 0 {
            self.sidestep_left -= 1;
            return false;
        }
        if !(cut >= HELD_CUT && !stopped && to_slot_m > distance) {
            self.held = 0;
            return false;
        }
        if self.held == 0 {
            self.from_m = to_slot_m;
        }
        self.held += 1;
        if self.held < rule.after_steps {
            return false;
        }
        self.held = 0;
        if self.from_m - to_slot_m >= PROGRESS_SHARE * distance {
            return false; // it was getting there: watch the next stretch
        }
        self.sidestep_left = rule.sidestep_steps;
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const RULE: DeadlockRule =
        DeadlockRule { after_steps: 3, sidestep_steps: 2, angle_rad: std::f64::consts::FRAC_PI_2 };

    #[test]
    fn held_for_the_stated_steps_is_a_deadlock_then_the_point_steps_right_for_the_sidestep() {
        let (want, ahead) = ([0.2, 0.0], [4.0, 0.0]);
        let mut s = DeadlockState::default();
        assert_eq!(s.wish(&RULE, want, ahead), None, "no sidestep before a deadlock");
        let found: Vec<bool> = (0..3).map(|_| s.after(&RULE, 1.0, 0.25, 0.9, false)).collect();
        assert_eq!(found, [false, false, true], "found at the third held step");
        for _ in 0..2 {
            // Another robot dead ahead (+x): the point goes right (−y) at the wish's speed.
            let u = s.wish(&RULE, want, ahead).expect("sidestepping");
            assert!(u[0].abs() < 1e-15 && (u[1] + 0.2).abs() < 1e-15, "{u:?}");
            assert!(!s.after(&RULE, 1.0, 0.25, 0.9, false), "no deadlock counted within a sidestep");
        }
        assert_eq!(s.wish(&RULE, want, ahead), None, "the sidestep lasts 2 steps");
        let again: Vec<bool> = (0..3).map(|_| s.after(&RULE, 1.0, 0.25, 0.9, false)).collect();
        assert_eq!(again, [false, false, true], "held again after it: another one");
    }

    #[test]
    fn robots_that_meet_head_on_or_cross_at_one_point_all_step_the_same_way_round() {
        let mut s = DeadlockState::default();
        for _ in 0..3 {
            s.after(&RULE, 1.0, 0.25, 0.9, false);
        }
        // Two robots head-on along x: one goes to −y, the other to +y.
        let a = s.wish(&RULE, [0.2, 0.0], [1.0, 0.0]).unwrap();
        let b = s.wish(&RULE, [-0.2, 0.0], [-1.0, 0.0]).unwrap();
        assert!(a[1] < -0.19 && b[1] > 0.19, "{a:?} {b:?}");
        // Four robots crossing at the origin from (±1, ±1): each steps
        // right, so all go counterclockwise round the centre, as at a
        // roundabout where traffic keeps right (position × step > 0).
        for p in [[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]] {
            let to_centre = [-p[0], -p[1]];
            let u = s.wish(&RULE, [0.1 * to_centre[0], 0.1 * to_centre[1]], to_centre).unwrap();
            assert!(p[0] * u[1] - p[1] * u[0] > 0.0, "from {p:?}: {u:?}");
        }
        // Alone (nobody near): no sidestep.
        assert_eq!(s.wish(&RULE, [0.2, 0.0], [0.0, 0.0]), None);
    }

    #[test]
    fn progress_near_the_slot_or_a_stop_for_another_reason_is_no_deadlock() {
        for (label, to_slot, cut, stopped) in [
            ("getting closer by 0.06 m per stretch", [1.0, 0.98, 0.94], 0.9, false),
            ("within the safety distance of its slot", [0.2, 0.2, 0.2], 0.9, false),
            ("the filter took less than half the wish", [1.0, 1.0, 1.0], 0.49, false),
            ("no safe command, or stale poses", [1.0, 1.0, 1.0], 1.0, true),
        ] {
            let mut s = DeadlockState::default();
            let mut found = 0;
            for stretch in 0..4 {
                for &d in &to_slot {
                    found += u32::from(s.after(&RULE, d - 0.05 * stretch as f64, 0.25, cut, stopped));
                }
            }
            assert_eq!(found, 0, "{label}: a deadlock was found");
        }
        // A step at which the filter takes less starts the count again.
        let mut s = DeadlockState::default();
        s.after(&RULE, 1.0, 0.25, 0.9, false);
        s.after(&RULE, 1.0, 0.25, 0.9, false);
        s.after(&RULE, 1.0, 0.25, 0.4, false);
        assert!(!s.after(&RULE, 1.0, 0.25, 0.9, false) && !s.after(&RULE, 1.0, 0.25, 0.9, false));
        assert!(s.after(&RULE, 1.0, 0.25, 0.9, false));
    }
}
