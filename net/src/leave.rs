//! `formation leave --id ID`: asks follower ID of a running formation to
//! leave the run for good (docs/model.md §14), as SIGTERM to its agent
//! would, from any host that reaches the run: it puts on
//! `control/leave/<id>` until the follower's last telemetry says it left,
//! and says when. (With `--tls` it speaks with the monitor's certificate:
//! the operator's console.)
//!
//! Before it asks, it learns who is not running: the followers absent at
//! the start (the leader's start, repeated through the run, names them)
//! and those whose telemetry it does not hear for five batches (at least
//! 1 s), and then 2 s more (left, or gone). It refuses, in one line and
//! before asking, a follower that is not running, and a leave that with
//! those cuts a running follower off from the leader (Lemma 1).

use std::time::Duration;

use formation_exit::{zerr, Error};
use formation_protocol::codec;
use formation_protocol::names::MONITOR;
use formation_protocol::telemetry::{Telemetry, MAX_LEFT_WHY};

use crate::node::NodeArgs;

/// `formation leave` arguments.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct LeaveArgs {
    #[cfg_attr(feature = "clap", command(flatten))]
    pub node: NodeArgs,
    /// The follower that leaves.
    #[cfg_attr(feature = "clap", arg(long, value_name = "ID"))]
    pub id: u32,
    /// Leave even if, without this follower, others no longer reach the
    /// leader (Lemma 1; else refused, naming them).
    #[cfg_attr(feature = "clap", arg(long))]
    pub even_if_cut_off: bool,
    /// Give up when the follower has not said it left within this long (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 5.0, value_name = "SECONDS"))]
    pub timeout: f64,
}

/// How often the request is said until the follower answers.
const ASK_EVERY: Duration = Duration::from_millis(100);

/// Asks follower `--id` to leave; returns the line that says when it did.
pub async fn run(a: &LeaveArgs) -> Result<String, Error> {
    let (scenario, keys) = a.node.load(MONITOR)?;
    let id = a.id;
    if scenario.index_of(id).is_none() {
        let ids = formation_scenario::graph::id_list(scenario.graph.ids());
        return Err(Error::Input(format!("scenario {} has no follower {id} (ids: {ids})", scenario.name)));
    }
    if !(a.timeout.is_finite() && a.timeout > 0.0) {
        return Err(Error::Input(format!("--timeout must be a positive number of seconds, not {}", a.timeout)));
    }
    // Alone (before anything is asked of the network), then beside those not running.
    if let Some(cut) = scenario.graph.cut_off_without(&[id]).filter(|_| !a.even_if_cut_off) {
        return Err(Error::Input(format!(
            "formation leave --id {id}: {cut}: their estimates of the leader would drift (--even-if-cut-off to \
             leave anyway)"
        )));
    }
    let session = a.node.open(MONITOR, &scenario).await?;
    let out = not_running(&session, &keys, &scenario).await?;
    let cut = newly_cut_off(&scenario.graph, &out, id);
    let refusal = if out.contains(&id) {
        Some(format!(
            "formation leave --id {id}: follower {id} is not running in run {} (absent at the start, or its \
             telemetry silent for {:.1} s: it left, or is gone)",
            keys.run,
            (listen_for(&scenario) + LISTEN_MORE).as_secs_f64()
        ))
    } else {
        cut.as_ref().filter(|_| !a.even_if_cut_off).map(|cut| {
            format!(
                "formation leave --id {id}: {cut}: their estimates of the leader would drift (--even-if-cut-off to \
                 leave anyway)"
            )
        })
    };
    if let Some(line) = refusal {
        let _ = tokio::time::timeout(Duration::from_secs(1), session.close()).await;
        return Err(Error::Input(line));
    }
    let (tx, mut rx) = tokio::sync::mpsc::channel::<(u64, String)>(4);
    let _sub = session
        .declare_subscriber(keys.telemetry(id))
        .callback(move |s| {
            if let Some(Telemetry::Follower { id: from, left: Some(l), .. }) =
                codec::decode::<Telemetry>(&s.payload().to_bytes())
            {
                if from == id {
                    let _ =
                        tx.try_send((l.at_k, l.why.chars().filter(|c| !c.is_control()).take(MAX_LEFT_WHY).collect()));
                }
            }
        })
        .await
        .map_err(|e| zerr("listening to the follower's telemetry", e))?;
    let clock = &a.node.clock;
    let limit = clock.mono() + Duration::from_secs_f64(a.timeout);
    let left = loop {
        session.put(keys.leave(id), Vec::<u8>::new()).await.map_err(|e| zerr("asking the follower to leave", e))?;
        tokio::select! {
            l = rx.recv() => break l,
            _ = clock.pause(ASK_EVERY) => {}
        }
        if clock.mono() >= limit {
            break None;
        }
    };
    let _ = tokio::time::timeout(Duration::from_secs(1), session.close()).await;
    match left {
        Some((k, why)) => Ok(format!(
            "follower {id} left run {} at t = {:.3} s ({why}){}",
            keys.run,
            k as f64 * scenario.dt_s,
            if cut.is_none() { "" } else { " — the others it cut off from the leader now drift" }
        )),
        None => Err(Error::Run(format!(
            "follower {id} of run {} did not say it left within {} s: is its agent running, in this run (--run), \
             and reachable from here?",
            keys.run, a.timeout
        ))),
    }
}

/// How much longer `formation leave` listens when a follower is not heard
/// within [`listen_for`].
const LISTEN_MORE: Duration = Duration::from_secs(2);

/// How long `formation leave` listens for the followers' telemetry: five
/// batches of the scenario (on its time scale), at least 1 s.
fn listen_for(scenario: &formation_scenario::Scenario) -> Duration {
    let batch_s =
        scenario.network.telemetry_batch.max(1) as f64 * scenario.dt_s / scenario.network.time_scale.max(1e-3);
    Duration::from_secs_f64((5.0 * batch_s).clamp(1.0, 10.0))
}

/// The followers not running in the run: absent at the start (the
/// leader's start names them), or none of whose telemetry is heard for
/// [`listen_for`]. Empty when nothing of the run is heard (then the ask
/// itself says the run is not reachable).
async fn not_running(
    session: &zenoh::Session,
    keys: &formation_protocol::names::Keys,
    scenario: &formation_scenario::Scenario,
) -> Result<Vec<u32>, Error> {
    use std::collections::BTreeSet;
    use std::sync::{Arc, Mutex};
    let heard: Arc<Mutex<(BTreeSet<u32>, Option<Vec<u32>>)>> = Arc::default();
    let h = heard.clone();
    let _telemetry = session
        .declare_subscriber(keys.telemetry_all())
        .callback(move |s| {
            if let Some(Telemetry::Follower { id, left: None, .. }) =
                codec::decode::<Telemetry>(&s.payload().to_bytes())
            {
                h.lock().unwrap_or_else(|p| p.into_inner()).0.insert(id);
            }
        })
        .await
        .map_err(|e| zerr("listening to the followers' telemetry", e))?;
    let h = heard.clone();
    let _start = session
        .declare_subscriber(keys.start())
        .callback(move |s| {
            if let Some(start) = codec::decode::<formation_protocol::barrier::Start>(&s.payload().to_bytes()) {
                h.lock().unwrap_or_else(|p| p.into_inner()).1 = Some(start.absent);
            }
        })
        .await
        .map_err(|e| zerr("listening to the run's start", e))?;
    tokio::time::sleep(listen_for(scenario)).await;
    // A follower not heard yet may be slow rather than gone (a loaded
    // host): it gets [`LISTEN_MORE`] more before it is counted out.
    let unheard = |h: &(BTreeSet<u32>, Option<Vec<u32>>)| {
        let absent = h.1.clone().unwrap_or_default();
        scenario.graph.ids().iter().any(|i| !h.0.contains(i) && !absent.contains(i))
    };
    let nothing = |h: &(BTreeSet<u32>, Option<Vec<u32>>)| h.0.is_empty() && h.1.is_none();
    let first = heard.lock().unwrap_or_else(|p| p.into_inner()).clone();
    if !nothing(&first) && unheard(&first) {
        tokio::time::sleep(LISTEN_MORE).await;
    }
    let (running, absent) = heard.lock().unwrap_or_else(|p| p.into_inner()).clone();
    if nothing(&(running.clone(), absent.clone())) {
        return Ok(Vec::new());
    }
    let absent = absent.unwrap_or_default();
    Ok(scenario.graph.ids().iter().copied().filter(|i| absent.contains(i) || !running.contains(i)).collect())
}

/// Lemma 1 for a leave beside those not running (`out`): the line naming
/// the running followers that `id` leaving would cut off from the leader
/// (those already cut off before are not its doing), or None.
fn newly_cut_off(graph: &formation_scenario::graph::Graph, out: &[u32], id: u32) -> Option<String> {
    use formation_scenario::graph::followers_named;
    let before = graph.unreachable_without(out);
    let all: Vec<u32> = out.iter().copied().chain([id]).collect();
    let cut: Vec<u32> = graph.unreachable_without(&all).into_iter().filter(|i| !before.contains(i)).collect();
    if cut.is_empty() {
        return None;
    }
    Some(format!("without {}, {}", followers_named(&all), formation_scenario::graph::no_longer_reach(&cut)))
}
