//! The leader machine's loop on zenoh, shared by the leader
//! ([`crate::leader`]) and a standby that took the run over
//! ([`crate::standby`]): the subscribers that feed it the followers'
//! estimates, and the loop that tells it the time and sends what it answers.

use std::sync::Arc;

use zenoh::pubsub::Publisher;
use zenoh::Wait;

use crate::clock;
use crate::courier::Courier;
use crate::node::Shared;
use crate::ros2::topics::LeaderTopics;
use crate::telemetry;
use formation_exit::{zerr, Error};
use formation_protocol::codec;
use formation_protocol::counters::QueryCount;
use formation_protocol::leader::{LeaderBatch, LeaderMachine as Machine};
use formation_protocol::names::{self, Keys};
use formation_protocol::telemetry::Delivery;

/// One subscriber per hearing follower's estimate key: the machine files
/// how far each has reached, and the loop wakes when the window opens.
pub async fn watch_reached(
    session: &zenoh::Session,
    keys: &Keys,
    hearing: &[u32],
    shared: &Arc<Shared<Machine>>,
) -> Result<Vec<zenoh::pubsub::Subscriber<()>>, Error> {
    let mut subs = Vec::new();
    for &id in hearing {
        let sh = shared.clone();
        let sub = session
            .declare_subscriber(keys.estimate(id))
            .callback(move |s| {
                let key_id = names::last_chunk(s.key_expr().as_str()).parse::<u32>().ok();
                if sh.lock().handle_estimate(key_id, &s.payload().to_bytes()) {
                    sh.wake();
                }
            })
            .await
            .map_err(|e| zerr("declaring a subscriber", e))?;
        subs.push(sub);
    }
    Ok(subs)
}

/// A message on the leader's key from another process, for the machine
/// (a standby's watch; a leader's check for a higher term): the loop wakes
/// if the machine stood down.
pub fn hear_leader(shared: &Shared<Machine>, bytes: &[u8], now: std::time::Duration) {
    let mut m = shared.lock();
    let before = m.outcome().is_some();
    m.handle_leader(bytes, now);
    let ended = !before && m.outcome().is_some();
    drop(m);
    if ended {
        shared.wake();
    }
}

/// Listens on the leader's key for another process's messages (a leader
/// that took the run over in a higher term: this one stands down).
pub async fn watch_leader_key(
    session: &zenoh::Session,
    keys: &Keys,
    shared: &Arc<Shared<Machine>>,
    timebase: &clock::Timebase,
) -> Result<zenoh::pubsub::Subscriber<()>, Error> {
    let (sh, tb) = (shared.clone(), timebase.clone());
    session
        .declare_subscriber(keys.estimate(formation_protocol::wire::LEADER_ID))
        .allowed_origin(zenoh::sample::Locality::Remote)
        .callback(move |s| hear_leader(&sh, &s.payload().to_bytes(), tb.now()))
        .await
        .map_err(|e| zerr("listening on the leader's key", e))
}

/// The loop's side of the node: the machine, and where its answers go.
pub struct LeadLoop {
    pub shared: Arc<Shared<Machine>>,
    pub publisher: Publisher<'static>,
    pub courier: Arc<Courier>,
    pub timebase: clock::Timebase,
    /// Lock-step: hearing followers that reported their final step.
    pub followers_done: telemetry::Ends,
    pub queries: Arc<QueryCount>,
    pub topics: Option<LeaderTopics>,
    pub lockstep: bool,
    /// This process's start (ns since the Unix epoch), sent with telemetry.
    pub incarnation: u64,
    /// A standby: told the step once the machine has taken the run over.
    pub on_take_over: Option<tokio::sync::oneshot::Sender<u64>>,
}

impl LeadLoop {
    /// Feeds the machine the time until it is done, sleeping between turns
    /// until its next deadline (real time) or until the window opens
    /// (lock-step), on a thread of its own.
    pub fn drive(mut self) -> Result<(), String> {
        loop {
            if let Some(r) = self.turn() {
                return r;
            }
            self.shared.sleep(&self.timebase, self.lockstep, |m| m.poll_timeout());
        }
    }

    /// One turn: the machine is told the time and who is done, and what it
    /// answers goes out with its lock released. Some(outcome) once done.
    fn turn(&mut self) -> Option<Result<(), String>> {
        let mut m = self.shared.lock();
        for (&id, &end) in self.followers_done.lock().unwrap_or_else(|p| p.into_inner()).iter() {
            match end {
                None => m.handle_done(id),
                Some(_) => m.handle_gone(id),
            }
        }
        m.handle_timeout(self.timebase.now());
        let transmit: Vec<Vec<u8>> = std::iter::from_fn(|| m.poll_transmit()).collect();
        let batches: Vec<LeaderBatch> = std::iter::from_fn(|| m.poll_telemetry()).collect();
        let said: Vec<String> = std::iter::from_fn(|| m.poll_say()).collect();
        let state = m.take_state();
        let outcome = m.outcome().cloned();
        if let Some(k) = m.took_over() {
            if let Some(tell) = self.on_take_over.take() {
                let _ = tell.send(k);
            }
        }
        drop(m);
        if let (Some(t), Some((k, state))) = (self.topics.as_mut(), state) {
            if let Err(e) = t.publish(k, &state) {
                return Some(Err(e.to_string()));
            }
        }
        for bytes in transmit {
            if let Err(e) = self.publisher.put(bytes).wait() {
                return Some(Err(zerr("publishing", e).to_string()));
            }
        }
        for b in batches {
            let (first_k, end_k, c) = (b.first_k, b.end_k, &self.courier);
            let delivery = Delivery {
                available_from: c.available_from(first_k),
                incarnation: self.incarnation,
                courier: c.stats(),
            };
            c.push(first_k, end_k, codec::encode(&b.into_telemetry(delivery, self.queries.read())));
        }
        for line in said {
            crate::node::say(&line);
        }
        outcome
    }
}
