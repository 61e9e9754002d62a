//! A node's clock ([`Clock`]: every reading of the time a node makes goes
//! through the one it was given, this host's or a test's mock), and the
//! run's timebase on it ([`Timebase`]).
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

/// A node's clock: every reading a node makes of the time goes through one
/// (its monotonic clock, its wall clock, its sleeps). Nodes take it as an
/// argument ([`crate::node::NodeArgs::clock`]); [`Clock::real`] reads this
/// host's clocks, [`Clock::mock`] is a clock a test holds and moves
/// ([`Clock::advance`]; a sleep on it moves it to the sleep's end at once).
#[derive(Clone, Debug)]
pub struct Clock(Arc<Source>);

#[derive(Debug)]
enum Source {
    Real,
    /// A mock: its monotonic reading (from `base`) and wall clock at 0.
    Mock {
        base: Instant,
        mono: Mutex<Duration>,
        unix_at_zero: u64,
    },
}

impl Default for Clock {
    fn default() -> Self {
        Self::real()
    }
}

impl Clock {
    /// This host's clocks.
    pub fn real() -> Self {
        static REAL: OnceLock<Clock> = OnceLock::new();
        REAL.get_or_init(|| Clock(Arc::new(Source::Real))).clone()
    }

    /// A clock that reads 0 (monotonic) and `unix_ns` (wall) until moved.
    pub fn mock(unix_ns: u64) -> Self {
        let base = origin();
        Clock(Arc::new(Source::Mock { base, mono: Mutex::new(Duration::ZERO), unix_at_zero: unix_ns }))
    }

    /// Whether this is a mock (a test's clock).
    pub fn is_mock(&self) -> bool {
        matches!(&*self.0, Source::Mock { .. })
    }

    /// Moves a mock clock on by `by` (a real clock moves by itself).
    pub fn advance(&self, by: Duration) {
        if let Source::Mock { mono, .. } = &*self.0 {
            *mono.lock().unwrap_or_else(|p| p.into_inner()) += by;
        }
    }

    /// The monotonic clock now, as the protocol's machines take it
    /// ([`formation_protocol::Now`]): the time since its first reading.
    pub fn mono(&self) -> Duration {
        match &*self.0 {
            Source::Real => Instant::now().saturating_duration_since(origin()),
            Source::Mock { mono, .. } => *mono.lock().unwrap_or_else(|p| p.into_inner()),
        }
    }

    /// [`Clock::mono`] in ns.
    pub fn mono_ns(&self) -> i64 {
        self.mono().as_nanos() as i64
    }

    /// The monotonic clock now as an instant.
    pub fn instant(&self) -> Instant {
        self.instant_of(self.mono_ns())
    }

    /// The instant at which [`Clock::mono_ns`] reads `ns` (a time before
    /// the first reading is the first reading).
    pub fn instant_of(&self, ns: i64) -> Instant {
        let base = match &*self.0 {
            Source::Real => origin(),
            Source::Mock { base, .. } => *base,
        };
        base + Duration::from_nanos(ns.max(0) as u64)
    }

    /// Nanoseconds since the Unix epoch on this host's wall clock (0 for a
    /// clock set before 1970). Only the leader's timebase starts from it.
    pub fn unix_ns(&self) -> u64 {
        match &*self.0 {
            Source::Real => SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0),
            Source::Mock { unix_at_zero, .. } => unix_at_zero + self.mono().as_nanos() as u64,
        }
    }

    /// Sleeps until the instant `at` (a mock moves there at once).
    pub fn sleep_until(&self, at: Instant) {
        match &*self.0 {
            Source::Real => std::thread::sleep(at.saturating_duration_since(Instant::now())),
            Source::Mock { .. } => {
                let ahead = at.saturating_duration_since(self.instant());
                self.advance(ahead);
            }
        }
    }

    /// Waits `d` in a task: a real clock sleeps; a mock moves on by `d` at
    /// once, after letting the other tasks run.
    pub async fn pause(&self, d: Duration) {
        match &*self.0 {
            Source::Real => tokio::time::sleep(d).await,
            Source::Mock { .. } => {
                self.advance(d);
                tokio::task::yield_now().await;
            }
        }
    }

    /// Sleeps until [`Clock::mono`] reads `at`.
    pub fn sleep_until_mono(&self, at: Duration) {
        self.sleep_until(self.instant_of(at.as_nanos() as i64));
    }
}

fn origin() -> Instant {
    static ORIGIN: OnceLock<Instant> = OnceLock::new();
    *ORIGIN.get_or_init(Instant::now)
}

/// The run's timebase as this node knows it, on the node's clock.
#[derive(Clone, Debug)]
pub struct Timebase {
    clock: Clock,
    kind: Kind,
    /// The leader's stamped messages heard ([`Timebase::leader_sent`]):
    /// signs that it lives, for a wait on its clock.
    heard: Arc<std::sync::atomic::AtomicU64>,
}

#[derive(Clone, Debug)]
enum Kind {
    /// The leader's own: its monotonic clock plus this (its wall clock at
    /// its start, less the monotonic reading then).
    Own(i64),
    /// Another node's estimate of the leader's.
    Estimated(Arc<Mutex<Offset>>),
}

use Kind::{Estimated, Own};

impl Timebase {
    /// The leader's timebase on `clock`, started now.
    pub fn leader(clock: &Clock) -> Self {
        let mono = clock.mono_ns();
        Timebase { kind: Own(clock.unix_ns() as i64 - mono), clock: clock.clone(), heard: Default::default() }
    }

    /// A node's estimate on `clock`, with no exchange yet.
    pub fn estimated(clock: &Clock) -> Self {
        Timebase {
            kind: Estimated(Arc::new(Mutex::new(Offset::new()))),
            clock: clock.clone(),
            heard: Default::default(),
        }
    }

    /// The node's clock under this timebase.
    pub fn clock(&self) -> &Clock {
        &self.clock
    }

    fn offset(o: &Arc<Mutex<Offset>>) -> std::sync::MutexGuard<'_, Offset> {
        o.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Files an exchange with the leader (ignored by the leader's own).
    pub fn add(&self, x: Exchange) {
        if let Estimated(o) = &self.kind {
            let _ = Self::offset(o).add(x);
        }
    }

    /// Files the answers of one question, as [`Offset::add_answers`] judges
    /// them (ignored by the leader's own).
    pub fn add_answers(&self, answers: &[Exchange]) {
        if let Estimated(o) = &self.kind {
            Self::offset(o).add_answers(answers);
        }
    }

    /// A message the leader stamped `sent_ns` on its timebase arrived now.
    pub fn leader_sent(&self, sent_ns: i64) {
        self.heard.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if let Estimated(o) = &self.kind {
            Self::offset(o).leader_sent(sent_ns, self.clock.mono_ns());
        }
    }

    /// How many of the leader's stamped messages were heard so far.
    pub fn leader_heard(&self) -> u64 {
        self.heard.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// What the clock guard saw so far.
    pub fn guard_report(&self) -> formation_protocol::clockguard::GuardReport {
        match &self.kind {
            Own(_) => Default::default(),
            Estimated(o) => Self::offset(o).guard().report(),
        }
    }

    /// Whether a second clock has answered on `control/time`.
    pub fn second_clock(&self) -> bool {
        match &self.kind {
            Own(_) => false,
            Estimated(o) => Self::offset(o).guard().second_clock(),
        }
    }

    /// The estimate now (the leader's own: exact). None before any exchange.
    pub fn estimate(&self) -> Option<Estimate> {
        match &self.kind {
            Own(_) => Some(Estimate { offset_ns: 0.0, uncertainty_ns: 0.0, drift_ppm: 0.0, periods: 0, steps: 0 }),
            Estimated(o) => Self::offset(o).at(self.clock.mono_ns()),
        }
    }

    /// Exchanges filed so far.
    pub fn exchanges(&self) -> u64 {
        match &self.kind {
            Own(_) => 0,
            Estimated(o) => Self::offset(o).exchanges(),
        }
    }

    /// The estimate as `network.json` reports it (None before any exchange).
    pub fn report(&self) -> Option<formation_protocol::clock_estimate::ClockReport> {
        let e = self.estimate()?;
        let (mono, wall) = (self.clock.mono_ns(), self.clock.unix_ns() as i64);
        let offset_ns = self.at_mono(mono)? - wall;
        Some(formation_protocol::clock_estimate::ClockReport {
            offset_ms: offset_ns as f64 * 1e-6,
            uncertainty_us: e.uncertainty_ns * 1e-3,
            drift_ppm: e.drift_ppm,
            exchanges: self.exchanges(),
            steps: e.steps,
            guard: match &self.kind {
                Own(_) => Default::default(),
                Estimated(o) => Self::offset(o).guard().report(),
            },
        })
    }

    /// The timebase at this node's monotonic `ns` (None: no estimate yet).
    pub fn at_mono(&self, ns: i64) -> Option<i64> {
        match &self.kind {
            Own(c) => Some(ns + c),
            Estimated(o) => Self::offset(o).to_reference(ns),
        }
    }

    /// The timebase now (ns; None: no estimate yet).
    pub fn now_ns(&self) -> Option<i64> {
        self.at_mono(self.clock.mono_ns())
    }

    /// The instant of this node's clock at which the timebase reads `tb_ns`
    /// (None: no estimate yet).
    pub fn instant_at(&self, tb_ns: i64) -> Option<Instant> {
        let mono = match &self.kind {
            Own(c) => tb_ns - c,
            Estimated(o) => Self::offset(o).to_local(tb_ns)?,
        };
        Some(self.clock.instant_of(mono))
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
            self.clock.sleep_until(wake);
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
        Some(self.instant_at(at.as_nanos() as i64).unwrap_or_else(|| self.clock.instant() + (at - now)))
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
        let clock = Clock::real();
        let tb = Timebase::leader(&clock);
        let (wall, now) = (clock.unix_ns() as i64, tb.now_ns().expect("own"));
        assert!((wall - now).abs() < 5_000_000, "wall {wall} vs timebase {now}");
        let then = tb.instant_at(now + 1_000_000_000).expect("own");
        let d = then.saturating_duration_since(Instant::now());
        assert!(d > Duration::from_millis(990) && d <= Duration::from_secs(1), "{d:?}");
        assert_eq!(tb.estimate().map(|e| e.offset_ns), Some(0.0));
    }

    #[test]
    fn an_estimated_timebase_needs_an_exchange_and_then_follows_it() {
        let clock = Clock::real();
        let mono_ns = || clock.mono_ns();
        let tb = Timebase::estimated(&clock);
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

    /// A mock clock moves only when told to, or by a sleep on it, and the
    /// timebase on it follows: a node's loop on a mock clock runs in no
    /// time, to the nanosecond.
    #[test]
    fn a_mock_clock_moves_when_told_and_a_timebase_on_it_follows() {
        let clock = Clock::mock(1_700_000_000_000_000_000);
        let tb = Timebase::leader(&clock);
        assert_eq!((clock.mono(), tb.now_ns()), (Duration::ZERO, Some(1_700_000_000_000_000_000)));
        clock.advance(Duration::from_millis(250));
        assert_eq!(tb.now_ns(), Some(1_700_000_000_250_000_000));
        assert_eq!(clock.unix_ns(), 1_700_000_000_250_000_000);
        // A sleep until an hour later takes no wall time (a minute's guard:
        // a real one would take the hour) and moves the clock there.
        let began = Instant::now();
        tb.sleep_until(Duration::from_nanos(1_700_003_600_250_000_000));
        assert!(began.elapsed() < Duration::from_secs(60), "a mock sleep waited {:?}", began.elapsed());
        assert_eq!(tb.now(), Duration::from_nanos(1_700_003_600_250_000_000));
        assert_eq!(clock.mono(), Duration::from_millis(3_600_250));
        // A copy is the same clock.
        clock.clone().advance(Duration::from_nanos(1));
        assert_eq!(clock.mono_ns(), 3_600_250_000_001);
    }
}
