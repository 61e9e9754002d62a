//! The start barrier (see [`crate::net::node`] for the protocol).

use std::collections::BTreeSet;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::cli::CliError;
use crate::net::node::{self, Keys, Ready, Start};

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

fn zerr(what: &str, e: impl std::fmt::Display) -> CliError {
    CliError::Run(format!("{what}: {e}"))
}

fn lock(h: &Mutex<Heard>) -> std::sync::MutexGuard<'_, Heard> {
    h.lock().unwrap_or_else(|p| p.into_inner())
}

async fn listen(
    session: &zenoh::Session,
    keys: &Keys,
    heard: &Arc<Mutex<Heard>>,
    ready_too: bool,
) -> Result<Vec<zenoh::pubsub::Subscriber<()>>, CliError> {
    let mut subs = Vec::new();
    let h = heard.clone();
    subs.push(
        session
            .declare_subscriber(keys.hello("*"))
            .callback(move |s| {
                lock(&h).hello.insert(node::last_chunk(s.key_expr().as_str()).to_string());
            })
            .await
            .map_err(|e| zerr("declaring the hello subscriber", e))?,
    );
    let h = heard.clone();
    subs.push(
        session
            .declare_subscriber(keys.start())
            .callback(move |s| {
                if let Some(start) = node::decode::<Start>(&s.payload().to_bytes()) {
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
                    if let Some(r) = node::decode::<Ready>(&s.payload().to_bytes()) {
                        lock(&h).on_ready(node::last_chunk(s.key_expr().as_str()), r);
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
) -> Result<Start, CliError> {
    let heard = Arc::new(Mutex::new(Heard::new(fingerprint, &[])));
    let _subs = listen(session, keys, &heard, false).await?;
    let began = Instant::now();
    let ready = node::encode(&Ready { fingerprint });
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
                return Err(CliError::Input(format!(
                    "node {me}: no start for this scenario within {} s; ignored {ignored} start announcements \
                     of run {} with another scenario fingerprint (a leader with another scenario or --set values?)",
                    START_TIMEOUT.as_secs(),
                    keys.run
                )));
            }
            return Err(CliError::Run(format!(
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
) -> Result<(Start, tokio::task::JoinHandle<()>), CliError> {
    let heard = Arc::new(Mutex::new(Heard::new(fingerprint, expect_ready)));
    let subs = listen(session, keys, &heard, true).await?;
    let began = Instant::now();
    let me = node::LEADER_NODE;
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
                return Err(CliError::Input(format!(
                    "leader: nodes {} of run {} said ready only with another scenario fingerprint \
                     (a different scenario or other --set values than the leader?)",
                    foreign.join(", "),
                    keys.run
                )));
            }
            let mut waiting: BTreeSet<String> = hello_missing.into_iter().collect();
            waiting.extend(ready_missing);
            return Err(CliError::Run(format!(
                "leader: nodes {} of run {} not ready within {} s",
                waiting.into_iter().collect::<Vec<_>>().join(", "),
                keys.run,
                START_TIMEOUT.as_secs()
            )));
        }
        tokio::time::sleep(TICK).await;
    }
    drop(subs);
    let start = Start { fingerprint, epoch_unix_ns: node::unix_ns() + lead.as_nanos() as u64, time_scale };
    let bytes = node::encode(&start);
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
