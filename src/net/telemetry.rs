//! Telemetry for the monitor: every step of a node, in batches, on
//! `telemetry/<id>`. Never feeds control.

use formation_agent::LeaderState;
use serde::{Deserialize, Serialize};

use crate::error::Error;
use crate::net::codec::decode;
use crate::net::counters::Counters;
use crate::net::keys::Keys;
use crate::net::timing::LoopStats;
use crate::record::FollowerSample;

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
    },
    Leader {
        first_k: u64,
        /// The true leader state at steps first_k, first_k + 1, …
        states: Vec<LeaderState>,
        counters: Counters,
        done: bool,
        loop_stats: Option<LoopStats>,
    },
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
