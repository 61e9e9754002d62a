//! Telemetry that survives an outage. A control loop hands each batch to a
//! [`Courier`] and goes on (it never waits on the network); a thread of the
//! courier's own publishes it, and keeps it until the monitor acknowledges
//! it (`control/ack`, `telemetry::Ack`: the first step the
//! monitor does not hold). What is not acknowledged within [`RESEND`] is
//! sent again, oldest first, so a batch lost to a dead link, a router
//! restart or a full queue reaches the monitor once the way is clear.
//!
//! Sending again is paced so that it cannot swamp the network it waits
//! for: at most [`WINDOW_BYTES`] are in flight (sent, not acknowledged), and
//! while no acknowledgement arrives at all (a dead link) the time before
//! the next try doubles, up to [`MAX_RESEND`]; the first acknowledgement
//! that arrives again (the monitor sends one every 100 ms) resets it.
//!
//! The store is bounded: at most [`CAPACITY_STEPS`] unacknowledged steps
//! (200 s of a follower's telemetry at 1 kHz, about 32 MB). Past that the
//! oldest batch is dropped and counted, and the batches that follow tell
//! the monitor (`available_from`) so that it marks the steps as lost rather
//! than waiting for them.

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Unacknowledged steps the store holds before it drops the oldest batch.
pub const CAPACITY_STEPS: u64 = 200_000;
/// A batch not acknowledged this long after it was sent is sent again.
pub const RESEND: Duration = Duration::from_millis(300);
/// The longest wait between two tries while nothing is acknowledged.
pub const MAX_RESEND: Duration = Duration::from_millis(2400);
/// Bytes in flight (sent, not yet acknowledged) at most.
pub const WINDOW_BYTES: u64 = 256 * 1024;
/// How often the courier's thread looks for work when nothing wakes it.
const TICK: Duration = Duration::from_millis(20);

#[derive(Debug)]
struct Batch {
    /// Steps first_k..end_k.
    first_k: u64,
    end_k: u64,
    bytes: Arc<Vec<u8>>,
    sent: Option<Instant>,
}

/// What a courier did, for `network.json`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct CourierStats {
    /// Batches handed over by the loop.
    pub batches: u64,
    /// Batches sent again because no acknowledgement came in time.
    pub resent: u64,
    /// Steps dropped unacknowledged because the store was full.
    pub lost_steps: u64,
    /// The most bytes held unacknowledged at once.
    pub peak_held_bytes: u64,
}

#[derive(Debug, Default)]
struct State {
    queue: VecDeque<Batch>,
    /// Steps below this are held by the monitor.
    acked: u64,
    held_steps: u64,
    held_bytes: u64,
    closed: bool,
    stats: CourierStats,
    /// The current resend timeout (see the module docs).
    resend: Duration,
}

/// The store between a control loop and the network (see the module docs).
#[derive(Debug)]
pub struct Courier {
    state: Mutex<State>,
    changed: Condvar,
    capacity_steps: u64,
}

impl Courier {
    pub fn new(capacity_steps: u64) -> Self {
        let state = State { resend: RESEND, ..State::default() };
        Self { state: Mutex::new(state), changed: Condvar::new(), capacity_steps: capacity_steps.max(1) }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The first step the sender can still deliver, with `next_k` the first
    /// step of the batch about to be handed over: everything below the
    /// oldest batch held was acknowledged or dropped (and a restarted
    /// process holds nothing of its predecessor's). Batches carry it so that
    /// the monitor knows which missing steps will never come.
    pub fn available_from(&self, next_k: u64) -> u64 {
        self.lock().queue.front().map_or(next_k, |b| b.first_k)
    }

    /// Hands over the batch of steps first_k..end_k; never waits. Drops the
    /// oldest batches while the store would exceed its capacity.
    pub fn push(&self, first_k: u64, end_k: u64, bytes: Vec<u8>) {
        let mut s = self.lock();
        let steps = end_k.saturating_sub(first_k);
        while !s.queue.is_empty() && s.held_steps + steps > self.capacity_steps {
            if let Some(old) = s.queue.pop_front() {
                let n = old.end_k - old.first_k;
                s.held_steps -= n;
                s.held_bytes -= old.bytes.len() as u64;
                s.stats.lost_steps += n;
            }
        }
        s.held_steps += steps;
        s.held_bytes += bytes.len() as u64;
        s.stats.peak_held_bytes = s.stats.peak_held_bytes.max(s.held_bytes);
        s.stats.batches += 1;
        s.queue.push_back(Batch { first_k, end_k, bytes: Arc::new(bytes), sent: None });
        drop(s);
        self.changed.notify_all();
    }

    /// The monitor holds every step below `next_k`: forget those batches.
    pub fn ack(&self, next_k: u64) {
        let mut s = self.lock();
        // An acknowledgement arrived: the way to the monitor is open again.
        s.resend = RESEND;
        if next_k <= s.acked {
            return;
        }
        s.acked = next_k;
        while s.queue.front().is_some_and(|b| b.end_k <= next_k) {
            if let Some(b) = s.queue.pop_front() {
                s.held_steps -= b.end_k - b.first_k;
                s.held_bytes -= b.bytes.len() as u64;
            }
        }
        drop(s);
        self.changed.notify_all();
    }

    pub fn stats(&self) -> CourierStats {
        self.lock().stats
    }

    /// Steps handed over and not yet acknowledged.
    pub fn unacknowledged_steps(&self) -> u64 {
        self.lock().held_steps
    }

    /// The batches due now, oldest first, marked sent: if the oldest in
    /// flight has waited the resend timeout, everything in flight goes again
    /// (and the timeout doubles until an acknowledgement arrives); then
    /// batches never sent, while the window allows. Waits up to [`TICK`] for
    /// work.
    fn due(&self) -> Option<Vec<Arc<Vec<u8>>>> {
        let mut s = self.lock();
        let mut out = Vec::new();
        for attempt in 0..2 {
            let now = Instant::now();
            let State { queue, resend, stats, .. } = &mut *s;
            if queue.front().and_then(|b| b.sent).is_some_and(|t| now.duration_since(t) >= *resend) {
                for b in queue.iter_mut().take_while(|b| b.sent.is_some()) {
                    b.sent = None;
                    stats.resent += 1;
                }
                *resend = (*resend * 2).min(MAX_RESEND);
            }
            let mut in_flight: u64 = queue.iter().filter(|b| b.sent.is_some()).map(|b| b.bytes.len() as u64).sum();
            for b in queue.iter_mut().filter(|b| b.sent.is_none()) {
                let n = b.bytes.len() as u64;
                if in_flight > 0 && in_flight + n > WINDOW_BYTES {
                    break;
                }
                in_flight += n;
                out.push(b.bytes.clone());
                b.sent = Some(now);
            }
            if !out.is_empty() || (s.closed && s.queue.is_empty()) || attempt == 1 {
                break;
            }
            s = self.changed.wait_timeout(s, TICK).unwrap_or_else(|p| p.into_inner()).0;
        }
        if s.closed && s.queue.is_empty() {
            return None;
        }
        Some(out)
    }

    /// Waits until the monitor has acknowledged everything handed over, at
    /// most `limit`; true if so.
    pub fn drain(&self, limit: Duration) -> bool {
        let began = Instant::now();
        loop {
            if self.lock().queue.is_empty() {
                return true;
            }
            if began.elapsed() >= limit {
                return false;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

/// A courier and the thread that publishes from it with `publish` (which
/// may block on a slow or dead link; the loop never notices).
pub struct Delivery {
    pub courier: Arc<Courier>,
    thread: std::thread::JoinHandle<()>,
}

impl Delivery {
    pub fn start(capacity_steps: u64, publish: impl FnMut(&[u8]) -> Result<(), String> + Send + 'static) -> Self {
        let courier = Arc::new(Courier::new(capacity_steps));
        let c = courier.clone();
        let mut publish = publish;
        let thread = std::thread::spawn(move || {
            while let Some(batches) = c.due() {
                for bytes in batches {
                    // A failed put is like a lost one: sent again after RESEND.
                    let _ = publish(&bytes);
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
            s.queue.clear();
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
    use std::sync::atomic::{AtomicBool, Ordering};

    #[test]
    fn a_full_store_drops_the_oldest_and_says_what_is_still_available() {
        let c = Courier::new(100);
        for i in 0..5u64 {
            c.push(i * 40, (i + 1) * 40, vec![i as u8; 10]);
        }
        // 200 steps held at most 100: batches 0..120 dropped.
        assert_eq!(c.stats().lost_steps, 120, "{:?}", c.stats());
        assert_eq!(c.available_from(200), 120);
        assert_eq!(c.unacknowledged_steps(), 80);
        c.ack(160);
        assert_eq!((c.unacknowledged_steps(), c.available_from(200)), (40, 160));
        c.ack(100); // an old acknowledgement changes nothing
        assert_eq!(c.unacknowledged_steps(), 40);
        c.ack(200);
        assert_eq!(c.available_from(200), 200, "all acknowledged: the next batch is the first available");
    }

    #[test]
    fn unacknowledged_batches_are_sent_again_until_acknowledged() {
        // The link is dead for the first 700 ms: every put fails.
        let link_up = Arc::new(AtomicBool::new(false));
        let delivered = Arc::new(Mutex::new(Vec::<u8>::new()));
        let (up, got) = (link_up.clone(), delivered.clone());
        let d = Delivery::start(1000, move |b| {
            if up.load(Ordering::SeqCst) {
                got.lock().unwrap().push(b[0]);
                Ok(())
            } else {
                Err("down".into())
            }
        });
        let began = Instant::now();
        for i in 0..10u8 {
            d.courier.push(u64::from(i) * 10, u64::from(i + 1) * 10, vec![i]);
        }
        assert!(began.elapsed() < Duration::from_millis(100), "pushing waited {:?}", began.elapsed());
        std::thread::sleep(Duration::from_millis(700));
        link_up.store(true, Ordering::SeqCst);
        // Acknowledge what arrives, as the monitor does.
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(3) {
            let mut got: Vec<u8> = delivered.lock().unwrap().clone();
            got.sort_unstable();
            got.dedup();
            if got.len() == 10 {
                d.courier.ack(100);
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let stats = d.courier.stats();
        assert_eq!(d.finish(Duration::from_secs(1)), 0, "every step acknowledged ({stats:?})");
        assert!(stats.resent >= 10, "the batches lost to the dead link were sent again: {stats:?}");
    }

    #[test]
    fn sending_again_is_windowed_and_backs_off_while_nothing_is_acknowledged() {
        // A dead link for good: count the puts.
        let puts = Arc::new(Mutex::new(Vec::<(Duration, usize)>::new()));
        let p = puts.clone();
        let began = Instant::now();
        let d = Delivery::start(1_000_000, move |b| {
            p.lock().unwrap().push((began.elapsed(), b.len()));
            Err("down".into())
        });
        // 100 batches of 10 kB: four times the window.
        for i in 0..100u64 {
            d.courier.push(i * 50, i * 50 + 50, vec![0; 10 * 1024]);
        }
        std::thread::sleep(Duration::from_millis(2000));
        let log = puts.lock().unwrap().clone();
        let first: usize = log.iter().filter(|(t, _)| *t < Duration::from_millis(150)).count();
        assert_eq!(first as u64, WINDOW_BYTES / (10 * 1024), "the first try sends one window: {first} batches");
        // Tries at 0, 0.3 and 0.9 s (then 2.1 s): three windows in 2 s, not seven.
        let tries = log.len() / first;
        assert!(tries <= 3, "{tries} windows sent in 2 s without an acknowledgement (puts at {:?})", {
            let mut at: Vec<u128> = log.iter().map(|(t, _)| t.as_millis()).collect();
            at.dedup_by(|a, b| a.abs_diff(*b) < 50);
            at
        });
        // An acknowledgement resets the pace and frees the window.
        d.courier.ack(50 * 25);
        std::thread::sleep(Duration::from_millis(150));
        let after = puts.lock().unwrap().len() - log.len();
        assert_eq!(after as u64, WINDOW_BYTES / (10 * 1024), "after the acknowledgement, the next window: {after}");
        d.finish(Duration::from_millis(10));
    }

    #[test]
    fn a_publisher_stuck_for_good_does_not_hold_the_end_of_the_run() {
        let d = Delivery::start(1000, |_| loop {
            std::thread::sleep(Duration::from_secs(60));
        });
        for i in 0..10u64 {
            d.courier.push(i * 5, i * 5 + 5, vec![0; 8]);
        }
        let began = Instant::now();
        let lost = d.finish(Duration::from_millis(200));
        assert!(began.elapsed() < Duration::from_secs(2), "finish waited {:?}", began.elapsed());
        assert_eq!(lost, 50, "ten batches of five steps never acknowledged");
    }
}
