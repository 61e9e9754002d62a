//! The virtual leader as a networked node (the `leader` binary): publishes
//! (k, t, P_r, Ṗ_r, v_r, ω_r) for the followers that hear it (docs/model.md §13),
//! its true state per step as telemetry for the monitor's metrics, and
//! leads the start barrier.
//!
//! In lock-step the leader has no inputs; it runs at most [`WINDOW`] steps
//! ahead of the slowest follower that hears it (it watches their estimate
//! keys), so its messages never pile up without bound.

use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use formation_agent::LeaderState;
use formation_topology::wire::{self, EstimateMsg, Header, FORMAT_VERSION};
use formation_topology::{Scenario, Timing};
use zenoh::pubsub::Publisher;
use zenoh::Wait;

use crate::barrier::{self, Start};
use crate::codec;
use crate::counters::Counters;
use crate::courier::Courier;
use crate::error::{zerr, Error};
use crate::gate::{self, Kept, WINDOW};
use crate::names::{self, Keys, MONITOR};
use crate::node::{estimate_congestion, NodeArgs};
use crate::telemetry::{self, Telemetry};
use crate::timing::Pacer;

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
}

struct Reached {
    /// Latest step each hearing follower has published (i.e. reached).
    reached: Mutex<Vec<Option<u64>>>,
    /// The latest step the leader has published: a follower that hears it
    /// cannot be more than one step further (a claim beyond is forged).
    published: std::sync::atomic::AtomicU64,
    /// The step every hearing follower must reach for the leader's wait to
    /// end (0: not waiting): only the message that gets the slowest there
    /// wakes it, not every message.
    need: std::sync::atomic::AtomicU64,
    moved: Condvar,
}

pub async fn run(args: &LeaderArgs) -> Result<(), Error> {
    let (scenario, keys) = args.node.load(crate::names::LEADER)?;
    let time_scale = args.time_scale.unwrap_or(scenario.network.time_scale);
    if !(time_scale.is_finite() && time_scale > 0.0) {
        return Err(Error::Input(format!("--time-scale must be a positive number, not {time_scale}")));
    }
    if !(args.start_lead.is_finite() && args.start_lead >= 0.0) {
        return Err(Error::Input("--start-lead must be ≥ 0".into()));
    }
    let session = args.node.open(crate::names::LEADER).await?;
    let lead = Duration::from_secs_f64(args.start_lead);
    let result = run_leader(&session, &scenario, &keys, time_scale, lead, args.print_start).await;
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    result
}

pub async fn run_leader(
    session: &zenoh::Session,
    scenario: &Scenario,
    keys: &Keys,
    time_scale: f64,
    start_lead: Duration,
    print_start: bool,
) -> Result<(), Error> {
    // A second formation with this run name: refuse before saying anything.
    barrier::refuse_twin(session, keys, wire::LEADER_ID, scenario.steps()).await?;
    let hearing: Vec<u32> =
        (0..scenario.graph.len()).filter(|&i| scenario.graph.hears_leader(i)).map(|i| scenario.graph.id(i)).collect();
    let progress = Arc::new(Reached {
        reached: Mutex::new(vec![None; hearing.len()]),
        published: std::sync::atomic::AtomicU64::new(0),
        need: std::sync::atomic::AtomicU64::new(0),
        moved: Condvar::new(),
    });
    let mut subs = Vec::new();
    for (slot, &id) in hearing.iter().enumerate() {
        let p = progress.clone();
        subs.push(
            session
                .declare_subscriber(keys.estimate(id))
                .callback(move |s| {
                    let key_id = names::last_chunk(s.key_expr().as_str()).parse::<u32>().ok();
                    if let Ok(m) = wire::decode(&s.payload().to_bytes()) {
                        let published = p.published.load(std::sync::atomic::Ordering::Acquire);
                        if key_id == Some(m.header.sender) && m.header.step <= published.saturating_add(1) {
                            let mut r = p.reached.lock().unwrap_or_else(|e| e.into_inner());
                            r[slot] = Some(r[slot].map_or(m.header.step, |x| x.max(m.header.step)));
                            let need = p.need.load(std::sync::atomic::Ordering::Acquire);
                            let wake = need > 0 && r.iter().all(|x| x.is_some_and(|x| x >= need));
                            drop(r);
                            if wake {
                                p.moved.notify_all();
                            }
                        }
                    }
                })
                .await
                .map_err(|e| zerr("declaring a subscriber", e))?,
        );
    }
    let estimate_pub = session
        .declare_publisher(keys.estimate(wire::LEADER_ID))
        .congestion_control(estimate_congestion(scenario))
        .priority(crate::node::priority::ESTIMATE)
        .express(crate::node::estimate_express(scenario))
        .await
        .map_err(|e| zerr("declaring the estimate publisher", e))?;

    let lockstep = scenario.timing == Timing::Lockstep;
    // Lock-step: which hearing followers have completed the final step.
    let (done_subs, followers_done) = if lockstep {
        telemetry::watch_done(session, keys, &hearing, scenario.steps()).await?
    } else {
        (Vec::new(), Default::default())
    };
    let hellos: Vec<String> = hearing.iter().map(u32::to_string).collect();
    let mut ready: Vec<String> = scenario.graph.ids().iter().map(u32::to_string).collect();
    ready.push(MONITOR.to_string());
    let lead = if lockstep { Duration::ZERO } else { start_lead };
    let (start, announcer) = barrier::lead_start(session, keys, &hellos, &ready, scenario, time_scale, lead).await?;
    if print_start {
        use std::io::Write;
        let mut out = std::io::stdout().lock();
        let _ = writeln!(out, "start {} {}", start.epoch_unix_ns, start.time_scale).and_then(|()| out.flush());
    }

    let scenario = scenario.clone();
    // Telemetry through a bounded store and its own thread (see agent.rs).
    let (delivery, acks) = telemetry::start_delivery(session, keys, wire::LEADER_ID, &scenario).await?;
    let courier = delivery.courier.clone();
    let outcome = tokio::task::spawn_blocking(move || {
        leader_loop(&scenario, lockstep, &start, &progress, &estimate_pub, &courier, &followers_done)
    })
    .await
    .map_err(|e| Error::Run(format!("leader: loop panicked: {e}")))?;
    telemetry::finish_delivery(delivery, "leader").await;
    drop(acks);
    announcer.abort();
    drop(subs);
    drop(done_subs);
    outcome.map_err(|e| Error::Run(format!("leader: {e}")))
}

fn put(p: &Publisher<'_>, bytes: Vec<u8>) -> Result<(), String> {
    p.put(bytes).wait().map_err(|e| format!("publishing: {e}"))
}

fn leader_loop(
    s: &Scenario,
    lockstep: bool,
    start: &Start,
    progress: &Reached,
    estimate_pub: &Publisher<'_>,
    telemetry: &Courier,
    followers_done: &Mutex<std::collections::BTreeSet<u32>>,
) -> Result<(), String> {
    let steps = s.steps();
    let dt = s.dt_s;
    let batch_len = s.network.telemetry_batch.max(1) as usize;
    let msg = |k: u64, state: LeaderState| {
        wire::encode(&EstimateMsg {
            header: Header { version: FORMAT_VERSION, sender: wire::LEADER_ID, step: k, time_s: k as f64 * dt },
            state,
            fresh: true,
        })
    };
    let mut leader = s.leader();
    let mut counters = Counters::default();
    // Lock-step: the last WINDOW messages, republished if followers stall.
    let mut recent = Kept::new(gate::LEADER_KEPT);
    let mut state = leader.state(0.0);
    let first = msg(0, state);
    put(estimate_pub, first.clone())?;
    counters.sent += 1;
    recent.push(0, first);

    let mut pacer = (!lockstep).then(|| Pacer::new(start, dt));
    let mut batch: Vec<LeaderState> = Vec::with_capacity(batch_len);
    let mut first_k = 0u64;
    let incarnation = barrier::unix_ns();
    for k in 0..=steps {
        let last = k == steps;
        if let Some(p) = pacer.as_mut() {
            p.wait(k);
        }
        batch.push(state);
        if !last {
            leader.advance(&state, dt);
            state = leader.state((k + 1) as f64 * dt);
            if lockstep {
                wait_window(k + 1, progress, estimate_pub, &recent, &mut counters)?;
            }
            let bytes = msg(k + 1, state);
            progress.published.store(k + 1, std::sync::atomic::Ordering::Release);
            put(estimate_pub, bytes.clone())?;
            counters.sent += 1;
            if lockstep {
                recent.push(k + 1, bytes);
            }
        }
        if batch.len() >= batch_len || last {
            let t = Telemetry::Leader {
                first_k,
                states: std::mem::take(&mut batch),
                counters,
                done: last,
                loop_stats: if last { pacer.as_ref().map(Pacer::stats) } else { None },
                delivery: telemetry::Delivery {
                    available_from: telemetry.available_from(first_k),
                    incarnation,
                    courier: telemetry.stats(),
                },
            };
            telemetry.push(first_k, k + 1, codec::encode(&t));
            first_k = k + 1;
        }
    }
    if lockstep {
        // A follower may still wait for one of the last messages (lost?):
        // repeat what the slowest may have missed until every hearing
        // follower reports its final step, for at most LINGER.
        let hearing = progress.reached.lock().unwrap_or_else(|e| e.into_inner()).len();
        let began = Instant::now();
        let mut said = Instant::now();
        while began.elapsed() < LINGER {
            if followers_done.lock().unwrap_or_else(|e| e.into_inner()).len() >= hearing {
                break;
            }
            if said.elapsed() >= Duration::from_millis(200) {
                let slowest = gate::slowest_step(&progress.reached.lock().unwrap_or_else(|e| e.into_inner()));
                repeat(estimate_pub, &recent, slowest)?;
                said = Instant::now();
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    Ok(())
}

/// Repeats the kept messages the slowest hearing follower may lack; how many.
fn repeat(estimate_pub: &Publisher<'_>, recent: &Kept, slowest: u64) -> Result<u64, String> {
    let mut n = 0;
    for bytes in recent.leader_repeats(slowest) {
        put(estimate_pub, bytes.clone())?;
        n += 1;
    }
    Ok(n)
}

/// Lock-step: how long the leader keeps republishing after its last step.
const LINGER: Duration = Duration::from_secs(2);

/// Lock-step: waits until every hearing follower has reached step k − WINDOW.
fn wait_window(
    k: u64,
    progress: &Reached,
    estimate_pub: &Publisher<'_>,
    recent: &Kept,
    counters: &mut Counters,
) -> Result<(), String> {
    let Some(need) = k.checked_sub(WINDOW) else { return Ok(()) };
    let waited = Instant::now();
    let mut said = Instant::now();
    let mut warned = false;
    let mut reached = progress.reached.lock().unwrap_or_else(|e| e.into_inner());
    // (Set under the lock the callbacks take: none can miss it.)
    progress.need.store(need, std::sync::atomic::Ordering::Release);
    loop {
        let slowest = reached.iter().map(|r| r.unwrap_or(0)).min().unwrap_or(u64::MAX);
        if slowest >= need {
            progress.need.store(0, std::sync::atomic::Ordering::Release);
            return Ok(());
        }
        let (g, _) =
            progress.moved.wait_timeout(reached, Duration::from_millis(200)).unwrap_or_else(|e| e.into_inner());
        reached = g;
        if waited.elapsed() > Duration::from_secs(60) {
            return Err(format!("followers stopped before step {need} (no progress for 60 s)"));
        }
        // Safety net: repeat what the slowest follower may have missed, on a
        // clock of our own: a follower that keeps publishing without
        // advancing (a restart waiting for these very messages) wakes this
        // wait at every message.
        if said.elapsed() >= Duration::from_millis(200) {
            let slowest = gate::slowest_step(&reached);
            if !warned && waited.elapsed() > gate::STALL_WARNING {
                warned = true;
                crate::node::say(&format!(
                    "leader: waiting {:.0} s at step {k} for the followers that hear it (slowest at step {slowest}, \
                     {WINDOW} steps behind allowed); repeating steps {} on",
                    waited.elapsed().as_secs_f64(),
                    gate::leader_from_step(slowest)
                ));
            }
            drop(reached);
            let n = repeat(estimate_pub, recent, slowest)?;
            counters.sent += n;
            counters.republished += n;
            said = Instant::now();
            reached = progress.reached.lock().unwrap_or_else(|e| e.into_inner());
        }
    }
}
