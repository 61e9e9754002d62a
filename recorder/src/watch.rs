//! The monitor's rules for a run as a whole, fed the time and what it
//! heard: when the run started, when it is over and how it ended
//! (complete, idle, stopped by a signal), and how long each part took. No
//! socket and no clock: [`crate::monitor`] tells it the time.

use std::time::{Duration, Instant};

use formation_exit::shutdown::Signal;

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
    started_at: Option<Instant>,
    /// Silence counted against `idle` since the last telemetry, and the
    /// last look ([`Watch::on_tick`]).
    silent: Duration,
    looked: Instant,
}

/// The most one gap between two of the monitor's looks counts as silence:
/// it looks every 2 s (0.25 s on a terminal) while it runs, and a longer
/// gap is time it was not run itself, which says nothing of the others
/// (a loaded host: slow is not gone, `formation_protocol::patience`).
pub const LOOK_CAP: Duration = Duration::from_secs(4);

impl Watch {
    /// A monitor started at `began`, listening from `now`, that gives up
    /// after `idle` without telemetry.
    pub fn new(began: Instant, now: Instant, idle: Duration) -> Self {
        Self { began, idle, started_at: None, silent: Duration::ZERO, looked: now }
    }

    /// The leader's start arrived at `now`: the seconds from the monitor's
    /// start (network.json's `startup_s`). The idle clock restarts.
    pub fn on_start(&mut self, now: Instant) -> f64 {
        self.started_at.get_or_insert(now);
        self.heard(now);
        self.startup_s().unwrap_or(0.0)
    }

    /// Telemetry arrived at `now`; `complete`: the record now holds every
    /// node's final step. The run is then over.
    pub fn on_telemetry(&mut self, now: Instant, complete: bool) -> Option<Ending> {
        self.heard(now);
        complete.then_some(Ending::Complete)
    }

    /// Complete without new telemetry (a follower no longer waited for).
    pub fn on_telemetry_check(&self, complete: bool) -> Option<Ending> {
        complete.then_some(Ending::Complete)
    }

    fn heard(&mut self, now: Instant) {
        self.silent = Duration::ZERO;
        self.looked = now;
    }

    /// The periodic check at `now`: over once the run has been silent for
    /// the idle timeout, counting each gap between looks up to
    /// [`LOOK_CAP`]. Before the start the start barrier's own limit
    /// decides (its nodes may take long to come on a slow host; the
    /// barrier knows whom it waits for).
    pub fn on_tick(&mut self, now: Instant) -> Option<Ending> {
        self.silent += now.saturating_duration_since(self.looked).min(LOOK_CAP);
        self.looked = now;
        (self.started() && self.silent > self.idle).then_some(Ending::Idle)
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
        // Looks every 2 s up to `to` (as the monitor's status tick does).
        fn ticks(w: &mut Watch, s: impl Fn(f64) -> Instant, from: f64, to: f64) -> Option<Ending> {
            let mut t = from;
            while t + 2.0 < to {
                t += 2.0;
                assert_eq!(w.on_tick(s(t)), None, "at {t} s");
            }
            w.on_tick(s(to))
        }
        let mut w = Watch::new(t0, t0, Duration::from_secs(60));
        assert!(!w.started());
        assert_eq!(ticks(&mut w, s, 0.0, 100.0), None, "before the start the barrier decides");
        assert_eq!(w.on_start(s(101.5)), 101.5);
        assert_eq!(w.on_start(s(109.0)), 101.5, "the first start counts");
        assert_eq!(ticks(&mut w, s, 109.0, 169.0), None, "not before the timeout, the start restarted it");
        assert_eq!(w.on_tick(s(169.1)), Some(Ending::Idle));
        assert_eq!(w.on_telemetry(s(170.0), false), None);
        assert_eq!(ticks(&mut w, s, 170.0, 230.0), None);
        assert_eq!(w.on_tick(s(230.1)), Some(Ending::Idle));
        assert_eq!(w.on_telemetry(s(235.0), true), Some(Ending::Complete));
        assert_eq!(w.run_s(s(235.0)), Some(133.5));
        assert_eq!(w.startup_s(), Some(101.5));
        assert_eq!(w.wall_s(s(235.0)), 235.0);
    }

    /// A monitor not run for minutes (a loaded host) has not heard silence
    /// for minutes: each gap counts at most [`LOOK_CAP`].
    #[test]
    fn a_monitor_not_run_for_minutes_is_not_idle() {
        let t0 = Instant::now();
        let s = |x: f64| t0 + Duration::from_secs_f64(x);
        let mut w = Watch::new(t0, t0, Duration::from_secs(60));
        w.on_start(s(1.0));
        for (i, t) in [200.0, 400.0, 600.0].into_iter().enumerate() {
            assert_eq!(w.on_tick(s(t)), None, "look {i} after a gap of minutes");
        }
    }
}
