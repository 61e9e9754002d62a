//! The virtual leader as a networked node (the `leader` binary): a
//! translation between zenoh and [`formation_protocol::leader::LeaderMachine`],
//! which holds every rule (the trajectory, the lock-step window, pacing,
//! stamping, repeats, the linger, telemetry batches). Subscriber callbacks
//! feed it the estimates of the followers that hear it; a loop on a thread
//! of its own tells it the time, publishes what it answers, hands its
//! telemetry to the courier and sleeps until its next deadline. The node
//! also serves the run's timebase (its clock) and leads the start barrier.

use std::sync::Arc;
use std::time::Duration;

use formation_protocol::wire;
use formation_scenario::{Scenario, Timing};

use crate::clock;
use crate::clock_sync;
use crate::lead_loop::{watch_leader_key, watch_reached, LeadLoop};
use crate::node::{NodeArgs, Shared};
use crate::ros2::topics::LeaderTopics;
use crate::startup;
use crate::telemetry;
use formation_exit::Error;
use formation_protocol::barrier::{Quorum, Start};
use formation_protocol::counters::QueryCount;
use formation_protocol::leader::LeaderMachine as Machine;
use formation_protocol::names::{self, Keys, MONITOR};

/// `leader` arguments.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct LeaderArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub node: NodeArgs,
    /// Real-time mode: run time per wall-clock second [default: network.time_scale].
    #[cfg_attr(feature = "clap", arg(long, value_name = "X"))]
    pub time_scale: Option<f64>,
    /// Real-time mode: the epoch is announced this long before step 0 (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.5, value_name = "SECONDS"))]
    pub start_lead: f64,
    /// Print `start <epoch ns since the Unix epoch> <time scale>` on stdout
    /// once the run starts (for `formation lab`, which times faults by it).
    #[cfg_attr(feature = "clap", arg(long, hide = true))]
    pub print_start: bool,
    /// Start with those present: once --quorum-wait has passed (10 s if not
    /// given), start when N followers (and the monitor) are ready; the
    /// others are absent from the run, named in one line and in
    /// network.json [default: every follower].
    #[cfg_attr(feature = "clap", arg(long, value_name = "N"))]
    pub quorum: Option<usize>,
    /// With --quorum: start even if, without the absent followers, some
    /// present ones no longer reach the leader (else refused, naming them).
    #[cfg_attr(feature = "clap", arg(long, requires = "quorum"))]
    pub even_if_cut_off: bool,
    /// Stand by for the leader of a run (another process, on this host or
    /// another): take the run over, on its timebase and trajectory, once
    /// the leader has been silent for --take-over-after (docs/model.md §14).
    /// A leader gone before the run began (its claim on the run silent for
    /// --take-over-after, at least 1 s) is replaced from the start: this
    /// process then leads the start barrier itself (with --quorum, if given).
    #[cfg_attr(feature = "clap", arg(long, conflicts_with = "print_start"))]
    pub standby: bool,
    /// With --standby: how long the leader's silence lasts before this
    /// process takes over (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 0.5, value_name = "SECONDS", requires = "standby"))]
    pub take_over_after: f64,
}

/// How long a leader with --quorum but no --quorum-wait waits for everyone.
pub const QUORUM_WAIT: Duration = Duration::from_secs(10);

impl LeaderArgs {
    /// The quorum asked for, checked against the formation (exit 2).
    pub fn quorum(&self, scenario: &Scenario) -> Result<Option<Quorum>, Error> {
        let Some(followers) = self.quorum else { return Ok(None) };
        let wait = self.node.quorum_wait()?.unwrap_or(QUORUM_WAIT);
        let q = Quorum { followers, wait, even_if_cut_off: self.even_if_cut_off };
        q.check(scenario.graph.len()).map_err(Error::Input)?;
        Ok(Some(q))
    }
}

/// The leader node from its arguments to the end of its run, or until
/// `shutdown` (SIGINT or SIGTERM in the binary), which it returns: it stops
/// announcing the run's state at once and closes its session.
pub async fn run(
    args: &LeaderArgs,
    shutdown: impl std::future::Future<Output = formation_exit::shutdown::Signal>,
) -> Result<Option<formation_exit::shutdown::Signal>, Error> {
    let (scenario, keys) = args.node.load(names::LEADER)?;
    let time_scale = args.time_scale.unwrap_or(scenario.network.time_scale);
    if !(time_scale.is_finite() && time_scale > 0.0) {
        return Err(Error::Input(format!("--time-scale must be a positive number, not {time_scale}")));
    }
    if !(args.start_lead.is_finite() && args.start_lead >= 0.0) {
        return Err(Error::Input("--start-lead must be ≥ 0".into()));
    }
    let quorum = args.quorum(&scenario)?;
    if let (true, Some(source)) = (args.standby, scenario.live_leader()) {
        return Err(Error::Input(format!(
            "--standby: a leader steered live (leader.source = \"{source}\") cannot be taken over: a standby does not \
             hear what steers it; run without a standby"
        )));
    }
    let after = args.take_over_after;
    if !(after.is_finite() && after > 0.0) {
        return Err(Error::Input(format!("--take-over-after must be a positive number of seconds, not {after}")));
    }
    let session = args.node.open(names::LEADER, &scenario).await?;
    tokio::spawn(crate::denials::report(session.clone(), names::LEADER.to_string(), Some(keys.run.clone())));
    let lead = Duration::from_secs_f64(args.start_lead);
    let mut start = StartAs { time_scale, lead, print: args.print_start, quorum, standby: false, timebase: None };
    let clock = &args.node.clock;
    let leading = async {
        match args.standby {
            true => {
                match crate::standby::run(&session, &scenario, &keys, Duration::from_secs_f64(after), clock).await {
                    Ok(crate::standby::Ended::GoneBeforeStart(timebase)) => {
                        (start.standby, start.timebase) = (true, timebase);
                        run_leader(&session, &scenario, &keys, start, clock).await
                    }
                    other => other.map(drop),
                }
            }
            false => run_leader(&session, &scenario, &keys, start, clock).await,
        }
    };
    let result = tokio::select! {
        r = leading => r.map(|()| None),
        s = shutdown => Ok(Some(s)),
    };
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    result
}

/// How the leader starts its run: the time scale, how long before step 0
/// the epoch is announced (real time), whether the start is printed (for
/// `formation lab`), a quorum start if asked, and whether a standby leads
/// it (the leader gone before the start).
pub struct StartAs {
    pub time_scale: f64,
    pub lead: Duration,
    pub print: bool,
    pub quorum: Option<Quorum>,
    pub standby: bool,
    /// The run's timebase where it is not this process's own clock: a
    /// standby's estimate of the gone leader's, which the others follow.
    pub timebase: Option<clock::Timebase>,
}

pub async fn run_leader(
    session: &zenoh::Session,
    scenario: &Scenario,
    keys: &Keys,
    start_as: StartAs,
    clock: &clock::Clock,
) -> Result<(), Error> {
    let StartAs { time_scale, lead: start_lead, print: print_start, quorum, standby, timebase } = start_as;
    // A second formation with this run name: refuse before saying anything.
    let claiming = startup::refuse_twin(session, keys, wire::LEADER_ID, scenario.steps(), clock).await?;
    // The run's timebase is this leader's clock (a standby's estimate of
    // the gone leader's, which the others follow already); they ask it.
    let timebase = timebase.unwrap_or_else(|| clock::Timebase::leader(clock));
    let queries = Arc::new(QueryCount::default());
    let time_server = clock_sync::serve_counted(session, keys, timebase.clone(), queries.clone()).await?;
    let mut machine = Machine::new(scenario);
    if standby {
        machine.led_by_a_standby_from_the_start();
    }
    let hearing = machine.hearing().to_vec();
    let shared = Arc::new(Shared::new(machine));
    let subs = watch_reached(session, keys, &hearing, &shared).await?;
    let steered = crate::ros2::steer::subscribe(session, scenario, &shared, &timebase).await?;
    let estimate_pub =
        crate::node::control_publisher(session, keys.estimate(wire::LEADER_ID), scenario, "estimate").await?;

    let lockstep = scenario.timing == Timing::Lockstep;
    // Lock-step: which hearing followers have completed the final step.
    let (done_subs, followers_done) = if lockstep {
        telemetry::watch_done(session, keys, &hearing, scenario).await?
    } else {
        (Vec::new(), Default::default())
    };
    let hellos: Vec<String> = hearing.iter().map(u32::to_string).collect();
    let mut ready: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
    ready.push(MONITOR.to_string());
    let lead = if lockstep { Duration::ZERO } else { start_lead };
    let (start, announcer) =
        startup::lead_start(session, keys, &timebase, &hellos, &ready, scenario, time_scale, lead, quorum).await?;
    if !start.absent.is_empty() {
        crate::node::say(&absent_line(&start.absent, scenario));
    }
    if print_start {
        print_start_line(&start, &timebase);
    }

    // A leader robot publishes its own odometry and transforms.
    let robot = scenario.leader_profile.trajectory == formation_leader::Trajectory::External;
    let topics = match scenario.ros2 {
        Some(r) if !robot => Some(LeaderTopics::declare(session, scenario, r.domain_id, start.epoch_unix_ns).await?),
        _ => None,
    };
    // Telemetry through a bounded store and its own thread (see agent.rs).
    let (delivery, acks) = telemetry::start_delivery(session, keys, wire::LEADER_ID, scenario, clock).await?;
    {
        let mut m = shared.lock();
        m.start(&start, timebase.now());
        for &id in &start.absent {
            m.handle_gone(id);
        }
    }
    // From the start on: the claim to lead in this leader's term, and what
    // tells it that a standby took the run over in a higher one.
    drop(claiming);
    let term = shared.lock().term();
    let watcher = startup::Leading::claim(session, keys, clock, term).await?.watch(shared.clone(), keys.run.clone());
    let key_watch = watch_leader_key(session, keys, &shared, &timebase).await?;
    let node = LeadLoop {
        shared: shared.clone(),
        publisher: estimate_pub,
        courier: delivery.courier.clone(),
        timebase: timebase.clone(),
        followers_done,
        queries,
        topics,
        lockstep,
        incarnation: clock.unix_ns(),
        on_take_over: None,
    };
    let outcome = tokio::task::spawn_blocking(move || node.drive())
        .await
        .map_err(|e| Error::Run(format!("leader: loop panicked: {e}")))?;
    telemetry::finish_delivery(delivery, "leader").await;
    drop(acks);
    announcer.abort();
    watcher.abort();
    drop(key_watch);
    drop(time_server);
    drop(subs);
    drop(done_subs);
    if let Some(n) = steered.map(|s| s.refused.load(std::sync::atomic::Ordering::Relaxed)).filter(|&n| n > 0) {
        crate::node::say(&format!("leader: {n} message(s) of its source refused (undecodable, or in another frame)"));
    }
    outcome.map_err(|e| Error::Run(format!("leader: {e}")))
}

/// The leader's one line on a quorum start: who is absent, and whether the
/// others still reach the leader (Lemma 1).
fn absent_line(absent: &[u32], scenario: &Scenario) -> String {
    use formation_scenario::graph::followers_named;
    let cut = scenario.graph.unreachable_without(absent);
    let reach = match cut.len() {
        0 => "every present follower reaches the leader".to_string(),
        1 => format!("{} does not reach the leader (--even-if-cut-off)", followers_named(&cut)),
        _ => format!("{} do not reach the leader (--even-if-cut-off)", followers_named(&cut)),
    };
    format!("leader: started without {} (absent: not ready within the quorum wait); {reach}", followers_named(absent))
}

/// `start <epoch ns> <time scale> <ns ahead>` on stdout: the epoch, and how
/// far ahead of now it is on the leader's own clock (for a lab whose clock
/// is not the leader's).
fn print_start_line(start: &Start, timebase: &clock::Timebase) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let ahead = start.epoch_unix_ns as i64 - timebase.now_ns().unwrap_or(0);
    let _ = writeln!(out, "start {} {} {ahead}", start.epoch_unix_ns, start.time_scale).and_then(|()| out.flush());
}
