//! Telemetry leaves a control loop through a bounded store, never through a
//! blocking `put`: the loop hands each batch to an [`Outbox`] and goes on; a
//! thread of its own publishes from it, and may wait on a slow or dead link
//! without the loop noticing. The store holds at most [`CAPACITY`] batches
//! (at 1 kHz and 50 steps a batch, 200 s of a follower's telemetry, about
//! 33 MB); past that the oldest batch is dropped and counted.

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// Batches the outbox holds before it drops the oldest.
pub const CAPACITY: usize = 4096;

#[derive(Debug, Default)]
struct State {
    queue: VecDeque<Vec<u8>>,
    closed: bool,
    dropped: u64,
    pushed: u64,
    /// Batches whose publication returned (delivered or failed).
    finished: u64,
    delivered: u64,
}

/// A bounded first-in-first-out store of encoded telemetry batches.
#[derive(Debug)]
pub struct Outbox {
    state: Mutex<State>,
    changed: Condvar,
    capacity: usize,
}

impl Outbox {
    pub fn new(capacity: usize) -> Self {
        Self { state: Mutex::new(State::default()), changed: Condvar::new(), capacity: capacity.max(1) }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Hands a batch over; never waits. Returns false if the oldest batch
    /// had to be dropped to make room.
    pub fn push(&self, bytes: Vec<u8>) -> bool {
        let mut s = self.lock();
        let mut kept = true;
        if s.queue.len() >= self.capacity {
            s.queue.pop_front();
            s.dropped += 1;
            kept = false;
        }
        s.queue.push_back(bytes);
        s.pushed += 1;
        drop(s);
        self.changed.notify_all();
        kept
    }

    /// Batches dropped because the store was full.
    pub fn dropped(&self) -> u64 {
        self.lock().dropped
    }

    /// No more batches will come; the publisher stops once the store is empty.
    pub fn close(&self) {
        self.lock().closed = true;
        self.changed.notify_all();
    }

    /// The next batch to publish, waiting for one; `None` once closed and empty.
    pub fn next(&self) -> Option<Vec<u8>> {
        let mut s = self.lock();
        loop {
            if let Some(b) = s.queue.pop_front() {
                return Some(b);
            }
            if s.closed {
                return None;
            }
            s = self.changed.wait_timeout(s, Duration::from_millis(100)).unwrap_or_else(|p| p.into_inner()).0;
        }
    }

    /// Waits until every batch handed over has been published (or failed),
    /// at most `limit`; true if so.
    pub fn drain(&self, limit: Duration) -> bool {
        let began = Instant::now();
        loop {
            {
                let s = self.lock();
                if s.queue.is_empty() && s.finished + s.dropped == s.pushed {
                    return true;
                }
            }
            if began.elapsed() >= limit {
                return false;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

/// A thread publishing an outbox's batches with `publish` (which may block
/// on a slow or dead link) until the outbox is closed and empty.
pub struct Publishing {
    pub outbox: Arc<Outbox>,
    thread: std::thread::JoinHandle<()>,
}

impl Publishing {
    pub fn start(publish: impl FnMut(Vec<u8>) -> Result<(), String> + Send + 'static) -> Self {
        let outbox = Arc::new(Outbox::new(CAPACITY));
        let o = outbox.clone();
        let mut publish = publish;
        let thread = std::thread::spawn(move || {
            while let Some(b) = o.next() {
                let ok = publish(b).is_ok();
                let mut s = o.lock();
                s.finished += 1;
                s.delivered += u64::from(ok);
            }
        });
        Self { outbox, thread }
    }

    /// Batches handed over but not (yet) published.
    pub fn undelivered(&self) -> u64 {
        let s = self.outbox.lock();
        s.pushed - s.delivered
    }

    /// Waits up to `limit` for every batch to go out, then stops. Returns
    /// the batches not delivered: dropped when full, failed, or still
    /// queued or in flight behind a dead link at the limit (the thread is
    /// then left to the process's exit rather than waited for).
    pub fn finish(self, limit: Duration) -> u64 {
        let emptied = self.outbox.drain(limit);
        {
            let mut s = self.outbox.lock();
            s.queue.clear();
            s.closed = true;
        }
        self.outbox.changed.notify_all();
        let undelivered = self.undelivered();
        if emptied {
            let _ = self.thread.join();
        }
        undelivered
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

    #[test]
    fn a_full_outbox_drops_the_oldest_and_counts_it() {
        let o = Outbox::new(3);
        for i in 0..5u8 {
            o.push(vec![i]);
        }
        assert_eq!(o.dropped(), 2);
        o.close();
        let got: Vec<u8> = std::iter::from_fn(|| o.next()).map(|b| b[0]).collect();
        assert_eq!(got, vec![2, 3, 4]);
    }

    #[test]
    fn the_loop_never_waits_on_a_stuck_publisher() {
        // The publisher blocks until released; the loop pushes 100 batches meanwhile.
        let release = Arc::new(AtomicBool::new(false));
        let published = Arc::new(AtomicUsize::new(0));
        let (r, p) = (release.clone(), published.clone());
        let publishing = Publishing::start(move |_| {
            while !r.load(Ordering::SeqCst) {
                std::thread::sleep(Duration::from_millis(1));
            }
            p.fetch_add(1, Ordering::SeqCst);
            Ok(())
        });
        let began = Instant::now();
        for i in 0..100u8 {
            publishing.outbox.push(vec![i]);
        }
        let pushing = began.elapsed();
        assert!(pushing < Duration::from_millis(500), "pushing took {pushing:?} behind a stuck publisher");
        release.store(true, Ordering::SeqCst);
        assert_eq!(publishing.finish(Duration::from_secs(5)), 0);
        assert_eq!(published.load(Ordering::SeqCst), 100, "every batch is published once the link is back");
    }

    #[test]
    fn a_publisher_stuck_for_good_does_not_hold_the_end_of_the_run() {
        let publishing = Publishing::start(|_| loop {
            std::thread::sleep(Duration::from_secs(60));
        });
        for i in 0..10u8 {
            publishing.outbox.push(vec![i]);
        }
        let began = Instant::now();
        let lost = publishing.finish(Duration::from_millis(200));
        assert!(began.elapsed() < Duration::from_secs(2), "finish waited {:?}", began.elapsed());
        assert_eq!(lost, 10, "one batch in the stuck put and nine queued: all reported");
    }
}
