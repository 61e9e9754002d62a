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
    /// Deadlocks found and resolved by a sidestep to the right (eq. G6,
    /// `safety.deadlock_after`), or not looked for.
    #[serde(default)]
    pub deadlock: Option<crate::deadlock::DeadlockRule>,
    /// m the barrier's radius adds for the base's lag (eq. G3d,
    /// `safety.lag_margin`): `robot.lag` × the point's top speed; 0 without.
    #[serde(default)]
    pub lag_margin: f64,
}

impl SafetyParams {
    /// r of eq. G3: the barrier's radius between the two projected points,
    /// `distance` + 2 l, so that the centres (each within l of its point)
    /// stay at least `distance` apart whenever the points keep r; plus the
    /// lag's margin where asked for (eq. G3d).
    #[inline]
    pub fn barrier_radius(&self) -> f64 {
        self.distance + 2.0 * self.projection + self.lag_margin
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

/// How this follower knows another robot at step k (docs/model.md §16).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub enum Seen {
    /// Heard in time and running a filter of its own: each of the two
    /// takes half of the pair's barrier (eq. G3).
    #[default]
    Live,
    /// Not running (absent, left the run, taken for gone): standing at its
    /// pose; this robot takes the whole barrier (eq. G3b).
    Still,
    /// Not heard for `age_s`, longer than the silence time-out: somewhere
    /// within v_max × `age_s` of its last pose, that bound still `growing`
    /// until the robot is taken for gone (eq. G3c).
    Stale { age_s: f64, growing: bool },
}

/// The other robots' poses as this follower knows them at step k (the
/// simulator and lock-step agents: each one's pose of step k − 1; real
/// time: the newest heard), by scenario index; `own` is this follower's
/// index, skipped. `seen`, by the same index (empty: every robot
/// [`Seen::Live`]), says how each is known. `lost`: this follower has heard
/// no other robot for longer than the time after which a silent robot is
/// taken for gone, and stops (docs/model.md §16).
#[derive(Clone, Copy, Debug)]
pub struct Nearby<'a> {
    pub poses: &'a [Pose],
    pub own: usize,
    pub seen: &'a [Seen],
    pub lost: bool,
}

impl<'a> Nearby<'a> {
    /// No other robot known.
    pub const NONE: Nearby<'static> = Nearby { poses: &[], own: 0, seen: &[], lost: false };

    /// Every other robot live, its pose exact (the simulator, lock-step).
    pub fn fresh(poses: &'a [Pose], own: usize) -> Self {
        Self { poses, own, seen: &[], lost: false }
    }

    fn seen(&self, j: usize) -> Seen {
        self.seen.get(j).copied().unwrap_or_default()
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
    /// The robot was stopped for want of others' poses: it was lost, a
    /// stale robot of unbounded speed was within `radius`, or a stale
    /// robot's bound reached it (docs/model.md §16).
    pub blind: bool,
    /// A deadlock was found at this step (eq. G6a): the robot had been held
    /// short of its slot for `safety.deadlock_after`; a sidestep follows.
    pub deadlock: bool,
    /// This step's command was the controller's turned to the right (eq.
    /// G6b, a sidestep under way).
    pub sidestep: bool,
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
    /// Steps stopped for want of others' poses ([`GuardStep::blind`]).
    #[serde(default)]
    pub blind: u64,
    /// Deadlocks found (eq. G6a) and steps spent sidestepping (G6b).
    #[serde(default)]
    pub deadlocks: u64,
    #[serde(default)]
    pub sidestep: u64,
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
        self.deadlocks += u64::from(g.deadlock);
        self.sidestep += u64::from(g.sidestep);
    }

    /// Another tally added to this one (the largest change the largest):
    /// a run's figures from its followers'.
    pub fn merge(&mut self, t: &GuardTally) {
        self.steps += t.steps;
        self.saturated += t.saturated;
        self.filtered += t.filtered;
        self.change_max = self.change_max.max(t.change_max);
        self.change_sum += t.change_sum;
        self.infeasible += t.infeasible;
        self.blind += t.blind;
        self.deadlocks += t.deadlocks;
        self.sidestep += t.sidestep;
    }
}

/// The command the robot gets at step k from the controller's command, the
/// robot's pose and the others' (docs/model.md §16's order): clip to the
/// limits (G1a); filter (G2–G5); scale into the limits (G1b). Stopped, and
/// counted `blind`: a lost follower; a stale robot within `radius` when the
/// robots' speed has no bound (no `robot.v_max`); a stale robot's bound
/// that this robot cannot outrun within its limits.
pub fn apply(guard: &Guard, requested: Velocity, pose: &Pose, nearby: Nearby<'_>) -> (Velocity, GuardStep) {
    let mut step = GuardStep::default();
    let mut command = requested;
    if let Some(l) = &guard.limits {
        command = l.clip(requested);
        step.saturated = command != requested;
    }
    if let Some(s) = &guard.safety {
        let speed = guard.limits.map(|l| l.v_max);
        if nearby.lost || (speed.is_none() && stale_within_radius(s, pose, nearby)) {
            step.blind = true;
            return (Velocity::default(), step);
        }
        let f = filter(s, speed, command, pose, nearby);
        command = f.command;
        step.change = f.change;
        step.infeasible = !f.feasible;
        if let Some(l) = &guard.limits {
            let scaled = l.scale(command);
            if f.retreating && scaled != command {
                step.blind = true;
                return (Velocity::default(), step);
            }
            command = scaled;
        }
    }
    (command, step)
}

/// Whether a robot whose last known point is within `radius` of this one's
/// is stale: without a speed bound it may be anywhere near (stop).
fn stale_within_radius(s: &SafetyParams, pose: &Pose, nearby: Nearby<'_>) -> bool {
    let p = s.point(pose);
    nearby.poses.iter().enumerate().any(|(j, other)| {
        let q = s.point(other);
        let d2 = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2);
        j != nearby.own && matches!(nearby.seen(j), Seen::Stale { .. }) && d2 <= s.radius * s.radius
    })
}

/// What [`filter`] made of one command.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Filtered {
    pub command: Velocity,
    /// ‖u − û‖, m/s.
    pub change: f64,
    /// Whether (G4) had a solution (if not: a stop, (0, 0)).
    pub feasible: bool,
    /// A stale robot's bound is closing in: (G3c) asks this robot to move
    /// away, which scaling into the limits (G1b) may undo.
    pub retreating: bool,
}

/// Eq. G2–G5 for one robot: the unicycle command (v, ω) as the velocity u of
/// the point l ahead (G2), the barrier constraints of every other robot
/// that may be within `radius` and of the arena (G3), the closest u to û
/// that meets them all (G4), and back to (v, ω) (G5). `speed` bounds how
/// fast a stale robot may have moved (`robot.v_max`; none: stale robots
/// are left to [`apply`]'s stop).
pub fn filter(s: &SafetyParams, speed: Option<f64>, command: Velocity, pose: &Pose, nearby: Nearby<'_>) -> Filtered {
    let (sin, cos) = pose.theta.sin_cos();
    let l = s.projection;
    let p = [pose.x + l * cos, pose.y + l * sin];
    let want = g2(sin, cos, l, command);
    let mut program = Program::default();
    let r = s.barrier_radius();
    let r2 = r * r;
    // The nearest MAX_NEARBY that may be within `radius` (a stale robot's
    // point by its bound), by how close they may be.
    let mut near = [Near { key: f64::INFINITY, d: [0.0; 2], d2: 0.0, seen: Seen::Live }; MAX_NEARBY];
    for (j, other) in nearby.poses.iter().enumerate() {
        if j == nearby.own {
            continue;
        }
        let seen = nearby.seen(j);
        let reach = match (seen, speed) {
            (Seen::Stale { age_s, .. }, Some(v)) => v * age_s,
            (Seen::Stale { .. }, None) => continue,
            _ => 0.0,
        };
        let q = s.point(other);
        let d = [p[0] - q[0], p[1] - q[1]];
        let d2 = d[0] * d[0] + d[1] * d[1];
        // (A live or still robot's key is d² itself, as it always was.)
        let key = match reach {
            0.0 => d2,
            _ => (d2.sqrt() - reach).max(0.0).powi(2),
        };
        if key > s.radius * s.radius || !key.is_finite() {
            continue;
        }
        // Insert in order, dropping the farthest.
        let mut at = MAX_NEARBY;
        while at > 0 && near[at - 1].key > key {
            at -= 1;
        }
        if at < MAX_NEARBY {
            near.copy_within(at..MAX_NEARBY - 1, at + 1);
            near[at] = Near { key, d, d2, seen };
        }
    }
    let mut retreating = false;
    for n in near.iter().take_while(|n| n.key.is_finite()) {
        let (d, d2) = (n.d, n.d2);
        let a = [-2.0 * d[0], -2.0 * d[1]];
        match n.seen {
            // G3, this robot's half: −2 (p_i − p_j)ᵀ u_i ≤ ½ γ h³, h = ‖p_i − p_j‖² − r².
            Seen::Live => {
                let h = d2 - r2;
                program.push(a, 0.5 * s.gamma * h * h * h);
            }
            // G3b, all of it: the other robot does not move.
            Seen::Still => {
                let h = d2 - r2;
                program.push(a, s.gamma * h * h * h);
            }
            // G3c, all of it, the radius ρ = r + v_max age growing at v_max:
            // −2 (p_i − q_j)ᵀ u_i ≤ γ h³ − 2 ρ ρ̇, h = ‖p_i − q_j‖² − ρ².
            Seen::Stale { age_s, growing } => {
                let v = speed.unwrap_or(0.0);
                let rho = r + v * age_s;
                let rate = if growing { v } else { 0.0 };
                let h = d2 - rho * rho;
                let b = s.gamma * h * h * h - 2.0 * rho * rate;
                retreating |= b < 0.0;
                program.push(a, b);
            }
        }
    }
    if let Some([x0, x1, y0, y1]) = s.arena {
        // G3 at the walls: ±e_x,yᵀ u ≤ 0.4 γ (wall distance − r/2)³.
        let half = r / 2.0;
        let wall = |gap: f64| 0.4 * s.gamma * gap * gap * gap;
        program.push([1.0, 0.0], wall(x1 - half - p[0]));
        program.push([-1.0, 0.0], wall(p[0] - x0 - half));
        program.push([0.0, 1.0], wall(y1 - half - p[1]));
        program.push([0.0, -1.0], wall(p[1] - y0 - half));
    }
    let Some(u) = program.closest(want) else {
        let change = (want[0] * want[0] + want[1] * want[1]).sqrt();
        return Filtered { command: Velocity::default(), change, feasible: false, retreating };
    };
    let change = ((u[0] - want[0]).powi(2) + (u[1] - want[1]).powi(2)).sqrt();
    if change == 0.0 {
        // The command was safe: passed on untouched (no round trip through G5).
        return Filtered { command, change: 0.0, feasible: true, retreating };
    }
    let command = g5(sin, cos, l, u);
    Filtered { command, change, feasible: true, retreating }
}

/// Eq. G2: the velocity u of the point l ahead of the axle for (v, ω).
#[inline]
pub fn point_velocity(s: &SafetyParams, pose: &Pose, c: Velocity) -> [f64; 2] {
    let (sin, cos) = pose.theta.sin_cos();
    g2(sin, cos, s.projection, c)
}

/// Eq. G5: the command (v, ω) that moves the point l ahead of the axle at u.
#[inline]
pub fn from_point_velocity(s: &SafetyParams, pose: &Pose, u: [f64; 2]) -> Velocity {
    let (sin, cos) = pose.theta.sin_cos();
    g5(sin, cos, s.projection, u)
}

/// G2: u = R(θ) diag(1, l) (v, ω), with (sin θ, cos θ).
#[inline]
fn g2(sin: f64, cos: f64, l: f64, c: Velocity) -> [f64; 2] {
    [cos * c.v - l * sin * c.w, sin * c.v + l * cos * c.w]
}

/// G5: (v, ω) = diag(1, 1/l) R(θ)ᵀ u, with (sin θ, cos θ).
#[inline]
fn g5(sin: f64, cos: f64, l: f64, u: [f64; 2]) -> Velocity {
    Velocity::new(cos * u[0] + sin * u[1], (-sin * u[0] + cos * u[1]) / l)
}

/// Where the other robots within `radius` lie, seen from this robot's
/// point (eq. G6c): Σ (q_j − p) / ‖q_j − p‖², the nearer weighing more;
/// each by its last known pose.
pub fn crowd(s: &SafetyParams, pose: &Pose, nearby: Nearby<'_>) -> [f64; 2] {
    let p = s.point(pose);
    let mut sum = [0.0; 2];
    for (j, other) in nearby.poses.iter().enumerate() {
        let q = s.point(other);
        let d = [q[0] - p[0], q[1] - p[1]];
        let d2 = d[0] * d[0] + d[1] * d[1];
        if j != nearby.own && d2 > 0.0 && d2 <= s.radius * s.radius {
            sum = [sum[0] + d[0] / d2, sum[1] + d[1] / d2];
        }
    }
    sum
}

/// One other robot in [`filter`]'s program: how close it may be (squared,
/// the sort key), p_i − q_j, its square, and how it is known.
#[derive(Clone, Copy, Debug)]
struct Near {
    key: f64,
    d: [f64; 2],
    d2: f64,
    seen: Seen,
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

    const SAFETY: SafetyParams = SafetyParams {
        distance: 0.3,
        gamma: 100.0,
        projection: 0.05,
        radius: 2.0,
        arena: None,
        deadlock: None,
        lag_margin: 0.0,
    };

    /// [`filter`] without a speed bound, as (command, change, feasible).
    fn f3(s: &SafetyParams, c: Velocity, pose: &Pose, nearby: Nearby<'_>) -> (Velocity, f64, bool) {
        let f = filter(s, None, c, pose, nearby);
        (f.command, f.change, f.feasible)
    }

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
        let (out, change, ok) = f3(&SAFETY, c, &me, Nearby::fresh(&far, 0));
        assert_eq!((out, change, ok), (c, 0.0, true));
        // Outside the radius: not considered at all, however it moves.
        let beyond = [me, Pose::new(2.5, 0.0, 0.0)];
        assert_eq!(f3(&SAFETY, Velocity::new(10.0, 0.0), &me, Nearby::fresh(&beyond, 0)).0.v, 10.0);
    }

    #[test]
    fn head_on_the_filter_slows_the_robot_to_what_the_barrier_allows() {
        // Another robot 0.5 m ahead, facing us: its point is 0.4 m from ours.
        let me = Pose::new(0.0, 0.0, 0.0);
        let poses = [me, Pose::new(0.5, 0.0, std::f64::consts::PI)];
        let (out, change, ok) = f3(&SAFETY, Velocity::new(0.2, 0.0), &me, Nearby::fresh(&poses, 0));
        assert!(ok);
        // −2 (−0.4) u_x ≤ ½ γ h³, h = 0.16 − 0.16 = 0 at r = 0.4: u_x ≤ 0.
        assert!(out.v <= 1e-12 && change > 0.19, "{out:?}, change {change}");
        // Moving away is never restricted.
        let (back, change, _) = f3(&SAFETY, Velocity::new(-0.2, 0.0), &me, Nearby::fresh(&poses, 0));
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
                let (c, _, ok) = f3(&SAFETY, Velocity::new(0.22, 0.0), p, Nearby::fresh(&before, i));
                assert!(ok);
                p.advance(c, p.theta.sin_cos(), dt);
            }
            closest = closest.min((poses[0].x - poses[1].x).hypot(poses[0].y - poses[1].y));
        }
        assert!(closest >= SAFETY.distance, "closest {closest}");
        // Apart and past each other: two robots that stopped would pass the line above.
        assert!(poses[0].x > 0.5 && poses[1].x < -0.5, "not past each other after 20 s: {poses:?}");
    }

    #[test]
    fn the_arena_keeps_a_robot_in() {
        let s = SafetyParams { arena: Some([-1.0, 1.0, -1.0, 1.0]), ..SAFETY };
        let mut p = Pose::new(0.0, 0.0, 0.3);
        for _ in 0..3000 {
            let (c, _, ok) = f3(&s, Velocity::new(0.22, 0.0), &p, Nearby::NONE);
            assert!(ok);
            p.advance(c, p.theta.sin_cos(), 0.01);
            assert!(p.x.abs() < 1.0 && p.y.abs() < 1.0, "{p:?}");
        }
    }

    /// An interior-point solution made exact on its active set (the
    /// constraints it meets within 1e-5), as solvers' polishing does: of the
    /// wish, its projections onto each active line and the vertices of each
    /// active pair, the feasible one closest to the wish.
    fn polish(q: &Program, want: [f64; 2], x: [f64; 2]) -> [f64; 2] {
        let active: Vec<usize> = (0..q.n)
            .filter(|&i| (q.a[i][0] * x[0] + q.a[i][1] * x[1] - q.b[i]).abs() <= 1e-5 * (1.0 + q.b[i].abs()))
            .collect();
        let mut candidates = vec![want];
        for (k, &i) in active.iter().enumerate() {
            let a = q.a[i];
            let over = (a[0] * want[0] + a[1] * want[1] - q.b[i]) / (a[0] * a[0] + a[1] * a[1]);
            candidates.push([want[0] - over * a[0], want[1] - over * a[1]]);
            for &j in &active[k + 1..] {
                let c = q.a[j];
                let det = a[0] * c[1] - a[1] * c[0];
                if det.abs() > 1e-12 {
                    let (bi, bj) = (q.b[i], q.b[j]);
                    candidates.push([(bi * c[1] - a[1] * bj) / det, (a[0] * bj - c[0] * bi) / det]);
                }
            }
        }
        let d = |u: &[f64; 2]| (u[0] - want[0]).hypot(u[1] - want[1]);
        candidates.into_iter().filter(|u| q.feasible(*u)).min_by(|u, v| d(u).total_cmp(&d(v))).unwrap_or(x)
    }

    /// Whether u is optimal for the program by the KKT conditions: feasible,
    /// and û − u a non-negative combination of the normals of at most two
    /// constraints it meets (1e-9).
    fn kkt(q: &Program, want: [f64; 2], u: [f64; 2]) -> bool {
        let g = [want[0] - u[0], want[1] - u[1]];
        let active: Vec<usize> = (0..q.n)
            .filter(|&i| (q.a[i][0] * u[0] + q.a[i][1] * u[1] - q.b[i]).abs() <= 1e-9 * (1.0 + q.b[i].abs()))
            .collect();
        if !q.feasible(u) {
            return false;
        }
        if g[0].hypot(g[1]) <= 1e-12 {
            return true;
        }
        let on = |i: usize, l: f64| l >= -1e-12 && (g[0] - l * q.a[i][0]).hypot(g[1] - l * q.a[i][1]) <= 1e-9;
        active.iter().any(|&i| on(i, (g[0] * q.a[i][0] + g[1] * q.a[i][1]) / (q.a[i][0].powi(2) + q.a[i][1].powi(2))))
            || active.iter().enumerate().any(|(k, &i)| {
                active[k + 1..].iter().any(|&j| {
                    let (a, c) = (q.a[i], q.a[j]);
                    let det = a[0] * c[1] - a[1] * c[0];
                    let (li, lj) = ((g[0] * c[1] - c[0] * g[1]) / det, (a[0] * g[1] - g[0] * a[1]) / det);
                    det.abs() > 1e-12 && li >= -1e-12 && lj >= -1e-12
                })
            })
    }

    /// Eq. G4's exact program against a general conic solver (clarabel,
    /// an interior-point method) on 100,000 random programs of 1 to
    /// [`MAX_CONSTRAINTS`] constraints, feasible or not: the same point
    /// (within 1e-5 of clarabel's own, and within 1e-9 of it made exact on
    /// the constraints clarabel found active), or both without a solution;
    /// otherwise the instance is named.
    #[test]
    fn the_exact_program_agrees_with_a_general_solver_on_random_instances() {
        use clarabel::algebra::CscMatrix;
        use clarabel::solver::{
            DefaultSettingsBuilder, DefaultSolver, IPSolver, SolverStatus, SupportedConeT::NonnegativeConeT,
        };
        use rand_chacha::rand_core::{RngCore, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(65);
        let mut unit = move || (rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        let settings = DefaultSettingsBuilder::default()
            .verbose(false)
            .tol_gap_abs(1e-11)
            .tol_gap_rel(1e-11)
            .tol_feas(1e-11)
            .max_iter(200)
            .build()
            .expect("settings");
        let p = CscMatrix::new(2, 2, vec![0, 1, 2], vec![0, 1], vec![1.0, 1.0]);
        let (mut solved, mut empty, mut undecided, mut worst) = (0, 0, 0, 0.0_f64);
        for instance in 0..100_000 {
            let n = 1 + (unit() * MAX_CONSTRAINTS as f64) as usize % MAX_CONSTRAINTS;
            let mut q = Program::default();
            for _ in 0..n {
                let a = [4.0 * unit() - 2.0, 4.0 * unit() - 2.0];
                q.push(a, 1.5 * unit() - 0.3);
            }
            let want = [2.0 * unit() - 1.0, 2.0 * unit() - 1.0];
            let ours = q.closest(want);
            // min ½‖u‖² − ûᵀu subject to A u + s = b, s ≥ 0.
            let (mut rows, mut cols, mut vals) = (Vec::new(), Vec::new(), Vec::new());
            for i in 0..n {
                for c in 0..2 {
                    rows.push(i);
                    cols.push(c);
                    vals.push(q.a[i][c]);
                }
            }
            let a = CscMatrix::new_from_triplets(n, 2, rows, cols, vals);
            let cones = [NonnegativeConeT(n)];
            let solve = |settings: &clarabel::solver::DefaultSettings<f64>| {
                let mut solver = DefaultSolver::new(&p, &[-want[0], -want[1]], &a, &q.b[..n], &cones, settings.clone())
                    .expect("a well-formed program");
                solver.solve();
                (solver.solution.status, [solver.solution.x[0], solver.solution.x[1]])
            };
            let (mut status, mut x) = solve(&settings);
            if !matches!(status, SolverStatus::Solved | SolverStatus::PrimalInfeasible) {
                // Tight tolerances can stall on a nearly empty set: again at the defaults.
                (status, x) = solve(&DefaultSettingsBuilder::default().verbose(false).build().expect("defaults"));
            }
            let named = || format!("instance {instance}: want {want:?}, a {:?}, b {:?}", &q.a[..n], &q.b[..n]);
            match (ours, status) {
                (Some(u), SolverStatus::Solved | SolverStatus::AlmostSolved) => {
                    let raw = (u[0] - x[0]).hypot(u[1] - x[1]);
                    assert!(raw <= 1e-5, "{}: ours {u:?}, clarabel {x:?} ({raw:.2e} apart)", named());
                    let exact = polish(&q, want, x);
                    let off = (u[0] - exact[0]).hypot(u[1] - exact[1]);
                    assert!(
                        off <= 1e-9,
                        "{}: ours {u:?}, clarabel's {x:?}, on its active set exactly {exact:?} ({off:.2e} apart)",
                        named()
                    );
                    worst = worst.max(off);
                    solved += 1;
                }
                (None, SolverStatus::PrimalInfeasible | SolverStatus::AlmostPrimalInfeasible) => empty += 1,
                (Some(u), SolverStatus::MaxIterations | SolverStatus::InsufficientProgress) => {
                    // Clarabel undecided (a set a few 1e-9 wide): ours must
                    // then be optimal by its own conditions (KKT).
                    assert!(kkt(&q, want, u), "{}: clarabel {status:?}, ours {u:?} not optimal", named());
                    undecided += 1;
                }
                (ours, status) => panic!("{}: ours {ours:?}, clarabel {status:?} at {x:?}", named()),
            }
        }
        assert!(solved > 10_000 && empty > 10_000, "{solved} solved, {empty} without a solution: too few of one");
        assert!(undecided <= 100, "clarabel undecided on {undecided} programs");
        eprintln!(
            "exact program vs clarabel: {solved} solved alike (at most {worst:.1e} apart), {empty} empty alike, \
             {undecided} undecided by clarabel and optimal by KKT"
        );
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

    /// With another robot near, so that the filter acts: the guard's
    /// command is scale(filter(clip(c))), and each other order gives
    /// another command here (so a guard that changed the order fails).
    #[test]
    fn the_guard_clips_filters_and_scales_in_that_order() {
        let l = LIMITS;
        let g = Guard { limits: Some(l), safety: Some(SAFETY) };
        let me = Pose::new(0.0, 0.0, 0.0);
        // 0.46 m ahead, facing us: the filter turns the robot faster than w_max.
        let poses = [me, Pose::new(0.46, 0.01, std::f64::consts::PI)];
        let near = Nearby::fresh(&poses, 0);
        let asked = Velocity::new(0.5, -4.0);
        let (c, step) = apply(&g, asked, &me, near);
        let filtered = |v: Velocity| filter(&SAFETY, Some(l.v_max), v, &me, near).command;
        let expected = l.scale(filtered(l.clip(asked)));
        assert_eq!(c, expected);
        assert!(step.saturated && step.change > 0.0 && !step.infeasible, "{step:?}");
        assert!(l.within(c), "{c:?}");
        let others = [
            ("filter, clip", l.clip(filtered(asked))),
            ("filter, scale", l.scale(filtered(asked))),
            ("clip, filter", filtered(l.clip(asked))),
            ("clip, scale, filter", filtered(l.scale(l.clip(asked)))),
        ];
        for (order, other) in others {
            assert_ne!(other, expected, "{order} gives the same command: this case does not tell the orders apart");
        }
        let off = apply(&Guard::default(), Velocity::new(4.0, 9.0), &me, Nearby::NONE);
        assert_eq!(off.0, Velocity::new(4.0, 9.0));
    }

    #[test]
    fn without_a_speed_bound_a_stale_pose_within_the_radius_stops_the_robot_and_one_beyond_it_does_not() {
        let g = Guard { limits: None, safety: Some(SAFETY) };
        let me = Pose::new(0.0, 0.0, 0.0);
        let near = Pose::new(SAFETY.radius * 0.5, 0.0, 0.0);
        let far = Pose::new(SAFETY.radius * 3.0, 0.0, 0.0);
        let go = Velocity::new(0.1, 0.0);
        let poses = [me, near, far];
        let stale = Seen::Stale { age_s: 9.0, growing: true };
        let at = |seen: &[Seen]| apply(&g, go, &me, Nearby { poses: &poses, own: 0, seen, lost: false });
        let (c, step) = at(&[Seen::Live, stale, Seen::Live]);
        assert_eq!((c, step.blind), (Velocity::default(), true), "a stale robot at {} m", near.x);
        let (c, step) = at(&[Seen::Live, Seen::Live, stale]);
        assert!(!step.blind && c.v > 0.0, "a stale robot at {} m, beyond the radius, stopped it: {c:?}", far.x);
        let (_, step) = at(&[stale, Seen::Live, Seen::Live]);
        assert!(!step.blind, "its own entry is not another robot");
        let mut tally = GuardTally::default();
        tally.add(&GuardStep { blind: true, ..GuardStep::default() });
        assert_eq!(tally.blind, 1);
    }

    const LIMITS: Limits = Limits { v_max: 0.22, w_max: 2.84 };

    /// With `robot.v_max`, a robot not heard for `age` may be anywhere within
    /// v_max × age of its last pose: one beyond `radius` by less than that
    /// is in the program; one that may not be within it is not.
    #[test]
    fn a_stale_robot_counts_wherever_its_bound_may_have_brought_it() {
        let me = Pose::new(0.0, 0.0, 0.0);
        let poses = [me, Pose::new(SAFETY.radius + 0.6, 0.0, 0.0)];
        let fast = Velocity::new(30.0, 0.0);
        let run = |seen: Seen| {
            filter(
                &SAFETY,
                Some(LIMITS.v_max),
                fast,
                &me,
                Nearby { poses: &poses, own: 0, seen: &[Seen::Live, seen], lost: false },
            )
        };
        assert_eq!(run(Seen::Live).change, 0.0, "a live robot beyond the radius is left out");
        assert_eq!(
            run(Seen::Stale { age_s: 1.0, growing: true }).change,
            0.0,
            "0.22 m of reach does not bring it within"
        );
        let closing = run(Seen::Stale { age_s: 9.0, growing: true });
        assert!(closing.change > 0.0 && closing.command.v < fast.v, "1.98 m of reach: {closing:?}");
        let held = run(Seen::Stale { age_s: 9.0, growing: false });
        assert!(
            held.command.v > closing.command.v,
            "a bound no longer growing allows more: {held:?} against {closing:?}"
        );
    }

    /// A robot driving at one that stopped answering (and in truth stands
    /// where it was last heard) keeps outside its bound, distance + v_max ×
    /// age from that pose, for as long as it can outrun it; then it stops
    /// (blind) and never comes closer to the silent robot than `distance`.
    #[test]
    fn a_robot_keeps_outside_a_stale_robots_growing_bound_and_stops_when_it_cannot_outrun_it() {
        let g = Guard { limits: Some(LIMITS), safety: Some(SAFETY) };
        let silent = Pose::new(1.5, 0.0, std::f64::consts::PI);
        let mut me = Pose::new(0.0, 0.0, 0.0);
        let dt = 0.01;
        let (mut first_blind, mut closest) = (None, f64::INFINITY);
        for k in 0..1000 {
            let age_s = k as f64 * dt;
            let poses = [me, silent];
            let seen = [Seen::Live, Seen::Stale { age_s, growing: true }];
            let (c, step) =
                apply(&g, Velocity::new(0.22, 0.0), &me, Nearby { poses: &poses, own: 0, seen: &seen, lost: false });
            assert!(LIMITS.within(c), "step {k}: {c:?} beyond the limits");
            let gap = (me.x - silent.x).hypot(me.y - silent.y);
            closest = closest.min(gap);
            if step.blind {
                assert_eq!(c, Velocity::default());
                first_blind.get_or_insert((k, gap));
            } else if first_blind.is_none() {
                let bound = SAFETY.distance + LIMITS.v_max * age_s;
                assert!(
                    gap >= bound - 1e-3,
                    "step {k}: {gap:.4} m from the silent robot's last pose, its bound {bound:.4} m"
                );
            }
            me.advance(c, me.theta.sin_cos(), dt);
        }
        let (k, gap) = first_blind.expect("the bound, growing at v_max, overtook a robot that cannot reverse faster");
        assert!(k > 100, "stopped at step {k} ({gap:.3} m): it should first have kept ahead of the bound");
        assert!(closest >= SAFETY.distance, "came {closest:.4} m from the silent robot");
    }

    /// A robot that is not running (absent, left, gone) is an obstacle at
    /// its pose: this robot takes the whole barrier (G3b), so it may come
    /// closer than to a live robot, which takes half, never closer than
    /// `distance`, and it gets past (the command drives straight on).
    #[test]
    fn a_still_robot_takes_the_whole_barrier_and_is_never_reached() {
        let g = Guard { limits: Some(LIMITS), safety: Some(SAFETY) };
        let other = Pose::new(1.0, 0.02, std::f64::consts::PI);
        let approach = |seen: Seen| {
            let (mut me, mut closest) = (Pose::new(0.0, 0.0, 0.0), f64::INFINITY);
            for _ in 0..3000 {
                let poses = [me, other];
                let nearby = Nearby { poses: &poses, own: 0, seen: &[Seen::Live, seen], lost: false };
                let (c, _) = apply(&g, Velocity::new(0.22, 0.0), &me, nearby);
                me.advance(c, me.theta.sin_cos(), 0.01);
                closest = closest.min((me.x - other.x).hypot(me.y - other.y));
            }
            (closest, me.x)
        };
        let ((still, x_still), (live, _)) = (approach(Seen::Still), approach(Seen::Live));
        assert!(still >= SAFETY.distance && live >= SAFETY.distance, "closest: still {still:.4} m, live {live:.4} m");
        assert!(still < live, "against a still robot it may use the whole margin: {still:.4} m, live {live:.4} m");
        assert!(x_still > other.x + 1.0, "it did not get past the still robot: x = {x_still:.3} m after 30 s");
    }

    #[test]
    fn a_lost_follower_stops() {
        let g = Guard { limits: Some(LIMITS), safety: Some(SAFETY) };
        let me = Pose::new(0.0, 0.0, 0.0);
        let (c, step) = apply(&g, Velocity::new(0.2, 0.1), &me, Nearby { poses: &[me], own: 0, seen: &[], lost: true });
        assert_eq!((c, step.blind), (Velocity::default(), true));
    }
}
