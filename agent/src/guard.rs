//! Between the kinematic controller and the robot (docs/model.md §16): the
//! base's speed limits (eq. G1) and the safety filter, a decentralised
//! safety barrier certificate that keeps robots apart and inside an arena
//! (eq. G2–G5, Wang, Ames and Egerstedt 2017, as the Robotarium runs it).
//!
//! Pure and allocation-free: the filter is a quadratic program in two
//! variables with at most [`MAX_CONSTRAINTS`] constraints, solved exactly by
//! enumerating its active sets (the unconstrained point, each constraint's
//! projection, each pair's vertex) on fixed-size arrays.

use serde::{Deserialize, Serialize};

use formation_plant::{Pose, Velocity};

/// The base's limits (`[robot] v_max`, `w_max`): |v| ≤ v_max m/s, |ω| ≤ w_max rad/s.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Limits {
    pub v_max: f64,
    pub w_max: f64,
}

impl Limits {
    /// Eq. G1a: each channel clipped to its limit (the controller's demand).
    #[inline]
    pub fn clip(&self, c: Velocity) -> Velocity {
        Velocity::new(c.v.clamp(-self.v_max, self.v_max), c.w.clamp(-self.w_max, self.w_max))
    }

    /// Eq. G1b: both channels scaled by one factor s ∈ (0, 1] so that both
    /// are within their limits. A filtered command keeps its direction in the
    /// plane, so a command that met every barrier constraint still does
    /// (each constraint's bound is ≥ 0 while the robots are apart).
    #[inline]
    pub fn scale(&self, c: Velocity) -> Velocity {
        let s = (self.v_max / c.v.abs()).min(self.w_max / c.w.abs()).min(1.0);
        Velocity::new(c.v * s, c.w * s)
    }

    #[inline]
    pub fn within(&self, c: Velocity) -> bool {
        c.v.abs() <= self.v_max && c.w.abs() <= self.w_max
    }
}

/// `[safety]` with `filter = true`, validated.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SafetyParams {
    /// The closest two robots' centres may come, m (`safety.distance`).
    pub distance: f64,
    /// γ of eq. G3 (`safety.gamma`, the Robotarium's 100).
    pub gamma: f64,
    /// l, how far ahead of the axle the filtered point lies, m (`safety.projection`).
    pub projection: f64,
    /// Robots whose points are farther than this are left out, m (`safety.radius`).
    pub radius: f64,
    /// [x_min, x_max, y_min, y_max], m (`safety.arena`), or none.
    pub arena: Option<[f64; 4]>,
}

impl SafetyParams {
    /// r of eq. G3: the barrier's radius between the two projected points,
    /// `distance` + 2 l, so that the centres (each within l of its point)
    /// stay at least `distance` apart whenever the points keep r.
    #[inline]
    pub fn barrier_radius(&self) -> f64 {
        self.distance + 2.0 * self.projection
    }

    /// Eq. G2: the point l ahead of the axle.
    #[inline]
    pub fn point(&self, p: &Pose) -> [f64; 2] {
        let (s, c) = p.theta.sin_cos();
        [p.x + self.projection * c, p.y + self.projection * s]
    }
}

/// What sits between the controller and the robot: limits, filter, both or
/// neither (the paper's scenario).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Guard {
    pub limits: Option<Limits>,
    pub safety: Option<SafetyParams>,
}

impl Guard {
    pub fn is_off(&self) -> bool {
        self.limits.is_none() && self.safety.is_none()
    }
}

/// The other robots' poses as this follower knows them at step k (the
/// simulator and lock-step agents: each one's pose of step k − 1; real
/// time: the newest heard), by scenario index; `own` is this follower's
/// index, skipped. `stale`, by the same index (empty: none), marks a pose
/// not heard for longer than the scenario's silence time-out: a robot whose
/// last known point is within `safety.radius` and stale stops this one
/// (docs/model.md §16).
#[derive(Clone, Copy, Debug)]
pub struct Nearby<'a> {
    pub poses: &'a [Pose],
    pub own: usize,
    pub stale: &'a [bool],
}

impl<'a> Nearby<'a> {
    /// No other robot known.
    pub const NONE: Nearby<'static> = Nearby { poses: &[], own: 0, stale: &[] };

    /// Every pose fresh (the simulator, lock-step).
    pub fn fresh(poses: &'a [Pose], own: usize) -> Self {
        Self { poses, own, stale: &[] }
    }
}

/// Most other robots one filter takes (the nearest, when more are within
/// `radius`): with the arena's four, [`MAX_CONSTRAINTS`].
pub const MAX_NEARBY: usize = 12;
/// Most constraints of one robot's program.
pub const MAX_CONSTRAINTS: usize = MAX_NEARBY + 4;

/// What the guard did to one step's command (16 bytes: it rides in every
/// telemetry sample of a guarded run, and in the simulator's step).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GuardStep {
    /// ‖u − û‖ of eq. G4, m/s: how far the filter moved the point's velocity
    /// (0 when the command was already safe or the filter is off).
    pub change: f64,
    /// A limit clipped the controller's command (eq. G1a).
    pub saturated: bool,
    /// The program had no solution (the robots were already closer than the
    /// barrier's radius, or a robot was outside the arena): the robot was stopped.
    pub infeasible: bool,
    /// A robot within `radius` had a stale pose: the robot was stopped.
    pub blind: bool,
}

/// A step's guard counts, summed over a run (the run's safety figures).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GuardTally {
    pub steps: u64,
    /// Steps at which a limit clipped the command.
    pub saturated: u64,
    /// Steps at which the filter changed the command.
    pub filtered: u64,
    /// The largest change, m/s (‖u − û‖), and their sum.
    pub change_max: f64,
    pub change_sum: f64,
    /// Steps whose program had no solution (the robot stopped).
    pub infeasible: u64,
    /// Steps stopped because a robot within `radius` had a stale pose.
    #[serde(default)]
    pub blind: u64,
}

impl GuardTally {
    #[inline]
    pub fn add(&mut self, g: &GuardStep) {
        self.steps += 1;
        self.saturated += u64::from(g.saturated);
        self.filtered += u64::from(g.change > 0.0);
        self.change_max = self.change_max.max(g.change);
        self.change_sum += g.change;
        self.infeasible += u64::from(g.infeasible);
        self.blind += u64::from(g.blind);
    }
}

/// The command the robot gets at step k from the controller's command, the
/// robot's pose and the others' (docs/model.md §16's order): clip to the
/// limits (G1a); filter (G2–G5); scale into the limits (G1b).
pub fn apply(guard: &Guard, requested: Velocity, pose: &Pose, nearby: Nearby<'_>) -> (Velocity, GuardStep) {
    let mut step = GuardStep::default();
    let mut command = requested;
    if let Some(l) = &guard.limits {
        command = l.clip(requested);
        step.saturated = command != requested;
    }
    if let Some(s) = &guard.safety {
        if blind(s, pose, nearby) {
            step.blind = true;
            return (Velocity::default(), step);
        }
        let (filtered, change, feasible) = filter(s, command, pose, nearby);
        command = filtered;
        step.change = change;
        step.infeasible = !feasible;
        if let Some(l) = &guard.limits {
            command = l.scale(command);
        }
    }
    (command, step)
}

/// Whether a robot whose last known point is within `radius` of this one's
/// has a stale pose (the real-time rule of docs/model.md §16: stop).
fn blind(s: &SafetyParams, pose: &Pose, nearby: Nearby<'_>) -> bool {
    if !nearby.stale.contains(&true) {
        return false;
    }
    let p = s.point(pose);
    nearby.poses.iter().zip(nearby.stale).enumerate().any(|(j, (other, &stale))| {
        let q = s.point(other);
        let d2 = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2);
        stale && j != nearby.own && d2 <= s.radius * s.radius
    })
}

/// Eq. G2–G5 for one robot: the unicycle command (v, ω) as the velocity u of
/// the point l ahead (G2), the barrier constraints of every other robot
/// within `radius` and of the arena (G3), the closest u to û that meets them
/// all (G4), and back to (v, ω) (G5). Returns the command, ‖u − û‖ and
/// whether the program was feasible (if not: a stop, (0, 0)).
pub fn filter(s: &SafetyParams, command: Velocity, pose: &Pose, nearby: Nearby<'_>) -> (Velocity, f64, bool) {
    let (sin, cos) = pose.theta.sin_cos();
    let l = s.projection;
    let p = [pose.x + l * cos, pose.y + l * sin];
    // G2: u = R(θ) diag(1, l) (v, ω).
    let want = [cos * command.v - l * sin * command.w, sin * command.v + l * cos * command.w];
    let mut program = Program::default();
    let r2 = s.barrier_radius() * s.barrier_radius();
    // The nearest MAX_NEARBY within `radius`, by squared distance.
    let mut near = [(f64::INFINITY, [0.0; 2]); MAX_NEARBY];
    for (j, other) in nearby.poses.iter().enumerate() {
        if j == nearby.own {
            continue;
        }
        let q = s.point(other);
        let d = [p[0] - q[0], p[1] - q[1]];
        let d2 = d[0] * d[0] + d[1] * d[1];
        if d2 > s.radius * s.radius || !d2.is_finite() {
            continue;
        }
        // Insert in order, dropping the farthest.
        let mut at = MAX_NEARBY;
        while at > 0 && near[at - 1].0 > d2 {
            at -= 1;
        }
        if at < MAX_NEARBY {
            near.copy_within(at..MAX_NEARBY - 1, at + 1);
            near[at] = (d2, d);
        }
    }
    for &(d2, d) in near.iter().take_while(|n| n.0.is_finite()) {
        // G3, this robot's half: −2 (p_i − p_j)ᵀ u_i ≤ ½ γ h³, h = ‖p_i − p_j‖² − r².
        let h = d2 - r2;
        program.push([-2.0 * d[0], -2.0 * d[1]], 0.5 * s.gamma * h * h * h);
    }
    if let Some([x0, x1, y0, y1]) = s.arena {
        // G3 at the walls: ±e_x,yᵀ u ≤ 0.4 γ (wall distance − r/2)³.
        let half = s.barrier_radius() / 2.0;
        let wall = |gap: f64| 0.4 * s.gamma * gap * gap * gap;
        program.push([1.0, 0.0], wall(x1 - half - p[0]));
        program.push([-1.0, 0.0], wall(p[0] - x0 - half));
        program.push([0.0, 1.0], wall(y1 - half - p[1]));
        program.push([0.0, -1.0], wall(p[1] - y0 - half));
    }
    let Some(u) = program.closest(want) else {
        return (Velocity::default(), (want[0] * want[0] + want[1] * want[1]).sqrt(), false);
    };
    let change = ((u[0] - want[0]).powi(2) + (u[1] - want[1]).powi(2)).sqrt();
    if change == 0.0 {
        // The command was safe: passed on untouched (no round trip through G5).
        return (command, 0.0, true);
    }
    // G5: (v, ω) = diag(1, 1/l) R(θ)ᵀ u.
    (Velocity::new(cos * u[0] + sin * u[1], (-sin * u[0] + cos * u[1]) / l), change, true)
}

/// Eq. G4: min ‖u − û‖² subject to aᵢᵀ u ≤ bᵢ, u ∈ ℝ².
#[derive(Clone, Copy, Debug)]
struct Program {
    a: [[f64; 2]; MAX_CONSTRAINTS],
    b: [f64; MAX_CONSTRAINTS],
    n: usize,
}

impl Default for Program {
    fn default() -> Self {
        Self { a: [[0.0; 2]; MAX_CONSTRAINTS], b: [0.0; MAX_CONSTRAINTS], n: 0 }
    }
}

impl Program {
    fn push(&mut self, a: [f64; 2], b: f64) {
        if self.n < MAX_CONSTRAINTS {
            self.a[self.n] = a;
            self.b[self.n] = b;
            self.n += 1;
        }
    }

    fn feasible(&self, u: [f64; 2]) -> bool {
        (0..self.n).all(|i| {
            let (a, b) = (self.a[i], self.b[i]);
            let slack = 1e-9 * (1.0 + b.abs() + (a[0] * u[0]).abs() + (a[1] * u[1]).abs());
            a[0] * u[0] + a[1] * u[1] <= b + slack
        })
    }

    /// The feasible point closest to `want`, or none. The optimum of a
    /// strictly convex program in the plane is the unconstrained point, the
    /// projection onto one constraint's line, or the vertex of two: every
    /// candidate is tried and the closest feasible one kept (exact, no
    /// iteration; at most 1 + n + n(n−1)/2 candidates).
    fn closest(&self, want: [f64; 2]) -> Option<[f64; 2]> {
        if self.feasible(want) {
            return Some(want);
        }
        let mut best: Option<([f64; 2], f64)> = None;
        let mut consider = |u: [f64; 2]| {
            let d = (u[0] - want[0]).powi(2) + (u[1] - want[1]).powi(2);
            if u[0].is_finite() && u[1].is_finite() && best.is_none_or(|(_, e)| d < e) && self.feasible(u) {
                best = Some((u, d));
            }
        };
        for i in 0..self.n {
            let (a, b) = (self.a[i], self.b[i]);
            let aa = a[0] * a[0] + a[1] * a[1];
            let over = a[0] * want[0] + a[1] * want[1] - b;
            if aa > 0.0 && over > 0.0 {
                consider([want[0] - over / aa * a[0], want[1] - over / aa * a[1]]);
            }
        }
        for i in 0..self.n {
            for j in i + 1..self.n {
                let (a, c) = (self.a[i], self.a[j]);
                let det = a[0] * c[1] - a[1] * c[0];
                let scale = (a[0].hypot(a[1]) * c[0].hypot(c[1])).max(f64::MIN_POSITIVE);
                if det.abs() <= 1e-12 * scale {
                    continue;
                }
                let (bi, bj) = (self.b[i], self.b[j]);
                consider([(bi * c[1] - a[1] * bj) / det, (a[0] * bj - c[0] * bi) / det]);
            }
        }
        best.map(|(u, _)| u)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_guard_step_is_small_enough_to_ride_in_every_sample() {
        assert_eq!(std::mem::size_of::<GuardStep>(), 16);
        assert_eq!(std::mem::size_of::<Option<GuardStep>>(), 16, "the Option takes a bool's niche");
    }

    const SAFETY: SafetyParams =
        SafetyParams { distance: 0.3, gamma: 100.0, projection: 0.05, radius: 2.0, arena: None };

    #[test]
    fn limits_clip_each_channel_and_scale_both() {
        let l = Limits { v_max: 0.22, w_max: 2.84 };
        assert_eq!(l.clip(Velocity::new(4.0, -5.0)), Velocity::new(0.22, -2.84));
        assert_eq!(l.clip(Velocity::new(0.1, 1.0)), Velocity::new(0.1, 1.0));
        let s = l.scale(Velocity::new(0.44, 1.0));
        assert!((s.v - 0.22).abs() < 1e-15 && (s.w - 0.5).abs() < 1e-15, "{s:?}");
        assert!(l.within(l.scale(Velocity::new(-3.0, 9.0))));
        assert_eq!(l.scale(Velocity::default()), Velocity::default());
    }

    #[test]
    fn a_safe_command_passes_untouched() {
        let me = Pose::new(0.0, 0.0, 0.0);
        let far = [me, Pose::new(1.5, 0.0, 0.0)];
        let c = Velocity::new(0.2, 0.3);
        let (out, change, ok) = filter(&SAFETY, c, &me, Nearby::fresh(&far, 0));
        assert_eq!((out, change, ok), (c, 0.0, true));
        // Outside the radius: not considered at all, however it moves.
        let beyond = [me, Pose::new(2.5, 0.0, 0.0)];
        assert_eq!(filter(&SAFETY, Velocity::new(10.0, 0.0), &me, Nearby::fresh(&beyond, 0)).0.v, 10.0);
    }

    #[test]
    fn head_on_the_filter_slows_the_robot_to_what_the_barrier_allows() {
        // Another robot 0.5 m ahead, facing us: its point is 0.4 m from ours.
        let me = Pose::new(0.0, 0.0, 0.0);
        let poses = [me, Pose::new(0.5, 0.0, std::f64::consts::PI)];
        let (out, change, ok) = filter(&SAFETY, Velocity::new(0.2, 0.0), &me, Nearby::fresh(&poses, 0));
        assert!(ok);
        // −2 (−0.4) u_x ≤ ½ γ h³, h = 0.16 − 0.16 = 0 at r = 0.4: u_x ≤ 0.
        assert!(out.v <= 1e-12 && change > 0.19, "{out:?}, change {change}");
        // Moving away is never restricted.
        let (back, change, _) = filter(&SAFETY, Velocity::new(-0.2, 0.0), &me, Nearby::fresh(&poses, 0));
        assert_eq!((back.v, change), (-0.2, 0.0));
    }

    /// Two robots driving straight at each other, each filtering with the
    /// other's pose of the step before: their centres never come closer
    /// than `distance`.
    #[test]
    fn two_robots_head_on_stay_apart() {
        let dt = 0.01;
        let mut poses = [Pose::new(-1.0, 0.0, 0.0), Pose::new(1.0, 0.01, std::f64::consts::PI)];
        let mut closest = f64::INFINITY;
        for _ in 0..2000 {
            let before = poses;
            for (i, p) in poses.iter_mut().enumerate() {
                let (c, _, ok) = filter(&SAFETY, Velocity::new(0.22, 0.0), p, Nearby::fresh(&before, i));
                assert!(ok);
                p.advance(c, p.theta.sin_cos(), dt);
            }
            closest = closest.min((poses[0].x - poses[1].x).hypot(poses[0].y - poses[1].y));
        }
        assert!(closest >= SAFETY.distance, "closest {closest}");
    }

    #[test]
    fn the_arena_keeps_a_robot_in() {
        let s = SafetyParams { arena: Some([-1.0, 1.0, -1.0, 1.0]), ..SAFETY };
        let mut p = Pose::new(0.0, 0.0, 0.3);
        for _ in 0..3000 {
            let (c, _, ok) = filter(&s, Velocity::new(0.22, 0.0), &p, Nearby::NONE);
            assert!(ok);
            p.advance(c, p.theta.sin_cos(), 0.01);
            assert!(p.x.abs() < 1.0 && p.y.abs() < 1.0, "{p:?}");
        }
    }

    #[test]
    fn the_program_picks_the_vertex_when_two_constraints_bind() {
        let mut q = Program::default();
        q.push([1.0, 0.0], 0.0);
        q.push([0.0, 1.0], 0.0);
        assert_eq!(q.closest([1.0, 1.0]), Some([0.0, 0.0]));
        assert_eq!(q.closest([1.0, -1.0]), Some([0.0, -1.0]));
        q.push([-1.0, 0.0], -1.0); // x ≥ 1 and x ≤ 0: empty
        assert_eq!(q.closest([1.0, 1.0]), None);
    }

    #[test]
    fn the_guard_clips_filters_and_scales_in_that_order() {
        let g = Guard { limits: Some(Limits { v_max: 0.22, w_max: 2.84 }), safety: Some(SAFETY) };
        let me = Pose::new(0.0, 0.0, 0.0);
        let (c, step) = apply(&g, Velocity::new(4.0, 0.0), &me, Nearby::fresh(&[me], 0));
        assert_eq!(c, Velocity::new(0.22, 0.0));
        assert!(step.saturated && step.change == 0.0 && !step.infeasible);
        let off = apply(&Guard::default(), Velocity::new(4.0, 9.0), &me, Nearby::NONE);
        assert_eq!(off.0, Velocity::new(4.0, 9.0));
    }

    #[test]
    fn a_stale_pose_within_the_radius_stops_the_robot_and_one_beyond_it_does_not() {
        let g = Guard { limits: None, safety: Some(SAFETY) };
        let me = Pose::new(0.0, 0.0, 0.0);
        let near = Pose::new(SAFETY.radius * 0.5, 0.0, 0.0);
        let far = Pose::new(SAFETY.radius * 3.0, 0.0, 0.0);
        let go = Velocity::new(0.1, 0.0);
        let poses = [me, near, far];
        let (c, step) = apply(&g, go, &me, Nearby { poses: &poses, own: 0, stale: &[false, true, false] });
        assert_eq!((c, step.blind), (Velocity::default(), true), "a stale robot at {} m", near.x);
        let (c, step) = apply(&g, go, &me, Nearby { poses: &poses, own: 0, stale: &[false, false, true] });
        assert!(!step.blind && c.v > 0.0, "a stale robot at {} m, beyond the radius, stopped it: {c:?}", far.x);
        let (_, step) = apply(&g, go, &me, Nearby { poses: &poses, own: 0, stale: &[true, false, false] });
        assert!(!step.blind, "its own entry is not another robot");
        let mut tally = GuardTally::default();
        tally.add(&GuardStep { blind: true, ..GuardStep::default() });
        assert_eq!(tally.blind, 1);
    }
}
