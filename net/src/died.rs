//! Lock-step: a follower killed without a word (SIGKILL, a crash, a power
//! cut), over zenoh, as [`formation_protocol::died`] has the others agree
//! on its last step. Each agent holds a liveliness token per follower while
//! its process lives, and drops it only after its last telemetry is
//! acknowledged (one that left or finished is known to the monitor before
//! its token goes). Each agent hears every token's loss, says for each of
//! its followers what it holds of the one that died, and applies the step
//! the monitor names; the monitor's side is `crate::monitor::deaths`.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::{Arc, Mutex};

use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::sample::SampleKind;
use zenoh::Wait;

use formation_exit::{zerr, Error};
use formation_protocol::codec::{decode, encode};
use formation_protocol::died::{Died, Holding};
use formation_protocol::follower::FollowerMachine;
use formation_protocol::names::{last_chunk, Keys};

/// Liveliness as one node hears it: the followers whose tokens it has
/// seen (`Put`, history included) and those lost (`Delete`), in order.
#[derive(Debug, Default)]
pub struct Tokens {
    pub alive: BTreeSet<u32>,
    pub lost: Vec<u32>,
    /// Grows with every token heard or lost: a reader that saw this count
    /// has nothing new to look at.
    pub changes: u64,
}

pub type SharedTokens = Arc<Mutex<Tokens>>;

/// Declares the subscriber that files the run's followers' tokens into
/// `tokens` (with history: those alive now first).
pub async fn hear_tokens(session: &zenoh::Session, keys: &Keys, tokens: SharedTokens) -> Result<Subscriber<()>, Error> {
    session
        .liveliness()
        .declare_subscriber(keys.alive_all())
        .history(true)
        .callback(move |s| {
            let Ok(id) = last_chunk(s.key_expr().as_str()).parse::<u32>() else { return };
            let mut t = tokens.lock().unwrap_or_else(|p| p.into_inner());
            t.changes += 1;
            match s.kind() {
                SampleKind::Put => {
                    t.alive.insert(id);
                }
                SampleKind::Delete => {
                    t.alive.remove(&id);
                    t.lost.push(id);
                }
            }
        })
        .await
        .map_err(|e| zerr("declaring the liveliness subscriber", e))
}

/// Follower `id`'s token, held while the process lives.
pub async fn declare_token(session: &zenoh::Session, keys: &Keys, id: u32) -> Result<LivelinessToken, Error> {
    session.liveliness().declare_token(keys.alive(id)).await.map_err(|e| zerr("declaring the liveliness token", e))
}

/// One follower's side of a death in lock-step: the losses heard, its
/// holdings said once per follower lost, and the steps the monitor named,
/// applied once.
pub struct Watch {
    id: u32,
    fingerprint: u64,
    tokens: SharedTokens,
    named: Arc<Mutex<BTreeMap<u32, Died>>>,
    said: Mutex<BTreeSet<u32>>,
    applied: Mutex<BTreeSet<u32>>,
    /// The token changes and the named steps already looked at (a turn
    /// with nothing new costs two locks, no copy).
    looked: Mutex<(u64, usize)>,
    holds: Publisher<'static>,
    _subscribers: (Subscriber<()>, Subscriber<()>),
}

impl Watch {
    /// For follower `id` of a process on `session`.
    pub async fn start(session: &zenoh::Session, keys: &Keys, id: u32, fingerprint: u64) -> Result<Self, Error> {
        let tokens: SharedTokens = Default::default();
        let losses = hear_tokens(session, keys, tokens.clone()).await?;
        let named: Arc<Mutex<BTreeMap<u32, Died>>> = Default::default();
        let n = named.clone();
        let died = session
            .declare_subscriber(keys.died())
            .callback(move |s| {
                let Some(d) = decode::<Died>(&s.payload().to_bytes()) else { return };
                if d.fingerprint == fingerprint {
                    n.lock().unwrap_or_else(|p| p.into_inner()).entry(d.follower).or_insert(d);
                }
            })
            .await
            .map_err(|e| zerr("declaring the died subscriber", e))?;
        let holds = session
            .declare_publisher(keys.holds(id))
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .map_err(|e| zerr("declaring the holdings publisher", e))?;
        let (said, applied, looked) = Default::default();
        Ok(Self { id, fingerprint, tokens, named, said, applied, looked, holds, _subscribers: (losses, died) })
    }

    /// Between two of the machine's turns: says what `m` holds of each
    /// follower newly lost, and applies each step the monitor named.
    pub fn tell(&self, m: &mut FollowerMachine) {
        let mut looked = self.looked.lock().unwrap_or_else(|p| p.into_inner());
        let changes = self.tokens.lock().unwrap_or_else(|p| p.into_inner()).changes;
        let named = self.named.lock().unwrap_or_else(|p| p.into_inner()).len();
        if (changes, named) == *looked {
            return;
        }
        *looked = (changes, named);
        let (lost, alive) = {
            let t = self.tokens.lock().unwrap_or_else(|p| p.into_inner());
            (t.lost.clone(), t.alive.clone())
        };
        let mut said = self.said.lock().unwrap_or_else(|p| p.into_inner());
        // A restarted agent's token is back: a later loss is said again.
        said.retain(|j| !alive.contains(j));
        for j in lost.into_iter().filter(|&j| j != self.id && !alive.contains(&j)) {
            if said.insert(j) {
                let h: Holding = m.holding_of(j, self.fingerprint);
                if let Err(e) = self.holds.put(encode(&h)).wait() {
                    crate::node::say(&format!("follower {}: {}", self.id, zerr("saying what it holds", e)));
                }
            }
        }
        let named: Vec<Died> = self.named.lock().unwrap_or_else(|p| p.into_inner()).values().copied().collect();
        let mut applied = self.applied.lock().unwrap_or_else(|p| p.into_inner());
        for d in named {
            if d.follower != self.id && applied.insert(d.follower) {
                m.handle_died(&d);
            }
        }
    }
}
