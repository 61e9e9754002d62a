//! Per link, what the receiver measures of each source's messages: their
//! one-way latency (its receipt minus the sender's stamp, both on the run's
//! timebase, so across hosts whose clocks disagree) and their age when used
//! (real time: the receiver's step minus the step of the message it used).
//! Bounded memory and no allocation per message: a log-linear histogram.

use serde::{Deserialize, Serialize};

/// Values below this are counted exactly; above, 8 buckets per doubling
/// (a percentile is off by at most 12.5 %).
const EXACT: u64 = 64;
const PER_DOUBLING: u64 = 8;
const BUCKETS: usize = (EXACT + PER_DOUBLING * (64 - 6)) as usize;

/// Counts of non-negative integers in bounded memory.
#[derive(Clone, Debug)]
pub struct Histogram {
    counts: Box<[u64; BUCKETS]>,
    n: u64,
    max: u64,
}

impl Default for Histogram {
    fn default() -> Self {
        Self { counts: Box::new([0; BUCKETS]), n: 0, max: 0 }
    }
}

fn bucket(v: u64) -> usize {
    if v < EXACT {
        return v as usize;
    }
    let log = 63 - u64::from(v.leading_zeros()); // ≥ 6
    let mantissa = (v >> (log - 3)) & (PER_DOUBLING - 1);
    (EXACT + (log - 6) * PER_DOUBLING + mantissa) as usize
}

/// The smallest value of a bucket.
fn floor(b: usize) -> u64 {
    let b = b as u64;
    if b < EXACT {
        return b;
    }
    let (log, mantissa) = (6 + (b - EXACT) / PER_DOUBLING, (b - EXACT) % PER_DOUBLING);
    (1 << log) | (mantissa << (log - 3))
}

impl Histogram {
    pub fn record(&mut self, v: u64) {
        self.counts[bucket(v).min(BUCKETS - 1)] += 1;
        self.n += 1;
        self.max = self.max.max(v);
    }

    pub fn count(&self) -> u64 {
        self.n
    }

    pub fn max(&self) -> u64 {
        self.max
    }

    /// The q-quantile (0 ≤ q ≤ 1): the smallest value of the bucket that
    /// holds it (never above the maximum); 0 when empty.
    pub fn quantile(&self, q: f64) -> u64 {
        if self.n == 0 {
            return 0;
        }
        let rank = ((q.clamp(0.0, 1.0) * self.n as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (b, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return floor(b).min(self.max);
            }
        }
        self.max
    }

    /// (p50, p99, max).
    pub fn summary(&self) -> [u64; 3] {
        [self.quantile(0.5), self.quantile(0.99), self.max]
    }
}

/// One source's messages at one receiver.
#[derive(Clone, Debug, Default)]
pub struct LinkMeter {
    /// One-way latency, µs.
    pub latency_us: Histogram,
    /// Age at use, steps.
    pub age_steps: Histogram,
}

/// What `network.json` says of one link (source → this node).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LinkStats {
    /// The sender (0: the leader).
    pub source: u32,
    /// Messages whose latency was measured.
    pub messages: u64,
    /// One-way latency, µs: p50, p99, max.
    pub latency_us: [u64; 3],
    /// Steps that used one of its messages (real time).
    pub uses: u64,
    /// Age at use, steps: p50, p99, max.
    pub age_steps: [u64; 3],
    /// Real time: messages on the source's key that came from a second
    /// sender (see `inbox::Twin`).
    #[serde(default)]
    pub twin_messages: u64,
    /// The receiver's step when it flagged the source as twinned.
    #[serde(default)]
    pub twin_since: Option<u64>,
}

impl LinkMeter {
    /// The latency of a message stamped `sent_ns` and received at `now_ns`
    /// (both on the run's timebase); unstamped ones are not counted, and an
    /// arrival the clocks' uncertainty puts before its sending counts 0.
    pub fn received(&mut self, sent_ns: i64, now_ns: i64) {
        if sent_ns > 0 {
            self.latency_us.record((now_ns - sent_ns).max(0) as u64 / 1_000);
        }
    }

    pub fn stats(&self, source: u32) -> LinkStats {
        LinkStats {
            source,
            messages: self.latency_us.count(),
            latency_us: self.latency_us.summary(),
            uses: self.age_steps.count(),
            age_steps: self.age_steps.summary(),
            twin_messages: 0,
            twin_since: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_are_exact_below_64_and_within_an_eighth_above() {
        for v in [0, 1, 63, 64, 65, 100, 1_000, 123_456, 1 << 40, u64::MAX] {
            let f = floor(bucket(v));
            assert!(f <= v, "{v}: floor {f}");
            if v < EXACT {
                assert_eq!(f, v);
            } else {
                assert!((v - f) as f64 <= v as f64 / 8.0, "{v}: floor {f}");
            }
        }
        assert_eq!(bucket(u64::MAX), BUCKETS - 1);
    }

    #[test]
    fn percentiles_of_a_known_set() {
        let mut h = Histogram::default();
        assert_eq!(h.summary(), [0, 0, 0]);
        for v in 1..=1000u64 {
            h.record(v);
        }
        let [p50, p99, max] = h.summary();
        assert!((448..=500).contains(&p50), "p50 {p50}");
        assert!((896..=990).contains(&p99), "p99 {p99}");
        assert_eq!(max, 1000);
        assert_eq!(h.count(), 1000);
    }

    #[test]
    fn a_link_counts_stamped_messages_and_clamps_what_the_clocks_put_before_sending() {
        let mut m = LinkMeter::default();
        m.received(0, 5_000_000);
        m.received(1_000_000, 1_020_000);
        m.received(2_000_000, 1_999_000);
        m.age_steps.record(1);
        let s = m.stats(3);
        assert_eq!((s.source, s.messages, s.uses), (3, 2, 1));
        assert_eq!(s.latency_us, [0, 20, 20]);
        assert_eq!(s.age_steps, [1, 1, 1]);
    }
}
