//! The monitor's side of a follower killed in lock-step
//! ([`formation_protocol::died`], the agents' side in `crate::died`): it
//! hears the run's liveliness tokens and what every follower still running
//! holds of one lost, names the step its links are cut from once all of
//! them have said it, and records the death.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::{Arc, Mutex};

use zenoh::pubsub::{Publisher, Subscriber};

use formation_exit::{zerr, Error};
use formation_protocol::codec::{decode, encode};
use formation_protocol::died::{Died, Holding};
use formation_protocol::names::{last_chunk, Keys};
use formation_protocol::patience::Patience;
use formation_recorder::Recorder;
use formation_scenario::Scenario;

/// How often the monitor looks (its node's tick; a longer gap is time it
/// was not run, [`Patience`]).
const LOOK: std::time::Duration = std::time::Duration::from_millis(20);

use crate::died::{hear_tokens, SharedTokens};

/// Holdings by the follower that died, then by who said it.
type Holdings = Arc<Mutex<BTreeMap<u32, BTreeMap<u32, Holding>>>>;

/// One look's time, as the monitor's clock reads it (`Clock::mono`).
pub type Now = std::time::Duration;

pub struct Deaths {
    tokens: SharedTokens,
    /// Followers whose died row kills them: named at once.
    planned: BTreeSet<u32>,
    /// `network.gone_after`: another follower whose token stayed lost
    /// that long (as [`Patience`] counts it) is named killed; without it,
    /// none is (lock-step waits for a restarted agent, docs/model.md §14).
    grace: Option<std::time::Duration>,
    /// Since when each token lost and not back is waited on.
    lost_since: BTreeMap<u32, Patience>,
    holdings: Holdings,
    /// Followers named killed, with the step and their last messages (said
    /// again on every look, so that a node that missed it hears it).
    named: BTreeMap<u32, Died>,
    /// Tokens lost of followers that left or finished first: not deaths.
    through: BTreeSet<u32>,
    followers: Vec<u32>,
    fingerprint: u64,
    died: Publisher<'static>,
    _subscribers: (Subscriber<()>, Subscriber<()>),
}

impl Deaths {
    pub async fn declare(session: &zenoh::Session, keys: &Keys, scenario: &Scenario) -> Result<Self, Error> {
        let followers = scenario.graph.ids();
        let fingerprint = formation_protocol::barrier::fingerprint(scenario);
        let tokens: SharedTokens = Default::default();
        let token_sub = hear_tokens(session, keys, tokens.clone()).await?;
        let holdings: Holdings = Default::default();
        let h = holdings.clone();
        let holds_sub = session
            .declare_subscriber(keys.holds_all())
            .callback(move |s| {
                let Some(said) = decode::<Holding>(&s.payload().to_bytes()) else { return };
                let key_id = last_chunk(s.key_expr().as_str()).parse::<u32>().ok();
                if said.fingerprint == fingerprint && key_id == Some(said.sender) {
                    h.lock().unwrap_or_else(|p| p.into_inner()).entry(said.died).or_default().insert(said.sender, said);
                }
            })
            .await
            .map_err(|e| zerr("declaring the holdings subscriber", e))?;
        let died = session
            .declare_publisher(keys.died())
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .map_err(|e| zerr("declaring the died publisher", e))?;
        Ok(Self {
            planned: followers.iter().copied().filter(|&id| scenario.died(id)).collect(),
            grace: scenario.network.gone_after_s.map(std::time::Duration::from_secs_f64),
            lost_since: BTreeMap::new(),
            tokens,
            holdings,
            named: BTreeMap::new(),
            through: BTreeSet::new(),
            followers: followers.to_vec(),
            fingerprint,
            died,
            _subscribers: (token_sub, holds_sub),
        })
    }

    /// One look at `now`: each follower whose token was lost while it
    /// still had steps to send, and is not back, is named killed — at once
    /// if its died row says so, else once its token stayed lost
    /// `network.gone_after` — when every follower whose token is alive has
    /// said what it holds of it; the names are said again.
    pub async fn look(&mut self, recorder: &mut Recorder, now: Now) {
        let (lost, alive) = {
            let t = self.tokens.lock().unwrap_or_else(|p| p.into_inner());
            (t.lost.clone(), t.alive.clone())
        };
        for j in lost {
            if self.named.contains_key(&j) || self.through.contains(&j) || !self.followers.contains(&j) {
                continue;
            }
            if recorder.through(j) {
                self.through.insert(j);
                continue;
            }
            if alive.contains(&j) {
                // Restarted: what was said of it before is old.
                self.lost_since.remove(&j);
                self.holdings.lock().unwrap_or_else(|p| p.into_inner()).remove(&j);
                continue;
            }
            let waited = self.lost_since.entry(j).or_insert_with(|| Patience::new(now, LOOK)).look(now);
            if !(self.planned.contains(&j) || self.grace.is_some_and(|g| waited >= g)) {
                continue;
            }
            let said = self.holdings.lock().unwrap_or_else(|p| p.into_inner()).get(&j).cloned().unwrap_or_default();
            let running = self.followers.iter().filter(|&&f| f != j && alive.contains(&f) && !recorder.through(f));
            if running.clone().all(|f| said.contains_key(f)) {
                let said: Vec<Holding> = said.values().copied().collect();
                let d = Died::named(self.fingerprint, j, &said);
                self.named.insert(j, d);
                recorder.died(j, d.at_k, d.pose);
            }
        }
        for d in self.named.values() {
            let _ = self.died.put(encode(d)).await;
        }
    }
}
