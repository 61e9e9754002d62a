//! The courier's thread: a [`Store`] behind a lock, shared by the control
//! loop that hands batches over and a thread of its own that publishes them
//! (see [`formation_protocol::courier`] for the rules it keeps).

use formation_protocol::courier::{CourierStats, Store};
use formation_protocol::patience::Patience;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Duration;

use crate::clock::Clock;

/// The longest the sending thread sleeps with nothing in flight; it is
/// woken at once by a batch handed over, an acknowledgement that frees the
/// window for a waiting batch, or the end.
const IDLE: Duration = Duration::from_secs(1);

#[derive(Debug)]
struct State {
    store: Store,
    closed: bool,
}

/// The store between a control loop and the network (see the module
/// docs): a [`Store`] behind a lock, shared by the loop that hands batches
/// over and the thread that sends them.
#[derive(Debug)]
pub struct Courier {
    state: Mutex<State>,
    changed: Condvar,
    clock: Clock,
}

impl Courier {
    pub fn new(capacity_steps: u64, clock: Clock) -> Self {
        let state = Mutex::new(State { store: Store::new(capacity_steps), closed: false });
        Self { state, changed: Condvar::new(), clock }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// [`Store::available_from`].
    pub fn available_from(&self, next_k: u64) -> u64 {
        self.lock().store.available_from(next_k)
    }

    /// Hands over the batch of steps first_k..end_k; never waits.
    pub fn push(&self, first_k: u64, end_k: u64, bytes: Vec<u8>) {
        self.lock().store.push(first_k, end_k, bytes);
        self.changed.notify_all();
    }

    /// The monitor holds every step below `next_k`. The sending thread is
    /// woken only if a batch waits for the window this frees: otherwise
    /// the acknowledgement only moves its next resend later, and it wakes
    /// at the earlier time, finds nothing due and sleeps on (at 100 Hz the
    /// monitor's ten acknowledgements a second were most of its wake-ups).
    pub fn ack(&self, next_k: u64) {
        let mut s = self.lock();
        s.store.ack(next_k);
        let waiting = s.store.has_unsent();
        drop(s);
        if waiting {
            self.changed.notify_all();
        }
    }

    pub fn stats(&self) -> CourierStats {
        self.lock().store.stats()
    }

    /// Steps handed over and not yet acknowledged.
    pub fn unacknowledged_steps(&self) -> u64 {
        self.lock().store.unacknowledged_steps()
    }

    /// The batches due now ([`Store::due`]); with none, waits until the
    /// oldest batch in flight is due again (at most [`IDLE`]) or the loop
    /// hands one over. None once closed and empty.
    fn due(&self) -> Option<Vec<Arc<Vec<u8>>>> {
        let mut s = self.lock();
        let mut out = s.store.due(self.clock.mono());
        if out.is_empty() && !(s.closed && s.store.is_empty()) {
            let wait = s.store.next_resend().map_or(IDLE, |at| at.saturating_sub(self.clock.mono()).min(IDLE));
            s = self.changed.wait_timeout(s, wait).unwrap_or_else(|p| p.into_inner()).0;
            out = s.store.due(self.clock.mono());
        }
        if s.closed && s.store.is_empty() {
            return None;
        }
        Some(out)
    }

    /// Waits until the monitor has acknowledged everything handed over;
    /// true if so. It gives up, false, once the monitor has acknowledged
    /// nothing new for `limit` as [`Patience`] counts it: an
    /// acknowledgement of more starts the count again (a monitor that
    /// files a backlog slowly is slow, not gone), and time this thread was
    /// not run counts only a look's cap (issue 64: on one core a starved
    /// monitor took more than ten seconds to file 100 followers' last
    /// batches, and each follower gave its telemetry up).
    pub fn drain(&self, limit: Duration) -> bool {
        self.drain_looking(limit, |_| ())
    }

    /// [`Courier::drain`], calling `between(now)` after each look (a test
    /// acknowledges there, on a mock clock, with no thread to race).
    fn drain_looking(&self, limit: Duration, mut between: impl FnMut(Duration)) -> bool {
        const LOOK: Duration = Duration::from_millis(5);
        let mut patience = Patience::new(self.clock.mono(), LOOK * 10);
        loop {
            let (empty, acknowledged) = {
                let s = self.lock();
                (s.store.is_empty(), s.store.acknowledged())
            };
            if empty {
                return true;
            }
            let now = self.clock.mono();
            patience.alive(now, acknowledged);
            if patience.look(now) >= limit {
                return false;
            }
            between(now);
            self.clock.sleep_until_mono(now + LOOK);
        }
    }
}

/// A courier and the thread that publishes from it with `publish` (which
/// may block on a slow or dead link; the loop never notices). A put that
/// fails is like a lost one: sent again after the resend back-off, so
/// `publish` returns nothing.
pub struct CourierThread {
    pub courier: Arc<Courier>,
    thread: std::thread::JoinHandle<()>,
}

impl CourierThread {
    pub fn start(capacity_steps: u64, clock: Clock, publish: impl FnMut(&[u8]) + Send + 'static) -> Self {
        let courier = Arc::new(Courier::new(capacity_steps, clock));
        let c = courier.clone();
        let mut publish = publish;
        let thread = std::thread::spawn(move || {
            while let Some(batches) = c.due() {
                for bytes in batches {
                    publish(&bytes);
                }
            }
        });
        Self { courier, thread }
    }

    /// Waits up to `limit` for the monitor to acknowledge everything, then
    /// stops. Returns the steps it never acknowledged (the thread is left to
    /// the process's exit if it is stuck in a put on a dead link).
    pub fn finish(self, limit: Duration) -> u64 {
        let acknowledged = self.courier.drain(limit);
        let left = self.courier.unacknowledged_steps();
        {
            let mut s = self.courier.lock();
            s.store.clear();
            s.closed = true;
        }
        self.courier.changed.notify_all();
        if acknowledged {
            let _ = self.thread.join();
        }
        left
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The thread around the store: a publisher stuck for good in a put
    /// does not hold the end of the run; the steps never acknowledged are
    /// reported.
    #[test]
    fn a_publisher_stuck_for_good_does_not_hold_the_end_of_the_run() {
        let d = CourierThread::start(1000, Clock::real(), |_| loop {
            std::thread::sleep(Duration::from_secs(60));
        });
        for i in 0..10u64 {
            d.courier.push(i * 5, i * 5 + 5, vec![0; 8]);
        }
        let lost = d.finish(Duration::from_millis(200));
        assert_eq!(lost, 50, "ten batches of five steps never acknowledged");
    }

    /// On a mock clock a node's wait for the monitor's acknowledgements
    /// (an hour's here) passes in the clock's own sleeps: no wall time (a
    /// minute's guard: a real wait would take the hour).
    #[test]
    fn on_a_mock_clock_the_wait_for_acknowledgements_takes_no_wall_time() {
        let clock = Clock::mock(0);
        let d = CourierThread::start(1000, clock.clone(), |_| {});
        d.courier.push(0, 5, vec![0; 8]);
        let began = std::time::Instant::now();
        let lost = d.finish(Duration::from_secs(3600));
        assert_eq!(lost, 5, "five steps never acknowledged");
        assert!(began.elapsed() < Duration::from_secs(60), "waited {:?} of wall time", began.elapsed());
        let waited = clock.mono();
        let hour = Duration::from_secs(3600);
        assert!(waited >= hour && waited < hour + Duration::from_millis(10), "{waited:?} on the mock");
    }

    /// Slow is not gone: a monitor that acknowledges one batch every 3 s
    /// (each a sign it is filing a backlog) is waited for 27 s, past the
    /// ten seconds of silence that end the wait; once it stops, the wait
    /// ends ten seconds after its last acknowledgement, with the steps it
    /// never acknowledged counted.
    #[test]
    fn a_monitor_that_acknowledges_slowly_is_waited_for_and_one_that_stops_is_not() {
        let clock = Clock::mock(0);
        let c = Courier::new(1000, clock.clone());
        for i in 0..10u64 {
            c.push(i * 5, i * 5 + 5, vec![0; 8]);
        }
        let every = Duration::from_secs(3);
        let slow = |now: Duration| c.ack(5 * (now.as_millis() / every.as_millis()).min(10) as u64);
        assert!(c.drain_looking(Duration::from_secs(10), slow), "{} steps left", c.unacknowledged_steps());
        assert!((Duration::from_secs(30)..Duration::from_millis(30_010)).contains(&clock.mono()), "{:?}", clock.mono());

        let clock = Clock::mock(0);
        let c = Courier::new(1000, clock.clone());
        for i in 0..10u64 {
            c.push(i * 5, i * 5 + 5, vec![0; 8]);
        }
        let stops = |now: Duration| c.ack(5 * (now.as_millis() / every.as_millis()).min(3) as u64);
        assert!(!c.drain_looking(Duration::from_secs(10), stops));
        assert_eq!(c.unacknowledged_steps(), 35, "three batches acknowledged, seven not");
        let gave_up = clock.mono();
        assert!((Duration::from_secs(19)..Duration::from_millis(19_010)).contains(&gave_up), "gave up at {gave_up:?}");
    }
}
