//! The virtual leader as a networked node (the `leader` binary): publishes
//! (k, t, P_r, Ṗ_r, v_r, ω_r) for the followers that hear it (docs/model.md §13),
//! its true state per step as telemetry for the monitor's metrics, and
//! leads the start barrier.
//!
//! In lock-step the leader has no inputs; it runs at most [`WINDOW`] steps
//! ahead of the slowest follower that hears it (it watches their estimate
//! keys), so its messages never pile up without bound.

use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use formation_agent::LeaderState;
use formation_topology::wire::{self, EstimateMsg, Header, FORMAT_VERSION};
use formation_topology::{Scenario, Timing};
use zenoh::pubsub::Publisher;
use zenoh::Wait;

use crate::barrier::Start;
use crate::clock;
use crate::clock_sync;
use crate::codec;
use crate::counters::Counters;
use crate::courier::Courier;
use crate::error::{zerr, Error};
use crate::gate::{self, Kept, WINDOW};
use crate::names::{self, Keys, MONITOR};
use crate::node::{estimate_congestion, NodeArgs};
use crate::pacing::Pacer;
use crate::ros2::topics::LeaderTopics;
use crate::startup;
use crate::telemetry::{self, Telemetry};

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

/// Lock-step: files a hearing follower's message (`slot`, received on the
/// key of `key_id`) in how far each has reached. Counted only from the
/// follower itself and for a step it can have reached: at most one past the
/// leader's newest (`published`). Whether it was counted.
fn note_reached(reached: &mut [Option<u64>], slot: usize, key_id: Option<u32>, h: &Header, published: u64) -> bool {
    if key_id != Some(h.sender) || h.step > published.saturating_add(1) || slot >= reached.len() {
        return false;
    }
    reached[slot] = Some(reached[slot].map_or(h.step, |x| x.max(h.step)));
    true
}

/// Lock-step: whether every hearing follower has reached `need` (0: the
/// leader is not waiting), by [`gate::window_open`].
fn window_reached(reached: &[Option<u64>], need: u64) -> bool {
    need > 0 && gate::window_open(reached, need)
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
    let session = args.node.open(crate::names::LEADER, &scenario).await?;
    tokio::spawn(crate::denials::report(session.clone(), crate::names::LEADER.to_string(), Some(keys.run.clone())));
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
    startup::refuse_twin(session, keys, wire::LEADER_ID, scenario.steps()).await?;
    // The run's timebase is this leader's clock; the others ask it from now on.
    let timebase = clock::Timebase::leader();
    let queries = Arc::new(crate::counters::QueryCount::default());
    let time_server = clock_sync::serve_counted(session, keys, timebase.clone(), queries.clone()).await?;
    let hearing: Vec<u32> =
        (0..scenario.graph.len()).filter(|&i| scenario.graph.hears_leader(i)).map(|i| scenario.graph.id(i)).collect();
    let progress = Arc::new(Reached {
        reached: Mutex::new(vec![None; hearing.len()]),
        published: std::sync::atomic::AtomicU64::new(0),
        need: std::sync::atomic::AtomicU64::new(0),
        moved: Condvar::new(),
    });
    let subs = watch_reached(session, keys, &hearing, &progress).await?;
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
    let (start, announcer) =
        startup::lead_start(session, keys, &timebase, &hellos, &ready, scenario, time_scale, lead).await?;
    if print_start {
        print_start_line(&start, &timebase);
    }

    let mut topics = match scenario.ros2 {
        Some(r) => Some(LeaderTopics::declare(session, scenario, r.domain_id, start.epoch_unix_ns).await?),
        None => None,
    };
    let scenario = scenario.clone();
    let timebase = timebase.clone();
    // Telemetry through a bounded store and its own thread (see agent.rs).
    let (delivery, acks) = telemetry::start_delivery(session, keys, wire::LEADER_ID, &scenario).await?;
    let courier = delivery.courier.clone();
    let outcome = tokio::task::spawn_blocking(move || {
        leader_loop(
            &scenario,
            lockstep,
            &start,
            &timebase,
            &progress,
            &estimate_pub,
            &courier,
            &followers_done,
            &queries,
            topics.as_mut(),
        )
    })
    .await
    .map_err(|e| Error::Run(format!("leader: loop panicked: {e}")))?;
    telemetry::finish_delivery(delivery, "leader").await;
    drop(acks);
    announcer.abort();
    drop(time_server);
    drop(subs);
    drop(done_subs);
    outcome.map_err(|e| Error::Run(format!("leader: {e}")))
}

/// Lock-step: one subscriber per hearing follower's estimate key, filing
/// how far each has reached ([`note_reached`]) and waking the loop when the
/// slowest reaches what it waits for.
async fn watch_reached(
    session: &zenoh::Session,
    keys: &Keys,
    hearing: &[u32],
    progress: &Arc<Reached>,
) -> Result<Vec<zenoh::pubsub::Subscriber<()>>, Error> {
    let mut subs = Vec::new();
    for (slot, &id) in hearing.iter().enumerate() {
        let p = progress.clone();
        let sub = session
            .declare_subscriber(keys.estimate(id))
            .callback(move |s| {
                let key_id = names::last_chunk(s.key_expr().as_str()).parse::<u32>().ok();
                let Ok(m) = wire::decode(&s.payload().to_bytes()) else { return };
                let published = p.published.load(std::sync::atomic::Ordering::Acquire);
                let mut r = p.reached.lock().unwrap_or_else(|e| e.into_inner());
                if note_reached(&mut r, slot, key_id, &m.header, published) {
                    let wake = window_reached(&r, p.need.load(std::sync::atomic::Ordering::Acquire));
                    drop(r);
                    if wake {
                        p.moved.notify_all();
                    }
                }
            })
            .await
            .map_err(|e| zerr("declaring a subscriber", e))?;
        subs.push(sub);
    }
    Ok(subs)
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

fn put(p: &Publisher<'_>, bytes: Vec<u8>) -> Result<(), Error> {
    p.put(bytes).wait().map_err(|e| zerr("publishing", e))
}

#[allow(clippy::too_many_arguments)]
fn leader_loop(
    s: &Scenario,
    lockstep: bool,
    start: &Start,
    timebase: &clock::Timebase,
    progress: &Reached,
    estimate_pub: &Publisher<'_>,
    telemetry: &Courier,
    followers_done: &Mutex<std::collections::BTreeSet<u32>>,
    queries: &crate::counters::QueryCount,
    mut topics: Option<&mut LeaderTopics>,
) -> Result<(), Error> {
    let steps = s.steps();
    let dt = s.dt_s;
    let batch_len = s.network.telemetry_batch.max(1) as usize;
    let msg = |k: u64, state: LeaderState| {
        wire::encode(&EstimateMsg {
            header: Header {
                version: FORMAT_VERSION,
                sender: wire::LEADER_ID,
                step: k,
                time_s: k as f64 * dt,
                sent_ns: timebase.now_ns().unwrap_or(0),
            },
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

    let mut pacer = (!lockstep).then(|| Pacer::new(start, dt, timebase.clone()));
    let mut batch: Vec<LeaderState> = Vec::with_capacity(batch_len);
    let mut first_k = 0u64;
    let incarnation = clock::unix_ns();
    for k in 0..=steps {
        let last = k == steps;
        if let Some(p) = pacer.as_mut() {
            p.wait(k);
        }
        batch.push(state);
        if let Some(t) = topics.as_deref_mut() {
            t.publish(k, &state)?;
        }
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
            (counters.time_queries, counters.time_queries_peak_per_s) = queries.read();
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
        linger(progress, estimate_pub, &recent, followers_done)?;
    }
    Ok(())
}

/// Lock-step, after the last step: a follower may still wait for one of
/// the last messages (lost?): repeat what the slowest may have missed until
/// every hearing follower reports its final step, for at most [`LINGER`].
fn linger(
    progress: &Reached,
    estimate_pub: &Publisher<'_>,
    recent: &Kept,
    followers_done: &Mutex<std::collections::BTreeSet<u32>>,
) -> Result<(), Error> {
    let hearing = progress.reached.lock().unwrap_or_else(|e| e.into_inner()).len();
    let mut linger = gate::Wait::new(clock::mono(), gate::LINGER_REPEAT_EVERY, LINGER);
    while let gate::WaitStep::Wait { repeat: again, .. } = linger.poll(clock::mono()) {
        if followers_done.lock().unwrap_or_else(|e| e.into_inner()).len() >= hearing {
            break;
        }
        if again {
            let slowest = gate::slowest_step(&progress.reached.lock().unwrap_or_else(|e| e.into_inner()));
            repeat(estimate_pub, recent, slowest)?;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    Ok(())
}

/// Repeats the kept messages the slowest hearing follower may lack; how many.
fn repeat(estimate_pub: &Publisher<'_>, recent: &Kept, slowest: u64) -> Result<u64, Error> {
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
) -> Result<(), Error> {
    let Some(need) = gate::leader_needs(k) else { return Ok(()) };
    let mut wait = gate::Wait::new(crate::clock::mono(), gate::LEADER_REPEAT_EVERY, gate::LEADER_STALL);
    let mut reached = progress.reached.lock().unwrap_or_else(|e| e.into_inner());
    // (Set under the lock the callbacks take: none can miss it.)
    progress.need.store(need, std::sync::atomic::Ordering::Release);
    loop {
        if gate::window_open(&reached, need) {
            progress.need.store(0, std::sync::atomic::Ordering::Release);
            return Ok(());
        }
        let (g, _) = progress.moved.wait_timeout(reached, gate::LEADER_REPEAT_EVERY).unwrap_or_else(|e| e.into_inner());
        reached = g;
        let now = crate::clock::mono();
        let gate::WaitStep::Wait { repeat: again, warn } = wait.poll(now) else {
            return Err(Error::Run(format!(
                "followers stopped before step {need} (no progress for {} s)",
                gate::LEADER_STALL.as_secs()
            )));
        };
        let slowest = gate::slowest_step(&reached);
        if warn {
            crate::node::say(&format!(
                "leader: waiting {:.0} s at step {k} for the followers that hear it (slowest at step {slowest}, \
                 {WINDOW} steps behind allowed); repeating steps {} on",
                wait.waited(now).as_secs_f64(),
                gate::leader_from_step(slowest)
            ));
        }
        // Safety net: repeat what the slowest follower may have missed, on
        // the wait's own clock: a follower that keeps publishing without
        // advancing (a restart waiting for these very messages) wakes this
        // wait at every message.
        if again {
            drop(reached);
            let n = repeat(estimate_pub, recent, slowest)?;
            counters.sent += n;
            counters.republished += n;
            reached = progress.reached.lock().unwrap_or_else(|e| e.into_inner());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(sender: u32, step: u64) -> Header {
        Header { version: FORMAT_VERSION, sender, step, time_s: 0.0, sent_ns: 0 }
    }

    #[test]
    fn a_follower_counts_only_on_its_own_key_and_never_beyond_the_leader() {
        let mut r = vec![None, None];
        assert!(note_reached(&mut r, 0, Some(1), &header(1, 5), 10));
        assert!(!note_reached(&mut r, 0, Some(2), &header(1, 7), 10), "forged: on another follower's key");
        assert!(!note_reached(&mut r, 0, None, &header(1, 7), 10), "a key that is no id");
        assert!(!note_reached(&mut r, 0, Some(1), &header(1, 12), 10), "beyond the leader's newest + 1");
        assert!(note_reached(&mut r, 0, Some(1), &header(1, 11), 10), "one past the leader's newest");
        assert!(note_reached(&mut r, 0, Some(1), &header(1, 3), 10), "an old repeat");
        assert_eq!(r, [Some(11), None], "the furthest step counts");
        assert!(!note_reached(&mut r, 5, Some(1), &header(1, 3), 10), "a slot out of range");
    }

    #[test]
    fn the_window_opens_when_every_hearing_follower_reached_the_step() {
        assert!(!window_reached(&[Some(9), None], 5), "one not heard yet");
        assert!(!window_reached(&[Some(9), Some(4)], 5));
        assert!(window_reached(&[Some(9), Some(5)], 5));
        assert!(!window_reached(&[Some(9), Some(5)], 0), "not waiting");
        assert!(window_reached(&[], 5), "nobody hears the leader");
    }
}
