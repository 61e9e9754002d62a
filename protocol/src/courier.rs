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
//! each try that goes unanswered doubles the time before the next, up to
//! [`MAX_RESEND`]. An acknowledgement that moves forward resets it; so does
//! the first one after a try that heard none (a dead link is back: the
//! monitor sends one every 100 ms). One that arrives but does not move
//! forward does not: the monitor is there but did not get what was sent,
//! because it is behind (its queue full). Resending every 300 ms into it,
//! 150 couriers kept such a monitor full: 12,156 telemetry messages
//! dropped in one run (docs/performance.md).
//!
//! The store is bounded: at most [`CAPACITY_STEPS`] unacknowledged steps
//! (200 s of a follower's telemetry at 1 kHz, about 32 MB). Past that the
//! oldest batch is dropped and counted, and the batches that follow tell
//! the monitor (`available_from`) so that it marks the steps as lost rather
//! than waiting for them.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use crate::Now;

/// Unacknowledged steps the store holds before it drops the oldest batch.
pub const CAPACITY_STEPS: u64 = 200_000;
/// A batch not acknowledged this long after it was sent is sent again.
pub const RESEND: Duration = Duration::from_millis(300);
/// The longest wait between two tries while nothing is acknowledged.
pub const MAX_RESEND: Duration = Duration::from_millis(2400);
/// Bytes in flight (sent, not yet acknowledged) at most.
pub const WINDOW_BYTES: u64 = 256 * 1024;

#[derive(Debug)]
struct Batch {
    /// Steps first_k..end_k.
    first_k: u64,
    end_k: u64,
    bytes: Arc<Vec<u8>>,
    sent: Option<Now>,
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

/// The courier's state and rules without a thread, a lock or a clock:
/// batches are handed over ([`Store::push`]), acknowledged
/// ([`Store::ack`]), and [`Store::due`] says, for the time `now` it is
/// given, which batches to send. Tested in virtual time.
#[derive(Debug)]
pub struct Store {
    queue: VecDeque<Batch>,
    capacity_steps: u64,
    /// Steps below this are held by the monitor.
    acked: u64,
    held_steps: u64,
    held_bytes: u64,
    stats: CourierStats,
    /// The current resend timeout (see the module docs).
    resend: Duration,
    /// An acknowledgement arrived since the last try.
    heard: bool,
    /// The last try that went again heard no acknowledgement at all.
    silent: bool,
}

impl Store {
    pub fn new(capacity_steps: u64) -> Self {
        Self {
            queue: VecDeque::new(),
            capacity_steps: capacity_steps.max(1),
            acked: 0,
            held_steps: 0,
            held_bytes: 0,
            stats: CourierStats::default(),
            resend: RESEND,
            heard: false,
            silent: false,
        }
    }

    /// The first step the sender can still deliver, with `next_k` the first
    /// step of the batch about to be handed over: everything below the
    /// oldest batch held was acknowledged or dropped (and a restarted
    /// process holds nothing of its predecessor's). Batches carry it so that
    /// the monitor knows which missing steps will never come.
    pub fn available_from(&self, next_k: u64) -> u64 {
        self.queue.front().map_or(next_k, |b| b.first_k)
    }

    /// Takes the batch of steps first_k..end_k. Drops the oldest batches
    /// while the store would exceed its capacity.
    pub fn push(&mut self, first_k: u64, end_k: u64, bytes: Vec<u8>) {
        let steps = end_k.saturating_sub(first_k);
        while !self.queue.is_empty() && self.held_steps + steps > self.capacity_steps {
            if let Some(old) = self.queue.pop_front() {
                let n = old.end_k - old.first_k;
                self.held_steps -= n;
                self.held_bytes -= old.bytes.len() as u64;
                self.stats.lost_steps += n;
            }
        }
        self.held_steps += steps;
        self.held_bytes += bytes.len() as u64;
        self.stats.peak_held_bytes = self.stats.peak_held_bytes.max(self.held_bytes);
        self.stats.batches += 1;
        self.queue.push_back(Batch { first_k, end_k, bytes: Arc::new(bytes), sent: None });
    }

    /// The monitor holds every step below `next_k`: forget those batches.
    pub fn ack(&mut self, next_k: u64) {
        // After silence the way to the monitor is open again.
        if std::mem::take(&mut self.silent) {
            self.resend = RESEND;
        }
        self.heard = true;
        if next_k <= self.acked {
            return;
        }
        // Progress: the monitor keeps up again.
        self.resend = RESEND;
        self.acked = next_k;
        while self.queue.front().is_some_and(|b| b.end_k <= next_k) {
            if let Some(b) = self.queue.pop_front() {
                self.held_steps -= b.end_k - b.first_k;
                self.held_bytes -= b.bytes.len() as u64;
            }
        }
    }

    pub fn stats(&self) -> CourierStats {
        self.stats
    }

    /// Steps handed over and not yet acknowledged.
    pub fn unacknowledged_steps(&self) -> u64 {
        self.held_steps
    }

    /// The first step the monitor does not yet hold, as its newest
    /// acknowledgement said (0 before any): it grows while the monitor
    /// keeps up, however slowly.
    pub fn acknowledged(&self) -> u64 {
        self.acked
    }

    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }

    /// Forgets everything held (the end of a run).
    pub fn clear(&mut self) {
        self.queue.clear();
    }

    /// The batches due at `now`, oldest first, marked sent: if the oldest in
    /// flight has waited the resend timeout, everything in flight goes again
    /// (and the timeout doubles until an acknowledgement moves forward, or
    /// one comes after silence); then batches never sent, while the window
    /// allows.
    pub fn due(&mut self, now: Now) -> Vec<Arc<Vec<u8>>> {
        let mut out = Vec::new();
        let Self { queue, resend, stats, heard, silent, .. } = self;
        if queue.front().and_then(|b| b.sent).is_some_and(|t| now.saturating_sub(t) >= *resend) {
            for b in queue.iter_mut().take_while(|b| b.sent.is_some()) {
                b.sent = None;
                stats.resent += 1;
            }
            *resend = (*resend * 2).min(MAX_RESEND);
            *silent = !std::mem::take(heard);
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
        out
    }

    /// Whether a batch waits that was never sent (held back by the window).
    pub fn has_unsent(&self) -> bool {
        self.queue.iter().any(|b| b.sent.is_none())
    }

    /// When the oldest batch in flight is due again (None: nothing in flight).
    pub fn next_resend(&self) -> Option<Now> {
        self.queue.front().and_then(|b| b.sent).map(|t| t + self.resend)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Virtual time: `t0 + ms`.
    fn at(t0: Now, ms: u64) -> Now {
        t0 + Duration::from_millis(ms)
    }

    #[test]
    fn a_full_store_drops_the_oldest_and_says_what_is_still_available() {
        let mut c = Store::new(100);
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

    /// A link dead for 700 ms loses every put; what it lost is sent again
    /// once the resend timeout passes, until acknowledged.
    #[test]
    fn unacknowledged_batches_are_sent_again_until_acknowledged() {
        let t0 = Now::ZERO;
        let mut c = Store::new(1000);
        for i in 0..10u64 {
            c.push(i * 10, (i + 1) * 10, vec![i as u8]);
        }
        let mut delivered = std::collections::BTreeSet::new();
        // Every 20 ms the sender asks what is due; the link is up from 700 ms.
        for ms in (0..3000).step_by(20) {
            for b in c.due(at(t0, ms)) {
                if ms >= 700 {
                    delivered.insert(b[0]);
                }
            }
            if delivered.len() == 10 {
                c.ack(100);
                break;
            }
        }
        let stats = c.stats();
        assert_eq!(c.unacknowledged_steps(), 0, "every step acknowledged ({stats:?}, delivered {delivered:?})");
        assert!(stats.resent >= 10, "the batches lost to the dead link were sent again: {stats:?}");
        assert_eq!(c.next_resend(), None, "nothing left in flight");
        assert!(!c.has_unsent(), "nothing waits to be sent");
    }

    #[test]
    fn sending_again_is_windowed_and_backs_off_while_nothing_is_acknowledged() {
        let t0 = Now::ZERO;
        let mut c = Store::new(1_000_000);
        // 100 batches of 10 kB: four times the window.
        for i in 0..100u64 {
            c.push(i * 50, i * 50 + 50, vec![0; 10 * 1024]);
        }
        let window = (WINDOW_BYTES / (10 * 1024)) as usize;
        // A dead link for good: which milliseconds send how many batches.
        let mut tries = Vec::new();
        for ms in (0..5000).step_by(10) {
            let n = c.due(at(t0, ms)).len();
            if n > 0 {
                tries.push((ms, n));
            }
        }
        // One window at 0, then again after 0.3, 0.6, 1.2, 2.4 and 2.4 s.
        assert_eq!(tries, vec![(0, window), (300, window), (900, window), (2100, window), (4500, window)]);
        assert_eq!(c.next_resend(), Some(at(t0, 4500) + MAX_RESEND), "the timeout stops doubling at MAX_RESEND");
        assert!(c.has_unsent(), "batches wait behind the window (the courier's thread is woken for them)");
        // An acknowledgement resets the pace and frees the window.
        c.ack(50 * 25);
        assert_eq!(c.due(at(t0, 4510)).len(), window, "after the acknowledgement, the next window at once");
        assert_eq!(c.next_resend(), Some(at(t0, 4510) + RESEND), "and the resend timeout is back to RESEND");
    }

    /// The tries of 100 batches of 10 kB over 5 s, with `ack(ms)` asked
    /// every 100 ms for an acknowledgement to deliver.
    fn tries(c: &mut Store, ack: impl Fn(u64) -> Option<u64>) -> Vec<(u64, usize)> {
        for i in 0..100u64 {
            c.push(i * 50, i * 50 + 50, vec![0; 10 * 1024]);
        }
        let mut tries = Vec::new();
        for ms in (0..5000).step_by(10) {
            if let Some(k) = ack(ms).filter(|_| ms % 100 == 50) {
                c.ack(k);
            }
            let n = c.due(at(Now::ZERO, ms)).len();
            if n > 0 {
                tries.push((ms, n));
            }
        }
        tries
    }

    /// A monitor that is there (it acknowledges every 100 ms) but behind
    /// (what it acknowledges does not move): the tries back off as for a
    /// dead link, instead of every 300 ms.
    #[test]
    fn acknowledgements_that_do_not_move_forward_leave_the_tries_backing_off() {
        let mut c = Store::new(1_000_000);
        let window = (WINDOW_BYTES / (10 * 1024)) as usize;
        let tries = tries(&mut c, |_| Some(0));
        assert_eq!(tries, vec![(0, window), (300, window), (900, window), (2100, window), (4500, window)]);
    }

    /// A dead link that comes back: the first acknowledgement after the
    /// silence, though it does not move forward (what was sent was lost),
    /// resets the pace: the next try 300 ms after the last, not 2.4 s.
    #[test]
    fn the_first_acknowledgement_after_silence_resets_the_pace() {
        let mut c = Store::new(1_000_000);
        let window = (WINDOW_BYTES / (10 * 1024)) as usize;
        // Dead until 2.2 s; from then on the monitor acknowledges, without progress.
        let tries = tries(&mut c, |ms| (ms >= 2200).then_some(0));
        assert_eq!(
            tries,
            vec![
                (0, window),
                (300, window),
                (900, window),
                (2100, window),
                (2400, window),
                (3000, window),
                (4200, window)
            ],
            "the acknowledgement at 2.25 s after a silent try brings the next one to 2.4 s (not 4.5 s); then, no \
             progress, the tries back off again"
        );
    }
}
