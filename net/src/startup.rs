//! The start barrier on zenoh: the subscribers that feed
//! [`barrier::Join`] and [`barrier::Lead`] what a node hears, the puts
//! they ask for, and the leader's repeated start. The rules are in
//! [`formation_protocol::barrier`]; this module only translates.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use formation_scenario::Scenario;

use crate::clock::{self, Clock};
use formation_exit::{zerr, Error};
use formation_protocol::barrier::{
    fingerprint, key_digests, Hears, Join, JoinStep, Lead, LeadStep, Quorum, Ready, ReadyForm, Start, TICK,
};
use formation_protocol::codec;
use formation_protocol::names::{self, Keys};

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// Whose hellos and readies a node listens to: everybody's (one wildcard
/// subscriber), or only the named nodes' (one subscriber each, so that the
/// router forwards a node's barrier traffic only to those who need it: with
/// N nodes, N·degree messages a tick instead of N²).
#[derive(Clone, Copy)]
enum Whom<'a> {
    All,
    Only(&'a [String]),
}

impl Whom<'_> {
    fn keys(self, all: String, one: impl Fn(&str) -> String) -> Vec<String> {
        match self {
            Whom::All => vec![all],
            Whom::Only(names) => names.iter().map(|n| one(n)).collect(),
        }
    }
}

/// A node needing more nodes than this listens to everybody's barrier traffic.
const FEW: usize = 32;

/// A barrier machine and what wakes its loop: anything it hears for the
/// first time (its `news`), so that a node on the slow idle tick answers a
/// newcomer's hello, and sees the start, at once.
struct Waiting<H> {
    machine: Mutex<H>,
    wake: tokio::sync::Notify,
    clock: Clock,
}

impl<H: Hears> Waiting<H> {
    fn new(machine: H, clock: &Clock) -> Arc<Self> {
        Arc::new(Self { machine: Mutex::new(machine), wake: tokio::sync::Notify::new(), clock: clock.clone() })
    }

    /// The node's monotonic clock now.
    fn now(&self) -> Duration {
        self.clock.mono()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, H> {
        lock(&self.machine)
    }

    /// Feeds the machine; wakes the loop if that was news.
    fn hear(&self, f: impl FnOnce(&mut H)) {
        let mut m = self.lock();
        let before = m.news();
        f(&mut m);
        let news = m.news() != before;
        drop(m);
        if news {
            self.wake.notify_one();
        }
    }

    /// Until the next tick, or at once on news.
    async fn pause(&self) {
        let next = self.lock().next_tick(self.now());
        tokio::select! {
            _ = tokio::time::sleep(next) => {}
            _ = self.wake.notified() => {}
        }
    }
}

async fn listen<H: Hears + Send + 'static>(
    session: &zenoh::Session,
    keys: &Keys,
    waiting: &Arc<Waiting<H>>,
    from: Whom<'_>,
) -> Result<Vec<zenoh::pubsub::Subscriber<()>>, Error> {
    let mut subs = Vec::new();
    let declare = |key: String, on: Box<dyn Fn(&str, &[u8]) + Send + Sync>| {
        session
            .declare_subscriber(key)
            .callback(move |s| on(names::last_chunk(s.key_expr().as_str()), &s.payload().to_bytes()))
    };
    for key in from.keys(keys.hello("*"), |n| keys.hello(n)) {
        let w = waiting.clone();
        subs.push(
            declare(key, Box::new(move |from, _| w.hear(|m| m.on_hello(from))))
                .await
                .map_err(|e| zerr("declaring the hello subscriber", e))?,
        );
    }
    let w = waiting.clone();
    let on_start = move |_: &str, bytes: &[u8]| {
        if let Some(start) = codec::decode::<Start>(bytes) {
            let now = w.now();
            w.hear(|m| m.on_start(start, now));
        }
    };
    subs.push(declare(keys.start(), Box::new(on_start)).await.map_err(|e| zerr("declaring the start subscriber", e))?);
    let w = waiting.clone();
    let on_abort = move |_: &str, bytes: &[u8]| {
        // Not a refusal (garbage, or a forger's bytes): the monitor counts it
        // in network.json's control_puts; the node waits on.
        if let Some(reason) = formation_protocol::barrier::abort_reason(bytes) {
            w.hear(|m| m.on_abort(reason));
        }
    };
    subs.push(declare(keys.abort(), Box::new(on_abort)).await.map_err(|e| zerr("declaring the abort subscriber", e))?);
    for key in from.keys(keys.ready_all(), |n| keys.ready(n)) {
        let w = waiting.clone();
        let on_ready = move |from: &str, bytes: &[u8]| {
            if let Some(r) = codec::decode::<Ready>(bytes) {
                let now = w.now();
                w.hear(|m| m.on_ready(from, r, now));
            }
        };
        subs.push(declare(key, Box::new(on_ready)).await.map_err(|e| zerr("declaring the ready subscriber", e))?);
    }
    Ok(subs)
}

/// An agent or the monitor (`me`): says hello until it has heard every node
/// in `needs`, then says ready until the leader's start, which it returns.
/// Call after declaring the node's data subscribers.
pub async fn wait_for_start(
    session: &zenoh::Session,
    keys: &Keys,
    me: &str,
    needs: &[String],
    scenario: &Scenario,
    clock: &Clock,
    quorum_wait: Option<Duration>,
) -> Result<Start, Error> {
    let mut join = Join::new(me, &keys.run, needs, scenario, clock.mono());
    if let Some(wait) = quorum_wait {
        join = join.with_quorum_wait(wait);
    }
    if std::env::var_os(crate::node::LAUNCHED_ENV).is_some() {
        join = join.without_waiting_line();
    }
    let waiting = Waiting::new(join, clock);
    let from = if needs.len() <= FEW { Whom::Only(needs) } else { Whom::All };
    let _subs = listen(session, keys, &waiting, from).await?;
    let fingerprint = fingerprint(scenario);
    let ready_full = codec::encode(&Ready { fingerprint, keys: key_digests(scenario) });
    let ready_short = codec::encode(&Ready { fingerprint, keys: Vec::new() });
    loop {
        let step = waiting.lock().poll(waiting.now());
        let ready = match step {
            JoinStep::Started(start) => return Ok(start),
            JoinStep::Failed(e) => return Err(e),
            JoinStep::Wait { ready, warning } => {
                if let Some(w) = warning {
                    crate::node::say(&w);
                }
                ready
            }
        };
        session.put(keys.hello(me), Vec::<u8>::new()).await.map_err(|e| zerr("saying hello", e))?;
        if let Some(form) = ready {
            let bytes = if form == ReadyForm::Full { &ready_full } else { &ready_short };
            session.put(keys.ready(me), bytes.clone()).await.map_err(|e| zerr("saying ready", e))?;
        }
        waiting.pause().await;
    }
}

/// The leader: says hello until it has heard the hellos in `needs_hello`
/// and every node of `expect_ready` ready (with this scenario's
/// fingerprint); then announces [`Start`] (epoch `lead` from now on its
/// `timebase`) and keeps announcing it every 100 ms until the returned task
/// is aborted.
#[allow(clippy::too_many_arguments)]
pub async fn lead_start(
    session: &zenoh::Session,
    keys: &Keys,
    timebase: &clock::Timebase,
    needs_hello: &[String],
    expect_ready: &[String],
    scenario: &Scenario,
    time_scale: f64,
    lead: Duration,
    quorum: Option<Quorum>,
) -> Result<(Start, tokio::task::JoinHandle<()>), Error> {
    let clock = timebase.clock();
    let mut machine = Lead::new(&keys.run, needs_hello, expect_ready, scenario, clock.mono());
    if let Some(q) = quorum {
        machine = machine.with_quorum(q, scenario.graph.clone());
    }
    let waiting = Waiting::new(machine, clock);
    let subs = listen(session, keys, &waiting, Whom::All).await?;
    loop {
        let step = waiting.lock().poll(waiting.now());
        match step {
            LeadStep::Go => break,
            LeadStep::Failed(e) => return Err(e),
            LeadStep::Refuse { reason, error } => {
                // As a refusal must read (key names from another node's ready
                // may hold anything): else the nodes would ignore it.
                let reason = formation_protocol::barrier::as_abort_reason(&reason);
                // Tell every node waiting for the start, so none waits it out.
                for _ in 0..5 {
                    let _ = session.put(keys.abort(), reason.clone().into_bytes()).await;
                    tokio::time::sleep(TICK).await;
                }
                return Err(error);
            }
            LeadStep::Wait { warnings } => warnings.iter().for_each(|w| crate::node::say(w)),
        }
        session.put(keys.hello(names::LEADER_NODE), Vec::<u8>::new()).await.map_err(|e| zerr("saying hello", e))?;
        waiting.pause().await;
    }
    drop(subs);
    let now = timebase.now_ns().unwrap_or(0).max(0) as u64;
    let start = waiting.lock().start(now, lead, time_scale);
    let task = announce(session, keys, timebase, start.clone());
    Ok((start, task))
}

/// Announces `start` every 100 ms until the returned task is aborted (the
/// leader through its run, and a standby once it has taken the run over),
/// each announcement stamped on `timebase` when it leaves: a floor for
/// every node's estimate of the leader's clock.
pub fn announce(
    session: &zenoh::Session,
    keys: &Keys,
    timebase: &clock::Timebase,
    start: Start,
) -> tokio::task::JoinHandle<()> {
    let (session, key, timebase) = (session.clone(), keys.start(), timebase.clone());
    tokio::spawn(async move {
        loop {
            let sent_ns = timebase.now_ns().unwrap_or(0);
            if session.put(&key, codec::encode(&Start { sent_ns, ..start.clone() })).await.is_err() {
                return;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    })
}

/// A claim to lead said through the run, with the leader's term (the
/// leader from its start, a standby once it took over): the claims of
/// other processes it hears, and its own.
pub struct Leading {
    _saying: Claiming,
    _listening: zenoh::pubsub::Subscriber<()>,
    heard: Arc<Mutex<Vec<formation_protocol::claim::Claim>>>,
    mine: formation_protocol::claim::Claim,
}

impl Leading {
    /// Says this process's claim to lead in `term` on `control/claim/0`,
    /// every [`CLAIM_EVERY`], and listens there for the others'.
    pub async fn claim(session: &zenoh::Session, keys: &Keys, clock: &Clock, term: u32) -> Result<Self, Error> {
        use formation_protocol::claim::Claim;
        let id = formation_protocol::wire::LEADER_ID;
        let mine = Claim::new(id, clock.unix_ns(), nonce(id), std::process::id(), &host()).in_term(term);
        let (listening, heard) = listen_for_claims(session, keys, &mine).await?;
        let publisher =
            session.declare_publisher(keys.claim(id)).await.map_err(|e| zerr("declaring the claim to lead", e))?;
        let saying = Claiming::say(publisher, codec::encode(&mine));
        Ok(Self { _saying: saying, _listening: listening, heard, mine })
    }

    /// The line this process ends with if another that outranks it (a
    /// higher term; of one term, the lower nonce) is heard: it stands down.
    pub fn deferral(&self, run: &str) -> Option<String> {
        let heard = lock(&self.heard);
        let first = heard.iter().filter(|c| self.mine.outranked_by(c)).max_by_key(|c| c.term)?;
        Some(format!(
            "run {run}: two leaders: another (process {} on host {}) leads in term {}; this one (process {}, term {}) \
             stands down and ends",
            first.pid, first.host, first.term, self.mine.pid, self.mine.term
        ))
    }

    /// Watches the claims heard every [`CLAIM_EVERY`]: on one that
    /// outranks this process's, the leader machine stands down (and its
    /// loop wakes). Ends with the run.
    pub fn watch(
        self,
        shared: Arc<crate::node::Shared<formation_protocol::leader::LeaderMachine>>,
        run: String,
    ) -> tokio::task::JoinHandle<()> {
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(CLAIM_EVERY).await;
                if let Some(line) = self.deferral(&run) {
                    shared.lock().stand_down(line);
                    shared.wake();
                    return;
                }
                if shared.lock().outcome().is_some() {
                    return;
                }
            }
        })
    }
}

/// How long a node listens for a twin before it joins a run.
pub const TWIN_LISTEN: Duration = Duration::from_millis(300);

/// How often a node says its claim to its identity ([`formation_protocol::claim`])
/// from before it publishes anything until its run starts.
pub const CLAIM_EVERY: Duration = Duration::from_millis(100);

/// A node's claim to its identity, said every [`CLAIM_EVERY`] until this is
/// dropped (when the node's run has started: from then on its estimates
/// on its own key tell a later twin).
pub struct Claiming(tokio::task::JoinHandle<()>);

impl Claiming {
    /// Says `bytes` (an encoded claim) on `publisher` every [`CLAIM_EVERY`].
    fn say(publisher: zenoh::pubsub::Publisher<'static>, bytes: Vec<u8>) -> Self {
        Claiming(tokio::spawn(async move {
            loop {
                let _ = publisher.put(bytes.clone()).await;
                tokio::time::sleep(CLAIM_EVERY).await;
            }
        }))
    }
}

impl Drop for Claiming {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// A number no other process draws: std's per-process random hash keys.
fn nonce(id: u32) -> u64 {
    use std::hash::BuildHasher;
    std::collections::hash_map::RandomState::new().hash_one((id, std::process::id()))
}

/// This host's name, for the line that names a twin.
fn host() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname").map_or_else(|_| "?".into(), |h| h.trim().to_string())
}

/// Refuses to take part in a run where another process has this node's
/// identity (`id`: 0 the leader, else a follower): a second formation
/// started with the same run name, or a second process for one follower,
/// whether it began earlier or at the same moment. Called before the node
/// publishes anything; for [`TWIN_LISTEN`] it says its claim on
/// `control/claim/<id>` and listens there and on its own estimate key. A
/// process that hears a claim of one that holds the identity already, or
/// of one claiming it at once with a lower nonce
/// ([`formation_protocol::claim::Claim::yields_to`]: no clock is read), or
/// an estimate of its own id, gives way; the one that keeps the identity
/// goes on saying its claim, settled, until the run starts (drop the
/// [`Claiming`]). (A forged message
/// can still make a node refuse where traffic is not authenticated.)
pub async fn refuse_twin(
    session: &zenoh::Session,
    keys: &Keys,
    id: u32,
    steps: u64,
    clock: &Clock,
) -> Result<Claiming, Error> {
    use formation_protocol::claim::{self, Claim};
    let mine = Claim::new(id, clock.unix_ns(), nonce(id), std::process::id(), &host());
    let heard = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let h = heard.clone();
    let sub = session
        .declare_subscriber(keys.estimate(id))
        .callback(move |sample| {
            // Only a well-formed estimate from this very id, of a step of
            // the run, counts (garbage on the key is the inbox's business).
            let bytes = sample.payload().to_bytes();
            if formation_protocol::wire::decode(&bytes).is_ok_and(|m| m.header.sender == id && m.header.step <= steps) {
                h.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        })
        .await
        .map_err(|e| zerr("listening for a twin", e))?;
    let (claim_sub, claims) = listen_for_claims(session, keys, &mine).await?;
    let publisher =
        session.declare_publisher(keys.claim(id)).await.map_err(|e| zerr("declaring this node's claim", e))?;
    let bytes = codec::encode(&mine);
    let until = clock.mono() + TWIN_LISTEN;
    while clock.mono() < until {
        publisher.put(bytes.clone()).await.map_err(|e| zerr("saying this node's claim", e))?;
        clock.pause(CLAIM_EVERY.min(until.saturating_sub(clock.mono()))).await;
    }
    drop((sub, claim_sub));
    let who = if id == 0 { "the leader".to_string() } else { format!("follower {id}") };
    let n = heard.load(std::sync::atomic::Ordering::Relaxed);
    if n > 0 {
        return Err(Error::Input(format!(
            "run {}: {who} is already running on this network ({n} of its estimates in {} ms): another formation \
             with the same run name, or a second process for {who}. Give this formation another name with --run \
             NAME, or stop the other process",
            keys.run,
            TWIN_LISTEN.as_millis()
        )));
    }
    if let Some(first) = claim::winner(&mine, lock(&claims).iter()) {
        return Err(Error::Input(format!(
            "run {}: {who} was started twice at once; the other ({}) keeps it, this one (process {}) gives way. \
             Stop one of them, or give this formation another name with --run NAME",
            keys.run,
            first.describe(&mine),
            mine.pid
        )));
    }
    // Kept: from now on a newcomer gives way to it.
    Ok(Claiming::say(publisher, codec::encode(&mine.settled())))
}

/// The claims of other processes to `mine`'s identity heard on its key
/// (a few distinct ones are all a decision needs), until the subscriber
/// is dropped.
async fn listen_for_claims(
    session: &zenoh::Session,
    keys: &Keys,
    mine: &formation_protocol::claim::Claim,
) -> Result<(zenoh::pubsub::Subscriber<()>, Arc<Mutex<Vec<formation_protocol::claim::Claim>>>), Error> {
    use formation_protocol::claim::Claim;
    let heard: Arc<Mutex<Vec<Claim>>> = Arc::default();
    let (h, id, own) = (heard.clone(), mine.id, mine.nonce);
    let sub = session
        .declare_subscriber(keys.claim(id))
        .callback(move |sample| {
            let Some(other) = codec::decode::<Claim>(&sample.payload().to_bytes()) else { return };
            let mut h = lock(&h);
            if other.id == id && other.nonce != own && h.len() < 16 && !h.contains(&other) {
                h.push(other);
            }
        })
        .await
        .map_err(|e| zerr("listening for another process's claim", e))?;
    Ok((sub, heard))
}
