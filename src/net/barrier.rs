//! The start barrier (see [`crate::net::node`] for the protocol).

use std::collections::{BTreeMap, BTreeSet};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::cli::CliError;
use crate::net::node::{self, Keys, Ready, Start};

/// How long a node waits at the barrier before giving up.
pub const START_TIMEOUT: Duration = Duration::from_secs(120);
const TICK: Duration = Duration::from_millis(50);

#[derive(Default)]
struct Heard {
    hello: BTreeSet<String>,
    ready: BTreeMap<String, u64>,
    start: Option<Start>,
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
                    lock(&h).start.get_or_insert(start);
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
                        lock(&h).ready.insert(node::last_chunk(s.key_expr().as_str()).to_string(), r.fingerprint);
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
    let heard = Arc::new(Mutex::new(Heard::default()));
    let _subs = listen(session, keys, &heard, false).await?;
    let began = Instant::now();
    let ready = node::encode(&Ready { fingerprint });
    loop {
        let (start, waiting) = {
            let h = lock(&heard);
            (h.start, missing(|n| h.hello.contains(n), needs))
        };
        if let Some(start) = start {
            if start.fingerprint != fingerprint {
                return Err(CliError::Input(format!(
                    "node {me}: the leader of run {} loaded a different scenario (or other --set values)",
                    keys.run
                )));
            }
            return Ok(start);
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
    let heard = Arc::new(Mutex::new(Heard::default()));
    let subs = listen(session, keys, &heard, true).await?;
    let began = Instant::now();
    let me = node::LEADER_NODE;
    loop {
        let (hello_missing, ready_missing, foreign) = {
            let h = lock(&heard);
            let foreign: Vec<String> =
                h.ready.iter().filter(|(_, &f)| f != fingerprint).map(|(n, _)| n.clone()).collect();
            (missing(|n| h.hello.contains(n), needs_hello), missing(|n| h.ready.contains_key(n), expect_ready), foreign)
        };
        if !foreign.is_empty() {
            return Err(CliError::Input(format!(
                "nodes {} of run {} loaded a different scenario (or other --set values) than the leader",
                foreign.join(", "),
                keys.run
            )));
        }
        if hello_missing.is_empty() && ready_missing.is_empty() {
            break;
        }
        session.put(keys.hello(me), Vec::<u8>::new()).await.map_err(|e| zerr("saying hello", e))?;
        if began.elapsed() > START_TIMEOUT {
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
