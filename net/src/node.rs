//! What every node shares: its command-line arguments, loading its
//! scenario, opening its session, the quality of service of its traffic,
//! and its one-line messages. (The shell that runs a node, with its
//! logging, runtime and exit status, is the `formation` binary's.)

use std::path::PathBuf;
use std::time::Duration;

use formation_scenario::Scenario;

use crate::session::{self, ZenohArgs};
use formation_exit::Error;
use formation_protocol::names::Keys;

/// Said once at the start of a run without `--tls`.
pub const UNAUTHENTICATED: &str = "warning: no --tls: this run's traffic is unauthenticated and unencrypted; \
any process that reaches its ports can read it, forge estimates or abort the run (make certificates with \
`formation certs` and pass --tls DIR)";
/// Set by `formation launch` and the lab on the nodes they start: the run
/// has said [`UNAUTHENTICATED`] once already.
pub const LAUNCHED_ENV: &str = "FORMATION_LAUNCHED";
pub use crate::session::ZENOH_LOG_ENV;

/// [`UNAUTHENTICATED`] on stderr for a node started by hand without `--tls`.
pub fn warn_if_unauthenticated(zenoh: &ZenohArgs) {
    if zenoh.tls.is_none() && std::env::var_os(LAUNCHED_ENV).is_none() {
        say(UNAUTHENTICATED);
    }
}

/// What a networked run refuses of a scenario that `formation sim` runs.
pub fn networked(scenario: &Scenario) -> Result<(), Error> {
    let d = scenario.network.delay_steps;
    if d > 0 && scenario.timing == formation_scenario::Timing::Lockstep {
        return Err(Error::Input(format!(
            "network.delay_steps = {d} applies to formation sim and real-time runs; a lock-step run uses each \
             step's own messages (set timing = \"realtime\", or network.delay_steps = 0)"
        )));
    }
    // Lock-step performs a died row (the agent kills itself, crate::died).
    let realtime = scenario.timing == formation_scenario::Timing::Realtime;
    if let Some(f) = scenario.faults.iter().find(|f| f.died && realtime) {
        let who = match f.target {
            formation_scenario::FaultTarget::Node(id) => id,
            formation_scenario::FaultTarget::Link(a, _) => a,
        };
        return Err(Error::Input(format!(
            "the fault row killing follower {who} at {} s (died = true) is performed in lock-step and modelled by \
             formation sim; a real-time run does not kill its agents from the scenario (formation lab --kill-agent \
             {who}@{} kills one in real time)",
            f.from_s, f.from_s
        )));
    }
    Ok(())
}

/// A real-time run without a communication delay: what it will not match.
pub fn realtime_hint(scenario: &Scenario) -> Option<String> {
    (scenario.timing == formation_scenario::Timing::Realtime && scenario.network.delay_steps == 0).then(|| {
        "note: real time with network.delay_steps = 0: each step uses whichever of its sources' step-k and \
         step-(k−1) messages has arrived, which formation sim does not model; with network.delay_steps = 1 the run \
         is the one `formation sim --set network.delay_steps=1` predicts"
            .to_string()
    })
}

/// Arguments every node takes.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct NodeArgs {
    /// Scenario file (TOML); every node of a run must load the same one.
    #[cfg_attr(feature = "clap", arg(long, value_name = "FILE"))]
    pub scenario: PathBuf,
    /// Override a scenario value, as `formation sim --set` (repeatable).
    #[cfg_attr(feature = "clap", arg(long = "set", value_name = "KEY=VALUE"))]
    pub overrides: Vec<String>,
    /// Run name: the key namespace `formation/<run>/…` [default: scenario name].
    #[cfg_attr(feature = "clap", arg(long, value_name = "NAME"))]
    pub run: Option<String>,
    #[cfg_attr(feature = "clap", command(flatten))]
    pub zenoh: ZenohArgs,
    /// Give up when no router or peer answers at start-up within this long (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = 10.0, value_name = "SECONDS"))]
    pub open_timeout: f64,
    /// Start with those present: from this long after it began waiting
    /// (s), the node is ready without the neighbours it has not heard, and
    /// a leader with --quorum starts without the followers not ready
    /// [default: everyone waits for everyone].
    #[cfg_attr(feature = "clap", arg(long, value_name = "SECONDS"))]
    pub quorum_wait: Option<f64>,
    /// The node's clock: every reading of the time it makes (this host's
    /// clocks; a test may give it a mock).
    #[cfg_attr(feature = "clap", arg(skip))]
    pub clock: crate::clock::Clock,
}

impl NodeArgs {
    /// Loads the scenario and resolves the run name (bad input: exit 2).
    ///
    /// `identity` is the node's name in its certificate (`leader`,
    /// `monitor`, `agent-<id>`): with `--tls`, its files are checked here,
    /// and the folder's policy must be the one this scenario's topology gives.
    pub fn load(&self, identity: &str) -> Result<(Scenario, Keys), Error> {
        let scenario = Scenario::load(&self.scenario, &self.overrides).map_err(|e| Error::Input(e.to_string()))?;
        networked(&scenario)?;
        let run = self.run.clone().unwrap_or_else(|| scenario.name.clone());
        formation_protocol::names::validate_run_name(&run).map_err(|e| Error::Input(e.to_string()))?;
        let zenoh = self.zenoh_as(identity);
        zenoh.to_config().map_err(|e| Error::Input(format!("zenoh options: {e}")))?;
        if let Some(dir) = &self.zenoh.tls {
            crate::identity::identity_for(dir, identity, &scenario).map_err(|e| Error::Input(e.0))?;
        }
        Ok((scenario, Keys::new(&run)))
    }

    /// `--quorum-wait`, checked (bad input: exit 2).
    pub fn quorum_wait(&self) -> Result<Option<Duration>, Error> {
        self.quorum_wait.map(formation_protocol::barrier::quorum_wait).transpose().map_err(Error::Input)
    }

    fn zenoh_as(&self, identity: &str) -> ZenohArgs {
        ZenohArgs { identity: Some(identity.to_string()), ..self.zenoh.clone() }
    }

    /// Opens the session, with the limits of the scenario's traffic
    /// ([`crate::limits`]); says once after a few seconds what it is waiting
    /// for, and gives up after `--open-timeout` naming the endpoints.
    pub async fn open(&self, identity: &str, scenario: &Scenario) -> Result<zenoh::Session, Error> {
        let zenoh = ZenohArgs { traffic: Some(crate::limits::Traffic::of(scenario)), ..self.zenoh_as(identity) };
        // Said once its input is known to be good (bad input stays one line).
        warn_if_unauthenticated(&zenoh);
        let opening = session::open(&zenoh);
        tokio::pin!(opening);
        if !(self.open_timeout.is_finite() && self.open_timeout > 0.0) {
            return Err(Error::Input(format!("--open-timeout must be positive, not {}", self.open_timeout)));
        }
        let limit = Duration::from_secs_f64(self.open_timeout);
        let began = self.clock.mono();
        let waited = || self.clock.mono().saturating_sub(began);
        let mut said = false;
        loop {
            let wait = Duration::from_secs(3).min(limit.saturating_sub(waited()).max(Duration::from_millis(10)));
            match tokio::time::timeout(wait, &mut opening).await {
                Ok(result) => return result.map_err(|e| Error::Run(e.to_string())),
                Err(_) if waited() >= limit => {
                    return Err(Error::Run(format!(
                        "no zenoh router or peer answered at {} within {} s (is the router running?)",
                        self.endpoints(),
                        self.open_timeout
                    )))
                }
                Err(_) if !said => {
                    say(&format!("waiting for {} …", self.endpoints()));
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

/// How an estimate publisher meets a full queue (a slow or dead peer).
/// Real time: `Drop`, the newest wins — every step re-sends the whole state,
/// and a control loop that must meet its period never waits on a `put`.
/// Lock-step: `Block`, since every step's message is needed and the loop
/// waits for its peers by design (lost start-up messages are re-sent).
pub fn estimate_congestion(scenario: &Scenario) -> zenoh::qos::CongestionControl {
    match scenario.timing {
        formation_scenario::Timing::Realtime => zenoh::qos::CongestionControl::Drop,
        formation_scenario::Timing::Lockstep => zenoh::qos::CongestionControl::Block,
    }
}

/// Whether estimates skip zenoh's batching. Lock-step: yes, every step
/// waits for them. Real time: no. An express message takes a whole batch
/// of its priority's queue (2 by default), so a transport that is held up
/// for a few milliseconds (a router descheduled on a busy host) drops every
/// estimate after the second; batched, a stall of that length costs a few
/// kilobytes of queue and nothing is dropped. Without back-pressure a
/// batched message leaves at once.
pub fn estimate_express(scenario: &Scenario) -> bool {
    scenario.timing == formation_scenario::Timing::Lockstep
}

/// A publisher of control traffic on `key` (estimates, poses): the
/// estimates' congestion control ([`estimate_congestion`]), priority and
/// batching ([`estimate_express`]); `what` names it in an error.
pub async fn control_publisher(
    session: &zenoh::Session,
    key: String,
    scenario: &Scenario,
    what: &str,
) -> Result<zenoh::pubsub::Publisher<'static>, formation_exit::Error> {
    session
        .declare_publisher(key)
        .congestion_control(estimate_congestion(scenario))
        .priority(priority::ESTIMATE)
        .express(estimate_express(scenario))
        .await
        .map_err(|e| formation_exit::zerr(&format!("declaring the {what} publisher"), e))
}

/// Zenoh priorities of a run's traffic. Each priority has a queue of its own
/// in every transport (and the router's), served highest first: estimates
/// never wait behind telemetry, not even behind the burst a node sends
/// again after an outage. Acknowledgements come next, telemetry last.
pub mod priority {
    use zenoh::qos::Priority;
    pub const ESTIMATE: Priority = Priority::RealTime;
    pub const ACK: Priority = Priority::InteractiveHigh;
    pub const TELEMETRY: Priority = Priority::DataLow;
}

/// One line on stderr in a single write, so that the lines of processes
/// sharing a terminal do not interleave mid-line.
pub fn say(line: &str) {
    use std::io::Write;
    let mut l = String::with_capacity(line.len() + 1);
    l.push_str(line);
    l.push('\n');
    let _ = std::io::stderr().lock().write_all(l.as_bytes());
}

/// A protocol machine shared by a node's subscriber callbacks (which feed
/// it what arrives) and the node's loop (which tells it the time).
pub struct Shared<M> {
    machine: std::sync::Mutex<M>,
    /// Lock-step: what the loop waits for arrived.
    woken: std::sync::Condvar,
}

impl<M> Shared<M> {
    pub fn new(machine: M) -> Self {
        Self { machine: std::sync::Mutex::new(machine), woken: std::sync::Condvar::new() }
    }

    pub fn lock(&self) -> std::sync::MutexGuard<'_, M> {
        self.machine.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Wakes a lock-step loop waiting in [`Shared::sleep`].
    pub fn wake(&self) {
        self.woken.notify_all();
    }

    /// Until the machine's next deadline (`next`, on the run's timebase): a
    /// precise sleep in real time; in lock-step a wait that [`Shared::wake`]
    /// ends early.
    pub fn sleep(&self, timebase: &crate::clock::Timebase, lockstep: bool, next: impl Fn(&mut M) -> Option<Duration>) {
        let mut m = self.lock();
        let Some(at) = next(&mut m) else { return };
        let t = timebase.now();
        if at <= t {
            return;
        }
        if lockstep {
            let _ = self.woken.wait_timeout(m, at - t).unwrap_or_else(|p| p.into_inner());
        } else {
            drop(m);
            timebase.sleep_until(at);
        }
    }
}
