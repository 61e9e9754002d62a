//! `formation robot --id i`: a stand-in robot that speaks ROS 2. It runs
//! the project's velocity-commanded robot for follower i (the plant
//! `formation sim` runs for `robot.model = "velocity"`, with the same noise
//! stream), takes `/follower_<i>/cmd_vel` and publishes
//! `/follower_<i>/odom` and its transforms, as a TurtleBot or Gazebo's
//! diff-drive plugin would. `launch --robots stand-in` starts one per
//! follower, so the whole loop runs through the ROS 2 wire.
//!
//! Lock-step: odometry of step k is stamped k Δt and sent again every
//! [`REPEAT_EVERY`] until step k's command arrives (its attachment's
//! source time names the step); then the robot advances one step. It ends
//! after the last step's command, or gives up after `--stall-timeout`.
//! Real time: every period the robot advances with the newest command
//! (zero when none came for `robot.cmd_timeout`, said when it fires, as a
//! base's driver does) and publishes its odometry stamped with the wall
//! clock; it ends on Ctrl-C or SIGTERM, or when commands stop for
//! [`DONE_AFTER`] after they had begun.
//!
//! At its end it says, from its own side, what it was sent: how many
//! commands, the largest |v| and |ω|, and how many were beyond the
//! scenario's `robot.v_max` and `w_max`.

use std::future::Future;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use formation_plant::{Drive, NoiseSource, Velocity, VelocityRobot};
use formation_ros2::msgs::{Odometry, TFMessage, Twist};
use formation_scenario::{Scenario, Timing};

use super::rmw_node::{RosNode, RosPublisher};
use super::topics::{odometry, OdomFrame, Stamps, QOS};
use crate::clock::Clock;
use crate::node::NodeArgs;
use formation_exit::Error;
use formation_ros2::planar::Frames;

/// Lock-step: odometry is said again this often while its command is awaited.
pub const REPEAT_EVERY: Duration = Duration::from_millis(100);
/// A robot slower than this (m/s, rad/s) has stopped.
pub const STOPPED_V: f64 = 0.005;
pub const STOPPED_W: f64 = 0.02;
/// Real time: commands that stop this long after they began end the run.
pub const DONE_AFTER: Duration = Duration::from_secs(3);

/// `robot` arguments.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct RobotArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub node: NodeArgs,
    /// The follower whose robot this is.
    #[cfg_attr(feature = "clap", arg(long, value_name = "ID"))]
    pub id: u32,
    /// Lock-step: give up if commands stop arriving for this long (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 60.0, value_name = "SECONDS"))]
    pub stall_timeout: f64,
}

/// A command as it arrived: the twist and the step its source time names.
#[derive(Clone, Copy, Debug)]
struct Command {
    v: Velocity,
    source_ns: Option<i64>,
    arrived: Duration,
}

/// Runs the stand-in robot until the run ends (or `shutdown`).
pub async fn run(args: &RobotArgs, shutdown: impl Future<Output = ()>) -> Result<(), Error> {
    if args.node.zenoh.tls.is_some() {
        return Err(Error::Input(
            "formation robot: --tls is not for robots (ROS 2 robots do not hold the formation's certificates); run \
             the robot on a network ROS 2 trusts"
                .into(),
        ));
    }
    let (scenario, _keys) = args.node.load(&format!("robot-{}", args.id))?;
    let index = scenario.index_of(args.id).ok_or_else(|| {
        let all: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
        Error::Input(format!("scenario {} has no follower {} (ids: {})", scenario.name, args.id, all.join(", ")))
    })?;
    let Drive::Velocity { lag_s } = scenario.control.drive else {
        return Err(Error::Input(format!(
            "formation robot: scenario {} has robot.model = \"torque\"; a robot driven through ROS 2 takes velocity \
             commands (set robot.model = \"velocity\")",
            scenario.name
        )));
    };
    if !(args.stall_timeout.is_finite() && args.stall_timeout > 0.0) {
        return Err(Error::Input("--stall-timeout must be positive".into()));
    }
    let domain = scenario.ros2.map_or(0, |r| r.domain_id);
    let session = args.node.open(&format!("robot-{}", args.id), &scenario).await?;
    let namespace = super::follower_namespace(args.id);
    let node = RosNode::declare(&session, domain, &namespace, "robot").await?;
    let congestion = crate::node::estimate_congestion(&scenario);
    let mut out = Outputs {
        odom: node.publisher("odom", QOS, congestion).await?,
        tf: node.publisher("/tf", QOS, congestion).await?,
        frames: super::topics::follower_frames(&scenario, args.id),
        frame: OdomFrame::of(&scenario, index),
    };
    let latest: Arc<Mutex<Option<Command>>> = Arc::new(Mutex::new(None));
    let l = latest.clone();
    let clock = args.node.clock.clone();
    let c = clock.clone();
    let received: Arc<Mutex<Received>> = Arc::default();
    let r = received.clone();
    let _commands = node
        .subscribe::<Twist, _>("cmd_vel", QOS, move |m, att| {
            let Ok(t) = m else { return };
            let v = Velocity::new(t.linear.x, t.angular.z);
            if v.is_finite() {
                r.lock().unwrap_or_else(|p| p.into_inner()).add(v);
                let c = Command { v, source_ns: att.map(|a| a.source_timestamp_ns), arrived: c.mono() };
                *l.lock().unwrap_or_else(|p| p.into_inner()) = Some(c);
            }
        })
        .await?;
    let spec = &scenario.followers[index];
    let plant = Plant {
        id: spec.id,
        robot: VelocityRobot::new(lag_s, spec.pose, spec.velocity),
        noise: NoiseSource::new(scenario.covariance, scenario.noise, scenario.seed, spec.id),
    };
    let stall = Duration::from_secs_f64(args.stall_timeout);
    let scenario2 = scenario.clone();
    let work = tokio::task::spawn_blocking(move || match scenario2.timing {
        Timing::Lockstep => lockstep(&scenario2, plant, &mut out, &latest, stall, &clock),
        Timing::Realtime => realtime(&scenario2, plant, &mut out, &latest, &clock),
    });
    let result = tokio::select! {
        r = work => r.map_err(|e| Error::Run(format!("robot {}: loop panicked: {e}", args.id)))?,
        () = shutdown => Ok(()),
    };
    drop(_commands);
    drop(node);
    let line = received.lock().unwrap_or_else(|p| p.into_inner()).line(args.id, &scenario);
    crate::node::say(&line);
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    result
}

/// What the robot was sent over the run, as the robot saw it.
#[derive(Debug, Default)]
struct Received {
    commands: u64,
    v_peak: f64,
    w_peak: f64,
}

impl Received {
    fn add(&mut self, v: Velocity) {
        self.commands += 1;
        self.v_peak = self.v_peak.max(v.v.abs());
        self.w_peak = self.w_peak.max(v.w.abs());
    }

    /// "robot 3: 3001 commands received, |v| ≤ 0.2200 m/s, |ω| ≤ 2.8400 rad/s; none beyond robot.v_max, w_max".
    fn line(&self, id: u32, s: &Scenario) -> String {
        let beyond = match s.control.guard.limits {
            None => String::new(),
            Some(l) if self.v_peak <= l.v_max && self.w_peak <= l.w_max => {
                "; none beyond robot.v_max, w_max".to_string()
            }
            Some(l) => format!("; BEYOND robot.v_max = {} m/s or w_max = {} rad/s", l.v_max, l.w_max),
        };
        format!(
            "robot {id}: {} commands received, |v| ≤ {:.4} m/s, |ω| ≤ {:.4} rad/s{beyond}",
            self.commands, self.v_peak, self.w_peak
        )
    }
}

/// The robot and its noise: what `formation sim` steps for this follower.
struct Plant {
    id: u32,
    robot: VelocityRobot,
    noise: NoiseSource,
}

impl Plant {
    fn advance(&mut self, command: Velocity, dt_s: f64) {
        let draw = self.noise.draw();
        self.robot.advance(command, dt_s, draw);
    }
}

struct Outputs {
    odom: RosPublisher<Odometry>,
    tf: RosPublisher<TFMessage>,
    frames: Frames,
    /// Where its odometry frame sits (`robot.odom_origin`): the odometry
    /// reports the pose in it, /tf places it in the world.
    frame: OdomFrame,
}

impl Outputs {
    /// The odometry of `p` (the true pose, its heading as a quaternion, and
    /// the measured velocity z), and its transforms.
    fn publish(&mut self, ns: i64, p: &Plant) -> Result<(), Error> {
        self.publish_odometry(ns, p)?;
        self.tf.put(&self.frame.transforms(&self.frames, ns, p.robot.pose), ns)
    }

    /// The odometry alone: a lock-step repeat of a step (its transforms
    /// again with the same stamp would make tf2 listeners warn of repeated
    /// data, TF_REPEATED_DATA).
    fn publish_odometry(&mut self, ns: i64, p: &Plant) -> Result<(), Error> {
        self.odom.put(&odometry(&self.frames, ns, self.frame.local(p.robot.pose), p.robot.measurement), ns)
    }
}

fn lockstep(
    s: &Scenario,
    mut plant: Plant,
    out: &mut Outputs,
    latest: &Mutex<Option<Command>>,
    stall: Duration,
    clock: &Clock,
) -> Result<(), Error> {
    let stamps = Stamps::of(s, 0);
    let steps = s.steps();
    let mut k = 0u64;
    out.publish(stamps.ns(0), &plant)?;
    let mut said = clock.mono();
    let mut heard = clock.mono();
    loop {
        let command = *latest.lock().unwrap_or_else(|p| p.into_inner());
        match command {
            Some(c) if c.source_ns == Some(stamps.ns(k)) => {
                if k == steps {
                    return Ok(());
                }
                plant.advance(c.v, s.dt_s);
                k += 1;
                out.publish(stamps.ns(k), &plant)?;
                said = clock.mono();
                heard = said;
            }
            _ => {
                let now = clock.mono();
                if now - heard > stall {
                    return Err(Error::Run(format!(
                        "no command for step {k} on cmd_vel for {:.0} s (stall timeout): is the agent running?",
                        stall.as_secs_f64()
                    )));
                }
                if now - said >= REPEAT_EVERY {
                    out.publish_odometry(stamps.ns(k), &plant)?;
                    said = now;
                }
                clock.sleep_until_mono(now + Duration::from_micros(50));
            }
        }
    }
}

fn realtime(
    s: &Scenario,
    mut plant: Plant,
    out: &mut Outputs,
    latest: &Mutex<Option<Command>>,
    clock: &Clock,
) -> Result<(), Error> {
    let period = Duration::from_secs_f64(s.dt_s / formation_protocol::barrier::positive_scale(s.network.time_scale));
    let timeout = Duration::from_secs_f64(s.cmd_timeout_s);
    let began = clock.mono();
    let mut began_driving = false;
    let mut timed_out = false;
    // Since when the robot is told to stop (a zero command or the time-out), and why.
    let mut stopping: Option<(u64, &str)> = None;
    out.publish(clock.unix_ns() as i64, &plant)?;
    for tick in 1u64.. {
        let due = began + period * tick as u32;
        clock.sleep_until_mono(due);
        let now = clock.mono();
        let command = *latest.lock().unwrap_or_else(|p| p.into_inner());
        let fresh = command.filter(|c| now.saturating_sub(c.arrived) <= timeout);
        if !began_driving && fresh.is_some() {
            began_driving = true;
            crate::node::say(&format!("robot {}: driving (first command at unix {} ns)", plant.id, clock.unix_ns()));
        }
        if began_driving && fresh.is_none() != timed_out {
            timed_out = fresh.is_none();
            if timed_out {
                crate::node::say(&format!(
                    "robot {}: no command for robot.cmd_timeout = {} s: stopping",
                    plant.id, s.cmd_timeout_s
                ));
            }
        }
        if began_driving && command.is_some_and(|c| now.saturating_sub(c.arrived) > DONE_AFTER) {
            return Ok(());
        }
        let u = fresh.map_or(Velocity::default(), |c| c.v);
        let moving = plant.robot.velocity.v.abs() > STOPPED_V || plant.robot.velocity.w.abs() > STOPPED_W;
        match (u == Velocity::default(), stopping) {
            (true, None) if moving => {
                stopping = Some((clock.unix_ns(), if fresh.is_some() { "a zero command" } else { "the time-out" }))
            }
            (false, _) => stopping = None,
            _ => {}
        }
        plant.advance(u, s.dt_s);
        if let Some((since, why)) = stopping {
            let v = plant.robot.velocity;
            if v.v.abs() <= STOPPED_V && v.w.abs() <= STOPPED_W {
                let now = clock.unix_ns();
                crate::node::say(&format!(
                    "robot {}: stopped at unix {now} ns (|v| ≤ {STOPPED_V} m/s, |ω| ≤ {STOPPED_W} rad/s), told to at \
                     unix {since} ns by {why}, {:.3} s before",
                    plant.id,
                    now.saturating_sub(since) as f64 * 1e-9
                ));
                stopping = None;
            }
        }
        out.publish(clock.unix_ns() as i64, &plant)?;
    }
    Ok(())
}
