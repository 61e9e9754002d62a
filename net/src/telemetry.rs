//! Telemetry for the monitor: every step of a node, in batches, on
//! `telemetry/<id>`. Never feeds control.

use formation_agent::LeaderState;
use serde::{Deserialize, Serialize};

use crate::codec::decode;
use crate::counters::Counters;
use crate::courier::CourierStats;
use crate::error::Error;
use crate::names::Keys;
use crate::timing::LoopStats;
use formation_record::FollowerSample;

/// Telemetry for the monitor: every step of a node, in batches. Never feeds control.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Telemetry {
    Follower {
        id: u32,
        /// Step of `samples[0]`.
        first_k: u64,
        samples: Vec<FollowerSample>,
        counters: Counters,
        /// The node has sent its final step.
        done: bool,
        loop_stats: Option<LoopStats>,
        delivery: Delivery,
        /// What the network did to this node during the batch's steps.
        events: Vec<NetEvent>,
    },
    Leader {
        first_k: u64,
        /// The true leader state at steps first_k, first_k + 1, …
        states: Vec<LeaderState>,
        counters: Counters,
        done: bool,
        loop_stats: Option<LoopStats>,
        delivery: Delivery,
    },
}

/// How the sender's telemetry gets through (see [`crate::courier`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Delivery {
    /// Steps below this that the monitor does not hold will never come
    /// (dropped from a full store, or produced by an earlier process).
    pub available_from: u64,
    /// This process's start (ns since the Unix epoch): a new value from the
    /// same node means it was restarted.
    pub incarnation: u64,
    pub courier: CourierStats,
}

/// One entry of a node's network timeline (`network.json`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct NetEvent {
    /// The step at which the node noticed.
    pub k: u64,
    pub what: EventKind,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub enum EventKind {
    /// A source (0: the leader) is heard again, or for the first time.
    Heard(u32),
    /// A source fell silent (nothing newer than `network.silence_timeout`).
    Silent(u32),
    /// The session lost its last router (client mode).
    RouterLost,
    /// The session has a router again.
    RouterBack,
    /// No source heard for `network.rejoin_after`: the estimate dead-reckons.
    Isolated,
    /// A source heard again after isolation (docs/model.md §14's rejoin).
    Rejoined,
}

impl EventKind {
    pub fn describe(&self) -> String {
        let name = |s: u32| if s == 0 { "the leader".to_string() } else { format!("follower {s}") };
        match *self {
            EventKind::Heard(s) => format!("hears {}", name(s)),
            EventKind::Silent(s) => format!("{} silent", name(s)),
            EventKind::RouterLost => "router lost".into(),
            EventKind::RouterBack => "router back".into(),
            EventKind::Isolated => "isolated: no source heard, dead-reckoning".into(),
            EventKind::Rejoined => "rejoined".into(),
        }
    }
}

/// The monitor's acknowledgements on `control/ack`, about every 100 ms:
/// per node (0: the leader), the first step it does not hold.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Ack {
    pub fingerprint: u64,
    pub next_k: Vec<(u32, u64)>,
}

/// Lock-step end of run: the followers among `ids` that have reported (on
/// their telemetry key) that they completed the final step. Nodes that feed
/// them keep republishing their last messages until then (bounded), so a
/// message lost near the end is recovered.
pub async fn watch_done(
    session: &zenoh::Session,
    keys: &Keys,
    ids: &[u32],
    steps: u64,
) -> Result<
    (Vec<zenoh::pubsub::Subscriber<()>>, std::sync::Arc<std::sync::Mutex<std::collections::BTreeSet<u32>>>),
    Error,
> {
    let done = std::sync::Arc::new(std::sync::Mutex::new(std::collections::BTreeSet::new()));
    let mut subs = Vec::new();
    for &id in ids {
        let d = done.clone();
        let sub = session
            .declare_subscriber(keys.telemetry(id))
            .callback(move |s| {
                if let Some(Telemetry::Follower { id: sender, first_k, samples, done: true, .. }) =
                    decode::<Telemetry>(&s.payload().to_bytes())
                {
                    if sender == id && first_k.checked_add(samples.len() as u64) == Some(steps + 1) {
                        d.lock().unwrap_or_else(|p| p.into_inner()).insert(id);
                    }
                }
            })
            .await
            .map_err(|e| Error::Run(format!("declaring a telemetry subscriber: {e}")))?;
        subs.push(sub);
    }
    Ok((subs, done))
}

/// Feeds the monitor's acknowledgements for `node` (0: the leader) to its
/// courier. Acknowledgements from a monitor of another scenario are ignored.
pub async fn subscribe_acks(
    session: &zenoh::Session,
    keys: &Keys,
    node: u32,
    fingerprint: u64,
    courier: std::sync::Arc<crate::courier::Courier>,
) -> Result<zenoh::pubsub::Subscriber<()>, Error> {
    session
        .declare_subscriber(keys.ack())
        .callback(move |s| {
            if let Some(ack) = decode::<Ack>(&s.payload().to_bytes()) {
                if ack.fingerprint == fingerprint {
                    if let Some(&(_, next_k)) = ack.next_k.iter().find(|(n, _)| *n == node) {
                        courier.ack(next_k);
                    }
                }
            }
        })
        .await
        .map_err(|e| Error::Run(format!("declaring the acknowledgement subscriber: {e}")))
}

/// The telemetry of `node` (0: the leader) leaves through a [`Delivery`]:
/// its publisher (droppable in real time: the courier sends again what is
/// lost) and the subscriber that feeds it the monitor's acknowledgements.
pub async fn start_delivery(
    session: &zenoh::Session,
    keys: &Keys,
    node: u32,
    scenario: &formation_topology::Scenario,
) -> Result<(crate::courier::Delivery, zenoh::pubsub::Subscriber<()>), Error> {
    use zenoh::Wait;
    let publisher = session
        .declare_publisher(keys.telemetry(node))
        .congestion_control(crate::node::estimate_congestion(scenario))
        .priority(crate::node::priority::TELEMETRY)
        .await
        .map_err(|e| Error::Run(format!("declaring the telemetry publisher: {e}")))?;
    let delivery = crate::courier::Delivery::start(crate::courier::CAPACITY_STEPS, move |bytes| {
        publisher.put(bytes.to_vec()).wait().map_err(|e| format!("publishing: {e}"))
    });
    let fingerprint = crate::barrier::fingerprint(scenario);
    let acks = subscribe_acks(session, keys, node, fingerprint, delivery.courier.clone()).await?;
    Ok((delivery, acks))
}

/// A finished node waits this long for the monitor to acknowledge its telemetry.
pub const DRAIN: std::time::Duration = std::time::Duration::from_secs(10);

/// Waits (off the async runtime) up to [`DRAIN`] for the monitor to
/// acknowledge everything, and says how many steps it did not.
pub async fn finish_delivery(delivery: crate::courier::Delivery, who: &str) {
    let unacknowledged = tokio::task::spawn_blocking(move || delivery.finish(DRAIN)).await.unwrap_or(0);
    if unacknowledged > 0 {
        eprintln!(
            "{who}: the monitor did not acknowledge {unacknowledged} steps of telemetry within {} s",
            DRAIN.as_secs()
        );
    }
}
