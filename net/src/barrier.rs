//! The start barrier, and its messages `Ready` and `Start`.
//!
//! Zenoh peers connect asynchronously, and a message put before the other
//! side knows of a subscription is silently lost. So before anything steps:
//! every node declares its subscribers, then repeats `hello` every 50 ms. A
//! node is *ready* once it has heard the `hello` of every node it receives
//! from (an agent: its neighbours and, if a_i0 = 1, the leader; the monitor:
//! everybody): the same transport that carried the hello carried the
//! subscriber declarations made before it. Ready nodes repeat `ready` (with
//! a fingerprint of their scenario) until the leader, having heard every
//! agent and the monitor ready with its own fingerprint, repeats `start`
//! (the run's epoch and time scale). Nobody stops saying `hello` before the
//! start, so nobody waits forever for a hello.

use std::collections::BTreeSet;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use formation_topology::Scenario;
use serde::{Deserialize, Serialize};

use crate::codec;
use crate::error::{zerr, Error};
use crate::names::{self, Keys};

/// "I can hear everyone I need": sent by agents and the monitor.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Ready {
    pub fingerprint: u64,
    /// Per scenario key, a digest of its value ([`key_digests`]), so that a
    /// mismatch can name the keys that differ.
    #[serde(default)]
    pub keys: Vec<(String, u64)>,
}

/// The leader's go: the run's epoch (wall clock, ns since the Unix epoch:
/// step k is due at epoch + k Δt / time_scale in real time) and time scale.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Start {
    pub fingerprint: u64,
    pub epoch_unix_ns: u64,
    pub time_scale: f64,
}

impl Start {
    /// The epoch as a tokio/std instant of this process.
    pub fn epoch_instant(&self) -> std::time::Instant {
        let now_i = std::time::Instant::now();
        let now_ns = unix_ns();
        if self.epoch_unix_ns >= now_ns {
            now_i + Duration::from_nanos(self.epoch_unix_ns - now_ns)
        } else {
            now_i.checked_sub(Duration::from_nanos(now_ns - self.epoch_unix_ns)).unwrap_or(now_i)
        }
    }
}

pub fn unix_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

/// A fingerprint of the scenario as loaded (file plus overrides), so that
/// nodes started with different scenarios refuse to run together.
pub fn fingerprint(s: &Scenario) -> u64 {
    let text = serde_json::to_string(&s.source).unwrap_or_default();
    // FNV-1a, 64 bit.
    text.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3))
}

/// Every leaf of the scenario file's settings (`robot.mass`,
/// `followers.3.offset`, …) with an FNV-1a digest of its value.
pub fn key_digests(s: &Scenario) -> Vec<(String, u64)> {
    fn walk(prefix: &str, v: &serde_json::Value, out: &mut Vec<(String, u64)>) {
        let join = |k: &str| if prefix.is_empty() { k.to_string() } else { format!("{prefix}.{k}") };
        match v {
            serde_json::Value::Object(m) => m.iter().for_each(|(k, v)| walk(&join(k), v, out)),
            serde_json::Value::Array(a) if a.iter().any(|x| x.is_object()) => {
                a.iter().enumerate().for_each(|(i, v)| walk(&join(&(i + 1).to_string()), v, out))
            }
            leaf => out.push((prefix.to_string(), fnv(leaf.to_string().as_bytes()))),
        }
    }
    let mut out = Vec::new();
    walk("", &serde_json::to_value(&s.source).unwrap_or_default(), &mut out);
    out
}

fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3))
}

/// The keys whose digests differ between `a` and `b` (or that only one has).
pub fn differing_keys(a: &[(String, u64)], b: &[(String, u64)]) -> Vec<String> {
    let (ma, mb): (std::collections::BTreeMap<_, _>, std::collections::BTreeMap<_, _>) =
        (a.iter().cloned().collect(), b.iter().cloned().collect());
    let mut keys: BTreeSet<&String> = ma.keys().collect();
    keys.extend(mb.keys());
    keys.into_iter().filter(|k| ma.get(*k) != mb.get(*k)).cloned().collect()
}

/// "robot.mass, dt" (at most 5, then "and N more").
fn key_list(keys: &[String]) -> String {
    let mut s = keys.iter().take(5).cloned().collect::<Vec<_>>().join(", ");
    if keys.len() > 5 {
        s += &format!(" and {} more", keys.len() - 5);
    }
    s
}

/// A node heard only with another scenario for this long is refused (the
/// leader), or gives up (an agent hearing only a foreign start).
pub const MISMATCH_GRACE: Duration = Duration::from_secs(5);

/// How long a node waits at the barrier before giving up.
pub const START_TIMEOUT: Duration = Duration::from_secs(120);
const TICK: Duration = Duration::from_millis(50);
/// A ready carries the scenario's key digests once in this many.
const DIGESTS_EVERY: u64 = 20;

#[derive(Default)]
struct Heard {
    /// This node's scenario fingerprint: Start and Ready with another are ignored.
    fingerprint: u64,
    /// The leader: the nodes whose Ready counts (any other name is ignored).
    expected: BTreeSet<String>,
    hello: BTreeSet<String>,
    /// Expected nodes heard ready with this node's fingerprint.
    ready: BTreeSet<String>,
    /// Expected nodes heard ready with another fingerprint (not counted as ready).
    ready_foreign: BTreeSet<String>,
    /// The first Start with this node's fingerprint.
    start: Option<Start>,
    /// Start or Ready messages ignored for another fingerprint (or an unexpected name).
    ignored: u64,
    /// This node's key digests, and per node ready with another
    /// fingerprint, the keys that differ and when it was first heard so.
    mine: Vec<(String, u64)>,
    differ: std::collections::BTreeMap<String, (Vec<String>, Instant)>,
    /// When a start with another fingerprint was first heard.
    foreign_start: Option<Instant>,
    /// The leader's reason for refusing the run, if it did.
    abort: Option<String>,
}

impl Heard {
    fn new(fingerprint: u64, expected: &[String]) -> Self {
        Self { fingerprint, expected: expected.iter().cloned().collect(), ..Self::default() }
    }

    fn on_start(&mut self, start: Start) {
        if start.fingerprint == self.fingerprint {
            self.start.get_or_insert(start);
        } else {
            self.ignored += 1;
            self.foreign_start.get_or_insert_with(Instant::now);
        }
    }

    fn on_ready(&mut self, name: &str, r: Ready) {
        if !self.expected.contains(name) {
            self.ignored += 1;
        } else if r.fingerprint == self.fingerprint {
            self.ready.insert(name.to_string());
        } else {
            self.ignored += 1;
            self.ready_foreign.insert(name.to_string());
            // Most readies carry no digests: the keys that differ are known
            // from the first that does.
            let e = self.differ.entry(name.to_string()).or_insert_with(|| (Vec::new(), Instant::now()));
            if e.0.is_empty() && !r.keys.is_empty() {
                e.0 = differing_keys(&self.mine, &r.keys);
            }
        }
    }
}

fn lock(h: &Mutex<Heard>) -> std::sync::MutexGuard<'_, Heard> {
    h.lock().unwrap_or_else(|p| p.into_inner())
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

async fn listen(
    session: &zenoh::Session,
    keys: &Keys,
    heard: &Arc<Mutex<Heard>>,
    from: Whom<'_>,
) -> Result<Vec<zenoh::pubsub::Subscriber<()>>, Error> {
    let mut subs = Vec::new();
    for key in from.keys(keys.hello("*"), |n| keys.hello(n)) {
        let h = heard.clone();
        subs.push(
            session
                .declare_subscriber(key)
                .callback(move |s| {
                    lock(&h).hello.insert(names::last_chunk(s.key_expr().as_str()).to_string());
                })
                .await
                .map_err(|e| zerr("declaring the hello subscriber", e))?,
        );
    }
    let h = heard.clone();
    subs.push(
        session
            .declare_subscriber(keys.start())
            .callback(move |s| {
                if let Some(start) = codec::decode::<Start>(&s.payload().to_bytes()) {
                    lock(&h).on_start(start);
                }
            })
            .await
            .map_err(|e| zerr("declaring the start subscriber", e))?,
    );
    let h = heard.clone();
    subs.push(
        session
            .declare_subscriber(keys.abort())
            .callback(move |s| {
                let reason = String::from_utf8_lossy(&s.payload().to_bytes()).chars().take(500).collect::<String>();
                if !reason.is_empty() {
                    lock(&h).abort.get_or_insert(reason);
                }
            })
            .await
            .map_err(|e| zerr("declaring the abort subscriber", e))?,
    );
    for key in from.keys(keys.ready_all(), |n| keys.ready(n)) {
        let h = heard.clone();
        subs.push(
            session
                .declare_subscriber(key)
                .callback(move |s| {
                    if let Some(r) = codec::decode::<Ready>(&s.payload().to_bytes()) {
                        lock(&h).on_ready(names::last_chunk(s.key_expr().as_str()), r);
                    }
                })
                .await
                .map_err(|e| zerr("declaring the ready subscriber", e))?,
        );
    }
    Ok(subs)
}

fn missing(have: impl Fn(&str) -> bool, needs: &[String]) -> Vec<String> {
    needs.iter().filter(|n| !have(n)).cloned().collect()
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
) -> Result<Start, Error> {
    let fingerprint = self::fingerprint(scenario);
    // The nodes it needs count when they say ready with another scenario.
    let mut h0 = Heard::new(fingerprint, needs);
    h0.mine = key_digests(scenario);
    let heard = Arc::new(Mutex::new(h0));
    let from = if needs.len() <= FEW { Whom::Only(needs) } else { Whom::All };
    let _subs = listen(session, keys, &heard, from).await?;
    let began = Instant::now();
    // The key digests (a few KB for a large scenario) go with every
    // DIGESTS_EVERY-th ready only; the fingerprint with every one.
    let ready_full = codec::encode(&Ready { fingerprint, keys: key_digests(scenario) });
    let ready_short = codec::encode(&Ready { fingerprint, keys: Vec::new() });
    let mut readies = 0u64;
    let mut warned = false;
    loop {
        let (start, waiting, ignored, foreign_since, mismatched) = {
            let h = lock(&heard);
            let mismatched = h
                .differ
                .iter()
                .find(|(n, (_, since))| !h.ready.contains(*n) && since.elapsed() >= MISMATCH_GRACE)
                .map(|(n, (k, _))| (n.clone(), k.clone()));
            (h.start, missing(|n| h.hello.contains(n), needs), h.ignored, h.foreign_start, mismatched)
        };
        if let Some(start) = start {
            return Ok(start);
        }
        if let Some(reason) = lock(&heard).abort.clone() {
            return Err(Error::Input(format!("node {me}: the leader refused run {}: {reason}", keys.run)));
        }
        if let Some((n, differ)) = mismatched {
            let n = if n == "0" { "the leader".to_string() } else { format!("node {n}") };
            return Err(Error::Input(format!(
                "node {me}: {n} of run {} runs another scenario, {} (another file or --set values)",
                keys.run,
                if differ.is_empty() {
                    "with other keys".to_string()
                } else {
                    format!("differing in {}", key_list(&differ))
                }
            )));
        }
        if foreign_since.is_some_and(|t| t.elapsed() >= MISMATCH_GRACE * 2) {
            // Heard for 10 s: the leader of this run has another scenario.
            return Err(Error::Input(format!(
                "node {me}: the leader of run {} has another scenario (another file or --set values; the \
                 leader's own message names the keys that differ); no start for this one in {} s",
                keys.run,
                (MISMATCH_GRACE * 2).as_secs()
            )));
        }
        if foreign_since.is_some() && !warned {
            // Said at once, not only at the time limit; not fatal, since a
            // forged announcement must not stop a genuine run.
            eprintln!(
                "node {me}: the leader of run {} announces another scenario (another file or --set values?); \
                 waiting up to {} s for a start with this one",
                keys.run,
                (MISMATCH_GRACE * 2).as_secs()
            );
            warned = true;
        }
        session.put(keys.hello(me), Vec::<u8>::new()).await.map_err(|e| zerr("saying hello", e))?;
        if waiting.is_empty() {
            let ready = if readies % DIGESTS_EVERY == 0 { &ready_full } else { &ready_short };
            readies += 1;
            session.put(keys.ready(me), ready.clone()).await.map_err(|e| zerr("saying ready", e))?;
        }
        if began.elapsed() > START_TIMEOUT {
            let what = if waiting.is_empty() {
                "the leader's start".to_string()
            } else {
                format!("nodes {}", waiting.join(", "))
            };
            if waiting.is_empty() && foreign_since.is_some() {
                return Err(Error::Input(format!(
                    "node {me}: no start for this scenario within {} s; ignored {ignored} start announcements \
                     of run {} with another scenario fingerprint (a leader with another scenario or --set values?)",
                    START_TIMEOUT.as_secs(),
                    keys.run
                )));
            }
            return Err(Error::Run(format!(
                "node {me}: no word from {what} within {} s (run {})",
                START_TIMEOUT.as_secs(),
                keys.run
            )));
        }
        tokio::time::sleep(TICK).await;
    }
}

/// The leader: says hello until it has heard the hellos in `needs_hello`
/// and every node of `expect_ready` ready (with this scenario's
/// fingerprint); then announces [`Start`] (epoch `lead` from now) and keeps
/// announcing it every 100 ms until the returned task is aborted.
pub async fn lead_start(
    session: &zenoh::Session,
    keys: &Keys,
    needs_hello: &[String],
    expect_ready: &[String],
    scenario: &Scenario,
    time_scale: f64,
    lead: Duration,
) -> Result<(Start, tokio::task::JoinHandle<()>), Error> {
    let fingerprint = self::fingerprint(scenario);
    let mut h0 = Heard::new(fingerprint, expect_ready);
    h0.mine = key_digests(scenario);
    let heard = Arc::new(Mutex::new(h0));
    let subs = listen(session, keys, &heard, Whom::All).await?;
    let began = Instant::now();
    let me = names::LEADER_NODE;
    let mut warned: Vec<String> = Vec::new();
    loop {
        let (hello_missing, ready_missing, foreign) = {
            let h = lock(&heard);
            // Nodes heard only with another fingerprint (possibly forged): still missing.
            let foreign: Vec<(String, Vec<String>, Duration)> = h
                .ready_foreign
                .iter()
                .filter(|n| !h.ready.contains(*n))
                .map(|n| {
                    let (keys, since) = h.differ.get(n).cloned().unwrap_or_else(|| (Vec::new(), Instant::now()));
                    (n.clone(), keys, since.elapsed())
                })
                .collect();
            (missing(|n| h.hello.contains(n), needs_hello), missing(|n| h.ready.contains(n), expect_ready), foreign)
        };
        if hello_missing.is_empty() && ready_missing.is_empty() {
            break;
        }
        let differs = |keys_differ: &[String]| {
            if keys_differ.is_empty() {
                "(the keys that differ are not known: an older build?)".to_string()
            } else {
                format!("differing in {}", key_list(keys_differ))
            }
        };
        for (n, keys_differ, since) in &foreign {
            if *since >= MISMATCH_GRACE {
                let reason = format!("node {n} runs another scenario, {}", differs(keys_differ));
                // Tell every node waiting for the start, so none waits it out.
                for _ in 0..5 {
                    let _ = session.put(keys.abort(), reason.clone().into_bytes()).await;
                    tokio::time::sleep(TICK).await;
                }
                return Err(Error::Input(format!(
                    "leader: {reason} in run {} (another file or --set values)",
                    keys.run
                )));
            }
            if warned.contains(n) {
                continue;
            }
            eprintln!(
                "leader: node {n} of run {} is ready with another scenario, {}; waiting up to {} s for it to run \
                 this one",
                keys.run,
                differs(keys_differ),
                MISMATCH_GRACE.as_secs()
            );
            warned.push(n.clone());
        }
        session.put(keys.hello(me), Vec::<u8>::new()).await.map_err(|e| zerr("saying hello", e))?;
        if began.elapsed() > START_TIMEOUT {
            let mut waiting: BTreeSet<String> = hello_missing.into_iter().collect();
            waiting.extend(ready_missing);
            return Err(Error::Run(format!(
                "leader: nodes {} of run {} not ready within {} s",
                waiting.into_iter().collect::<Vec<_>>().join(", "),
                keys.run,
                START_TIMEOUT.as_secs()
            )));
        }
        tokio::time::sleep(TICK).await;
    }
    drop(subs);
    let start = Start { fingerprint, epoch_unix_ns: unix_ns() + lead.as_nanos() as u64, time_scale };
    let bytes = codec::encode(&start);
    let session = session.clone();
    let key = keys.start();
    let task = tokio::spawn(async move {
        loop {
            if session.put(&key, bytes.clone()).await.is_err() {
                return;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    });
    Ok((start, task))
}

/// How long a node listens for a twin before it joins a run.
pub const TWIN_LISTEN: Duration = Duration::from_millis(300);

/// Refuses to take part in a run where a process with this node's identity
/// (`id`: 0 the leader, else a follower) already publishes estimates: a
/// second formation started with the same run name, or a second process
/// for one follower. Called before the node publishes anything; listens to
/// its own estimate key for [`TWIN_LISTEN`]. (A forged message can still
/// make a node refuse: traffic is not authenticated yet.)
pub async fn refuse_twin(session: &zenoh::Session, keys: &Keys, id: u32, steps: u64) -> Result<(), Error> {
    let heard = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let h = heard.clone();
    let sub = session
        .declare_subscriber(keys.estimate(id))
        .callback(move |sample| {
            // Only a well-formed estimate from this very id, of a step of
            // the run, counts (garbage on the key is the inbox's business).
            let bytes = sample.payload().to_bytes();
            if formation_topology::wire::decode(&bytes).is_ok_and(|m| m.header.sender == id && m.header.step <= steps) {
                h.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        })
        .await
        .map_err(|e| zerr("listening for a twin", e))?;
    tokio::time::sleep(TWIN_LISTEN).await;
    drop(sub);
    let n = heard.load(std::sync::atomic::Ordering::Relaxed);
    if n == 0 {
        return Ok(());
    }
    let who = if id == 0 { "the leader".to_string() } else { format!("follower {id}") };
    Err(Error::Input(format!(
        "run {}: {who} is already running on this network ({n} of its estimates in {} ms): another formation \
         with the same run name, or a second process for {who}. Give this formation another name with --run \
         NAME, or stop the other process",
        keys.run,
        TWIN_LISTEN.as_millis()
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn foreign_start_and_ready_are_ignored_and_counted() {
        let mut h = Heard::new(7, &["1".to_string(), "monitor".to_string()]);
        let start = |fingerprint| Start { fingerprint, epoch_unix_ns: 1, time_scale: 1.0 };
        // A foreign start first is not kept; the genuine one after it is.
        h.on_start(start(8));
        assert_eq!(h.start, None);
        h.on_start(start(7));
        h.on_start(start(9));
        assert_eq!(h.start.map(|s| s.fingerprint), Some(7));
        // Ready from names outside the expected set, or with another fingerprint, does not count.
        let ready = |fingerprint| Ready { fingerprint, keys: vec![] };
        h.on_ready("rogue", ready(8));
        h.on_ready("rogue", ready(7));
        h.on_ready("1", ready(8));
        assert!(h.ready.is_empty());
        assert_eq!(h.ready_foreign.iter().collect::<Vec<_>>(), ["1"]);
        h.on_ready("1", ready(7));
        h.on_ready("monitor", ready(7));
        assert_eq!(h.ready.len(), 2);
        assert_eq!(h.ignored, 5);
    }

    #[test]
    fn a_mismatch_names_the_keys_that_differ() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        let a = Scenario::load(&path, &[]).expect("scenario");
        let b = Scenario::load(&path, &["robot.mass=12".to_string(), "dt=0.002".to_string()]).expect("scenario");
        let (da, db) = (key_digests(&a), key_digests(&b));
        assert!(da.len() > 20, "{} keys", da.len());
        assert_eq!(differing_keys(&da, &da), Vec::<String>::new());
        assert_eq!(differing_keys(&da, &db), ["dt", "robot.mass"]);
        let mut h = Heard::new(fingerprint(&a), &["3".to_string()]);
        h.mine = da;
        h.on_ready("3", Ready { fingerprint: fingerprint(&b), keys: db });
        assert_eq!(h.differ["3"].0, ["dt", "robot.mass"]);
    }
}
