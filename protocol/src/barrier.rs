//! The start barrier, and its messages `Ready` and `Start`.
//!
//! Zenoh peers connect asynchronously, and a message put before the other
//! side knows of a subscription is silently lost. So before anything steps:
//! every node declares its subscribers, then repeats `hello` every 50 ms
//! (every second once it has heard nothing new for 2 s; anything new wakes
//! it at once, see [`Hears::next_tick`]). A
//! node is *ready* once it has heard the `hello` of every node it receives
//! from (an agent: its neighbours and, if a_i0 = 1, the leader; the monitor:
//! everybody): the same transport that carried the hello carried the
//! subscriber declarations made before it. Ready nodes repeat `ready` (with
//! a fingerprint of their scenario) until the leader, having heard every
//! agent and the monitor ready with its own fingerprint, repeats `start`
//! (the run's epoch and time scale). Nobody stops saying `hello` before the
//! start, so nobody waits forever for a hello.
//!
//! This module holds the barrier's rules as two plain state machines, fed
//! what a node heard and the time, and asked every [`TICK`] what to do:
//! [`Join`] (an agent or the monitor) and [`Lead`] (the leader). They own
//! no socket and read no clock, so their tests run in virtual time;
//! [`crate::startup`] puts them on zenoh.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use crate::Now;

use formation_scenario::{Graph, Scenario};
use serde::{Deserialize, Serialize};

use formation_exit::Error;

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
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Start {
    pub fingerprint: u64,
    pub epoch_unix_ns: u64,
    pub time_scale: f64,
    /// The leader's timebase when this announcement left it (ns): a floor
    /// for every node's estimate of the leader's clock (`clockguard`).
    pub sent_ns: i64,
    /// The followers the run starts without (a quorum start, [`Quorum`]),
    /// by id, ascending: every node treats them as gone before step 0.
    pub absent: Vec<u32>,
}

impl Start {
    /// The time scale, 1 where the announced one is not positive.
    pub fn scale(&self) -> f64 {
        positive_scale(self.time_scale)
    }
}

/// A time scale as used: `scale` if positive, else 1.
pub fn positive_scale(scale: f64) -> f64 {
    if scale > 0.0 {
        scale
    } else {
        1.0
    }
}

/// A fingerprint of the scenario as loaded (file plus overrides), so that
/// nodes started with different scenarios refuse to run together.
pub fn fingerprint(s: &Scenario) -> u64 {
    let text = serde_json::to_string(&s.source).unwrap_or_default();
    // A recorded leader: the record itself, not only its path (two hosts
    // whose files differ run different formations).
    let recording = s
        .leader_recording
        .iter()
        .flat_map(|l| [l.pose.x, l.pose.y, l.pose.theta, l.v, l.w].into_iter().flat_map(f64::to_le_bytes));
    // FNV-1a, 64 bit.
    text.bytes()
        .chain(recording)
        .fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3))
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

/// After this long at the barrier a node says, once, whom it still waits
/// for (it waited silently until [`START_TIMEOUT`]).
pub const SAY_WAITING_AFTER: Duration = Duration::from_secs(10);
/// How often a waiting node says hello (and ready) and asks its machine
/// what to do.
pub const TICK: Duration = Duration::from_millis(50);
/// How often a waiting node that has heard nothing new for [`QUIET_AFTER`]
/// says hello: a node started long before the others costs next to nothing
/// while it waits (20 wake-ups a second were a third of an idle agent's CPU).
/// What is new (a hello, a ready, the start) wakes it at once.
pub const IDLE_TICK: Duration = Duration::from_secs(1);
/// Nothing new heard for this long: tick every [`IDLE_TICK`].
pub const QUIET_AFTER: Duration = Duration::from_secs(2);
/// A ready carries the scenario's key digests once in this many.
const DIGESTS_EVERY: u64 = 20;

/// What a node heard at the barrier, filed by [`Join`] and [`Lead`].
#[derive(Default)]
struct Heard {
    /// This node's scenario fingerprint: Start and Ready with another are ignored.
    fingerprint: u64,
    /// The nodes whose Ready counts (any other name is ignored).
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
    differ: BTreeMap<String, (Vec<String>, Now)>,
    /// When a start with another fingerprint was first heard.
    foreign_start: Option<Now>,
    /// The leader's reason for refusing the run, if it did.
    abort: Option<String>,
    /// Counts what was heard for the first time (a node's hello or ready,
    /// the start, a refusal): a waiting node is woken when it changes.
    news: u64,
}

impl Heard {
    fn new(scenario: &Scenario, expected: &[String]) -> Self {
        Self {
            fingerprint: fingerprint(scenario),
            expected: expected.iter().cloned().collect(),
            mine: key_digests(scenario),
            ..Self::default()
        }
    }

    fn on_hello(&mut self, name: &str) {
        if !self.hello.contains(name) {
            self.hello.insert(name.to_string());
            self.news += 1;
        }
    }

    fn on_start(&mut self, start: Start, now: Now) {
        if start.fingerprint == self.fingerprint {
            self.news += u64::from(self.start.is_none());
            self.start.get_or_insert(start);
        } else {
            self.ignored += 1;
            self.news += u64::from(self.foreign_start.is_none());
            self.foreign_start.get_or_insert(now);
        }
    }

    fn on_ready(&mut self, name: &str, r: Ready, now: Now) {
        if !self.expected.contains(name) {
            self.ignored += 1;
        } else if r.fingerprint == self.fingerprint {
            self.news += u64::from(self.ready.insert(name.to_string()));
        } else {
            self.ignored += 1;
            self.news += u64::from(self.ready_foreign.insert(name.to_string()));
            // Most readies carry no digests: the keys that differ are known
            // from the first that does.
            let e = self.differ.entry(name.to_string()).or_insert_with(|| (Vec::new(), now));
            if e.0.is_empty() && !r.keys.is_empty() {
                e.0 = differing_keys(&self.mine, &r.keys);
            }
        }
    }

    fn on_abort(&mut self, reason: &str) {
        let reason: String = reason.chars().take(500).collect();
        if !reason.is_empty() {
            self.news += u64::from(self.abort.is_none());
            self.abort.get_or_insert(reason);
        }
    }

    fn missing(&self, of: &BTreeSet<String>, needs: &[String]) -> Vec<String> {
        needs.iter().filter(|n| !of.contains(*n)).cloned().collect()
    }
}

/// Most bytes of the leader's refusal of a run (`control/abort`).
pub const MAX_ABORT_BYTES: usize = 4096;

/// The leader's refusal of a run as it is put on `control/abort`: a line of
/// text. Anything else (empty, not UTF-8, control characters, too long) is
/// not one, and a node counts it and waits on (random bytes taken as a
/// refusal stopped every node, with the bytes as its cause).
pub fn abort_reason(bytes: &[u8]) -> Option<&str> {
    if bytes.is_empty() || bytes.len() > MAX_ABORT_BYTES {
        return None;
    }
    let text = std::str::from_utf8(bytes).ok()?;
    (!text.chars().any(char::is_control)).then_some(text)
}

/// `reason` as [`abort_reason`] takes it: control characters left out, cut
/// (at a character) to [`MAX_ABORT_BYTES`].
pub fn as_abort_reason(reason: &str) -> String {
    let mut out = String::new();
    for c in reason.chars().filter(|c| !c.is_control()) {
        if out.len() + c.len_utf8() > MAX_ABORT_BYTES {
            break;
        }
        out.push(c);
    }
    out
}

/// When a waiting node last heard something new, for its tick.
#[derive(Default)]
struct Quiet {
    news: u64,
    since: Option<Now>,
}

impl Quiet {
    /// [`TICK`] while something new was heard within [`QUIET_AFTER`] (or
    /// the node just began), else [`IDLE_TICK`].
    fn next_tick(&mut self, news: u64, now: Now) -> Duration {
        if self.since.is_none() || news != self.news {
            (self.news, self.since) = (news, Some(now));
        }
        let quiet_for = self.since.map_or(Duration::ZERO, |t| now.saturating_sub(t));
        if quiet_for < QUIET_AFTER {
            TICK
        } else {
            IDLE_TICK
        }
    }
}

/// "node 3" or "the leader", for a node name in control keys.
fn node_phrase(n: &str) -> String {
    if n == crate::names::LEADER_NODE {
        "the leader".to_string()
    } else {
        format!("node {n}")
    }
}

/// What a node hears at the barrier, fed to its machine ([`Join`] or
/// [`Lead`]) as it arrives, with the time.
pub trait Hears {
    fn on_hello(&mut self, from: &str);
    fn on_ready(&mut self, from: &str, ready: Ready, now: Now);
    /// The leader's start (the leader itself ignores starts).
    fn on_start(&mut self, start: Start, now: Now);
    /// The leader's refusal of the run (the leader itself ignores it).
    fn on_abort(&mut self, reason: &str);
    /// Counts what was heard for the first time (a node's hello or ready,
    /// the start, a refusal): the caller wakes the node (polls at once) when
    /// it changes.
    fn news(&self) -> u64;
    /// How long to wait after the tick at `now` before the next one (unless
    /// [`Hears::news`] changes first): [`TICK`], or [`IDLE_TICK`] once
    /// nothing new was heard for [`QUIET_AFTER`].
    fn next_tick(&mut self, now: Now) -> Duration;
}

impl Hears for Join {
    fn on_hello(&mut self, from: &str) {
        self.heard.on_hello(from);
    }
    fn on_ready(&mut self, from: &str, ready: Ready, now: Now) {
        self.heard.on_ready(from, ready, now);
    }
    fn on_start(&mut self, start: Start, now: Now) {
        self.heard.on_start(start, now);
    }
    fn on_abort(&mut self, reason: &str) {
        self.heard.on_abort(reason);
    }
    fn news(&self) -> u64 {
        self.heard.news
    }
    fn next_tick(&mut self, now: Now) -> Duration {
        self.quiet.next_tick(self.heard.news, now)
    }
}

impl Hears for Lead {
    fn on_hello(&mut self, from: &str) {
        self.heard.on_hello(from);
    }
    fn on_ready(&mut self, from: &str, ready: Ready, now: Now) {
        self.heard.on_ready(from, ready, now);
    }
    fn on_start(&mut self, _: Start, _: Now) {}
    fn on_abort(&mut self, _: &str) {}
    fn news(&self) -> u64 {
        self.heard.news
    }
    fn next_tick(&mut self, now: Now) -> Duration {
        self.quiet.next_tick(self.heard.news, now)
    }
}

/// What a node waiting for the start does at a tick.
#[derive(Debug, PartialEq)]
pub enum JoinStep {
    /// Say hello; say ready too (with the key digests, or without) once
    /// every needed node is heard; print `warning` if there is one.
    Wait { ready: Option<ReadyForm>, warning: Option<String> },
    /// The leader's start with this node's scenario: run.
    Started(Start),
    /// Give up, with the line to end on.
    Failed(Error),
}

/// Which of the two encodings of this node's [`Ready`] to send.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReadyForm {
    /// With every key's digest, so that a mismatch can name the keys.
    Full,
    /// The fingerprint alone.
    Short,
}

/// The barrier of an agent or the monitor (`me`): hello until it has heard
/// every node it needs, then ready, until the leader's start.
pub struct Join {
    me: String,
    run: String,
    needs: Vec<String>,
    heard: Heard,
    began: Now,
    /// The time waited that counts against [`START_TIMEOUT`]: only what
    /// this node was awake to watch (a node not run for seconds has not
    /// waited seconds for the others, [`crate::patience`]).
    patience: crate::patience::Patience,
    readies: u64,
    warned: bool,
    /// Whom it waits for is said (or, under a launch, left to the leader's
    /// one line: hundreds of agents would each say it).
    said_waiting: bool,
    quiet: Quiet,
    /// A start with those present ([`Quorum`]): from this long after it
    /// began, it says ready without the needed nodes it has not heard
    /// (they may be absent from the run).
    quorum_wait: Option<Duration>,
}

impl Join {
    /// Says ready from `wait` on even without every needed node heard: the
    /// leader may start with those present ([`Quorum`]).
    pub fn with_quorum_wait(mut self, wait: Duration) -> Self {
        self.quorum_wait = Some(wait);
        self
    }

    /// Leaves the "still waiting" line to the leader (a launch's nodes).
    pub fn without_waiting_line(mut self) -> Self {
        self.said_waiting = true;
        self
    }

    /// `needs`: the nodes `me` receives from (they count when they say
    /// ready with another scenario); `now`: when it began waiting.
    pub fn new(me: &str, run: &str, needs: &[String], scenario: &Scenario, now: Now) -> Self {
        Self {
            me: me.to_string(),
            run: run.to_string(),
            needs: needs.to_vec(),
            heard: Heard::new(scenario, needs),
            began: now,
            patience: crate::patience::Patience::new(now, IDLE_TICK),
            readies: 0,
            warned: false,
            said_waiting: false,
            quiet: Quiet { news: 0, since: Some(now) },
            quorum_wait: None,
        }
    }

    /// Start and Ready messages ignored (another scenario, or an unexpected sender).
    pub fn ignored(&self) -> u64 {
        self.heard.ignored
    }

    /// What to do at `now` (called every tick, [`Hears::next_tick`]).
    pub fn poll(&mut self, now: Now) -> JoinStep {
        let (me, run, h) = (&self.me, &self.run, &self.heard);
        if let Some(start) = &h.start {
            return JoinStep::Started(start.clone());
        }
        if let Some(reason) = &h.abort {
            return JoinStep::Failed(Error::Input(format!("node {me}: the leader refused run {run}: {reason}")));
        }
        let mismatched = h
            .differ
            .iter()
            .find(|(n, (_, since))| !h.ready.contains(*n) && now.saturating_sub(*since) >= MISMATCH_GRACE);
        if let Some((n, (differ, _))) = mismatched {
            return JoinStep::Failed(Error::Input(format!(
                "node {me}: {} of run {run} runs another scenario, {} (another file or --set values)",
                node_phrase(n),
                if differ.is_empty() {
                    "with other keys".to_string()
                } else {
                    format!("differing in {}", key_list(differ))
                }
            )));
        }
        let foreign_for = h.foreign_start.map(|t| now.saturating_sub(t));
        if foreign_for.is_some_and(|d| d >= MISMATCH_GRACE * 2) {
            // Heard for 10 s: the leader of this run has another scenario.
            return JoinStep::Failed(Error::Input(format!(
                "node {me}: the leader of run {run} has another scenario (another file or --set values; the \
                 leader's own message names the keys that differ); no start for this one in {} s",
                (MISMATCH_GRACE * 2).as_secs()
            )));
        }
        let waiting = h.missing(&h.hello, &self.needs);
        if self.patience.look(now) > START_TIMEOUT {
            if waiting.is_empty() && foreign_for.is_some() {
                return JoinStep::Failed(Error::Input(format!(
                    "node {me}: no start for this scenario within {} s; ignored {} start announcements of run \
                     {run} with another scenario fingerprint (a leader with another scenario or --set values?)",
                    START_TIMEOUT.as_secs(),
                    h.ignored
                )));
            }
            let what = if waiting.is_empty() {
                "the leader's start".to_string()
            } else {
                format!("nodes {}", waiting.join(", "))
            };
            return JoinStep::Failed(Error::Run(format!(
                "node {me}: no word from {what} within {} s (run {run})",
                START_TIMEOUT.as_secs()
            )));
        }
        // Said at once, not only at the time limit; not fatal, since a
        // forged announcement must not stop a genuine run.
        let warning = (foreign_for.is_some() && !self.warned).then(|| {
            format!(
                "node {me}: the leader of run {run} announces another scenario (another file or --set values?); \
                 waiting up to {} s for a start with this one",
                (MISMATCH_GRACE * 2).as_secs()
            )
        });
        self.warned |= warning.is_some();
        // Whom it still waits for, once, after a while (a node not started, or
        // one that cannot reach this one), rather than silence until it gives up.
        let warning = match warning {
            None if !self.said_waiting
                && foreign_for.is_none()
                && now.saturating_sub(self.began) >= SAY_WAITING_AFTER =>
            {
                self.said_waiting = true;
                let what = if waiting.is_empty() {
                    "the leader's start".to_string()
                } else {
                    format!("{} {}", if waiting.len() == 1 { "node" } else { "nodes" }, waiting.join(", "))
                };
                Some(format!(
                    "node {}: still waiting for {what} after {} s (run {}; is it started, and can it reach this \
                     node?); giving up at {} s",
                    self.me,
                    SAY_WAITING_AFTER.as_secs(),
                    self.run,
                    START_TIMEOUT.as_secs()
                ))
            }
            w => w,
        };
        // The key digests (a few KB for a large scenario) go with every
        // DIGESTS_EVERY-th ready only; the fingerprint with every one.
        let quorum_over = self.quorum_wait.is_some_and(|w| now.saturating_sub(self.began) >= w);
        let ready = (waiting.is_empty() || quorum_over).then(|| {
            let form = if self.readies % DIGESTS_EVERY == 0 { ReadyForm::Full } else { ReadyForm::Short };
            self.readies += 1;
            form
        });
        JoinStep::Wait { ready, warning }
    }
}

/// What the leader does at a tick of the barrier.
#[derive(Debug, PartialEq)]
pub enum LeadStep {
    /// Say hello; print each warning.
    Wait { warnings: Vec<String> },
    /// Every node is heard and ready with this scenario: announce the start.
    Go,
    /// A node runs another scenario: tell every waiting node `reason`
    /// (the abort key), then end with `error`.
    Refuse { reason: String, error: Error },
    /// Give up, with the line to end on.
    Failed(Error),
}

/// The leader's barrier: hello until it has heard the hellos it needs and
/// every expected node ready with its scenario.
pub struct Lead {
    run: String,
    needs_hello: Vec<String>,
    expect_ready: Vec<String>,
    heard: Heard,
    began: Now,
    /// The time waited that counts against [`START_TIMEOUT`]: only what
    /// this node was awake to watch (a node not run for seconds has not
    /// waited seconds for the others, [`crate::patience`]).
    patience: crate::patience::Patience,
    warned: BTreeSet<String>,
    said_waiting: bool,
    quiet: Quiet,
    /// A start with those present, and the graph its Lemma-1 check reads.
    quorum: Option<(Quorum, Graph)>,
    /// The followers the start goes without (set when it goes).
    absent: Vec<u32>,
}

/// How long after its quorum wait the leader decides who is absent: the
/// followers' own waits (the same `--quorum-wait`) end about when the
/// leader's does, and a follower that waited for an absent neighbour says
/// ready only then.
pub const QUORUM_GRACE: Duration = Duration::from_secs(1);

/// A start with those present (docs/model.md §14): from `wait` (and
/// [`QUORUM_GRACE`]) after the leader began waiting, it starts as soon as at least `followers`
/// followers are ready (and every other node it expects, the monitor);
/// the followers not ready then are absent from the run. Before `wait`
/// only a complete formation starts.
#[derive(Clone, Debug, PartialEq)]
pub struct Quorum {
    pub followers: usize,
    pub wait: Duration,
    /// Start even if, without the absent, a present follower no longer
    /// reaches the leader (Lemma 1); else the leader refuses, naming them.
    pub even_if_cut_off: bool,
}

/// `--quorum-wait SECONDS` checked: more than 0, and short enough that the
/// leader's decision ([`QUORUM_GRACE`] later) comes before the start's
/// time limit ([`START_TIMEOUT`]). One line if not.
pub fn quorum_wait(seconds: f64) -> Result<Duration, String> {
    let most = (START_TIMEOUT - QUORUM_GRACE).as_secs_f64();
    if seconds > 0.0 && seconds < most {
        Ok(Duration::from_secs_f64(seconds))
    } else {
        Err(format!(
            "--quorum-wait {seconds}: give 0 < seconds < {most} (the start's time limit, {} s, less the leader's \
             {} s to decide)",
            START_TIMEOUT.as_secs(),
            QUORUM_GRACE.as_secs()
        ))
    }
}

impl Quorum {
    /// The quorum checked against a formation of `n` followers: one line
    /// if it cannot be met or means nothing.
    pub fn check(&self, n: usize) -> Result<(), String> {
        if self.followers < 1 || self.followers > n {
            return Err(format!(
                "--quorum {}: a quorum is 1 to {n} followers (this formation has {n})",
                self.followers
            ));
        }
        quorum_wait(self.wait.as_secs_f64())?;
        Ok(())
    }
}

impl Lead {
    pub fn new(run: &str, needs_hello: &[String], expect_ready: &[String], scenario: &Scenario, now: Now) -> Self {
        Self {
            run: run.to_string(),
            needs_hello: needs_hello.to_vec(),
            expect_ready: expect_ready.to_vec(),
            heard: Heard::new(scenario, expect_ready),
            began: now,
            patience: crate::patience::Patience::new(now, IDLE_TICK),
            warned: BTreeSet::new(),
            said_waiting: false,
            quiet: Quiet { news: 0, since: Some(now) },
            quorum: None,
            absent: Vec::new(),
        }
    }

    /// Starts with those present ([`Quorum`]) on `graph`, the scenario's.
    pub fn with_quorum(mut self, quorum: Quorum, graph: Graph) -> Self {
        self.quorum = Some((quorum, graph));
        self
    }

    /// The followers the start went without (empty until it goes, and for
    /// a complete formation).
    pub fn absent(&self) -> &[u32] {
        &self.absent
    }

    /// Start and Ready messages ignored (another scenario, or an unexpected sender).
    pub fn ignored(&self) -> u64 {
        self.heard.ignored
    }

    /// With a [`Quorum`] whose wait is over: go without the followers
    /// missing if enough are ready and nothing else is missing; refuse if
    /// the graph without them breaks Lemma 1 (unless told to go on).
    fn quorum_step(&mut self, missing: &BTreeSet<String>, now: Now) -> Option<LeadStep> {
        let (q, graph) = self.quorum.as_ref()?;
        if now.saturating_sub(self.began) < q.wait + QUORUM_GRACE {
            return None;
        }
        let absent: Vec<u32> = graph.ids().iter().copied().filter(|id| missing.contains(&id.to_string())).collect();
        let others_missing = missing.iter().any(|n| n.parse::<u32>().map_or(true, |id| !graph.ids().contains(&id)));
        if others_missing || graph.len() - absent.len() < q.followers {
            return None;
        }
        if let Some(cut) = graph.cut_off_without(&absent).filter(|_| !q.even_if_cut_off) {
            let reason = format!("{cut}: not started (--even-if-cut-off starts anyway)");
            let error = Error::Input(format!("leader: {reason} (run {})", self.run));
            return Some(LeadStep::Refuse { reason, error });
        }
        self.absent = absent;
        Some(LeadStep::Go)
    }

    /// What to do at `now` (called every tick, [`Hears::next_tick`]).
    pub fn poll(&mut self, now: Now) -> LeadStep {
        let h = &self.heard;
        let hello_missing = h.missing(&h.hello, &self.needs_hello);
        let ready_missing = h.missing(&h.ready, &self.expect_ready);
        if hello_missing.is_empty() && ready_missing.is_empty() {
            return LeadStep::Go;
        }
        let missing: BTreeSet<String> = hello_missing.iter().chain(&ready_missing).cloned().collect();
        if let Some(step) = self.quorum_step(&missing, now) {
            return step;
        }
        let (run, h) = (&self.run, &self.heard);
        let differs = |keys: &[String]| {
            if keys.is_empty() {
                "(the keys that differ are not known: an older build?)".to_string()
            } else {
                format!("differing in {}", key_list(keys))
            }
        };
        let mut warnings = Vec::new();
        // Nodes heard only with another fingerprint (possibly forged): still missing.
        for n in h.ready_foreign.iter().filter(|n| !h.ready.contains(*n)) {
            let (keys, since) = h.differ.get(n).cloned().unwrap_or((Vec::new(), now));
            if now.saturating_sub(since) >= MISMATCH_GRACE {
                let reason = format!("node {n} runs another scenario, {}", differs(&keys));
                let error = Error::Input(format!("leader: {reason} in run {run} (another file or --set values)"));
                return LeadStep::Refuse { reason, error };
            }
            if self.warned.insert(n.clone()) {
                warnings.push(format!(
                    "leader: node {n} of run {run} is ready with another scenario, {}; waiting up to {} s for it to \
                     run this one",
                    differs(&keys),
                    MISMATCH_GRACE.as_secs()
                ));
            }
        }
        let waiting: BTreeSet<String> = hello_missing.into_iter().chain(ready_missing).collect();
        let waiting = waiting.into_iter().collect::<Vec<_>>().join(", ");
        if self.patience.look(now) > START_TIMEOUT {
            return LeadStep::Failed(Error::Run(format!(
                "leader: nodes {waiting} of run {run} not ready within {} s",
                START_TIMEOUT.as_secs()
            )));
        }
        if !self.said_waiting && now.saturating_sub(self.began) >= SAY_WAITING_AFTER {
            self.said_waiting = true;
            warnings.push(format!(
                "leader: still waiting for nodes {waiting} after {} s (run {run}; are they started, and can they \
                 reach this node?); giving up at {} s",
                SAY_WAITING_AFTER.as_secs(),
                START_TIMEOUT.as_secs()
            ));
        }
        LeadStep::Wait { warnings }
    }

    /// The start to announce, `lead` after `now_unix_ns` (the wall clock
    /// when the machine said [`LeadStep::Go`]).
    pub fn start(&self, now_unix_ns: u64, lead: Duration, time_scale: f64) -> Start {
        Start {
            fingerprint: self.heard.fingerprint,
            epoch_unix_ns: now_unix_ns + lead.as_nanos() as u64,
            time_scale,
            sent_ns: now_unix_ns as i64,
            absent: self.absent.clone(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A refusal is a line of text; random bytes on `control/abort` (which
    /// stopped every node, with the bytes as the cause) are not one.
    #[test]
    fn only_a_line_of_text_is_a_refusal() {
        let line = "node 1 runs another scenario, differing in dt";
        assert_eq!(abort_reason(line.as_bytes()), Some(line));
        assert_eq!(abort_reason("é — ü".as_bytes()), Some("é — ü"));
        for (bytes, why) in [
            (&b""[..], "empty"),
            (&b"I%Se\x00J\xff(\x8f0E"[..], "not UTF-8, a NUL"),
            (&b"two\nlines"[..], "a newline"),
            (&b"\x1b[2Jclear"[..], "an escape"),
            (&[b'a'; MAX_ABORT_BYTES + 1][..], "too long"),
        ] {
            assert_eq!(abort_reason(bytes), None, "{why}: {bytes:?}");
        }
        // The leader's own refusal always reads as one, whatever key names it quotes.
        for text in ["keys a\nb and \u{1b}[2J", &"é".repeat(MAX_ABORT_BYTES)] {
            let r = as_abort_reason(text);
            assert_eq!(abort_reason(r.as_bytes()), Some(r.as_str()), "{text:?}");
        }
    }

    fn paper(sets: &[&str]) -> Scenario {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        Scenario::load(&path, &sets.iter().map(|s| s.to_string()).collect::<Vec<_>>()).expect("scenario")
    }

    fn names(n: &[&str]) -> Vec<String> {
        n.iter().map(|s| s.to_string()).collect()
    }

    fn ready(s: &Scenario) -> Ready {
        Ready { fingerprint: fingerprint(s), keys: key_digests(s) }
    }

    fn start(s: &Scenario) -> Start {
        Start { fingerprint: fingerprint(s), epoch_unix_ns: 1, time_scale: 1.0, sent_ns: 0, absent: Vec::new() }
    }

    /// Polls every tick from `from` to `to` (virtual time), returning every step.
    fn ticks<S>(poll: &mut impl FnMut(Now) -> S, t0: Now, from: Duration, to: Duration) -> Vec<S> {
        let mut out = Vec::new();
        let mut t = from;
        while t <= to {
            out.push(poll(t0 + t));
            t += TICK;
        }
        out
    }

    /// A node waiting long for others ticks once a second, not twenty
    /// times; whatever it hears for the first time wakes it (its `news`
    /// changes) and puts it back on the fast tick; repeats are no news.
    #[test]
    fn a_quiet_wait_ticks_slowly_and_news_brings_the_fast_tick_back() {
        let s = paper(&[]);
        let t0 = Now::from_secs(100);
        let mut j = Join::new("1", "r", &names(&["2", "leader"]), &s, t0);
        assert_eq!(j.next_tick(t0), TICK, "a node that just began");
        assert_eq!(j.next_tick(t0 + QUIET_AFTER - TICK), TICK);
        assert_eq!(j.next_tick(t0 + QUIET_AFTER), IDLE_TICK, "nothing heard for {QUIET_AFTER:?}");
        let before = j.news();
        j.on_hello("2");
        assert_eq!(j.news(), before + 1, "a first hello is news");
        j.on_hello("2");
        assert_eq!(j.news(), before + 1, "a repeated hello is not");
        let t = t0 + Duration::from_secs(30);
        assert_eq!(j.next_tick(t), TICK, "news puts the fast tick back");
        assert_eq!(j.next_tick(t + QUIET_AFTER), IDLE_TICK);
        j.on_start(start(&s), t + QUIET_AFTER);
        assert_eq!(j.news(), before + 2, "the start is news");
        j.on_start(start(&s), t + QUIET_AFTER);
        assert_eq!(j.news(), before + 2);

        let mut l = Lead::new("r", &names(&["1"]), &names(&["1"]), &s, t0);
        assert_eq!(l.next_tick(t0 + QUIET_AFTER), IDLE_TICK);
        l.on_ready("1", ready(&s), t0 + QUIET_AFTER);
        l.on_ready("1", ready(&s), t0 + QUIET_AFTER);
        assert_eq!(l.news(), 1, "one node's first ready, once");
        assert_eq!(l.next_tick(t0 + QUIET_AFTER), TICK);
    }

    #[test]
    fn foreign_start_and_ready_are_ignored_and_counted() {
        let t = Now::ZERO;
        let s = paper(&[]);
        let other = paper(&["dt=0.002"]);
        let mut h = Heard::new(&s, &names(&["1", "monitor"]));
        // A foreign start first is not kept; the genuine one after it is.
        h.on_start(start(&other), t);
        assert_eq!(h.start, None);
        h.on_start(start(&s), t);
        h.on_start(start(&paper(&["dt=0.005"])), t);
        assert_eq!(h.start.as_ref().map(|x| x.fingerprint), Some(fingerprint(&s)));
        // Ready from names outside the expected set, or with another fingerprint, does not count.
        h.on_ready("rogue", ready(&other), t);
        h.on_ready("rogue", ready(&s), t);
        h.on_ready("1", ready(&other), t);
        assert!(h.ready.is_empty());
        assert_eq!(h.ready_foreign.iter().collect::<Vec<_>>(), ["1"]);
        h.on_ready("1", ready(&s), t);
        h.on_ready("monitor", ready(&s), t);
        assert_eq!(h.ready.len(), 2);
        assert_eq!(h.ignored, 5);
    }

    #[test]
    fn a_mismatch_names_the_keys_that_differ() {
        let a = paper(&[]);
        let b = paper(&["robot.mass=12", "dt=0.002"]);
        let (da, db) = (key_digests(&a), key_digests(&b));
        assert!(da.len() > 20, "{} keys", da.len());
        assert_eq!(differing_keys(&da, &da), Vec::<String>::new());
        assert_eq!(differing_keys(&da, &db), ["dt", "robot.mass"]);
        let mut h = Heard::new(&a, &names(&["3"]));
        h.on_ready("3", ready(&b), Now::ZERO);
        assert_eq!(h.differ["3"].0, ["dt", "robot.mass"]);
    }

    #[test]
    fn an_agent_says_hello_then_ready_until_the_start() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let mut j = Join::new("2", "r", &names(&["1", "3", "0"]), &s, t0);
        assert_eq!(j.poll(t0), JoinStep::Wait { ready: None, warning: None }, "hello only, nobody heard");
        j.on_hello("1");
        j.on_hello("0");
        j.on_hello("7"); // not needed: changes nothing
        assert_eq!(j.poll(t0 + TICK), JoinStep::Wait { ready: None, warning: None }, "node 3 not heard yet");
        j.on_hello("3");
        // Ready, with the key digests once in DIGESTS_EVERY.
        let forms: Vec<_> = ticks(&mut |t| j.poll(t), t0, TICK * 2, TICK * 42)
            .into_iter()
            .map(|x| match x {
                JoinStep::Wait { ready: Some(f), warning: None } => f,
                other => panic!("{other:?}"),
            })
            .collect();
        assert_eq!(forms.len(), 41);
        let full: Vec<usize> =
            forms.iter().enumerate().filter(|(_, f)| **f == ReadyForm::Full).map(|(i, _)| i).collect();
        assert_eq!(full, [0, 20, 40]);
        j.on_start(start(&s), t0 + TICK * 43);
        assert_eq!(j.poll(t0 + TICK * 43), JoinStep::Started(start(&s)));
    }

    #[test]
    fn an_agent_gives_up_after_the_timeout_naming_who_it_never_heard() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let mut j = Join::new("2", "r", &names(&["1", "3", "0"]), &s, t0);
        j.on_hello("1");
        // Looking every second, as an idle waiting node does.
        for i in 1..START_TIMEOUT.as_secs() {
            assert!(matches!(j.poll(t0 + Duration::from_secs(i)), JoinStep::Wait { .. }), "{i} s");
        }
        assert!(matches!(j.poll(t0 + START_TIMEOUT), JoinStep::Wait { .. }), "not before the timeout");
        match j.poll(t0 + START_TIMEOUT + TICK) {
            JoinStep::Failed(Error::Run(m)) => {
                assert_eq!(m, "node 2: no word from nodes 3, 0 within 120 s (run r)")
            }
            other => panic!("{other:?}"),
        }
        // Every node heard, but no start: the leader's start is what is missing.
        let mut j = Join::new("monitor", "r", &names(&["0"]), &s, t0);
        j.on_hello("0");
        for i in 1..=START_TIMEOUT.as_secs() {
            j.poll(t0 + Duration::from_secs(i));
        }
        match j.poll(t0 + START_TIMEOUT + TICK) {
            JoinStep::Failed(Error::Run(m)) => assert!(m.contains("no word from the leader's start"), "{m}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_foreign_start_warns_once_and_ends_the_wait_after_ten_seconds() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let other = paper(&["robot.mass=12"]);
        let mut j = Join::new("4", "r", &names(&["0"]), &s, t0);
        j.on_hello("0");
        j.on_start(start(&other), t0 + Duration::from_secs(1));
        let steps = ticks(&mut |t| j.poll(t), t0, Duration::from_secs(1), Duration::from_secs(11) - TICK);
        let warnings: Vec<_> = steps.iter().filter(|x| matches!(x, JoinStep::Wait { warning: Some(_), .. })).collect();
        assert_eq!(warnings.len(), 1, "warned once, at once: {:?}", &steps[..2]);
        assert!(matches!(steps[0], JoinStep::Wait { warning: Some(_), .. }));
        assert!(steps.iter().all(|x| matches!(x, JoinStep::Wait { .. })), "still waiting before 10 s");
        match j.poll(t0 + Duration::from_secs(11)) {
            JoinStep::Failed(Error::Input(m)) => assert!(m.contains("the leader of run r has another scenario"), "{m}"),
            other => panic!("{other:?}"),
        }
        // A genuine start within the 10 s wins over the forged one.
        let mut j = Join::new("4", "r", &names(&["0"]), &s, t0);
        j.on_start(start(&other), t0);
        j.on_start(start(&s), t0 + Duration::from_secs(9));
        assert_eq!(j.poll(t0 + Duration::from_secs(12)), JoinStep::Started(start(&s)));
        assert_eq!(j.ignored(), 1);
    }

    #[test]
    fn a_neighbour_with_another_scenario_ends_the_wait_naming_the_keys() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let other = paper(&["robot.mass=12"]);
        let mut j = Join::new("1", "r", &names(&["2", "0"]), &s, t0);
        j.on_ready("2", ready(&other), t0);
        assert!(matches!(j.poll(t0 + MISMATCH_GRACE - TICK), JoinStep::Wait { .. }));
        match j.poll(t0 + MISMATCH_GRACE) {
            JoinStep::Failed(Error::Input(m)) => {
                assert_eq!(m, "node 1: node 2 of run r runs another scenario, differing in robot.mass (another file or --set values)")
            }
            other => panic!("{other:?}"),
        }
        // One that comes round to this scenario in time is no mismatch.
        let mut j = Join::new("1", "r", &names(&["2", "0"]), &s, t0);
        j.on_ready("2", ready(&other), t0);
        j.on_ready("2", ready(&s), t0 + TICK);
        assert!(matches!(j.poll(t0 + MISMATCH_GRACE * 2), JoinStep::Wait { .. }));
    }

    /// A node not started: the others say whom they wait for once, after
    /// 10 s (they waited silently for the 120 s of the time limit).
    #[test]
    fn a_waiting_node_names_whom_it_waits_for_once() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let mut j = Join::new("1", "r", &names(&["2", "0"]), &s, t0);
        j.on_hello("0");
        assert_eq!(j.poll(t0 + TICK), JoinStep::Wait { ready: None, warning: None });
        match j.poll(t0 + SAY_WAITING_AFTER) {
            JoinStep::Wait { warning: Some(w), .. } => {
                assert!(w.starts_with("node 1: still waiting for node 2 after 10 s (run r;"), "{w}")
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(j.poll(t0 + SAY_WAITING_AFTER + TICK), JoinStep::Wait { ready: None, warning: None }, "once");
        let mut l = Lead::new("r", &names(&["1", "monitor"]), &names(&["1", "monitor"]), &s, t0);
        l.on_hello("1");
        assert_eq!(l.poll(t0 + TICK), LeadStep::Wait { warnings: vec![] });
        match l.poll(t0 + SAY_WAITING_AFTER) {
            LeadStep::Wait { warnings } => {
                assert_eq!(warnings.len(), 1, "{warnings:?}");
                assert!(
                    warnings[0].starts_with("leader: still waiting for nodes 1, monitor after 10 s"),
                    "{warnings:?}"
                );
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(l.poll(t0 + SAY_WAITING_AFTER + TICK), LeadStep::Wait { warnings: vec![] }, "once");
    }

    fn quorum(followers: usize, even_if_cut_off: bool) -> Quorum {
        Quorum { followers, wait: Duration::from_secs(5), even_if_cut_off }
    }

    /// The paper's ring 1–2–4–3–1, the leader heard by follower 1: with
    /// `ready` ready (and hellos from them), a leader with `q`.
    fn leader_with(q: Quorum, ready_ones: &[&str]) -> Lead {
        let s = paper(&[]);
        let mut l = Lead::new("r", &names(&["1"]), &names(&["1", "2", "3", "4", "monitor"]), &s, Now::ZERO)
            .with_quorum(q, s.graph.clone());
        for n in ready_ones {
            l.on_hello(n);
            l.on_ready(n, ready(&s), Now::ZERO);
        }
        l
    }

    /// Issue 50: a quorum start goes without the followers not ready once
    /// its wait is over, not before, and the start names them.
    #[test]
    fn a_quorum_starts_without_the_absent_after_its_wait_and_names_them() {
        let mut l = leader_with(quorum(3, false), &["1", "2", "4", "monitor"]);
        let wait = Duration::from_secs(5) + QUORUM_GRACE;
        assert!(matches!(l.poll(Now::ZERO + wait - TICK), LeadStep::Wait { .. }), "not before the wait");
        assert_eq!(l.poll(Now::ZERO + wait), LeadStep::Go);
        assert_eq!(l.absent(), &[3]);
        assert_eq!(l.start(1_000, Duration::ZERO, 1.0).absent, vec![3]);
        // Everyone ready: a complete start at once, nobody absent.
        let mut all = leader_with(quorum(3, false), &["1", "2", "3", "4", "monitor"]);
        assert_eq!(all.poll(Now::ZERO), LeadStep::Go);
        assert!(all.start(1_000, Duration::ZERO, 1.0).absent.is_empty());
        // Too few followers, or the monitor missing: it waits on.
        for (ready_ones, why) in
            [(&["1", "2", "monitor"][..], "two of four"), (&["1", "2", "3", "4"][..], "no monitor")]
        {
            let mut l = leader_with(quorum(3, false), ready_ones);
            assert!(matches!(l.poll(Now::ZERO + wait * 2), LeadStep::Wait { .. }), "{why}");
        }
    }

    /// Without follower 1 (the one that hears the leader) the others no
    /// longer reach it (Lemma 1): refused in one line naming them, unless
    /// told to go on.
    #[test]
    fn a_quorum_that_cuts_followers_off_the_leader_is_refused_naming_them() {
        let at = Now::ZERO + Duration::from_secs(5) + QUORUM_GRACE;
        let mut l = leader_with(quorum(3, false), &["2", "3", "4", "monitor"]);
        match l.poll(at) {
            LeadStep::Refuse { reason, .. } => assert!(
                reason.starts_with("without follower 1, followers 2, 3, 4 no longer reach the leader (Lemma 1)")
                    && !reason.contains('\n'),
                "{reason}"
            ),
            other => panic!("{other:?}"),
        }
        let mut l = leader_with(quorum(3, true), &["2", "3", "4", "monitor"]);
        assert_eq!(l.poll(at), LeadStep::Go);
        assert_eq!(l.absent(), &[1]);
    }

    #[test]
    fn a_quorum_outside_the_formation_or_a_wait_out_of_range_is_refused() {
        for (n, ok) in [(0, false), (1, true), (4, true), (5, false)] {
            assert_eq!(quorum(n, false).check(4).is_ok(), ok, "quorum {n}: {:?}", quorum(n, false).check(4));
        }
        assert_eq!(
            quorum(0, false).check(4).unwrap_err(),
            "--quorum 0: a quorum is 1 to 4 followers (this formation has 4)"
        );
        for w in [0.0, 119.0, 121.0] {
            let q = Quorum { wait: Duration::from_secs_f64(w), ..quorum(2, false) };
            assert!(q.check(4).is_err(), "wait {w} s");
        }
    }

    /// A follower whose neighbour may be absent says ready from the quorum
    /// wait on, without having heard it.
    #[test]
    fn with_a_quorum_wait_a_node_says_ready_without_an_absent_neighbour() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let wait = Duration::from_secs(5);
        let mut j = Join::new("1", "r", &names(&["2", "0"]), &s, t0).with_quorum_wait(wait);
        j.on_hello("0");
        assert!(matches!(j.poll(t0 + wait - TICK), JoinStep::Wait { ready: None, .. }), "not before the wait");
        assert!(matches!(j.poll(t0 + wait), JoinStep::Wait { ready: Some(_), .. }));
        let mut plain = Join::new("1", "r", &names(&["2", "0"]), &s, t0);
        plain.on_hello("0");
        assert!(matches!(plain.poll(t0 + wait * 4), JoinStep::Wait { ready: None, .. }), "no quorum: waits");
    }

    #[test]
    fn the_leaders_refusal_ends_every_wait_with_its_reason() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let mut j = Join::new("3", "r", &names(&["0"]), &s, t0);
        j.on_abort("");
        assert!(matches!(j.poll(t0), JoinStep::Wait { .. }), "an empty abort is no reason");
        j.on_abort(&"x".repeat(2000));
        match j.poll(t0 + TICK) {
            JoinStep::Failed(Error::Input(m)) => {
                assert!(m.starts_with("node 3: the leader refused run r: xxx"), "{m}");
                assert!(m.len() < 600, "a reason is cut to 500 characters: {}", m.len());
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn the_leader_goes_once_every_node_is_heard_and_ready() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let mut l = Lead::new("r", &names(&["1", "2"]), &names(&["1", "2", "monitor"]), &s, t0);
        assert_eq!(l.poll(t0), LeadStep::Wait { warnings: vec![] });
        l.on_hello("1");
        l.on_hello("2");
        l.on_ready("1", ready(&s), t0);
        l.on_ready("2", ready(&s), t0);
        l.on_ready("intruder", ready(&s), t0);
        assert_eq!(l.poll(t0 + TICK), LeadStep::Wait { warnings: vec![] }, "the monitor is not ready");
        l.on_ready("monitor", ready(&s), t0 + TICK);
        assert_eq!(l.poll(t0 + TICK * 2), LeadStep::Go);
        assert_eq!(l.ignored(), 1);
        let go = l.start(1_000, Duration::from_millis(300), 2.0);
        assert_eq!(
            go,
            Start {
                fingerprint: fingerprint(&s),
                epoch_unix_ns: 300_001_000,
                time_scale: 2.0,
                sent_ns: 1_000,
                absent: Vec::new()
            }
        );
    }

    #[test]
    fn the_leader_warns_once_then_refuses_a_node_with_another_scenario() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let other = paper(&["dt=0.002"]);
        let mut l = Lead::new("r", &names(&["1"]), &names(&["1"]), &s, t0);
        l.on_hello("1");
        l.on_ready("1", ready(&other), t0 + TICK);
        let steps = ticks(&mut |t| l.poll(t), t0, TICK, MISMATCH_GRACE);
        let warned: Vec<_> = steps
            .iter()
            .flat_map(|x| match x {
                LeadStep::Wait { warnings } => warnings.clone(),
                other => panic!("{other:?}"),
            })
            .collect();
        assert_eq!(warned.len(), 1, "{warned:?}");
        assert!(warned[0].contains("node 1 of run r is ready with another scenario, differing in dt"), "{}", warned[0]);
        match l.poll(t0 + TICK + MISMATCH_GRACE) {
            LeadStep::Refuse { reason, error: Error::Input(m) } => {
                assert_eq!(reason, "node 1 runs another scenario, differing in dt");
                assert_eq!(
                    m,
                    "leader: node 1 runs another scenario, differing in dt in run r (another file or --set values)"
                );
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn the_leader_gives_up_naming_the_nodes_not_ready() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let mut l = Lead::new("r", &names(&["1", "2"]), &names(&["1", "2", "monitor"]), &s, t0);
        l.on_hello("1");
        l.on_ready("1", ready(&s), t0);
        for i in 1..START_TIMEOUT.as_secs() {
            assert!(matches!(l.poll(t0 + Duration::from_secs(i)), LeadStep::Wait { .. }), "{i} s");
        }
        assert!(matches!(l.poll(t0 + START_TIMEOUT), LeadStep::Wait { .. }));
        match l.poll(t0 + START_TIMEOUT + TICK) {
            LeadStep::Failed(Error::Run(m)) => {
                assert_eq!(m, "leader: nodes 2, monitor of run r not ready within 120 s")
            }
            other => panic!("{other:?}"),
        }
    }

    /// A leader and an agent that were not run for minutes (a loaded host)
    /// have not waited minutes: the time limit counts what they watched.
    #[test]
    fn nodes_not_run_for_minutes_have_not_waited_minutes() {
        let (s, t0) = (paper(&[]), Now::ZERO);
        let mut l = Lead::new("r", &names(&["1", "2"]), &names(&["1", "2", "monitor"]), &s, t0);
        let mut j = Join::new("2", "r", &names(&["1", "3", "0"]), &s, t0);
        for minutes in [3, 6, 9] {
            let now = t0 + Duration::from_secs(60 * minutes);
            assert!(matches!(l.poll(now), LeadStep::Wait { .. }), "the leader after {minutes} min starved");
            assert!(matches!(j.poll(now), JoinStep::Wait { .. }), "the agent after {minutes} min starved");
        }
    }
}
