//! The timebase on zenoh: the leader answers `control/time` with its
//! timebase when a question arrived and when it answers; every other node
//! asks every [`EVERY`] (faster at first) and files each answer as a
//! four-timestamp exchange in its [`Timebase`]. The estimate itself is
//! [`formation_protocol::clock_estimate`]'s.

use std::time::Duration;

use serde::{Deserialize, Serialize};
use zenoh::Wait;

use crate::clock::{Clock, Timebase};
use formation_exit::{zerr, Error};
use formation_protocol::clock_estimate::Exchange;
use formation_protocol::codec;
use formation_protocol::names::Keys;

/// The leader's answer: its timebase when the question arrived (`t2`) and
/// when it answered (`t3`), ns.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TimeReply {
    pub t2: i64,
    pub t3: i64,
}

/// How often a node asks during the run.
pub const EVERY: Duration = Duration::from_millis(250);
/// The first questions come this quickly, this many of them.
const FIRST_EVERY: Duration = Duration::from_millis(20);
const FIRST: u32 = 10;
/// How often a node never answered for [`UNANSWERED_AFTER`] asks (or at
/// once when it hears the leader's start). Before that, as always: nodes
/// started together meet well within it, and their clocks are estimated
/// exactly as before.
const UNANSWERED_EVERY: Duration = Duration::from_secs(1);
const UNANSWERED_AFTER: Duration = Duration::from_secs(10);
/// A question unanswered this long is lost.
const TIMEOUT: Duration = Duration::from_secs(1);

/// The leader: answers every question with its timebase, until the
/// returned queryable is dropped; `count` counts the questions.
pub async fn serve_counted(
    session: &zenoh::Session,
    keys: &Keys,
    timebase: Timebase,
    count: std::sync::Arc<formation_protocol::counters::QueryCount>,
) -> Result<zenoh::query::Queryable<()>, Error> {
    session
        .declare_queryable(keys.time())
        .callback(move |query| {
            let t2 = timebase.now_ns().unwrap_or(0);
            count.note(t2);
            let reply = |t3| codec::encode(&TimeReply { t2, t3 });
            let _ = query.reply(query.key_expr().clone(), reply(timebase.now_ns().unwrap_or(0))).wait();
        })
        .await
        .map_err(|e| zerr("declaring the time queryable", e))
}

/// [`serve_counted`] without looking at the count.
pub async fn serve(
    session: &zenoh::Session,
    keys: &Keys,
    timebase: Timebase,
) -> Result<zenoh::query::Queryable<()>, Error> {
    serve_counted(session, keys, timebase, Default::default()).await
}

/// A node's questions to the leader's timebase; they stop when this is dropped.
pub struct Following(tokio::task::JoinHandle<()>);

impl Drop for Following {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// A node: asks the leader's timebase until the returned guard is dropped,
/// filing every answer in `timebase`; `quarter_step_ns`: an uncertainty
/// beyond this is reported once on stderr, naming `me`.
pub fn follow(session: zenoh::Session, keys: &Keys, timebase: Timebase, me: String, quarter_step_ns: f64) -> Following {
    let key = keys.time();
    let start_key = keys.start();
    Following(tokio::spawn(async move {
        // The leader's start announcements (every 100 ms through the run)
        // carry its timebase when sent: a floor no answer may fall below.
        // They also wake a node that has never been answered (no leader
        // for a while, asked once a second) to ask at once.
        let stamps = timebase.clone();
        let heard_start = std::sync::Arc::new(tokio::sync::Notify::new());
        let wake = heard_start.clone();
        let _floor = session
            .declare_subscriber(start_key)
            .callback(move |s| {
                if let Some(start) = codec::decode::<formation_protocol::barrier::Start>(&s.payload().to_bytes()) {
                    stamps.leader_sent(start.sent_ns);
                    wake.notify_one();
                }
            })
            .await;
        let mut asked = 0u32;
        let clock = timebase.clock().clone();
        let (began, mut answered) = (clock.mono(), false);
        let mut warned = false;
        let mut named = false;
        loop {
            let answers = ask_all(&session, &key, &clock).await;
            timebase.add_answers(&answers);
            // Never answered for UNANSWERED_AFTER (no leader yet, long after
            // a launch's nodes have met): one question a second, so that a
            // node waiting idle costs next to nothing.
            answered |= !answers.is_empty();
            if !answered && clock.mono().saturating_sub(began) > UNANSWERED_AFTER {
                tokio::select! {
                    _ = tokio::time::sleep(UNANSWERED_EVERY) => {}
                    _ = heard_start.notified() => {}
                }
                continue;
            }
            asked = asked.saturating_add(1);
            if !named && timebase.second_clock() {
                named = true;
                let worst = timebase.guard_report().worst_disagreement_ms;
                crate::node::say(&format!(
                    "{me}: a second clock answers on {key}, {worst:.1} ms from the leader's: its answers are \
                     refused (another process imitating the leader? with --tls only the leader may answer)"
                ));
            }
            // Judged once the drift is measured (before, its allowance dominates).
            if !warned {
                let measured = |e: &formation_protocol::clock_estimate::Estimate| {
                    e.periods >= formation_protocol::clock_estimate::MIN_SLOPE_PERIODS
                };
                if let Some(e) = timebase.estimate().filter(|e| measured(e) && e.uncertainty_ns > quarter_step_ns) {
                    warned = true;
                    crate::node::say(&format!(
                        "{me}: the leader's clock is known only to ±{:.3} ms (more than a quarter step, {:.3} ms): \
                         steps may be early or late by that much",
                        e.uncertainty_ns * 1e-6,
                        quarter_step_ns * 1e-6
                    ));
                }
            }
            tokio::time::sleep(if asked < FIRST { FIRST_EVERY } else { EVERY }).await;
        }
    }))
}

/// One exchange: None if unanswered (within [`TIMEOUT`]) or garbled.
pub async fn ask(session: &zenoh::Session, key: &str, clock: &Clock) -> Option<Exchange> {
    ask_all(session, key, clock).await.into_iter().next()
}

/// Answers to one question beyond this many are not read (a flood of
/// responders cannot hold a node's memory).
const MAX_ANSWERS: usize = 8;

/// One question and every answer to it (zenoh's consolidation off: a
/// second responder's answer is not merged into the leader's), in the
/// order they came, within [`TIMEOUT`]; garbled ones left out.
///
/// The question, and with it the answer (zenoh gives a reply its query's
/// congestion control, `Block` by default for a query), is dropped rather
/// than waited for when the link's queue is full: the leader answers on
/// zenoh's own thread, the one that empties its queues, and an answer that
/// waited for room there held the whole link until zenoh closed it 5 s
/// later. An experimental build with zenoh's QoS off (one queue per link,
/// estimates included; a config file doing that is now refused) stalled
/// the paper's lock-step run that way in 21 of 25 runs. A dropped question
/// is one unanswered, asked again at the next turn.
pub async fn ask_all(session: &zenoh::Session, key: &str, clock: &Clock) -> Vec<Exchange> {
    let t1 = clock.mono_ns();
    let mut answers = Vec::new();
    let Ok(replies) = session
        .get(key)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .congestion_control(zenoh::qos::CongestionControl::Drop)
        .timeout(TIMEOUT)
        .await
    else {
        return answers;
    };
    while let Ok(reply) = replies.recv_async().await {
        let t4 = clock.mono_ns();
        if let Ok(sample) = reply.result() {
            if let Some(r) = codec::decode::<TimeReply>(&sample.payload().to_bytes()) {
                answers.push(Exchange { t1, t2: r.t2, t3: r.t3, t4 });
                if answers.len() >= MAX_ANSWERS {
                    break;
                }
            }
        }
    }
    answers
}

/// A node after the start: waits until its timebase has an estimate. It
/// gives up after `limit` of silence, counted as [`Patience`] counts it:
/// only the time this node was awake to watch, from the leader's last word
/// (its start announcements come every 100 ms: a leader that speaks is slow
/// to answer, not gone); and after [`ALIVE_LIMIT`] times `limit` of
/// watching a leader that speaks but never answers. The error names which.
pub async fn wait_for_estimate(timebase: &Timebase, keys: &Keys, me: &str, limit: Duration) -> Result<(), Error> {
    let clock = timebase.clock();
    let (mut silent, mut watched) =
        (Patience::new(clock.mono(), FIRST_EVERY), Patience::new(clock.mono(), FIRST_EVERY));
    while timebase.estimate().is_none() {
        let now = clock.mono();
        silent.alive(now, timebase.leader_heard());
        if silent.look(now) > limit {
            return Err(Error::Input(format!(
                "{me}: cannot estimate the leader's clock: no answer on {} and no word from the leader for {} s \
                 (of this node's own time awake; is the leader reachable from this host, and of this build?)",
                keys.time(),
                limit.as_secs()
            )));
        }
        if watched.look(now) > limit * ALIVE_LIMIT {
            return Err(Error::Input(format!(
                "{me}: cannot estimate the leader's clock: the leader is heard but has not answered on {} in {} s \
                 (of this node's own time awake)",
                keys.time(),
                (limit * ALIVE_LIMIT).as_secs()
            )));
        }
        tokio::time::sleep(FIRST_EVERY).await;
    }
    Ok(())
}

/// A leader heard but never answering is given this many times the limit
/// of a silent one.
const ALIVE_LIMIT: u32 = 12;

use formation_protocol::patience::Patience;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_node_that_hears_no_time_gives_up_naming_the_key() {
        let rt = tokio::runtime::Builder::new_current_thread().enable_time().build().expect("runtime");
        let keys = Keys { run: "r".into() };
        let clock = Clock::real();
        let tb = Timebase::estimated(&clock);
        match rt.block_on(wait_for_estimate(&tb, &keys, "follower 3", Duration::ZERO)) {
            Err(Error::Input(m)) => assert!(
                m.starts_with("follower 3: cannot estimate the leader's clock: no answer on formation/r/control/time"),
                "{m}"
            ),
            other => panic!("{other:?}"),
        }
        // One exchange is enough to go on.
        let t1 = clock.mono_ns();
        tb.add(Exchange { t1, t2: 10, t3: 20, t4: t1 + 1_000 });
        assert_eq!(rt.block_on(wait_for_estimate(&tb, &keys, "follower 3", Duration::ZERO)), Ok(()));
    }

    #[test]
    fn a_reply_is_refused_unless_it_is_one() {
        let r = TimeReply { t2: -5, t3: 7 };
        assert_eq!(codec::decode::<TimeReply>(&codec::encode(&r)), Some(r));
        assert_eq!(codec::decode::<TimeReply>(b"not a reply at all"), None);
    }
}
