//! What steers a live leader (`leader.source = "cmd_vel"`, `"path"` or
//! `"robot"`, docs/model.md §18): the newest command, route or odometry
//! heard and when, and at each step the input the leader takes (a route
//! once, and it never goes stale). A command beyond the leader's
//! limits is clipped and counted (the first one named); one that is not
//! finite is refused and counted. Input silent for the source's time-out
//! stops the leader, and the operator is told when it falls silent and
//! when it is heard again. No clock: time is an argument.

use std::sync::Arc;
use std::time::Duration;

use formation_leader::{Input, Profile};
use formation_plant::{Pose, Velocity};
use formation_scenario::shape::first_outside;

use crate::Now;

/// The topic each live source listens on (in the leader's namespace).
pub fn topic_of(profile: &Profile) -> Option<&'static str> {
    use formation_leader::Trajectory;
    match profile.trajectory {
        Trajectory::Commanded { .. } => Some("/leader/cmd_vel"),
        Trajectory::Routed { .. } => Some("/leader/path"),
        Trajectory::External => Some("/leader/odom"),
        _ => None,
    }
}

/// Counts of what the source sent.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SteerCounts {
    /// Messages taken.
    pub taken: u64,
    /// Commands beyond the leader's limits, taken clipped.
    pub clipped: u64,
    /// Messages refused (a quantity that is not finite).
    pub refused: u64,
    /// Times the input fell silent for the time-out during the run.
    pub silences: u64,
}

/// A live leader's input: see the module documentation.
#[derive(Clone, Debug)]
pub struct Steering {
    profile: Profile,
    topic: &'static str,
    timeout: Duration,
    latest: Option<(Input, Now)>,
    /// Whether the leader stands for want of input (said once per silence).
    silent: bool,
    /// A planner's route not yet taken by the leader.
    route: Option<Arc<[[f64; 2]]>>,
    /// Where a route's points must lie: x ∈ [x0, x1], y ∈ [y0, y1].
    arena: Option<[f64; 4]>,
    pub counts: SteerCounts,
}

impl Steering {
    /// The input of a leader of `profile` (None for a scripted one); its
    /// input goes stale after `timeout`.
    pub fn of(profile: Profile, timeout: Duration) -> Option<Self> {
        let topic = topic_of(&profile)?;
        let counts = SteerCounts::default();
        Some(Self { profile, topic, timeout, latest: None, silent: true, route: None, arena: None, counts })
    }

    /// Routes must keep inside `arena` ([x0, x1, y0, y1], `safety.arena`).
    pub fn within(mut self, arena: Option<[f64; 4]>) -> Self {
        self.arena = arena;
        self
    }

    /// A planner's route (its points in the world, in order): taken for
    /// the next step, or refused, and the first refusal
    /// named, for a point that is not finite or lies outside the arena.
    pub fn route(&mut self, points: Vec<[f64; 2]>) -> Option<String> {
        let everywhere = [f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY];
        if let Some(i) = first_outside(&points, self.arena.unwrap_or(everywhere)) {
            self.counts.refused += 1;
            let where_ = match self.arena {
                Some([x0, x1, y0, y1]) => format!("outside the arena x ∈ [{x0}, {x1}], y ∈ [{y0}, {y1}] or not finite"),
                None => "not finite".into(),
            };
            return (self.counts.refused == 1).then(|| {
                format!(
                    "leader: a route on {} is refused: its point {} ({}, {}) is {where_}; the leader keeps its route, \
                     and every such route is counted",
                    self.topic,
                    i + 1,
                    points[i][0],
                    points[i][1]
                )
            });
        }
        self.counts.taken += 1;
        self.route = Some(points.into());
        None
    }

    /// A velocity command (v, ω) heard at `now`: taken within the limits.
    /// A line to say for the first command clipped.
    pub fn command(&mut self, command: Velocity, now: Now) -> Option<String> {
        let Some((taken, clipped)) = self.profile.clip(command) else {
            self.counts.refused += 1;
            return None;
        };
        self.counts.taken += 1;
        self.latest = Some((Input::Command(taken), now));
        if !clipped {
            return None;
        }
        self.counts.clipped += 1;
        (self.counts.clipped == 1).then(|| {
            format!(
                "leader: a command of {} m/s, {} rad/s on {} is beyond the leader's limits ({}): taken as {} m/s, {} \
                 rad/s; every such command is clipped and counted",
                command.v,
                command.w,
                self.topic,
                self.limits(),
                taken.v,
                taken.w
            )
        })
    }

    /// The leader robot's odometry heard at `now` (its pose in the world).
    pub fn odometry(&mut self, pose: Pose, twist: Velocity, now: Now) {
        if !(pose.is_finite() && twist.is_finite()) {
            self.counts.refused += 1;
            return;
        }
        self.counts.taken += 1;
        self.latest = Some((Input::Odometry { pose, twist }, now));
    }

    /// The input for the step computed at `now` (run time `t_s`), and a
    /// line to say when the input falls silent or is heard again.
    pub fn input(&mut self, now: Now, t_s: f64) -> (Input, Option<String>) {
        if let formation_leader::Trajectory::Routed { .. } = self.profile.trajectory {
            // A route stands until the next: it does not go stale.
            return (self.route.take().map_or(Input::Silent, Input::Route), None);
        }
        let fresh = self.latest.clone().filter(|(_, at)| now.saturating_sub(*at) <= self.timeout);
        let said = match (fresh.is_some(), self.silent) {
            (true, true) => {
                self.silent = false;
                Some(format!("leader: {} heard at t = {t_s:.2} s: the leader follows it", self.topic))
            }
            (false, false) => {
                (self.silent, self.counts.silences) = (true, self.counts.silences + 1);
                Some(format!(
                    "leader: {} silent for {} s at t = {t_s:.2} s: the leader stops where it is until it is heard again",
                    self.topic,
                    self.timeout.as_secs_f64()
                ))
            }
            _ => None,
        };
        (fresh.map_or(Input::Silent, |(input, _)| input), said)
    }

    /// The end-of-run line: what the source sent and what was done with it.
    pub fn summary(&self) -> String {
        let c = self.counts;
        let what = match self.profile.trajectory {
            formation_leader::Trajectory::Commanded { .. } => "commands",
            formation_leader::Trajectory::Routed { .. } => "routes",
            _ => "odometry messages",
        };
        let clipped = match self.profile.trajectory {
            formation_leader::Trajectory::Commanded { .. } => {
                format!(", {} clipped to the leader's limits ({})", c.clipped, self.limits())
            }
            _ => String::new(),
        };
        if let formation_leader::Trajectory::Routed { .. } = self.profile.trajectory {
            return format!(
                "leader: {} {what} taken from {}, {} refused (a point outside the arena or not finite)",
                c.taken, self.topic, c.refused
            );
        }
        format!(
            "leader: {} {what} taken from {}{clipped}, {} refused (not finite); silent for {} s {} time(s)",
            c.taken,
            self.topic,
            c.refused,
            self.timeout.as_secs_f64(),
            c.silences
        )
    }

    fn limits(&self) -> String {
        match self.profile.trajectory {
            formation_leader::Trajectory::Commanded { speed_mps, turn_rate } => {
                format!("|v| ≤ {speed_mps} m/s, |ω| ≤ {turn_rate} rad/s")
            }
            _ => "none".into(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_leader::Trajectory;

    fn cmd_vel() -> Steering {
        let p = Profile { trajectory: Trajectory::Commanded { speed_mps: 0.2, turn_rate: 1.0 }, ramp_s: 0.0 };
        Steering::of(p, Duration::from_millis(500)).expect("a live source")
    }

    #[test]
    fn a_scripted_leader_has_no_steering() {
        assert!(Steering::of(Profile { trajectory: Trajectory::Paper, ramp_s: 0.5 }, Duration::ZERO).is_none());
    }

    #[test]
    fn commands_are_clipped_counted_and_go_stale_after_the_time_out() {
        let mut s = cmd_vel();
        let ms = Duration::from_millis;
        let (input, said) = s.input(ms(0), 0.0);
        assert_eq!((input, said), (Input::Silent, None), "it stands before the first command, without a word");
        let first = s.command(Velocity::new(0.5, 0.0), ms(100)).expect("the first clip is named");
        assert!(first.contains("0.5 m/s") && first.contains("|v| ≤ 0.2 m/s"), "{first}");
        assert_eq!(s.command(Velocity::new(-0.5, 2.0), ms(200)), None, "later clips are counted, not said");
        assert_eq!(s.command(Velocity::new(f64::INFINITY, 0.0), ms(250)), None);
        let (input, said) = s.input(ms(300), 0.3);
        assert_eq!(input, Input::Command(Velocity::new(-0.2, 1.0)));
        assert!(said.is_some_and(|l| l.contains("heard at t = 0.30 s")));
        // 500 ms after the newest command it is still fresh; 1 ms later it is not.
        assert_eq!(s.input(ms(700), 0.7).0, Input::Command(Velocity::new(-0.2, 1.0)));
        let (input, said) = s.input(ms(701), 0.701);
        assert_eq!(input, Input::Silent);
        assert!(said.is_some_and(|l| l.contains("silent for 0.5 s at t = 0.70 s")));
        assert_eq!(s.input(ms(800), 0.8), (Input::Silent, None), "a silence is said once");
        s.command(Velocity::new(0.1, 0.0), ms(900));
        assert!(s.input(ms(900), 0.9).1.is_some_and(|l| l.contains("heard at")));
        assert_eq!(s.counts, SteerCounts { taken: 3, clipped: 2, refused: 1, silences: 1 });
        let end = s.summary();
        assert!(end.contains("3 commands taken from /leader/cmd_vel, 2 clipped") && end.contains("1 refused"), "{end}");
    }

    #[test]
    fn a_robots_odometry_is_taken_as_it_is_and_refused_when_not_finite() {
        let p = Profile { trajectory: Trajectory::External, ramp_s: 0.0 };
        let mut s = Steering::of(p, Duration::from_millis(500)).expect("live");
        let pose = Pose::new(1.0, 2.0, 0.3);
        s.odometry(pose, Velocity::new(9.0, 0.0), Duration::ZERO);
        s.odometry(Pose::new(f64::NAN, 0.0, 0.0), Velocity::new(0.0, 0.0), Duration::ZERO);
        assert_eq!(s.input(Duration::ZERO, 0.0).0, Input::Odometry { pose, twist: Velocity::new(9.0, 0.0) });
        assert_eq!((s.counts.taken, s.counts.refused), (1, 1));
        assert!(s.summary().contains("1 odometry messages taken from /leader/odom"));
    }

    #[test]
    fn a_route_is_taken_once_for_the_next_step_and_one_outside_the_arena_is_refused() {
        let p = Profile {
            trajectory: Trajectory::Routed { speed_mps: 0.2, turn_rate: 1.0, turn_gain: 2.0, reach_m: 0.1 },
            ramp_s: 0.0,
        };
        let mut s = Steering::of(p, Duration::from_millis(500)).expect("live").within(Some([-2.0, 2.0, -1.0, 1.0]));
        assert_eq!(s.input(Duration::ZERO, 0.0), (Input::Silent, None), "no route: nothing to take");
        assert_eq!(s.route(vec![[1.0, 0.5], [1.5, -0.5]]), None);
        let refused = s.route(vec![[1.0, 0.5], [3.0, 0.0]]).expect("named");
        assert!(refused.contains("point 2 (3, 0) is outside the arena x ∈ [-2, 2], y ∈ [-1, 1]"), "{refused}");
        assert_eq!(s.route(vec![[f64::NAN, 0.0]]), None, "later refusals are counted, not said");
        let route: Arc<[[f64; 2]]> = Arc::from([[1.0, 0.5], [1.5, -0.5]]);
        assert_eq!(s.input(Duration::from_secs(60), 60.0), (Input::Route(route), None), "a route never goes stale");
        assert_eq!(s.input(Duration::from_secs(61), 61.0).0, Input::Silent, "taken once");
        assert_eq!((s.counts.taken, s.counts.refused), (1, 2));
        assert!(s.summary().contains("1 routes taken from /leader/path, 2 refused"), "{}", s.summary());
    }
}
