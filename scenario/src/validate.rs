//! A parsed [`ScenarioFile`] checked, field by field, into a [`Scenario`]:
//! every bound, the graph against Lemma 1, the fault table, the safety
//! filter; an error names the field, its line or the `--set` that gave it.

use std::path::Path;
use std::sync::Arc;

use formation_control::{
    ControlParams, DeadlockRule, DynamicGains, EstimatorGains, Fault, FilterParams, Frame, Guard, KinematicGains,
    Limits, RejoinPolicy, RejoinRule, SafetyParams, Shunting,
};
use formation_leader::{LeaderState, Profile, Trajectory};
use formation_plant::{Disturbance, Drive, NoiseCov, Pose, RobotParams, Velocity};

use crate::error::ScenarioError;
use crate::file::{
    LeaderFile, RobotModel, SafetyFile, ScenarioFile, ShapeFile, DEFAULT_CMD_TIMEOUT_S, DEFAULT_LAG_S,
    DEFAULT_LEADER_TIMEOUT_S,
};
use crate::graph::Graph;
use crate::shape::{assign, closest, named, total_cost, MAX_ASSIGNED, SHAPES};

use crate::scenario::*;
use crate::syntax::*;

/// Collects validation failures of one field.
pub(crate) struct Check<'a> {
    label: &'a str,
    source: Option<&'a str>,
    /// What `--set` gave a value: an error about it names the assignment,
    /// never a line of the file the user did not write.
    overridden: &'a [(String, String)],
    /// [`MAX_FOLLOWERS`], or more for a scenario built in code ([`Scenario::from_toml_sized`]).
    most_followers: usize,
}

impl Check<'_> {
    fn fail(&self, field: &str, message: impl Into<String>) -> ScenarioError {
        self.fail_with(field, &[], message)
    }

    /// A failure of `field` that also depends on the `related` fields: if
    /// any of them came from `--set`, the error names that assignment.
    fn fail_with(&self, field: &str, related: &[&str], message: impl Into<String>) -> ScenarioError {
        let message = message.into();
        // Every `--set` among them, in the command line's order: with
        // `--set dt=0.3 --set duration=1` both are the cause.
        let mut given: Vec<&str> =
            std::iter::once(field).chain(related.iter().copied()).filter_map(|f| self.assignment_of(f)).collect();
        let position = |a: &str| self.overridden.iter().position(|(_, b)| b == a);
        given.sort_by_key(|a| position(a));
        given.dedup();
        match given.is_empty() {
            false => {
                ScenarioError::Override { assignment: given.join(" --set "), message: format!("{field}: {message}") }
            }
            true => ScenarioError::Invalid {
                file: self.label.to_string(),
                line: self.source.and_then(|s| find_line(s, field)),
                field: field.to_string(),
                message,
            },
        }
    }

    /// The last `--set` that gave `field` its value (or the table or array
    /// holding it).
    fn assignment_of(&self, field: &str) -> Option<&str> {
        let covers =
            |key: &str| field.strip_prefix(key).is_some_and(|rest| rest.is_empty() || rest.starts_with(['.', '[']));
        self.overridden.iter().rev().find(|(key, _)| covers(key)).map(|(_, a)| a.as_str())
    }

    fn finite(&self, field: &str, values: &[f64]) -> Result<(), ScenarioError> {
        match values.iter().find(|v| !v.is_finite()) {
            Some(v) => Err(self.fail(field, format!("must be a finite number, got {v}"))),
            None => Ok(()),
        }
    }

    /// Finite and at most `limit` in size (a value beyond any robot's, whose
    /// square overflows the metrics: 1e300 m/s ran to an `inf` formation
    /// error with exit status 0).
    fn bounded(&self, field: &str, values: &[f64], limit: f64, unit: &str) -> Result<(), ScenarioError> {
        self.finite(field, values)?;
        match values.iter().find(|v| v.abs() > limit) {
            Some(v) => Err(self.fail(field, format!("{} is beyond ±{} {unit}", num(*v), num(limit)))),
            None => Ok(()),
        }
    }

    fn positive(&self, field: &str, values: &[f64]) -> Result<(), ScenarioError> {
        self.finite(field, values)?;
        match values.iter().find(|&&v| v <= 0.0) {
            Some(v) => Err(self.fail(field, format!("must be positive, got {v}"))),
            None => Ok(()),
        }
    }

    fn non_negative(&self, field: &str, values: &[f64]) -> Result<(), ScenarioError> {
        self.finite(field, values)?;
        match values.iter().find(|&&v| v < 0.0) {
            Some(v) => Err(self.fail(field, format!("must not be negative, got {v}"))),
            None => Ok(()),
        }
    }

    fn shunting(&self, field: &str, s: &Shunting) -> Result<(), ScenarioError> {
        self.non_negative(&format!("{field}.a"), &[s.a])?;
        self.positive(&format!("{field}.b"), &[s.b])?;
        self.positive(&format!("{field}.d"), &[s.d])
    }
}

pub(crate) fn validate(
    file: ScenarioFile,
    label: &str,
    default_name: &str,
    source: Option<&str>,
    overridden: &[(String, String)],
    most_followers: usize,
) -> Result<Scenario, ScenarioError> {
    let c = Check { label, source, overridden, most_followers };
    let name = validate_name(&c, file.name.clone().unwrap_or_else(|| default_name.to_string()))?;
    validate_steps(&c, &file)?;
    let estimate_init = match file.estimate_init.as_str() {
        "leader" => EstimateInit::Leader,
        "zero" => EstimateInit::Zero,
        other => return Err(c.fail("estimate_init", format!("`{other}` is not one of: leader, zero"))),
    };
    let timing = match file.timing.as_str() {
        "lockstep" => Timing::Lockstep,
        "realtime" => Timing::Realtime,
        other => return Err(c.fail("timing", format!("`{other}` is not one of: lockstep, realtime"))),
    };
    let (leader_profile, mut leader_pose) = validate_leader(&c, &file.leader)?;
    let leader_timeout_s = validate_source(&c, &file.leader, leader_profile, timing)?;
    let leader_recording = match leader_profile.trajectory {
        Trajectory::Recorded => read_recording(&c, &file)?,
        _ => Arc::from([]),
    };
    // A recorded leader starts where its record does (followers given by
    // `body_error` are placed against it).
    if let Some(first) = leader_recording.first() {
        leader_pose = first.pose;
    }
    validate_table_sizes(&c, &file)?;
    let followers = validate_followers(&c, &file, leader_pose)?;
    let graph = validate_graph(&c, &file, &followers)?;
    validate_gains(&c, &file)?;
    let fault = validate_fault(&c, &file)?;
    let drive = validate_drive(&c, &file)?;
    let faults = validate_faults(&c, &file, &followers, &graph)?;
    let (network, rejoin) = validate_network(&c, &file)?;
    let ros2 = validate_ros2(&c, &file, drive)?;
    let guard = validate_guard(&c, &file, &followers)?;
    let (frame, shapes) = validate_formation(&c, &file, &followers)?;
    validate_route(&c, &file)?;
    let cmd_timeout_s = file.robot.cmd_timeout.unwrap_or(DEFAULT_CMD_TIMEOUT_S);
    c.positive("robot.cmd_timeout", &[cmd_timeout_s])?;
    let odom_frame = file.ros2.odom_frame.clone().unwrap_or_else(|| DEFAULT_ODOM_FRAME.to_string());
    if odom_frame.trim().is_empty() || odom_frame.len() > 256 {
        return Err(c.fail("ros2.odom_frame", "a frame name of 1 to 256 characters (`{id}` for the follower's id)"));
    }
    let r = &file.robot;
    let robot = RobotParams {
        mass_kg: r.mass,
        inertia_kgm2: r.inertia,
        wheel_radius_m: r.wheel_radius,
        half_axle_m: r.half_axle,
    };
    Ok(Scenario {
        name,
        seed: file.seed,
        dt_s: file.dt,
        duration_s: file.duration,
        noise: file.noise,
        covariance: NoiseCov { q: file.covariance.q, r: file.covariance.r },
        estimate_init,
        timing,
        leader_profile,
        leader_pose,
        leader_route: file.leader.waypoints.clone().into(),
        leader_recording,
        leader_timeout_s,
        followers,
        shapes,
        graph,
        control: Arc::new(ControlParams { guard, frame, ..control_params(&file, robot, fault, rejoin, drive) }),
        robot,
        disturbance: Disturbance { linear_n: file.disturbance.dv, angular_nm: file.disturbance.dw },
        network,
        faults,
        ros2,
        safety_distance: file.safety.as_ref().map(|s| s.distance),
        cmd_timeout_s,
        odom_frame,
        source: file,
    })
}

/// `[robot] v_max`, `w_max` and `[safety]` (docs/model.md §16): limits that
/// are positive and finite; a safety distance the initial poses keep (the
/// pair that does not is named); an arena that holds every initial pose.
pub(crate) fn validate_guard(
    c: &Check<'_>,
    file: &ScenarioFile,
    followers: &[FollowerSpec],
) -> Result<Guard, ScenarioError> {
    let r = &file.robot;
    for (field, value) in [("robot.v_max", r.v_max), ("robot.w_max", r.w_max)] {
        if let Some(v) = value {
            c.positive(field, &[v])?;
        }
    }
    let limits = (r.v_max.is_some() || r.w_max.is_some())
        .then(|| Limits { v_max: r.v_max.unwrap_or(f64::INFINITY), w_max: r.w_max.unwrap_or(f64::INFINITY) });
    let Some(sf) = &file.safety else { return Ok(Guard { limits, safety: None }) };
    c.positive("safety.distance", &[sf.distance])?;
    if let Some((a, b, d)) = closest_pair(followers) {
        if d < sf.distance {
            return Err(c.fail_with(
                "safety.distance",
                &["followers"],
                format!(
                    "followers {} and {} start {} m apart, closer than the safety distance {} m",
                    a,
                    b,
                    num((d * 1e6).round() / 1e6),
                    num(sf.distance)
                ),
            ));
        }
    }
    c.positive("safety.gamma", &[sf.gamma])?;
    c.positive("safety.projection", &[sf.projection])?;
    c.positive("safety.radius", &[sf.radius])?;
    let params = SafetyParams {
        distance: sf.distance,
        gamma: sf.gamma,
        projection: sf.projection,
        radius: sf.radius,
        arena: sf.arena,
        deadlock: validate_deadlock(c, sf, file.dt)?,
        lag_margin: lag_margin(c, file, sf)?,
    };
    if sf.radius <= params.barrier_radius() {
        return Err(c.fail_with(
            "safety.radius",
            &["safety.distance", "safety.projection"],
            format!(
                "{} m must exceed the barrier's radius, distance + 2 × projection = {} m, or no robot is ever seen in time",
                num(sf.radius),
                num(params.barrier_radius())
            ),
        ));
    }
    if let Some(a) = sf.arena {
        c.bounded("safety.arena", &a, MAX_DISTANCE_M, "m")?;
        if a[0] >= a[1] || a[2] >= a[3] {
            return Err(c.fail(
                "safety.arena",
                format!("[x_min, x_max, y_min, y_max] = {a:?}: each min must be below its max"),
            ));
        }
        if let Some(f) =
            followers.iter().find(|f| !(a[0]..=a[1]).contains(&f.pose.x) || !(a[2]..=a[3]).contains(&f.pose.y))
        {
            return Err(c.fail_with(
                "safety.arena",
                &["followers"],
                format!(
                    "follower {} starts at ({}, {}), outside the arena x ∈ [{}, {}], y ∈ [{}, {}]",
                    f.id,
                    num(f.pose.x),
                    num(f.pose.y),
                    num(a[0]),
                    num(a[1]),
                    num(a[2]),
                    num(a[3])
                ),
            ));
        }
    }
    if sf.filter {
        check_filter_start(c, followers, &params)?;
    }
    Ok(Guard { limits, safety: sf.filter.then_some(params) })
}

/// Eq. G3d (docs/model.md §16), with `safety.lag_margin = true`: what the
/// barrier's radius adds for a base that takes a velocity command in time,
/// `robot.lag` × the point's top speed √(v_max² + (w_max l)²). It needs a
/// velocity robot (a torque robot has no lag) and both limits (without
/// them the margin has no bound): refused in one line otherwise.
pub(crate) fn lag_margin(c: &Check<'_>, file: &ScenarioFile, sf: &SafetyFile) -> Result<f64, ScenarioError> {
    let r = &file.robot;
    if !sf.lag_margin {
        return Ok(0.0);
    }
    if r.model != RobotModel::Velocity {
        return Err(c.fail(
            "safety.lag_margin",
            "is for a velocity-commanded robot's lag (robot.model = \"velocity\"); a torque robot has none",
        ));
    }
    let lag_s = r.lag.unwrap_or(DEFAULT_LAG_S);
    let (Some(v), Some(w)) = (r.v_max, r.w_max) else {
        return Err(c.fail(
            "safety.lag_margin",
            format!(
                "robot.lag ({} s) × the point's top speed needs robot.v_max and robot.w_max (without them the \
                 margin has no bound)",
                num(lag_s)
            ),
        ));
    };
    Ok(lag_s * v.hypot(w * sf.projection))
}

/// The filter's own geometry at step 0 (docs/model.md §16): every two
/// robots' points l ahead of the axle at least the barrier's radius r apart,
/// and every point at least r / 2 inside each wall: the set the filter
/// keeps the robots in (its guarantee holds from inside it only). The
/// offending pair or wall is named.
pub(crate) fn check_filter_start(
    c: &Check<'_>,
    followers: &[FollowerSpec],
    s: &SafetyParams,
) -> Result<(), ScenarioError> {
    let r = s.barrier_radius();
    let points: Vec<(u32, [f64; 2])> = followers.iter().map(|f| (f.id, s.point(&f.pose))).collect();
    for (i, (a, p)) in points.iter().enumerate() {
        for (b, q) in &points[i + 1..] {
            let d = (p[0] - q[0]).hypot(p[1] - q[1]);
            if d < r {
                return Err(c.fail_with(
                    "safety.distance",
                    &["followers", "safety.projection"],
                    format!(
                        "followers {a} and {b} start with their filtered points ({} m ahead of the axle) {} m \
                         apart, closer than the barrier's radius, distance + 2 × projection = {} m: they would \
                         start outside the set the filter keeps them in",
                        num(s.projection),
                        num((d * 1e6).round() / 1e6),
                        num(r)
                    ),
                ));
            }
        }
    }
    let Some([x0, x1, y0, y1]) = s.arena else { return Ok(()) };
    for (id, p) in &points {
        let walls = [(p[0] - x0, "x", x0), (x1 - p[0], "x", x1), (p[1] - y0, "y", y0), (y1 - p[1], "y", y1)];
        if let Some((gap, axis, at)) = walls.into_iter().find(|(gap, _, _)| *gap < r / 2.0) {
            return Err(c.fail_with(
                "safety.arena",
                &["followers", "safety.distance", "safety.projection"],
                format!(
                    "follower {id}'s filtered point starts {} m from the wall {axis} = {}, within the filter's \
                     margin r / 2 = {} m: it would start outside the set the filter keeps it in",
                    num((gap * 1e6).round() / 1e6),
                    num(at),
                    num(r / 2.0)
                ),
            ));
        }
    }
    Ok(())
}

/// `[safety] deadlock_after`, `sidestep`, `sidestep_angle` (eq. G6) in
/// steps: none with `deadlock_after = 0`.
pub(crate) fn validate_deadlock(
    c: &Check<'_>,
    sf: &SafetyFile,
    dt: f64,
) -> Result<Option<DeadlockRule>, ScenarioError> {
    c.non_negative("safety.deadlock_after", &[sf.deadlock_after])?;
    c.bounded("safety.deadlock_after", &[sf.deadlock_after], 1e6, "s")?;
    c.positive("safety.sidestep", &[sf.sidestep])?;
    c.bounded("safety.sidestep", &[sf.sidestep], 1e6, "s")?;
    let angle = sf.sidestep_angle;
    if !(angle > 0.0 && angle < std::f64::consts::PI) {
        return Err(
            c.fail("safety.sidestep_angle", format!("{} rad must be in (0, π): a turn to the right", num(angle)))
        );
    }
    if sf.deadlock_after == 0.0 {
        return Ok(None);
    }
    let steps = |s: f64| ((s / dt).round() as u64).max(1);
    Ok(Some(DeadlockRule {
        after_steps: steps(sf.deadlock_after),
        sidestep_steps: steps(sf.sidestep),
        angle_rad: angle,
    }))
}

/// The two followers whose initial positions are closest, and how far apart.
pub(crate) fn closest_pair(followers: &[FollowerSpec]) -> Option<(u32, u32, f64)> {
    let mut best: Option<(u32, u32, f64)> = None;
    for (i, a) in followers.iter().enumerate() {
        for b in &followers[i + 1..] {
            let d = (a.pose.x - b.pose.x).hypot(a.pose.y - b.pose.y);
            if best.is_none_or(|(_, _, e)| d < e) {
                best = Some((a.id, b.id, d));
            }
        }
    }
    best
}

/// `[ros2]`: off, or the domain and who moves the robots.
pub(crate) fn validate_ros2(
    c: &Check<'_>,
    file: &ScenarioFile,
    drive: Drive,
) -> Result<Option<Ros2Settings>, ScenarioError> {
    let r = &file.ros2;
    let robots = match r.robots.as_str() {
        "simulated" => RobotSource::Simulated,
        "stand-in" => RobotSource::StandIn,
        "external" => RobotSource::External,
        other => return Err(c.fail("ros2.robots", format!("`{other}` is not one of: simulated, stand-in, external"))),
    };
    if r.domain_id > MAX_DOMAIN_ID {
        return Err(
            c.fail("ros2.domain_id", format!("{} is above ROS 2's largest domain id, {MAX_DOMAIN_ID}", r.domain_id))
        );
    }
    c.positive("ros2.odom_timeout", &[r.odom_timeout])?;
    if robots.driven() && drive == Drive::Torque {
        return Err(c.fail_with(
            "ros2.robots",
            &["robot.model"],
            format!(
                "`{}`: a robot driven through ROS 2 takes velocity commands on cmd_vel; set robot.model = \"velocity\"",
                r.robots
            ),
        ));
    }
    if !(r.enabled || robots.driven()) {
        return Ok(None);
    }
    Ok(Some(Ros2Settings { domain_id: r.domain_id, robots, odom_timeout_s: r.odom_timeout }))
}

/// `name`: the run's folder and every key of its traffic.
pub(crate) fn validate_name(c: &Check<'_>, name: String) -> Result<String, ScenarioError> {
    if name.chars().count() > MAX_NAME_CHARS {
        let start: String = name.chars().take(20).collect();
        return Err(c.fail(
            "name",
            format!("`{start}…` is {} characters long, at most {MAX_NAME_CHARS}", name.chars().count()),
        ));
    }
    if name.is_empty() || !name.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '-' || ch == '_') {
        return Err(c.fail("name", format!("`{name}` must be non-empty and use only letters, digits, '-' and '_'")));
    }
    Ok(name)
}

/// `dt` and `duration`: a whole number of steps, at most [`MAX_STEPS`].
pub(crate) fn validate_steps(c: &Check<'_>, file: &ScenarioFile) -> Result<(), ScenarioError> {
    c.positive("dt", &[file.dt])?;
    c.positive("duration", &[file.duration])?;
    let (dt, duration) = (num(file.dt), num(file.duration));
    if file.dt > file.duration {
        return Err(c.fail_with(
            "dt",
            &["duration"],
            format!("a step of {dt} s is longer than the whole run (duration = {duration} s)"),
        ));
    }
    let ratio = file.duration / file.dt;
    if ratio > MAX_STEPS {
        return Err(c.fail_with(
            "duration",
            &["dt"],
            format!(
                "{duration} s at Δt = {dt} s is {} steps; a run may have at most {} (split it, or raise dt)",
                num(ratio.round()),
                num(MAX_STEPS)
            ),
        ));
    }
    if (ratio - ratio.round()).abs() > 1e-6 * ratio.max(1.0) {
        return Err(c.fail_with(
            "duration",
            &["dt"],
            format!("{duration} s is not a whole number of steps of {dt} s (T/Δt = {ratio})"),
        ));
    }
    Ok(())
}

/// `[leader]`: the trajectory and the leader's initial pose.
pub(crate) fn validate_leader(c: &Check<'_>, l: &LeaderFile) -> Result<(Profile, Pose), ScenarioError> {
    c.finite("leader.pose", &l.pose)?;
    c.non_negative("leader.ramp", &[l.ramp])?;
    c.finite("leader.speed", &[l.speed])?;
    c.finite("leader.radius", &[l.radius])?;
    let trajectory = match l.source.as_str() {
        "trajectory" => validate_trajectory(c, l)?,
        "cmd_vel" => {
            let turn_rate = l.turn_rate.unwrap_or(1.0);
            c.positive("leader.speed", &[l.speed])?;
            c.bounded("leader.speed", &[l.speed], MAX_SPEED, "m/s")?;
            c.positive("leader.turn_rate", &[turn_rate])?;
            Trajectory::Commanded { speed_mps: l.speed, turn_rate }
        }
        "path" if !l.waypoints.is_empty() => {
            return Err(c.fail("leader.waypoints", "not with source = \"path\": the route comes on /leader/path"))
        }
        "path" => {
            let (speed_mps, turn_rate, turn_gain, reach_m) = route_limits(c, l)?;
            Trajectory::Routed { speed_mps, turn_rate, turn_gain, reach_m }
        }
        "robot" => Trajectory::External,
        "recorded" => Trajectory::Recorded,
        other => {
            return Err(
                c.fail("leader.source", format!("`{other}` is not one of: trajectory, cmd_vel, path, robot, recorded"))
            )
        }
    };
    Ok((Profile { trajectory, ramp_s: l.ramp }, Pose::new(l.pose[0], l.pose[1], l.pose[2])))
}

/// `leader.trajectory` and its keys, for `source = "trajectory"`.
fn validate_trajectory(c: &Check<'_>, l: &LeaderFile) -> Result<Trajectory, ScenarioError> {
    let trajectory = match l.trajectory.as_str() {
        "paper" => Trajectory::Paper,
        "line" => Trajectory::Line { speed_mps: l.speed },
        "circle" | "figure-eight" if l.radius == 0.0 => return Err(c.fail("leader.radius", "must not be zero")),
        "circle" => Trajectory::Circle { speed_mps: l.speed, radius_m: l.radius },
        "figure-eight" => Trajectory::FigureEight { speed_mps: l.speed, radius_m: l.radius },
        "waypoints" => validate_waypoints(c, l)?,
        other => {
            return Err(c.fail(
                "leader.trajectory",
                format!("`{other}` is not one of: paper, line, circle, figure-eight, waypoints"),
            ))
        }
    };
    let route_keys = [
        ("waypoints", !l.waypoints.is_empty()),
        ("turn_rate", l.turn_rate.is_some()),
        ("turn_gain", l.turn_gain.is_some()),
        ("reach", l.reach.is_some()),
    ];
    match route_keys.iter().find(|(_, given)| *given) {
        Some((key, _)) if l.trajectory != "waypoints" => {
            Err(c.fail(&format!("leader.{key}"), "only for trajectory = \"waypoints\" (or source = \"path\")"))
        }
        _ => Ok(trajectory),
    }
}

/// A source's own keys (`recorded`, `timeout`) only with it; a live source
/// (`cmd_vel`, `robot`) only in real time. The time-out, s.
fn validate_source(c: &Check<'_>, l: &LeaderFile, p: Profile, timing: Timing) -> Result<f64, ScenarioError> {
    let live = p.is_live();
    if l.recorded.is_some() != (p.trajectory == Trajectory::Recorded) {
        return Err(match l.recorded {
            Some(_) => c.fail("leader.recorded", "only for source = \"recorded\""),
            None => c.fail("leader.recorded", "missing: source = \"recorded\" plays a run folder or its leader.csv"),
        });
    }
    // A live scenario with another source (`--set leader.source=recorded`
    // or `path`) keeps its time-out, unused; a scripted one has none.
    if l.timeout.is_some() && l.source == "trajectory" {
        return Err(c.fail("leader.timeout", "only for source = \"cmd_vel\" or \"robot\""));
    }
    if live && timing == Timing::Lockstep {
        return Err(c.fail_with(
            "leader.source",
            &["timing"],
            format!(
                "`{}` steers the leader while the run goes: it runs in real time (timing = \"realtime\"); \
                 lock-step plays such a run again from its record (source = \"recorded\")",
                l.source
            ),
        ));
    }
    let timeout = l.timeout.unwrap_or(DEFAULT_LEADER_TIMEOUT_S);
    c.positive("leader.timeout", &[timeout])?;
    c.bounded("leader.timeout", &[timeout], MAX_LEADER_TIMEOUT_S, "s")?;
    // A route's keys with a live source that has no route (a record played
    // again keeps the keys of the run it came from, unused).
    let given = [
        ("waypoints", !l.waypoints.is_empty(), &["trajectory", "recorded"][..]),
        ("turn_gain", l.turn_gain.is_some(), &["trajectory", "path", "recorded"]),
        ("reach", l.reach.is_some(), &["trajectory", "path", "recorded"]),
    ];
    if let Some((key, _, with)) = given.iter().find(|(_, set, with)| *set && !with.contains(&l.source.as_str())) {
        let with: Vec<String> = with.iter().filter(|w| **w != "recorded").map(|w| format!("\"{w}\"")).collect();
        return Err(
            c.fail(&format!("leader.{key}"), format!("not with source = \"{}\" (only {})", l.source, with.join(", ")))
        );
    }
    Ok(timeout)
}

/// The longest `leader.timeout`, s: a live leader silent for an hour has stopped.
const MAX_LEADER_TIMEOUT_S: f64 = 3600.0;

/// `source = "recorded"`: the record, read and checked against `dt` and the run's length.
fn read_recording(c: &Check<'_>, file: &ScenarioFile) -> Result<Arc<[LeaderState]>, ScenarioError> {
    let path = file.leader.recorded.as_deref().unwrap_or_default();
    let steps = (file.duration / file.dt).round() as u64;
    crate::recorded::read(Path::new(path), file.dt, steps)
        .map(Arc::from)
        .map_err(|e| c.fail_with("leader.recorded", &["dt", "duration"], e))
}

/// `trajectory = "waypoints"` (docs/model.md §17, eq. 17.6): a route of at
/// least one point, a positive speed, turn rate, gain and reach.
fn validate_waypoints(c: &Check<'_>, l: &LeaderFile) -> Result<Trajectory, ScenarioError> {
    if l.waypoints.is_empty() {
        return Err(c.fail("leader.waypoints", "missing: give the route's points, waypoints = [[x, y], …]"));
    }
    for p in &l.waypoints {
        c.bounded("leader.waypoints", p, MAX_DISTANCE_M, "m")?;
    }
    let (speed_mps, turn_rate, turn_gain, reach_m) = route_limits(c, l)?;
    Ok(Trajectory::Waypoints { speed_mps, turn_rate, turn_gain, reach_m })
}

/// A route's law (eq. 17.6): speed, turn rate, k_θ and reach, each positive.
fn route_limits(c: &Check<'_>, l: &LeaderFile) -> Result<(f64, f64, f64, f64), ScenarioError> {
    let (turn_rate, turn_gain, reach) =
        (l.turn_rate.unwrap_or(1.0), l.turn_gain.unwrap_or(2.0), l.reach.unwrap_or(0.1));
    c.positive("leader.speed", &[l.speed])?;
    c.bounded("leader.speed", &[l.speed], MAX_SPEED, "m/s")?;
    c.positive("leader.turn_rate", &[turn_rate])?;
    c.positive("leader.turn_gain", &[turn_gain])?;
    c.positive("leader.reach", &[reach])?;
    Ok((l.speed, turn_rate, turn_gain, reach))
}

/// The route inside `[safety] arena`, where one is given.
fn validate_route(c: &Check<'_>, file: &ScenarioFile) -> Result<(), ScenarioError> {
    let Some([x0, x1, y0, y1]) = file.safety.as_ref().and_then(|s| s.arena) else { return Ok(()) };
    match crate::shape::first_outside(&file.leader.waypoints, [x0, x1, y0, y1]) {
        Some(i) => Err(c.fail(
            "leader.waypoints",
            format!(
                "point {} ({}, {}) is outside the arena x ∈ [{}, {}], y ∈ [{}, {}]",
                i + 1,
                num(file.leader.waypoints[i][0]),
                num(file.leader.waypoints[i][1]),
                num(x0),
                num(x1),
                num(y0),
                num(y1)
            ),
        )),
        None => Ok(()),
    }
}

/// The lengths of `followers`, `edges` and `faults`, before any is read.
pub(crate) fn validate_table_sizes(c: &Check<'_>, file: &ScenarioFile) -> Result<(), ScenarioError> {
    if file.followers.is_empty() {
        return Err(c.fail("followers", "at least one follower is needed"));
    }
    if file.followers.len() > c.most_followers {
        return Err(c.fail(
            "followers",
            format!("{} followers; a scenario may have at most {}", file.followers.len(), c.most_followers),
        ));
    }
    if file.edges.len() > MAX_EDGES {
        return Err(c.fail("edges", format!("{} edges; a scenario may have at most {MAX_EDGES}", file.edges.len())));
    }
    if file.faults.len() > MAX_FAULT_ROWS {
        return Err(c.fail(
            "faults",
            format!("{} fault rows; the fault table may have at most {MAX_FAULT_ROWS}", file.faults.len()),
        ));
    }
    Ok(())
}

/// `[[followers]]`, in ascending id (the order of the graph).
pub(crate) fn validate_followers(
    c: &Check<'_>,
    file: &ScenarioFile,
    leader_pose: Pose,
) -> Result<Vec<FollowerSpec>, ScenarioError> {
    let mut order: Vec<usize> = (0..file.followers.len()).collect();
    order.sort_by_key(|&i| file.followers[i].id);
    if let Some(o) = file.robot.odom_origin.as_deref().filter(|o| !matches!(*o, "world" | "start")) {
        return Err(c.fail(
            "robot.odom_origin",
            format!("`{o}` is not one of: world, start (or give a follower its own odom_origin = [x, y, θ])"),
        ));
    }
    let mut followers = Vec::with_capacity(order.len());
    for (pos, &i) in order.iter().enumerate() {
        let f = &file.followers[i];
        let field = |k: &str| format!("followers[{i}].{k}");
        if f.id == 0 {
            return Err(c.fail(&field("id"), "0 is the leader's id; followers are numbered from 1"));
        }
        if pos > 0 && file.followers[order[pos - 1]].id == f.id {
            return Err(c.fail(&field("id"), format!("duplicate follower id {}", f.id)));
        }
        c.bounded(&field("offset"), &f.offset, MAX_DISTANCE_M, "m")?;
        c.bounded(&field("velocity"), &f.velocity, MAX_SPEED, "(m/s, rad/s)")?;
        let pose = match (f.pose, f.body_error) {
            (Some(p), None) => {
                c.bounded(&field("pose"), &p, MAX_DISTANCE_M, "(m, rad)")?;
                Pose::new(p[0], p[1], p[2])
            }
            (None, Some(e)) => {
                c.bounded(&field("body_error"), &e, MAX_DISTANCE_M, "(m, rad)")?;
                // Against the slot as `formation.frame` places it (§17).
                let offset = match file.formation.frame.as_deref() == Some("leader") {
                    true => {
                        let [x, y] = formation_control::slot::position(Frame::Leader, &leader_pose, f.offset);
                        [x - leader_pose.x, y - leader_pose.y]
                    }
                    false => f.offset,
                };
                pose_from_body_error(leader_pose, offset, e)
            }
            (Some(_), Some(_)) => return Err(c.fail(&field("pose"), "give either `pose` or `body_error`, not both")),
            (None, None) => return Err(c.fail(&field("pose"), "missing: give `pose` or `body_error`")),
        };
        let odom_origin = match (f.odom_origin, file.robot.odom_origin.as_deref()) {
            (Some(o), _) => {
                c.bounded(&field("odom_origin"), &o, MAX_DISTANCE_M, "(m, rad)")?;
                Some(Pose::new(o[0], o[1], o[2]))
            }
            (None, Some("start")) => Some(pose),
            (None, _) => None,
        };
        followers.push(FollowerSpec {
            id: f.id,
            offset: f.offset,
            pose,
            velocity: Velocity::new(f.velocity[0], f.velocity[1]),
            hears_leader: f.leader_link,
            odom_origin,
        });
    }
    Ok(followers)
}

/// `edges` and the followers' `leader_link`: a graph the leader reaches
/// whole (Lemma 1).
pub(crate) fn validate_graph(
    c: &Check<'_>,
    file: &ScenarioFile,
    followers: &[FollowerSpec],
) -> Result<Graph, ScenarioError> {
    let ids: Vec<u32> = followers.iter().map(|f| f.id).collect();
    let mut edges = Vec::with_capacity(file.edges.len());
    let mut seen = std::collections::HashSet::with_capacity(file.edges.len());
    for (e, &[a, b]) in file.edges.iter().enumerate() {
        let field = format!("edges[{e}]");
        let index = |id: u32| {
            ids.binary_search(&id).map_err(|_| c.fail(&field, format!("edge {a}–{b} names unknown follower {id}")))
        };
        let (ia, ib) = (index(a)?, index(b)?);
        if ia == ib {
            return Err(c.fail(&field, format!("self-loop {a}–{b}: a follower is not its own neighbour")));
        }
        if !seen.insert((ia.min(ib), ia.max(ib))) {
            return Err(c.fail(&field, format!("duplicate edge {a}–{b} (edges are undirected)")));
        }
        edges.push((ia, ib));
    }
    if !followers.iter().any(|f| f.hears_leader) {
        let message = "no follower hears the leader: give at least one follower `leader_link = true` (Lemma 1 needs the leader to reach every follower)";
        return Err(match c.assignment_of("followers") {
            Some(assignment) => ScenarioError::Override { assignment: assignment.to_string(), message: message.into() },
            None => c.fail("followers", message),
        });
    }
    let graph = Graph::new(ids, &edges, followers.iter().map(|f| f.hears_leader).collect());
    let unreachable = graph.unreachable();
    if !unreachable.is_empty() {
        return Err(match c.assignment_of("edges").or_else(|| c.assignment_of("followers")) {
            Some(assignment) => ScenarioError::Override {
                assignment: assignment.to_string(),
                message: ScenarioError::GraphNotConnected { file: String::new(), unreachable }.to_string(),
            },
            None => ScenarioError::GraphNotConnected { file: c.label.to_string(), unreachable },
        });
    }
    Ok(graph)
}

/// `[estimator]`, `[backstepping]`, `[sliding_mode]`, `[robot]`,
/// `[disturbance]`, `[covariance]`, `[asif]`: the gains and models.
pub(crate) fn validate_gains(c: &Check<'_>, file: &ScenarioFile) -> Result<(), ScenarioError> {
    let est = &file.estimator;
    c.positive("estimator.k", &est.k)?;
    c.non_negative("estimator.ka", &est.ka)?;
    c.non_negative("estimator.kb", &est.kb)?;
    let bs = &file.backstepping;
    // The paper's C₁, C₂, C₃ are positive (a negative C₁ ran to a 130 m
    // formation error with exit status 0).
    c.positive("backstepping.c1", &[bs.c1])?;
    c.positive("backstepping.c2", &[bs.c2])?;
    c.positive("backstepping.c3", &[bs.c3])?;
    c.shunting("backstepping.shunting", &bs.shunting)?;
    let sm = &file.sliding_mode;
    c.non_negative("sliding_mode.ca", &[sm.ca])?;
    c.non_negative("sliding_mode.cb", &[sm.cb])?;
    c.shunting("sliding_mode.shunting_v", &sm.shunting_v)?;
    c.shunting("sliding_mode.shunting_w", &sm.shunting_w)?;
    c.non_negative("sliding_mode.k1", &[sm.k1])?;
    c.non_negative("sliding_mode.k2", &[sm.k2])?;
    let r = &file.robot;
    c.positive("robot.mass", &[r.mass])?;
    c.positive("robot.inertia", &[r.inertia])?;
    c.positive("robot.wheel_radius", &[r.wheel_radius])?;
    c.positive("robot.half_axle", &[r.half_axle])?;
    c.finite("disturbance.dv", &[file.disturbance.dv])?;
    c.finite("disturbance.dw", &[file.disturbance.dw])?;
    c.non_negative("covariance.q", &file.covariance.q)?;
    c.positive("covariance.r", &file.covariance.r)?;
    c.positive("asif.rho_max", &file.asif.rho_max)
}

/// `[fault]`: the change of mass and inertia at one time, if any.
pub(crate) fn validate_fault(c: &Check<'_>, file: &ScenarioFile) -> Result<Option<Fault>, ScenarioError> {
    // Checked with or without a time: a -1 was accepted until one was set.
    c.positive("fault.mass_factor", &[file.fault.mass_factor])?;
    c.positive("fault.inertia_factor", &[file.fault.inertia_factor])?;
    let Some(time_s) = file.fault.time else { return Ok(None) };
    c.non_negative("fault.time", &[time_s])?;
    if time_s > file.duration {
        return Err(c.fail_with(
            "fault.time",
            &["duration"],
            format!("must lie within [0, duration] = [0, {}] s, got {time_s}", file.duration),
        ));
    }
    c.positive("fault.mass_factor", &[file.fault.mass_factor])?;
    c.positive("fault.inertia_factor", &[file.fault.inertia_factor])?;
    Ok(Some(Fault { time_s, mass_factor: file.fault.mass_factor, inertia_factor: file.fault.inertia_factor }))
}

/// `[robot] model` and `lag`: how the robot is driven (docs/model.md §15).
/// A lag belongs to a velocity-commanded robot only, and such a robot runs
/// no filter for a `[fault]` to change.
pub(crate) fn validate_drive(c: &Check<'_>, file: &ScenarioFile) -> Result<Drive, ScenarioError> {
    let r = &file.robot;
    match (r.model, r.lag) {
        (RobotModel::Torque, None) => Ok(Drive::Torque),
        (RobotModel::Torque, Some(_)) => Err(c.fail_with(
            "robot.lag",
            &["robot.model"],
            "only a velocity-commanded robot has a lag: set robot.model = \"velocity\" or remove lag",
        )),
        (RobotModel::Velocity, lag) => {
            let lag_s = lag.unwrap_or(DEFAULT_LAG_S);
            c.positive("robot.lag", &[lag_s])?;
            if lag_s > MAX_LAG_S {
                return Err(c.fail(
                    "robot.lag",
                    format!(
                        "must be at most {MAX_LAG_S} s (the time constant of the robot's velocity loop, in seconds), \
                         got {}",
                        num(lag_s)
                    ),
                ));
            }
            if file.fault.time.is_some() {
                return Err(c.fail_with(
                    "fault.time",
                    &["robot.model"],
                    "the fault changes the velocity filter's model, and a velocity-commanded robot \
                     (robot.model = \"velocity\") runs no filter",
                ));
            }
            Ok(Drive::Velocity { lag_s })
        }
    }
}

/// `[network]`: the networked run's settings and the rejoin rule.
pub(crate) fn validate_network(
    c: &Check<'_>,
    file: &ScenarioFile,
) -> Result<(NetworkSettings, RejoinRule), ScenarioError> {
    let n = &file.network;
    let dt = num(file.dt);
    c.positive("network.silence_timeout", &[n.silence_timeout])?;
    let policy = match n.rejoin.as_str() {
        "consensus" => RejoinPolicy::Consensus,
        "adopt" => RejoinPolicy::Adopt,
        other => return Err(c.fail("network.rejoin", format!("`{other}` is not one of: consensus, adopt"))),
    };
    c.positive("network.rejoin_after", &[n.rejoin_after])?;
    if n.rejoin_after / file.dt > MAX_STEPS {
        return Err(c.fail_with(
            "network.rejoin_after",
            &["dt"],
            format!(
                "{} s is {} steps of {dt} s, longer than any run may be ({} steps): a rejoining follower would never rejoin",
                num(n.rejoin_after),
                num((n.rejoin_after / file.dt).round()),
                num(MAX_STEPS)
            ),
        ));
    }
    let after_steps = (n.rejoin_after / file.dt).round() as u64;
    if after_steps == 0 {
        return Err(c.fail_with(
            "network.rejoin_after",
            &["dt"],
            format!(
                "{} s is less than half a step of {dt} s (give it a step or more: --set network.rejoin_after={dt})",
                num(n.rejoin_after)
            ),
        ));
    }
    c.positive("network.time_scale", &[n.time_scale])?;
    if n.telemetry_batch == 0 {
        return Err(c.fail("network.telemetry_batch", "must be at least 1"));
    }
    if n.delay_steps > MAX_DELAY_STEPS {
        return Err(c.fail("network.delay_steps", format!("{} is more than {MAX_DELAY_STEPS}", n.delay_steps)));
    }
    if let Some(g) = n.gone_after {
        c.positive("network.gone_after", &[g])?;
    }
    let settings = NetworkSettings {
        silence_timeout_s: n.silence_timeout,
        time_scale: n.time_scale,
        telemetry_batch: n.telemetry_batch,
        hearing_record: n.hearing_record,
        delay_steps: n.delay_steps,
        gone_after_s: n.gone_after,
    };
    Ok((settings, RejoinRule { policy, after_steps }))
}

/// The controllers, filter and model every follower shares, from a file
/// already validated.
pub(crate) fn control_params(
    file: &ScenarioFile,
    model: RobotParams,
    fault: Option<Fault>,
    rejoin: RejoinRule,
    drive: Drive,
) -> ControlParams {
    let (est, bs, sm) = (&file.estimator, &file.backstepping, &file.sliding_mode);
    ControlParams {
        estimator: EstimatorGains { k: est.k, ka: est.ka, kb: est.kb },
        kinematic: file.kinematic,
        kinematic_gains: KinematicGains { c1: bs.c1, c2: bs.c2, c3: bs.c3, shunting: bs.shunting },
        dynamic: file.dynamic,
        dynamic_gains: DynamicGains {
            ca: sm.ca,
            cb: sm.cb,
            shunting_v: sm.shunting_v,
            shunting_w: sm.shunting_w,
            k1: sm.k1,
            k2: sm.k2,
        },
        filter: FilterParams {
            kind: file.filter,
            q: file.covariance.q,
            r: file.covariance.r,
            rho_max: file.asif.rho_max,
        },
        model,
        fault,
        rejoin,
        dt_s: file.dt,
        drive,
        guard: Guard::default(),
        frame: Frame::World,
    }
}

/// docs/model.md §14's fault table: each row one link of the graph or one follower,
/// a window inside the run, a probability.
pub(crate) fn validate_faults(
    c: &Check<'_>,
    file: &ScenarioFile,
    followers: &[FollowerSpec],
    graph: &Graph,
) -> Result<Vec<LinkFault>, ScenarioError> {
    let ids = || followers.iter().map(|f| f.id.to_string()).collect::<Vec<_>>().join(", ");
    let mut out = Vec::with_capacity(file.faults.len());
    for (i, f) in file.faults.iter().enumerate() {
        let field = |k: &str| format!("faults[{i}].{k}");
        let target = match (f.node, f.link) {
            (Some(_), Some(_)) => return Err(c.fail(&field("node"), "give either `node` or `link`, not both")),
            (None, None) => {
                return Err(c.fail(
                    &format!("faults[{i}]"),
                    "missing: give `node = ID` (every link of a follower) or `link = [A, B]` (0 = the leader)",
                ))
            }
            // The leader silent on every link: a handover's gap, or, without
            // `to`, a leader gone for good (docs/model.md §14).
            (Some(0), None) => FaultTarget::Node(0),
            (Some(n), None) => {
                if graph.index_of(n).is_none() {
                    return Err(c.fail(&field("node"), format!("follower {n} is not in the scenario (ids: {})", ids())));
                }
                FaultTarget::Node(n)
            }
            (None, Some([a, b])) => {
                for id in [a, b] {
                    if id != 0 && graph.index_of(id).is_none() {
                        return Err(c.fail(
                            &field("link"),
                            format!("node {id} is not in the scenario (0 = the leader; followers: {})", ids()),
                        ));
                    }
                }
                if a == b {
                    return Err(c.fail(&field("link"), format!("{a}–{b} is not a link: both ends are node {a}")));
                }
                if !is_link(graph, a, b) {
                    return Err(c.fail(&field("link"), not_a_link(graph, a, b)));
                }
                FaultTarget::Link(a, b)
            }
        };
        c.finite(&field("from"), &[f.from])?;
        // No `to`: the rest of the run, its last step (t = T) included.
        let to = f.to.unwrap_or(file.duration + file.dt);
        c.finite(&field("to"), &[to])?;
        if f.from < 0.0 {
            return Err(c.fail(&field("from"), format!("{} s is before the run starts (t = 0)", f.from)));
        }
        if f.from >= to {
            return Err(
                c.fail(&field("to"), format!("the window [{}, {}) s is empty: `to` must be after `from`", f.from, to))
            );
        }
        if f.join {
            check_join(c, &field, target, f)?;
        }
        let leave = f.leave || f.died;
        if leave {
            check_leave(c, &field, target, f)?;
        }
        let fault = LinkFault { target, from_s: f.from, to_s: to, loss: f.loss, join: f.join, leave, died: f.died };
        let (from_k, to_k) = fault.steps(file.dt);
        if from_k >= to_k {
            return Err(c.fail(
                &field("to"),
                format!(
                    "the window [{}, {}) s covers no step of Δt = {} s (both ends round to step {from_k}): widen it",
                    f.from,
                    to,
                    num(file.dt)
                ),
            ));
        }
        // The last step is at t = T: a window that covers it ends one step
        // later (the model of a follower that leaves for good).
        if to_k > formation_control::math::step_at(file.duration, file.dt) + 1 {
            return Err(c.fail(
                &field("to"),
                format!(
                    "{} s is after the end of the run (T = {} s); leave `to` out for the rest of the run, its \
                     last step (t = T) included",
                    to, file.duration
                ),
            ));
        }
        c.finite(&field("loss"), &[f.loss])?;
        if !(0.0..=1.0).contains(&f.loss) {
            return Err(c.fail(&field("loss"), format!("{} is not a probability in [0, 1]", f.loss)));
        }
        out.push(fault);
    }
    Ok(out)
}

/// A join row (`join = true`): a follower, absent from the run's start
/// (`from = 0`, the link down) until `to`, which must be given.
pub(crate) fn check_join(
    c: &Check<'_>,
    field: &dyn Fn(&str) -> String,
    target: FaultTarget,
    f: &crate::file::LinkFaultFile,
) -> Result<(), ScenarioError> {
    let why = match target {
        FaultTarget::Node(0) => Some(("node", "the leader does not join: give a follower's id".to_string())),
        FaultTarget::Link(..) => Some(("link", "a join is a follower's: give `node = ID`, not `link`".to_string())),
        FaultTarget::Node(_) if f.from != 0.0 => {
            Some(("from", format!("a follower that joins is absent from the start: from = 0, not {}", f.from)))
        }
        FaultTarget::Node(_) if f.to.is_none() => Some(("to", "a join needs `to`, the time it joins (s)".to_string())),
        FaultTarget::Node(_) if f.loss != 1.0 => {
            Some(("loss", format!("a follower not yet started sends nothing: loss = 1, not {}", f.loss)))
        }
        FaultTarget::Node(_) => None,
    };
    refuse_row(c, field, why)
}

/// A fault row's one line, naming its key, or Ok.
pub(crate) fn refuse_row(
    c: &Check<'_>,
    field: &dyn Fn(&str) -> String,
    why: Option<(&str, String)>,
) -> Result<(), ScenarioError> {
    match why {
        Some((key, why)) => Err(c.fail(&field(key), why)),
        None => Ok(()),
    }
}

/// A leave row (`leave = true`): a follower, cut off from `from` to the
/// end of the run (no `to`), not also a join.
pub(crate) fn check_leave(
    c: &Check<'_>,
    field: &dyn Fn(&str) -> String,
    target: FaultTarget,
    f: &crate::file::LinkFaultFile,
) -> Result<(), ScenarioError> {
    let why = match target {
        FaultTarget::Node(0) => {
            Some(("node", "the leader does not leave: a handover is its own row (node = 0)".to_string()))
        }
        FaultTarget::Link(..) => Some(("link", "a leave is a follower's: give `node = ID`, not `link`".to_string())),
        FaultTarget::Node(_) if f.join => Some(("join", "a row is a join or a leave, not both".to_string())),
        FaultTarget::Node(_) if f.died && f.from <= 0.0 => {
            Some(("from", "a follower killed at the start is absent: give `from` after 0 (s)".to_string()))
        }
        FaultTarget::Node(_) if f.to.is_some() => {
            Some(("to", "a follower that leaves does not come back: leave `to` out (the rest of the run)".to_string()))
        }
        FaultTarget::Node(_) if f.loss != 1.0 => {
            Some(("loss", format!("a follower that left sends nothing: loss = 1, not {}", f.loss)))
        }
        FaultTarget::Node(_) => None,
    };
    refuse_row(c, field, why)
}

/// Why a–b is not a fault table's link: whom its follower end talks to.
pub(crate) fn not_a_link(graph: &Graph, a: u32, b: u32) -> String {
    let end = if a == 0 { b } else { a };
    let links = graph.index_of(end).map(|i| {
        let mut l: Vec<String> = graph.neighbours(i).iter().map(|&j| graph.id(j).to_string()).collect();
        if graph.hears_leader(i) {
            l.insert(0, "0".into());
        }
        l.join(", ")
    });
    format!("{a}–{b} is not a link of the scenario's graph (node {end} talks to: {})", links.unwrap_or_default())
}

/// Whether a and b (0 = the leader) talk to each other in the graph.
pub(crate) fn is_link(graph: &Graph, a: u32, b: u32) -> bool {
    match (a, b) {
        (0, f) | (f, 0) => graph.index_of(f).is_some_and(|i| graph.hears_leader(i)),
        (a, b) => match (graph.index_of(a), graph.index_of(b)) {
            (Some(ia), Some(ib)) => graph.neighbours(ia).contains(&ib),
            _ => false,
        },
    }
}
/// `[formation]`: the frame, and each shape change with its assignment.
pub(crate) fn validate_formation(
    c: &Check<'_>,
    file: &ScenarioFile,
    followers: &[FollowerSpec],
) -> Result<(Frame, Vec<ShapeChange>), ScenarioError> {
    let f = &file.formation;
    let frame = match f.frame.as_deref() {
        None | Some("world") => Frame::World,
        Some("leader") => Frame::Leader,
        Some(other) => return Err(c.fail("formation.frame", format!("`{other}` is not one of: world, leader"))),
    };
    let safety = file.safety.as_ref().map(|s| s.distance);
    let spacing = f.spacing.unwrap_or(safety.map_or(1.0, |d| 2.0 * d));
    c.positive("formation.spacing", &[spacing])?;
    c.bounded("formation.spacing", &[spacing], MAX_DISTANCE_M, "m")?;
    if !f.shapes.is_empty() && followers.len() > MAX_ASSIGNED {
        return Err(c.fail(
            "formation.shapes",
            format!("{} followers; a shape change assigns at most {MAX_ASSIGNED}", followers.len()),
        ));
    }
    let mut held: Vec<[f64; 2]> = followers.iter().map(|f| f.offset).collect();
    let mut changes = Vec::with_capacity(f.shapes.len());
    for (i, row) in f.shapes.iter().enumerate() {
        let field = |k: &str| format!("formation.shapes[{i}].{k}");
        c.finite(&field("at"), &[row.at])?;
        let after = changes.last().map_or(0.0, |p: &ShapeChange| p.at_s);
        if row.at <= after || row.at >= file.duration {
            let window = format!("after {} s and before the run's end ({} s)", num(after), num(file.duration));
            return Err(c.fail(&field("at"), format!("{} s is not {window}", num(row.at))));
        }
        let slots = slots_of(c, row, i, followers.len(), row.spacing.unwrap_or(spacing))?;
        if let (Some(d), Some((a, b, gap))) = (safety, closest(&slots)) {
            if gap < d {
                return Err(c.fail(
                    &field(if row.offsets.is_empty() { "spacing" } else { "offsets" }),
                    format!("slots {a} and {b} are {} m apart, closer than safety.distance ({} m)", num(gap), num(d)),
                ));
            }
        }
        let to = assign(&held, &slots);
        let cost = total_cost(&held, &slots, &to);
        held = to.iter().map(|&j| slots[j]).collect();
        let name = row.shape.clone().unwrap_or_else(|| "offsets".to_string());
        changes.push(ShapeChange {
            at_s: row.at,
            from_k: formation_control::math::step_at(row.at, file.dt),
            name,
            cost,
            offsets: held.clone(),
        });
    }
    Ok((frame, changes))
}

/// A row's slots: its named shape or its offsets, one per follower.
fn slots_of(c: &Check<'_>, row: &ShapeFile, i: usize, n: usize, spacing: f64) -> Result<Vec<[f64; 2]>, ScenarioError> {
    let field = |k: &str| format!("formation.shapes[{i}].{k}");
    match (&row.shape, row.offsets.is_empty()) {
        (Some(_), false) => Err(c.fail(&field("shape"), "give either `shape` or `offsets`, not both")),
        (None, true) => Err(c.fail(
            &format!("formation.shapes[{i}]"),
            format!("missing: give `shape` ({}) or `offsets`, one per follower", SHAPES.join(", ")),
        )),
        (Some(name), true) => {
            c.positive(&field("spacing"), &[spacing])?;
            named(name, n, spacing)
                .ok_or_else(|| c.fail(&field("shape"), format!("`{name}` is not one of: {}", SHAPES.join(", "))))
        }
        (None, false) if row.offsets.len() != n => Err(c.fail(
            &field("offsets"),
            format!("{} offsets for {n} followers: give one per follower", row.offsets.len()),
        )),
        (None, false) => {
            for o in &row.offsets {
                c.bounded(&field("offsets"), o, MAX_DISTANCE_M, "m")?;
            }
            Ok(row.offsets.clone())
        }
    }
}
