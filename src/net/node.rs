//! What every networked node shares: command-line arguments, key
//! expressions, the start barrier's control messages, telemetry payloads
//! and the checks applied to every received estimate message.
//!
//! # Keys (all under `formation/<run>/`)
//!
//! | key | who publishes | payload |
//! | --- | --- | --- |
//! | `estimate/<id>` | leader (id 0), follower id | [`wire::EstimateMsg`] (SPEC §13) |
//! | `telemetry/<id>` | leader (id 0), follower id | [`Telemetry`] |
//! | `control/hello/<node>` | every node, until the start | empty |
//! | `control/ready/<node>` | agents and monitor, until the start | [`Ready`] |
//! | `control/start` | leader, every 100 ms during the run | [`Start`] |
//!
//! `<node>` is `0` for the leader, the follower id, or `monitor`.
//!
//! # Start barrier
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

use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use formation_agent::{LeaderState, LinkLoss};
use formation_topology::wire::{self, EstimateMsg, Reject};
use formation_topology::Scenario;
use serde::{Deserialize, Serialize};

use crate::cli::CliError;
use crate::net::session::{self, ZenohArgs};
use crate::record::FollowerSample;

/// Arguments every node takes.
#[derive(clap::Args, Debug, Clone)]
pub struct NodeArgs {
    /// Scenario file (TOML); every node of a run must load the same one.
    #[arg(long, value_name = "FILE")]
    pub scenario: PathBuf,
    /// Override a scenario value, as `formation sim --set` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Run name: the key namespace `formation/<run>/…` [default: scenario name].
    #[arg(long, value_name = "NAME")]
    pub run: Option<String>,
    #[command(flatten)]
    pub zenoh: ZenohArgs,
    /// Give up when no router or peer answers at start-up within this long (s).
    #[arg(long, default_value_t = 30.0, value_name = "SECONDS")]
    pub open_timeout: f64,
}

impl NodeArgs {
    /// Loads the scenario and resolves the run name (bad input: exit 2).
    pub fn load(&self) -> Result<(Scenario, Keys), CliError> {
        let scenario = Scenario::load(&self.scenario, &self.overrides).map_err(|e| CliError::Input(e.to_string()))?;
        let run = self.run.clone().unwrap_or_else(|| scenario.name.clone());
        session::validate_run_name(&run).map_err(|e| CliError::Input(e.to_string()))?;
        self.zenoh.to_config().map_err(|e| CliError::Input(format!("zenoh options: {e}")))?;
        Ok((scenario, Keys::new(&run)))
    }

    /// Opens the session; says once after a few seconds what it is waiting
    /// for, and gives up after `--open-timeout` naming the endpoints.
    pub async fn open(&self) -> Result<zenoh::Session, CliError> {
        let opening = session::open(&self.zenoh);
        tokio::pin!(opening);
        if !(self.open_timeout.is_finite() && self.open_timeout > 0.0) {
            return Err(CliError::Input(format!("--open-timeout must be positive, not {}", self.open_timeout)));
        }
        let limit = Duration::from_secs_f64(self.open_timeout);
        let began = std::time::Instant::now();
        let mut said = false;
        loop {
            let wait = Duration::from_secs(3).min(limit.saturating_sub(began.elapsed()).max(Duration::from_millis(10)));
            match tokio::time::timeout(wait, &mut opening).await {
                Ok(result) => return result.map_err(|e| CliError::Run(e.to_string())),
                Err(_) if began.elapsed() >= limit => {
                    return Err(CliError::Run(format!(
                        "no zenoh router or peer answered at {} within {} s (is the router running?)",
                        self.endpoints(),
                        self.open_timeout
                    )))
                }
                Err(_) if !said => {
                    eprintln!("waiting for {} …", self.endpoints());
                    said = true;
                }
                Err(_) => {}
            }
        }
    }

    fn endpoints(&self) -> String {
        if self.zenoh.connect.is_empty() {
            "the configured endpoints".to_string()
        } else {
            self.zenoh.connect.join(", ")
        }
    }
}

/// The shell of every node binary: logging, a multi-thread runtime, and
/// errors as one line with exit status 2 (bad input) or 1 (failed run).
pub fn main_with<F, Fut>(f: F) -> std::process::ExitCode
where
    F: FnOnce() -> Fut,
    Fut: std::future::Future<Output = Result<std::process::ExitCode, CliError>>,
{
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_writer(std::io::stderr)
        .try_init();
    let runtime = match tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: cannot start the async runtime: {e}");
            return std::process::ExitCode::from(1);
        }
    };
    let result = runtime.block_on(f());
    // Zenoh's background tasks must not keep the process alive.
    runtime.shutdown_timeout(Duration::from_secs(1));
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            e.exit_code()
        }
    }
}

/// The key expressions of one run.
#[derive(Clone, Debug)]
pub struct Keys {
    pub run: String,
}

impl Keys {
    pub fn new(run: &str) -> Self {
        Self { run: run.to_string() }
    }
    pub fn estimate(&self, id: u32) -> String {
        session::key(&self.run, &format!("estimate/{id}"))
    }
    pub fn telemetry(&self, id: u32) -> String {
        session::key(&self.run, &format!("telemetry/{id}"))
    }
    pub fn telemetry_all(&self) -> String {
        session::key(&self.run, "telemetry/*")
    }
    pub fn hello(&self, node: &str) -> String {
        session::key(&self.run, &format!("control/hello/{node}"))
    }
    pub fn ready(&self, node: &str) -> String {
        session::key(&self.run, &format!("control/ready/{node}"))
    }
    pub fn ready_all(&self) -> String {
        session::key(&self.run, "control/ready/*")
    }
    pub fn start(&self) -> String {
        session::key(&self.run, "control/start")
    }
}

/// How an estimate publisher meets a full queue (a slow or dead peer).
/// Real time: `Drop`, the newest wins — every step re-sends the whole state,
/// and a control loop that must meet its period never waits on a `put`.
/// Lock-step: `Block`, since every step's message is needed and the loop
/// waits for its peers by design (lost start-up messages are re-sent).
pub fn estimate_congestion(scenario: &Scenario) -> zenoh::qos::CongestionControl {
    match scenario.timing {
        formation_topology::Timing::Realtime => zenoh::qos::CongestionControl::Drop,
        formation_topology::Timing::Lockstep => zenoh::qos::CongestionControl::Block,
    }
}

/// The last chunk of a key expression (`…/estimate/3` → `3`).
pub fn last_chunk(key: &str) -> &str {
    key.rsplit('/').next().unwrap_or("")
}

/// Node name of the monitor in control keys.
pub const MONITOR: &str = "monitor";
/// Node name of the leader in control keys (its wire id).
pub const LEADER_NODE: &str = "0";

fn bincode_config() -> bincode::config::Configuration {
    bincode::config::standard()
}

/// Encodes a control or telemetry payload.
pub fn encode<T: Serialize>(v: &T) -> Vec<u8> {
    bincode::serde::encode_to_vec(v, bincode_config()).unwrap_or_default()
}

/// Decodes a control or telemetry payload (None if malformed).
pub fn decode<T: for<'de> Deserialize<'de>>(bytes: &[u8]) -> Option<T> {
    match bincode::serde::decode_from_slice::<T, _>(bytes, bincode_config()) {
        Ok((v, used)) if used == bytes.len() => Some(v),
        _ => None,
    }
}

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

/// Per-reason counts of received estimate messages that were not used.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RejectCounts {
    pub malformed: u64,
    pub version: u64,
    pub non_finite: u64,
    pub wrong_sender: u64,
    pub not_neighbour: u64,
    /// An older step than one already used (also: duplicates of a used step).
    pub stale: u64,
    /// A step further ahead of the receiver's than any genuine sender can be.
    #[serde(default)]
    pub future: u64,
}

impl RejectCounts {
    pub fn add(&mut self, r: Reject) {
        match r {
            Reject::Malformed => self.malformed += 1,
            Reject::Version => self.version += 1,
            Reject::NonFinite => self.non_finite += 1,
            Reject::WrongSender => self.wrong_sender += 1,
            Reject::NotNeighbour => self.not_neighbour += 1,
            Reject::Stale => self.stale += 1,
            Reject::Future => self.future += 1,
        }
    }
    /// Everything but `stale` (which is lateness, not a bad message).
    pub fn invalid(&self) -> u64 {
        self.malformed + self.version + self.non_finite + self.wrong_sender + self.not_neighbour + self.future
    }
}

/// A node's message counters, sent with every telemetry batch.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Counters {
    /// Estimate messages published (republications included).
    pub sent: u64,
    /// Republications of a step's message while waiting (lock-step).
    pub republished: u64,
    /// Estimate messages received that passed every check.
    pub received: u64,
    /// Received too late to be used (lock-step: a duplicate of a used step;
    /// real time: older than the latest already held). Also in `rejected.stale`.
    pub late: u64,
    pub rejected: RejectCounts,
    /// (Real time) neighbour-steps left out of the estimator's sums because
    /// the neighbour was silent longer than `network.silence_timeout`.
    pub silent: u64,
    /// Messages removed by the scenario's fault table at this receiver (SPEC §14).
    #[serde(default)]
    pub fault_lost: u64,
}

/// Control-loop timing of a real-time node (µs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LoopStats {
    /// |actual period − nominal period|: p50, p99, max.
    pub period_error_p50_us: f64,
    pub period_error_p99_us: f64,
    pub period_error_max_us: f64,
    /// Wake-up after the step's due time: p50, p99, max.
    pub lateness_p50_us: f64,
    pub lateness_p99_us: f64,
    pub lateness_max_us: f64,
    pub steps: u64,
}

impl LoopStats {
    /// From the wake-up times (s since the epoch) of consecutive steps.
    pub fn from_wakeups(wake_s: &[f64], period_s: f64) -> Self {
        let mut period_err: Vec<f64> = wake_s.windows(2).map(|w| ((w[1] - w[0]) - period_s).abs() * 1e6).collect();
        let mut late: Vec<f64> =
            wake_s.iter().enumerate().map(|(k, w)| (w - k as f64 * period_s).max(0.0) * 1e6).collect();
        let (p50, p99, max) = percentiles(&mut period_err);
        let (l50, l99, lmax) = percentiles(&mut late);
        Self {
            period_error_p50_us: p50,
            period_error_p99_us: p99,
            period_error_max_us: max,
            lateness_p50_us: l50,
            lateness_p99_us: l99,
            lateness_max_us: lmax,
            steps: wake_s.len() as u64,
        }
    }
}

/// Control-loop timing gathered step by step in bounded memory: every sample
/// while few, then an evenly thinned subset (for the percentiles; the
/// maxima and the step count stay exact), so a run of any length fits.
#[derive(Clone, Debug)]
pub struct LoopTimer {
    period_s: f64,
    prev: Option<f64>,
    n: u64,
    /// Every `stride`-th step is kept.
    stride: u64,
    period_err: Vec<f64>,
    late: Vec<f64>,
    max_err: f64,
    max_late: f64,
}

impl LoopTimer {
    /// Samples kept (per quantity) before thinning.
    pub const CAP: usize = 1 << 16;

    pub fn new(period_s: f64) -> Self {
        Self {
            period_s,
            prev: None,
            n: 0,
            stride: 1,
            period_err: Vec::new(),
            late: Vec::new(),
            max_err: 0.0,
            max_late: 0.0,
        }
    }

    /// The wake-up of step k (s since the epoch).
    pub fn push(&mut self, k: u64, wake_s: f64) {
        let late = (wake_s - k as f64 * self.period_s).max(0.0) * 1e6;
        let err = self.prev.map(|p| ((wake_s - p) - self.period_s).abs() * 1e6);
        self.max_late = self.max_late.max(late);
        if let Some(e) = err {
            self.max_err = self.max_err.max(e);
        }
        if self.n % self.stride == 0 {
            self.late.push(late);
            if let Some(e) = err {
                self.period_err.push(e);
            }
            if self.late.len() >= Self::CAP {
                for v in [&mut self.late, &mut self.period_err] {
                    let mut i = 0;
                    v.retain(|_| {
                        i += 1;
                        i % 2 == 1
                    });
                }
                self.stride *= 2;
            }
        }
        self.n += 1;
        self.prev = Some(wake_s);
    }

    pub fn stats(&self) -> LoopStats {
        let (p50, p99, _) = percentiles(&mut self.period_err.clone());
        let (l50, l99, _) = percentiles(&mut self.late.clone());
        LoopStats {
            period_error_p50_us: p50,
            period_error_p99_us: p99,
            period_error_max_us: self.max_err,
            lateness_p50_us: l50,
            lateness_p99_us: l99,
            lateness_max_us: self.max_late,
            steps: self.n,
        }
    }
}

/// (p50, p99, max) of a sample set (sorted in place); zeros if empty.
pub fn percentiles(v: &mut [f64]) -> (f64, f64, f64) {
    if v.is_empty() {
        return (0.0, 0.0, 0.0);
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    (at(0.5), at(0.99), v[v.len() - 1])
}

/// Telemetry for the monitor: every step of a node, in batches. Never feeds control.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Telemetry {
    Follower {
        id: u32,
        /// Step of `samples[0]`.
        first_k: u64,
        samples: Vec<FollowerSample>,
        counters: Counters,
        /// The node has sent its final step.
        done: bool,
        loop_stats: Option<LoopStats>,
    },
    Leader {
        first_k: u64,
        /// The true leader state at steps first_k, first_k + 1, …
        states: Vec<LeaderState>,
        counters: Counters,
        done: bool,
        loop_stats: Option<LoopStats>,
    },
}

/// Lock-step end of run: the followers among `ids` that have reported (on
/// their telemetry key) that they completed the final step. Nodes that feed
/// them keep republishing their last messages until then (bounded), so a
/// message lost near the end is recovered.
pub async fn watch_done(
    session: &zenoh::Session,
    keys: &Keys,
    ids: &[u32],
    steps: u64,
) -> Result<
    (Vec<zenoh::pubsub::Subscriber<()>>, std::sync::Arc<std::sync::Mutex<std::collections::BTreeSet<u32>>>),
    CliError,
> {
    let done = std::sync::Arc::new(std::sync::Mutex::new(std::collections::BTreeSet::new()));
    let mut subs = Vec::new();
    for &id in ids {
        let d = done.clone();
        let sub = session
            .declare_subscriber(keys.telemetry(id))
            .callback(move |s| {
                if let Some(Telemetry::Follower { id: sender, first_k, samples, done: true, .. }) =
                    decode::<Telemetry>(&s.payload().to_bytes())
                {
                    if sender == id && first_k.checked_add(samples.len() as u64) == Some(steps + 1) {
                        d.lock().unwrap_or_else(|p| p.into_inner()).insert(id);
                    }
                }
            })
            .await
            .map_err(|e| CliError::Run(format!("declaring a telemetry subscriber: {e}")))?;
        subs.push(sub);
    }
    Ok((subs, done))
}

/// Where an estimate message came from, as the receiver sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    Leader,
    /// Index of the neighbour in the receiver's neighbour list.
    Neighbour(usize),
}

/// The receiving side's checks (SPEC §13, issue 3): decodes, and checks that
/// the header's sender is the key's, and that the sender is one this node
/// listens to. Staleness is the caller's (it depends on the timing mode).
pub fn check(
    key_id: Option<u32>,
    bytes: &[u8],
    hears_leader: bool,
    neighbour_ids: &[u32],
) -> Result<(Source, EstimateMsg), Reject> {
    let msg = wire::decode(bytes)?;
    if key_id != Some(msg.header.sender) {
        return Err(Reject::WrongSender);
    }
    let sender = msg.header.sender;
    if sender == wire::LEADER_ID {
        return if hears_leader { Ok((Source::Leader, msg)) } else { Err(Reject::NotNeighbour) };
    }
    match neighbour_ids.iter().position(|&j| j == sender) {
        Some(n) => Ok((Source::Neighbour(n), msg)),
        None => Err(Reject::NotNeighbour),
    }
}

/// The estimate messages one node has received and not yet used, per source.
#[derive(Debug, Default)]
pub struct Inbox {
    /// Lock-step: every step received and not yet used, by step.
    pending: Vec<BTreeMap<u64, LeaderState>>,
    /// The last step used (lock-step) or held (real time), per source.
    newest: Vec<Option<u64>>,
    /// Real time: the recent messages per source, in step order.
    history: Vec<VecDeque<(u64, LeaderState)>>,
    pub counters: Counters,
    lockstep: bool,
    /// The receiver's current step (set by its control loop).
    current: u64,
    /// Per source: how many steps ahead of the receiver's a message may be.
    ahead: Vec<u64>,
    /// Real time: the shared clock (epoch, period), once the start is known.
    clock: Option<(std::time::Instant, Duration)>,
    /// Per source: the fault table's loss decisions for the link (SPEC §14).
    links: Vec<LinkLoss>,
}

/// Lock-step: how far ahead of the receiver's step a neighbour's message can
/// be (it needs the receiver's step-k message before it publishes k + 1).
pub const LOCKSTEP_AHEAD: u64 = 2;
/// Real time: the default slack (steps) beyond the shared clock's step.
pub const REALTIME_AHEAD: u64 = 10;

impl Inbox {
    /// `sources` = neighbours (+1 for the leader, at the last slot, if heard).
    /// Every source may be `ahead` steps ahead of the receiver (see [`Inbox::set_ahead`]).
    pub fn new(sources: usize, lockstep: bool) -> Self {
        Self {
            pending: vec![BTreeMap::new(); sources],
            newest: vec![None; sources],
            history: vec![VecDeque::new(); sources],
            counters: Counters::default(),
            lockstep,
            current: 0,
            ahead: vec![if lockstep { LOCKSTEP_AHEAD } else { REALTIME_AHEAD }; sources],
            clock: None,
            links: vec![LinkLoss::none(); sources],
        }
    }

    /// The fault table's loss decisions per source (SPEC §14): a message the
    /// table removes is dropped on arrival and counted (`fault_lost`), and
    /// lock-step does not wait for it.
    pub fn set_links(&mut self, links: Vec<LinkLoss>) {
        debug_assert_eq!(links.len(), self.links.len());
        if links.len() == self.links.len() {
            self.links = links;
        }
    }

    /// How many steps ahead of the receiver's step a message of `slot` may be
    /// (further ahead: rejected as [`Reject::Future`]).
    pub fn set_ahead(&mut self, slot: usize, steps: u64) {
        self.ahead[slot] = steps;
    }

    /// Real time: the shared schedule (step k due at `epoch` + k `period`),
    /// so that the receiver's step is at least the clock's.
    pub fn set_clock(&mut self, epoch: std::time::Instant, period: Duration) {
        if !period.is_zero() {
            self.clock = Some((epoch, period));
        }
    }

    /// The step the receiver is at (or waiting for).
    pub fn set_step(&mut self, k: u64) {
        self.current = self.current.max(k);
    }

    /// The furthest step of `slot` a genuine sender can have sent by now.
    fn limit(&self, slot: usize) -> u64 {
        let mut base = self.current;
        if let Some((epoch, period)) = self.clock {
            let since = std::time::Instant::now().saturating_duration_since(epoch);
            base = base.max((since.as_secs_f64() / period.as_secs_f64()) as u64);
        }
        base.saturating_add(self.ahead[slot])
    }

    /// Files a checked message, or counts it as stale or from the future.
    pub fn accept(&mut self, slot: usize, msg: &EstimateMsg) {
        let step = msg.header.step;
        if step > self.limit(slot) {
            self.counters.rejected.add(Reject::Future);
            return;
        }
        if self.links[slot].lost(step) {
            self.counters.fault_lost += 1;
            return;
        }
        if self.newest[slot].is_some_and(|n| step <= n) {
            self.counters.late += 1;
            self.counters.rejected.add(Reject::Stale);
            return;
        }
        self.counters.received += 1;
        if self.lockstep {
            // A republication of a pending step keeps the first copy.
            self.pending[slot].entry(step).or_insert(msg.state);
        } else {
            self.newest[slot] = Some(step);
            let h = &mut self.history[slot];
            h.push_back((step, msg.state));
            if h.len() > HISTORY {
                h.pop_front();
            }
        }
    }

    pub fn reject(&mut self, r: Reject) {
        self.counters.rejected.add(r);
    }

    /// Lock-step: whether every source's step-k message is here (or removed
    /// by the fault table, so not to be waited for).
    pub fn has_all(&mut self, k: u64) -> bool {
        (0..self.pending.len()).all(|s| self.pending[s].contains_key(&k) || self.links[s].lost(k))
    }

    /// Lock-step: the slots whose step-k message is missing (and not removed by the table).
    pub fn missing(&mut self, k: u64) -> Vec<usize> {
        (0..self.pending.len()).filter(|&s| !self.pending[s].contains_key(&k) && !self.links[s].lost(k)).collect()
    }

    /// Lock-step: takes each source's step-k message, `None` where the fault
    /// table removed it (call after `has_all`).
    pub fn take(&mut self, k: u64, out: &mut Vec<Option<LeaderState>>) {
        out.clear();
        for (slot, p) in self.pending.iter_mut().enumerate() {
            // Drop anything older (cannot happen with has_all, but keeps memory bounded).
            while let Some((&s, _)) = p.first_key_value() {
                if s >= k {
                    break;
                }
                p.pop_first();
            }
            out.push(p.remove(&k));
            self.newest[slot] = Some(k);
        }
    }

    /// Real time: the newest message of a source stamped at or before step
    /// k (a node running behind the shared schedule never uses values from
    /// its future), if it is at most `max_age_steps` older than k; else the
    /// source counts as silent.
    pub fn latest(&mut self, slot: usize, k: u64, max_age_steps: u64) -> Option<LeaderState> {
        let h = &mut self.history[slot];
        // Keep the newest entry ≤ k and everything after it.
        while h.len() > 1 && h[1].0 <= k {
            h.pop_front();
        }
        match h.front() {
            Some(&(s, state)) if s <= k && k - s <= max_age_steps => Some(state),
            _ => {
                self.counters.silent += 1;
                None
            }
        }
    }
}

/// Real time: messages kept per source (newer than the receiver's step).
const HISTORY: usize = 1024;

#[cfg(test)]
mod tests {
    use super::*;
    use formation_topology::wire::{Header, FORMAT_VERSION};

    fn msg(sender: u32, step: u64) -> EstimateMsg {
        EstimateMsg {
            header: Header { version: FORMAT_VERSION, sender, step, time_s: step as f64 * 1e-3 },
            state: LeaderState { v: step as f64, ..Default::default() },
        }
    }

    #[test]
    fn checks_name_the_reason() {
        let bytes = wire::encode(&msg(2, 5));
        assert_eq!(check(Some(2), &bytes, false, &[2, 3]).map(|r| r.0), Ok(Source::Neighbour(0)));
        assert_eq!(check(Some(3), &bytes, false, &[2, 3]).map(|r| r.0), Err(Reject::WrongSender));
        assert_eq!(check(Some(2), &bytes, false, &[3]).map(|r| r.0), Err(Reject::NotNeighbour));
        assert_eq!(check(Some(2), b"junk", false, &[2]).map(|r| r.0), Err(Reject::Malformed));
        let leader = wire::encode(&msg(0, 5));
        assert_eq!(check(Some(0), &leader, true, &[2]).map(|r| r.0), Ok(Source::Leader));
        assert_eq!(check(Some(0), &leader, false, &[2]).map(|r| r.0), Err(Reject::NotNeighbour));
    }

    #[test]
    fn lockstep_inbox_waits_for_every_source_and_counts_stale() {
        let mut inbox = Inbox::new(2, true);
        inbox.accept(0, &msg(1, 0));
        assert!(!inbox.has_all(0));
        inbox.accept(1, &msg(2, 0));
        inbox.accept(1, &msg(2, 1));
        assert!(inbox.has_all(0));
        let mut out = Vec::new();
        inbox.take(0, &mut out);
        assert_eq!(out.len(), 2);
        assert!(out.iter().all(Option::is_some));
        inbox.accept(0, &msg(1, 0));
        assert_eq!(inbox.counters.rejected.stale, 1);
        assert!(!inbox.has_all(1));
    }

    #[test]
    fn realtime_inbox_keeps_the_latest_and_leaves_out_the_silent() {
        let mut inbox = Inbox::new(1, false);
        assert_eq!(inbox.latest(0, 0, 10), None);
        inbox.accept(0, &msg(1, 3));
        inbox.accept(0, &msg(1, 2));
        assert_eq!(inbox.counters.late, 1);
        inbox.accept(0, &msg(1, 6));
        // At step 5 the message stamped 6 is in the future: use 3.
        assert_eq!(inbox.latest(0, 5, 10).map(|s| s.v), Some(3.0));
        assert_eq!(inbox.latest(0, 6, 10).map(|s| s.v), Some(6.0));
        assert_eq!(inbox.latest(0, 17, 10), None);
        assert_eq!(inbox.counters.silent, 2);
    }

    #[test]
    fn far_future_steps_are_rejected_and_do_not_silence_the_sender() {
        // Lock-step: neighbours at most 2 steps ahead, the leader (slot 1) 10.
        let mut inbox = Inbox::new(2, true);
        inbox.set_ahead(1, 10);
        inbox.accept(0, &msg(1, u64::MAX));
        for s in 3..1000 {
            inbox.accept(0, &msg(1, s));
        }
        inbox.accept(1, &msg(0, 11));
        assert_eq!(inbox.counters.rejected.future, 1 + 997 + 1);
        assert_eq!(inbox.counters.rejected.stale, 0);
        // Nothing pending from the flood; the genuine messages still get through.
        assert!(inbox.pending.iter().all(|p| p.is_empty()));
        for s in 0..=2 {
            inbox.accept(0, &msg(1, s));
        }
        inbox.accept(1, &msg(0, 0));
        inbox.accept(1, &msg(0, 10));
        assert!(inbox.has_all(0));
        let mut out = Vec::new();
        inbox.take(0, &mut out);
        inbox.set_step(1);
        inbox.accept(0, &msg(1, 3));
        assert_eq!(inbox.counters.rejected.future, 999);
        assert_eq!(inbox.pending[0].len(), 3);

        // Real time: a far-future message is not held, so later genuine ones are used.
        let mut inbox = Inbox::new(1, false);
        inbox.set_ahead(0, 5);
        inbox.accept(0, &msg(1, u64::MAX));
        inbox.accept(0, &msg(1, 6));
        inbox.accept(0, &msg(1, 1));
        assert_eq!(inbox.counters.rejected.future, 2);
        assert_eq!(inbox.latest(0, 1, 10).map(|s| s.v), Some(1.0));
        inbox.set_step(10);
        inbox.accept(0, &msg(1, 9));
        assert_eq!(inbox.latest(0, 10, 10).map(|s| s.v), Some(9.0));
    }

    #[test]
    fn realtime_never_uses_a_message_from_the_receivers_future() {
        let mut inbox = Inbox::new(1, false);
        inbox.set_ahead(0, 10);
        inbox.accept(0, &msg(1, 8));
        // Held message newer than k: not used (and not "0 steps old").
        assert_eq!(inbox.latest(0, 5, 10), None);
        assert_eq!(inbox.latest(0, 8, 10).map(|s| s.v), Some(8.0));
    }

    #[test]
    fn loop_timer_matches_the_exact_stats_and_stays_bounded() {
        let wake: Vec<f64> = (0..1000).map(|k| k as f64 * 1e-3 + if k % 10 == 0 { 2e-5 } else { 0.0 }).collect();
        let mut t = LoopTimer::new(1e-3);
        for (k, w) in wake.iter().enumerate() {
            t.push(k as u64, *w);
        }
        let (a, b) = (t.stats(), LoopStats::from_wakeups(&wake, 1e-3));
        assert_eq!(a.steps, b.steps);
        for (x, y) in [
            (a.period_error_p50_us, b.period_error_p50_us),
            (a.period_error_p99_us, b.period_error_p99_us),
            (a.period_error_max_us, b.period_error_max_us),
            (a.lateness_p99_us, b.lateness_p99_us),
            (a.lateness_max_us, b.lateness_max_us),
        ] {
            assert!((x - y).abs() < 1e-6, "{x} vs {y}");
        }
        let mut t = LoopTimer::new(1e-3);
        for k in 0..(LoopTimer::CAP as u64 * 5) {
            t.push(k, k as f64 * 1e-3);
        }
        assert!(t.late.len() < LoopTimer::CAP && t.period_err.len() < LoopTimer::CAP);
        assert_eq!(t.stats().steps, LoopTimer::CAP as u64 * 5);
    }

    #[test]
    fn loop_stats_of_a_perfect_loop_are_zero() {
        let wake: Vec<f64> = (0..100).map(|k| k as f64 * 1e-3).collect();
        let s = LoopStats::from_wakeups(&wake, 1e-3);
        assert!(s.period_error_max_us < 1e-6 && s.lateness_max_us < 1e-6);
    }
}
