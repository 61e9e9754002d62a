//! A standby leader (`leader --standby`; docs/model.md §14): a second
//! leader process, on this host or another, that takes the run over when
//! the leader is gone. It is [`formation_protocol::leader::LeaderMachine`] made
//! with [`Machine::standby`], translated to zenoh as the leader is
//! ([`crate::leader`]), with what changes hands at the takeover:
//!
//! - **How it learns the leader is gone:** from the leader's silence on its
//!   estimate key (real time: a message every step; lock-step: at least a
//!   repeat every 200 ms while it waits), for `--take-over-after` seconds.
//!   Silence covers a killed process, a dead host and a cut cable alike, on
//!   every transport; a liveliness token would tell a closed session sooner,
//!   but not a host that stopped answering before the session's lease ends.
//! - **The timebase:** until it takes over it estimates the leader's clock
//!   as every node does; at the takeover it stops asking and answers
//!   `control/time` with that estimate, carried on by its own clock, and
//!   announces the run's start as the leader did.
//! - **Two leaders:** once it leads it is the leader of the next term: its
//!   messages and its claim on `control/claim/0` carry it. The leader says
//!   its claim (term 1) through its run and listens there and on its key.
//!   Of two processes that both lead (a leader cut off, then back), the one
//!   of the lower term stands down as soon as it hears the other's claim or
//!   messages: it ends, naming the other in one line; the followers use the
//!   highest term's messages only (docs/model.md §14). No clock is compared.

use std::sync::Arc;
use std::time::Duration;

use formation_protocol::wire;
use formation_scenario::{Scenario, Timing};

use crate::clock::{self, Clock};
use crate::lead_loop::{watch_leader_key, watch_reached, LeadLoop};
use crate::node::Shared;
use crate::{clock_sync, startup, telemetry};
use formation_exit::{zerr, Error};
use formation_protocol::barrier::Start;
use formation_protocol::codec;
use formation_protocol::counters::QueryCount;
use formation_protocol::leader::LeaderMachine as Machine;
use formation_protocol::names::Keys;

/// How long a standby waits to hear the run's start.
const START_LIMIT: Duration = Duration::from_secs(120);

/// Before the start the leader says its claim every 100 ms: a leader is
/// taken for gone when its claim has been silent this long, at least.
const GONE_BEFORE_START: Duration = Duration::from_secs(1);

/// How a standby's watch ended.
#[derive(Debug)]
pub enum Ended {
    /// The run ended (taken over or not).
    Run,
    /// The leader was gone before the run began: lead it from the start,
    /// on this estimate of the gone leader's clock where there is one (the
    /// followers estimate the same clock: a new one would be a second).
    GoneBeforeStart(Option<clock::Timebase>),
}

/// Stands by for the leader of the run `keys` names; takes the run over
/// once the leader has been silent for `after`; returns at the run's end,
/// or, when the leader's claim fell silent before the start, at once: the
/// caller then leads the run from its start.
pub async fn run(
    session: &zenoh::Session,
    scenario: &Scenario,
    keys: &Keys,
    after: Duration,
    clock: &Clock,
) -> Result<Ended, Error> {
    let me = "leader (standby)".to_string();
    let timebase = clock::Timebase::estimated(clock);
    let quarter_step_ns = scenario.dt_s * 1e9 / 4.0;
    let following = clock_sync::follow(session.clone(), keys, timebase.clone(), me.clone(), quarter_step_ns);
    let shared = Arc::new(Shared::new(Machine::standby(scenario, after)));
    let hearing = shared.lock().hearing().to_vec();
    let (start_tx, start_rx) = tokio::sync::watch::channel(None::<Start>);
    let start_sub = session
        .declare_subscriber(keys.start())
        .callback(move |s| {
            if let Some(start) = codec::decode::<Start>(&s.payload().to_bytes()) {
                start_tx.send_if_modified(|held| held.is_none() && held.replace(start).is_none());
            }
        })
        .await
        .map_err(|e| zerr("declaring the start subscriber", e))?;
    let leader_sub = watch_leader_key(session, keys, &shared, &timebase).await?;
    let reached = watch_reached(session, keys, &hearing, &shared).await?;
    crate::node::say(&format!(
        "{me}: standing by for run {} (taking over after {} s of silence)",
        keys.run,
        after.as_secs_f64()
    ));
    let Some(start) = wait_for_start(session, keys, start_rx, after.max(GONE_BEFORE_START), clock, &me).await? else {
        drop(following);
        let known = timebase.now_ns().is_some();
        return Ok(Ended::GoneBeforeStart(known.then_some(timebase)));
    };
    clock_sync::wait_for_estimate(&timebase, keys, &me, START_LIMIT).await?;
    shared.lock().handle_start(&start, timebase.now());
    drop(start_sub);

    let lockstep = scenario.timing == Timing::Lockstep;
    let (done_subs, followers_done) = match lockstep {
        true => telemetry::watch_done(session, keys, &hearing, scenario).await?,
        false => (Vec::new(), Default::default()),
    };
    let estimate_pub =
        crate::node::control_publisher(session, keys.estimate(wire::LEADER_ID), scenario, "estimate").await?;
    let (delivery, acks) = telemetry::start_delivery(session, keys, wire::LEADER_ID, scenario, clock).await?;
    let queries = Arc::new(QueryCount::default());
    let (tell, took_over) = tokio::sync::oneshot::channel();
    let node = LeadLoop {
        shared: shared.clone(),
        publisher: estimate_pub,
        courier: delivery.courier.clone(),
        timebase: timebase.clone(),
        followers_done,
        queries: queries.clone(),
        topics: None,
        lockstep,
        incarnation: clock.unix_ns(),
        on_take_over: Some(tell),
    };
    let driving = tokio::task::spawn_blocking(move || node.drive());
    let leading = Takeover { session, keys, timebase: &timebase, start, queries, shared: &shared };
    // Until the machine takes over (or the run ends without it).
    let held = match took_over.await {
        Ok(_) => Some(leading.lead(following).await?),
        Err(_) => None,
    };
    let outcome = driving.await.map_err(|e| Error::Run(format!("{me}: loop panicked: {e}")))?;
    telemetry::finish_delivery(delivery, "leader").await;
    drop((acks, held, leader_sub, reached, done_subs));
    outcome.map(|()| Ended::Run).map_err(|e| Error::Run(format!("{me}: {e}")))
}

/// The run's start, as the leader announces it (every 100 ms); None when
/// the leader's claim on the run, heard before, has been silent for `gone`
/// with no start (the leader died before the run began).
async fn wait_for_start(
    session: &zenoh::Session,
    keys: &Keys,
    mut rx: tokio::sync::watch::Receiver<Option<Start>>,
    gone: Duration,
    clock: &Clock,
    me: &str,
) -> Result<Option<Start>, Error> {
    use formation_protocol::claim::Claim;
    let last_claim = Arc::new(std::sync::Mutex::new(None::<Duration>));
    let (heard, c) = (last_claim.clone(), clock.clone());
    let _claims = session
        .declare_subscriber(keys.claim(wire::LEADER_ID))
        .callback(move |s| {
            if codec::decode::<Claim>(&s.payload().to_bytes()).is_some_and(|cl| cl.id == wire::LEADER_ID) {
                *heard.lock().unwrap_or_else(|p| p.into_inner()) = Some(c.mono());
            }
        })
        .await
        .map_err(|e| zerr("listening to the leader's claim", e))?;
    let limit = clock.mono() + START_LIMIT;
    loop {
        if let Some(start) = rx.borrow_and_update().clone() {
            return Ok(Some(start));
        }
        let now = clock.mono();
        let last = *last_claim.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(silent) = last.map(|l| now.saturating_sub(l)).filter(|&s| s >= gone) {
            crate::node::say(&format!(
                "{me}: the leader silent for {:.1} s before the run began: leading run {} from its start",
                silent.as_secs_f64(),
                keys.run
            ));
            return Ok(None);
        }
        if now >= limit {
            return Err(Error::Input(format!(
                "{me}: no start heard within {} s: is the leader of this run (same --run, same scenario) running \
                 and reachable?",
                START_LIMIT.as_secs()
            )));
        }
        let _ = tokio::time::timeout(Duration::from_millis(50), rx.changed()).await;
    }
}

/// What a standby takes on when it takes the run over.
struct Takeover<'a> {
    session: &'a zenoh::Session,
    keys: &'a Keys,
    timebase: &'a clock::Timebase,
    start: Start,
    queries: Arc<QueryCount>,
    shared: &'a Arc<Shared<Machine>>,
}

/// What the standby holds while it leads: the time server, the start's
/// announcer and its claim, watched for a higher term's.
struct Held {
    _time: zenoh::query::Queryable<()>,
    announcer: tokio::task::JoinHandle<()>,
    watcher: tokio::task::JoinHandle<()>,
}

impl Drop for Held {
    fn drop(&mut self) {
        self.announcer.abort();
        self.watcher.abort();
    }
}

impl Takeover<'_> {
    /// Stops estimating the leader's clock and serves that estimate as the
    /// run's timebase; announces the start; claims the lead in its term and
    /// stands down for a higher one.
    async fn lead(self, following: clock_sync::Following) -> Result<Held, Error> {
        drop(following);
        let time = clock_sync::serve_counted(self.session, self.keys, self.timebase.clone(), self.queries).await?;
        let announcer = startup::announce(self.session, self.keys, self.timebase, self.start);
        let term = self.shared.lock().term();
        let claim = startup::Leading::claim(self.session, self.keys, self.timebase.clock(), term).await?;
        let watcher = claim.watch(self.shared.clone(), self.keys.run.clone());
        Ok(Held { _time: time, announcer, watcher })
    }
}
