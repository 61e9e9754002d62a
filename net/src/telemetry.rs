//! Telemetry over zenoh: the lock-step end-of-run watch, the monitor's
//! acknowledgements, and each node's telemetry delivery. The messages
//! themselves are [`formation_protocol::telemetry`]'s.

use formation_exit::Error;
use formation_protocol::codec::decode;
use formation_protocol::names::Keys;
use formation_protocol::telemetry::{Ack, Telemetry};

/// Lock-step end of run: the followers among `ids` that have reported (on
/// their telemetry key) that they completed the final step or left, or
/// that the monitor named killed (`control/died`, crate::died: cut off
/// from the step it names, as one that left). Nodes that feed them keep
/// republishing their last messages until then (bounded), so a message
/// lost near the end is recovered.
pub async fn watch_done(
    session: &zenoh::Session,
    keys: &Keys,
    ids: &[u32],
    scenario: &formation_scenario::Scenario,
) -> Result<(Vec<zenoh::pubsub::Subscriber<()>>, Ends), Error> {
    let (steps, fingerprint) = (scenario.steps(), formation_protocol::barrier::fingerprint(scenario));
    let ends: Ends = Default::default();
    let mut subs = Vec::new();
    let (e, watched) = (ends.clone(), ids.to_vec());
    let died = session
        .declare_subscriber(keys.died())
        .callback(move |s| {
            let Some(d) = decode::<formation_protocol::died::Died>(&s.payload().to_bytes()) else { return };
            if d.fingerprint == fingerprint && watched.contains(&d.follower) {
                e.lock().unwrap_or_else(|p| p.into_inner()).entry(d.follower).or_insert(Some(d.at_k));
            }
        })
        .await
        .map_err(|e| Error::Run(format!("declaring the died subscriber: {e}")))?;
    subs.push(died);
    for &id in ids {
        let e = ends.clone();
        let sub = session
            .declare_subscriber(keys.telemetry(id))
            .callback(move |s| {
                let Some(t) = decode::<Telemetry>(&s.payload().to_bytes()) else { return };
                let end = match t.left_at(id) {
                    Some(k) => Some(Some(k)),
                    None => t.reports_final_step(id, steps).then_some(None),
                };
                if let Some(end) = end {
                    e.lock().unwrap_or_else(|p| p.into_inner()).entry(id).or_insert(end);
                }
            })
            .await
            .map_err(|e| Error::Run(format!("declaring a telemetry subscriber: {e}")))?;
        subs.push(sub);
    }
    Ok((subs, ends))
}

/// Lock-step: the followers watched by [`watch_done`] that are through, as
/// their telemetry said: None, done with the final step; Some(k), left the
/// run before step k.
pub type Ends = std::sync::Arc<std::sync::Mutex<std::collections::BTreeMap<u32, Option<u64>>>>;

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
            if let Some(next_k) = decode::<Ack>(&s.payload().to_bytes()).and_then(|a| a.next_k_of(fingerprint, node)) {
                courier.ack(next_k);
            }
        })
        .await
        .map_err(|e| Error::Run(format!("declaring the acknowledgement subscriber: {e}")))
}

/// The telemetry of `node` (0: the leader) leaves through a [`CourierThread`]:
/// its publisher (droppable in real time: the courier sends again what is
/// lost) and the subscriber that feeds it the monitor's acknowledgements.
pub async fn start_delivery(
    session: &zenoh::Session,
    keys: &Keys,
    node: u32,
    scenario: &formation_scenario::Scenario,
    clock: &crate::clock::Clock,
) -> Result<(crate::courier::CourierThread, zenoh::pubsub::Subscriber<()>), Error> {
    use zenoh::Wait;
    let publisher = session
        .declare_publisher(keys.telemetry(node))
        .congestion_control(crate::node::estimate_congestion(scenario))
        .priority(crate::node::priority::TELEMETRY)
        .await
        .map_err(|e| Error::Run(format!("declaring the telemetry publisher: {e}")))?;
    let capacity = formation_protocol::courier::CAPACITY_STEPS;
    let delivery = crate::courier::CourierThread::start(capacity, clock.clone(), move |bytes| {
        // A failed put is like a lost one: the courier sends it again.
        let _ = publisher.put(bytes.to_vec()).wait();
    });
    let fingerprint = formation_protocol::barrier::fingerprint(scenario);
    let acks = subscribe_acks(session, keys, node, fingerprint, delivery.courier.clone()).await?;
    Ok((delivery, acks))
}

/// A finished node gives its telemetry up once the monitor has acknowledged
/// nothing new for this long (while the node itself ran: a monitor filing a
/// backlog slowly is waited for, [`crate::courier::Courier::drain`]).
pub const DRAIN: std::time::Duration = std::time::Duration::from_secs(10);

/// Waits (off the async runtime) for the monitor to acknowledge
/// everything, until it acknowledged nothing new for [`DRAIN`], and says
/// how many steps it did not.
pub async fn finish_delivery(delivery: crate::courier::CourierThread, who: &str) {
    let unacknowledged = tokio::task::spawn_blocking(move || delivery.finish(DRAIN)).await.unwrap_or(0);
    if unacknowledged > 0 {
        crate::node::say(&format!(
            "{who}: the monitor did not acknowledge {unacknowledged} steps of telemetry (nothing new acknowledged for {} s)",
            DRAIN.as_secs()
        ));
    }
}
