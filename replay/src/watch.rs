//! The monitor's rules for a run as a whole, fed the time and what it
//! heard: when the run started, when it is over and how it ended
//! (complete, idle, stopped by a signal), and how long each part took. No
//! socket and no clock: [`crate::monitor`] tells it the time.

use std::time::{Duration, Instant};

/// How a monitored run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ending {
    /// Every node reported its final step.
    Complete,
    /// Ctrl-C (SIGINT).
    Interrupted,
    /// SIGTERM.
    Terminated,
    /// No telemetry for the idle timeout.
    Idle,
}

impl Ending {
    /// As the live page says it.
    pub fn name(self) -> &'static str {
        match self {
            Ending::Complete => "complete",
            Ending::Interrupted => "interrupted",
            Ending::Terminated => "terminated",
            Ending::Idle => "idle",
        }
    }
}

/// The signal that stops a monitored run: what the monitor's shutdown
/// future resolves to. The binary installs the handlers (`src/node.rs`); a
/// test passes a future of its own.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Signal {
    /// SIGINT (Ctrl-C).
    Interrupt,
    /// SIGTERM.
    Terminate,
}

impl From<Signal> for Ending {
    fn from(s: Signal) -> Self {
        match s {
            Signal::Interrupt => Ending::Interrupted,
            Signal::Terminate => Ending::Terminated,
        }
    }
}

/// One monitored run, from the monitor's start to its end.
#[derive(Clone, Debug)]
pub struct Watch {
    began: Instant,
    idle: Duration,
    last_heard: Instant,
    started_at: Option<Instant>,
}

impl Watch {
    /// A monitor started at `began`, listening from `now`, that gives up
    /// after `idle` without telemetry.
    pub fn new(began: Instant, now: Instant, idle: Duration) -> Self {
        Self { began, idle, last_heard: now, started_at: None }
    }

    /// The leader's start arrived at `now`: the seconds from the monitor's
    /// start (network.json's `startup_s`). The idle clock restarts.
    pub fn on_start(&mut self, now: Instant) -> f64 {
        self.started_at.get_or_insert(now);
        self.last_heard = now;
        self.startup_s().unwrap_or(0.0)
    }

    /// Telemetry arrived at `now`; `complete`: the record now holds every
    /// node's final step. The run is then over.
    pub fn on_telemetry(&mut self, now: Instant, complete: bool) -> Option<Ending> {
        self.last_heard = now;
        complete.then_some(Ending::Complete)
    }

    /// Complete without new telemetry (a follower no longer waited for).
    pub fn on_telemetry_check(&self, complete: bool) -> Option<Ending> {
        complete.then_some(Ending::Complete)
    }

    /// The periodic check at `now`: over once nothing was heard for the
    /// idle timeout (before the start as after it).
    pub fn on_tick(&self, now: Instant) -> Option<Ending> {
        (now.saturating_duration_since(self.last_heard) > self.idle).then_some(Ending::Idle)
    }

    pub fn started(&self) -> bool {
        self.started_at.is_some()
    }

    /// The monitor's start to the leader's start.
    pub fn startup_s(&self) -> Option<f64> {
        self.started_at.map(|t| t.saturating_duration_since(self.began).as_secs_f64())
    }

    /// The leader's start to `now` (None before the start).
    pub fn run_s(&self, now: Instant) -> Option<f64> {
        self.started_at.map(|t| now.saturating_duration_since(t).as_secs_f64())
    }

    /// The monitor's start to `now`.
    pub fn wall_s(&self, now: Instant) -> f64 {
        now.saturating_duration_since(self.began).as_secs_f64()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_is_idle_only_after_the_idle_timeout_without_telemetry() {
        let t0 = Instant::now();
        let s = |x: f64| t0 + Duration::from_secs_f64(x);
        let mut w = Watch::new(t0, t0, Duration::from_secs(60));
        assert!(!w.started());
        assert_eq!(w.on_tick(s(60.0)), None, "not before the timeout");
        assert_eq!(w.on_tick(s(60.1)), Some(Ending::Idle), "nobody came");
        assert_eq!(w.on_start(s(1.5)), 1.5);
        assert_eq!(w.on_start(s(9.0)), 1.5, "the first start counts");
        assert_eq!(w.on_tick(s(61.4)), None, "the start restarted the idle clock");
        assert_eq!(w.on_telemetry(s(30.0), false), None);
        assert_eq!(w.on_tick(s(90.0)), None);
        assert_eq!(w.on_tick(s(90.1)), Some(Ending::Idle));
        assert_eq!(w.on_telemetry(s(95.0), true), Some(Ending::Complete));
        assert_eq!(w.run_s(s(95.0)), Some(93.5));
        assert_eq!(w.startup_s(), Some(1.5));
        assert_eq!(w.wall_s(s(95.0)), 95.0);
    }
}
