//! The one place a node reads a clock, and the run's timebase.
//!
//! The run's timebase is the leader's: its monotonic clock, set at its start
//! to read its wall clock then (ns since the Unix epoch). The leader's
//! [`Start`] names the epoch on it. Every other node keeps a
//! [`formation_protocol::clock_estimate::Offset`] between its own monotonic clock and the leader's
//! timebase, from four-timestamp exchanges ([`crate::clock_sync`]), and turns
//! the run's times into instants of its own monotonic clock through it. No
//! decision compares two hosts' wall clocks: a node whose wall clock is off,
//! or stepped mid-run, runs the same.

use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use formation_protocol::clock_estimate::{Estimate, Exchange, Offset};

/// Nanoseconds since the Unix epoch on this host's wall clock (0 for a
/// clock set before 1970). Only the leader's timebase starts from it.
pub fn unix_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

fn origin() -> Instant {
    static ORIGIN: OnceLock<Instant> = OnceLock::new();
    *ORIGIN.get_or_init(Instant::now)
}

/// This process's monotonic clock, in ns since its first reading.
pub fn mono_ns() -> i64 {
    Instant::now().saturating_duration_since(origin()).as_nanos() as i64
}

/// This process's monotonic clock as the protocol's machines take it
/// ([`formation_protocol::Now`]): the time since its first reading.
pub fn mono() -> std::time::Duration {
    Instant::now().saturating_duration_since(origin())
}

/// Sleeps until [`mono`] reads `at` (at once if it does already).
pub fn sleep_until_mono(at: Duration) {
    std::thread::sleep(at.saturating_sub(mono()));
}

/// The instant at which [`mono_ns`] reads `ns` (a time before the first
/// reading is the first reading).
pub fn instant_of(ns: i64) -> Instant {
    origin() + Duration::from_nanos(ns.max(0) as u64)
}

/// The run's timebase as this node knows it.
#[derive(Clone, Debug)]
pub enum Timebase {
    /// The leader's own: its monotonic clock plus this (its wall clock at
    /// its start, less the monotonic reading then).
    Own(i64),
    /// Another node's estimate of the leader's.
    Estimated(Arc<Mutex<Offset>>),
}

impl Timebase {
    /// The leader's timebase, started now.
    pub fn leader() -> Self {
        let mono = mono_ns();
        Timebase::Own(unix_ns() as i64 - mono)
    }

    /// A node's estimate, with no exchange yet.
    pub fn estimated() -> Self {
        Timebase::Estimated(Arc::new(Mutex::new(Offset::new())))
    }

    fn offset(o: &Arc<Mutex<Offset>>) -> std::sync::MutexGuard<'_, Offset> {
        o.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Files an exchange with the leader (ignored by the leader's own).
    pub fn add(&self, x: Exchange) {
        if let Timebase::Estimated(o) = self {
            let _ = Self::offset(o).add(x);
        }
    }

    /// Files the answers of one question, as [`Offset::add_answers`] judges
    /// them (ignored by the leader's own).
    pub fn add_answers(&self, answers: &[Exchange]) {
        if let Timebase::Estimated(o) = self {
            Self::offset(o).add_answers(answers);
        }
    }

    /// A message the leader stamped `sent_ns` on its timebase arrived now.
    pub fn leader_sent(&self, sent_ns: i64) {
        if let Timebase::Estimated(o) = self {
            Self::offset(o).leader_sent(sent_ns, mono_ns());
        }
    }

    /// What the clock guard saw so far.
    pub fn guard_report(&self) -> formation_protocol::clockguard::GuardReport {
        match self {
            Timebase::Own(_) => Default::default(),
            Timebase::Estimated(o) => Self::offset(o).guard().report(),
        }
    }

    /// Whether a second clock has answered on `control/time`.
    pub fn second_clock(&self) -> bool {
        match self {
            Timebase::Own(_) => false,
            Timebase::Estimated(o) => Self::offset(o).guard().second_clock(),
        }
    }

    /// The estimate now (the leader's own: exact). None before any exchange.
    pub fn estimate(&self) -> Option<Estimate> {
        match self {
            Timebase::Own(_) => {
                Some(Estimate { offset_ns: 0.0, uncertainty_ns: 0.0, drift_ppm: 0.0, periods: 0, steps: 0 })
            }
            Timebase::Estimated(o) => Self::offset(o).at(mono_ns()),
        }
    }

    /// Exchanges filed so far.
    pub fn exchanges(&self) -> u64 {
        match self {
            Timebase::Own(_) => 0,
            Timebase::Estimated(o) => Self::offset(o).exchanges(),
        }
    }

    /// The estimate as `network.json` reports it (None before any exchange).
    pub fn report(&self) -> Option<formation_protocol::clock_estimate::ClockReport> {
        let e = self.estimate()?;
        let (mono, wall) = (mono_ns(), unix_ns() as i64);
        let offset_ns = self.at_mono(mono)? - wall;
        Some(formation_protocol::clock_estimate::ClockReport {
            offset_ms: offset_ns as f64 * 1e-6,
            uncertainty_us: e.uncertainty_ns * 1e-3,
            drift_ppm: e.drift_ppm,
            exchanges: self.exchanges(),
            steps: e.steps,
            guard: match self {
                Timebase::Own(_) => Default::default(),
                Timebase::Estimated(o) => Self::offset(o).guard().report(),
            },
        })
    }

    /// The timebase at this node's monotonic `ns` (None: no estimate yet).
    pub fn at_mono(&self, ns: i64) -> Option<i64> {
        match self {
            Timebase::Own(c) => Some(ns + c),
            Timebase::Estimated(o) => Self::offset(o).to_reference(ns),
        }
    }

    /// The timebase now (ns; None: no estimate yet).
    pub fn now_ns(&self) -> Option<i64> {
        self.at_mono(mono_ns())
    }

    /// The instant of this node's clock at which the timebase reads `tb_ns`
    /// (None: no estimate yet).
    pub fn instant_at(&self, tb_ns: i64) -> Option<Instant> {
        let mono = match self {
            Timebase::Own(c) => tb_ns - c,
            Timebase::Estimated(o) => Self::offset(o).to_local(tb_ns)?,
        };
        Some(instant_of(mono))
    }

    /// The timebase now as the protocol's machines take it
    /// ([`formation_protocol::Now`]: a duration since the Unix epoch on the
    /// leader's clock); zero before any estimate.
    pub fn now(&self) -> Duration {
        Duration::from_nanos(self.now_ns().unwrap_or(0).max(0) as u64)
    }

    /// Sleeps until the timebase reads `at` (at once if it does already),
    /// on this node's monotonic clock through the estimate, which follows
    /// the clocks' drift.
    pub fn sleep_until(&self, at: Duration) {
        if let Some(wake) = self.wake_instant(at) {
            std::thread::sleep(wake.saturating_duration_since(Instant::now()));
        }
    }

    /// The instant on this node's monotonic clock at which the timebase
    /// reads `at` (through the estimate; without one, `at` from now on);
    /// None if it reads that already.
    pub fn wake_instant(&self, at: Duration) -> Option<Instant> {
        let now = self.now();
        if at <= now {
            return None;
        }
        Some(self.instant_at(at.as_nanos() as i64).unwrap_or_else(|| Instant::now() + (at - now)))
    }

    /// How long ago the timebase read `tb_ns` (negative: still to come), in
    /// seconds; None before any estimate.
    pub fn since_s(&self, tb_ns: i64) -> Option<f64> {
        self.now_ns().map(|now| (now - tb_ns) as f64 * 1e-9)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_leaders_timebase_is_its_wall_clock_at_start_then_its_monotonic_clock() {
        let tb = Timebase::leader();
        let (wall, now) = (unix_ns() as i64, tb.now_ns().expect("own"));
        assert!((wall - now).abs() < 5_000_000, "wall {wall} vs timebase {now}");
        let then = tb.instant_at(now + 1_000_000_000).expect("own");
        let d = then.saturating_duration_since(Instant::now());
        assert!(d > Duration::from_millis(990) && d <= Duration::from_secs(1), "{d:?}");
        assert_eq!(tb.estimate().map(|e| e.offset_ns), Some(0.0));
    }

    #[test]
    fn an_estimated_timebase_needs_an_exchange_and_then_follows_it() {
        let tb = Timebase::estimated();
        assert_eq!(tb.now_ns(), None);
        assert_eq!(tb.instant_at(0), None);
        // The leader's timebase reads 5 s more than this node's clock.
        let t1 = mono_ns();
        tb.add(Exchange { t1, t2: t1 + 5_000_000_000 + 50_000, t3: t1 + 5_000_000_000 + 60_000, t4: t1 + 110_000 });
        let now = tb.now_ns().expect("an estimate");
        let expected = mono_ns() + 5_000_000_000;
        assert!((now - expected).abs() < 1_000_000, "{now} vs {expected}");
        let at = tb.instant_at(mono_ns() + 5_000_000_000 + 200_000_000).expect("an estimate");
        let d = at.saturating_duration_since(Instant::now());
        assert!(d > Duration::from_millis(190) && d <= Duration::from_millis(201), "{d:?}");
        assert_eq!(tb.exchanges(), 1);
    }
}
