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

use crate::error::Error;
use crate::net::codec;
use crate::net::keys::{self, Keys};

/// "I can hear everyone I need": sent by agents and the monitor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Ready {
    pub fingerprint: u64,
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

/// How long a node waits at the barrier before giving up.
pub const START_TIMEOUT: Duration = Duration::from_secs(120);
const TICK: Duration = Duration::from_millis(50);

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
        }
    }
}

fn zerr(what: &str, e: impl std::fmt::Display) -> Error {
    Error::Run(format!("{what}: {e}"))
}

fn lock(h: &Mutex<Heard>) -> std::sync::MutexGuard<'_, Heard> {
    h.lock().unwrap_or_else(|p| p.into_inner())
}

async fn listen(
    session: &zenoh::Session,
    keys: &Keys,
    heard: &Arc<Mutex<Heard>>,
    ready_too: bool,
) -> Result<Vec<zenoh::pubsub::Subscriber<()>>, Error> {
    let mut subs = Vec::new();
    let h = heard.clone();
    subs.push(
        session
            .declare_subscriber(keys.hello("*"))
            .callback(move |s| {
                lock(&h).hello.insert(keys::last_chunk(s.key_expr().as_str()).to_string());
            })
            .await
            .map_err(|e| zerr("declaring the hello subscriber", e))?,
    );
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
    if ready_too {
        let h = heard.clone();
        subs.push(
            session
                .declare_subscriber(keys.ready_all())
                .callback(move |s| {
                    if let Some(r) = codec::decode::<Ready>(&s.payload().to_bytes()) {
                        lock(&h).on_ready(keys::last_chunk(s.key_expr().as_str()), r);
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
    fingerprint: u64,
) -> Result<Start, Error> {
    let heard = Arc::new(Mutex::new(Heard::new(fingerprint, &[])));
    let _subs = listen(session, keys, &heard, false).await?;
    let began = Instant::now();
    let ready = codec::encode(&Ready { fingerprint });
    let mut warned = false;
    loop {
        let (start, waiting, ignored) = {
            let h = lock(&heard);
            (h.start, missing(|n| h.hello.contains(n), needs), h.ignored)
        };
        if let Some(start) = start {
            return Ok(start);
        }
        if ignored > 0 && !warned {
            // Said at once, not only at the time limit; not fatal, since a
            // forged announcement must not stop a genuine run.
            eprintln!(
                "node {me}: the leader of run {} announces another scenario (another file or --set values?); \
                 waiting up to {} s for a start with this one",
                keys.run,
                START_TIMEOUT.as_secs()
            );
            warned = true;
        }
        session.put(keys.hello(me), Vec::<u8>::new()).await.map_err(|e| zerr("saying hello", e))?;
        if waiting.is_empty() {
            session.put(keys.ready(me), ready.clone()).await.map_err(|e| zerr("saying ready", e))?;
        }
        if began.elapsed() > START_TIMEOUT {
            let what = if waiting.is_empty() {
                "the leader's start".to_string()
            } else {
                format!("nodes {}", waiting.join(", "))
            };
            if waiting.is_empty() && ignored > 0 {
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
    fingerprint: u64,
    time_scale: f64,
    lead: Duration,
) -> Result<(Start, tokio::task::JoinHandle<()>), Error> {
    let heard = Arc::new(Mutex::new(Heard::new(fingerprint, expect_ready)));
    let subs = listen(session, keys, &heard, true).await?;
    let began = Instant::now();
    let me = keys::LEADER_NODE;
    let mut warned: Vec<String> = Vec::new();
    loop {
        let (hello_missing, ready_missing, foreign) = {
            let h = lock(&heard);
            // Nodes heard only with another fingerprint (possibly forged): still missing.
            let foreign: Vec<String> = h.ready_foreign.iter().filter(|n| !h.ready.contains(*n)).cloned().collect();
            (missing(|n| h.hello.contains(n), needs_hello), missing(|n| h.ready.contains(n), expect_ready), foreign)
        };
        if hello_missing.is_empty() && ready_missing.is_empty() {
            break;
        }
        for n in &foreign {
            if warned.contains(n) {
                continue;
            }
            eprintln!(
                "leader: node {n} of run {} is ready with another scenario (another file or --set values?); \
                 waiting up to {} s for it to run this one",
                keys.run,
                START_TIMEOUT.as_secs()
            );
            warned.push(n.clone());
        }
        session.put(keys.hello(me), Vec::<u8>::new()).await.map_err(|e| zerr("saying hello", e))?;
        if began.elapsed() > START_TIMEOUT {
            if !foreign.is_empty() {
                return Err(Error::Input(format!(
                    "leader: nodes {} of run {} said ready only with another scenario fingerprint \
                     (a different scenario or other --set values than the leader?)",
                    foreign.join(", "),
                    keys.run
                )));
            }
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
        h.on_ready("rogue", Ready { fingerprint: 8 });
        h.on_ready("rogue", Ready { fingerprint: 7 });
        h.on_ready("1", Ready { fingerprint: 8 });
        assert!(h.ready.is_empty());
        assert_eq!(h.ready_foreign.iter().collect::<Vec<_>>(), ["1"]);
        h.on_ready("1", Ready { fingerprint: 7 });
        h.on_ready("monitor", Ready { fingerprint: 7 });
        assert_eq!(h.ready.len(), 2);
        assert_eq!(h.ignored, 5);
    }
}
