//! Control-loop timing: how late each real-time step woke up, in bounded
//! memory, and the percentiles `network.json` reports.

use serde::{Deserialize, Serialize};

/// Control-loop timing of a real-time node (µs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LoopStats {
    /// |actual period − nominal period|: p50, p99, max.
    pub period_error_p50_us: f64,
    pub period_error_p99_us: f64,
    pub period_error_max_us: f64,
    /// Wake-up after the step's due time: p50, p99, max.
    pub lateness_p50_us: f64,
    pub lateness_p99_us: f64,
    pub lateness_max_us: f64,
    pub steps: u64,
}

impl LoopStats {
    /// From the wake-up times (s since the epoch) of consecutive steps.
    pub fn from_wakeups(wake_s: &[f64], period_s: f64) -> Self {
        let mut period_err: Vec<f64> = wake_s.windows(2).map(|w| ((w[1] - w[0]) - period_s).abs() * 1e6).collect();
        let mut late: Vec<f64> =
            wake_s.iter().enumerate().map(|(k, w)| (w - k as f64 * period_s).max(0.0) * 1e6).collect();
        let (p50, p99, max) = percentiles(&mut period_err);
        let (l50, l99, lmax) = percentiles(&mut late);
        Self {
            period_error_p50_us: p50,
            period_error_p99_us: p99,
            period_error_max_us: max,
            lateness_p50_us: l50,
            lateness_p99_us: l99,
            lateness_max_us: lmax,
            steps: wake_s.len() as u64,
        }
    }
}

/// Control-loop timing gathered step by step in bounded memory: every sample
/// while few, then an evenly thinned subset (for the percentiles; the
/// maxima and the step count stay exact), so a run of any length fits.
#[derive(Clone, Debug)]
pub struct LoopTimer {
    period_s: f64,
    prev: Option<f64>,
    n: u64,
    /// Every `stride`-th step is kept.
    stride: u64,
    period_err: Vec<f64>,
    late: Vec<f64>,
    max_err: f64,
    max_late: f64,
}

impl LoopTimer {
    /// Samples kept (per quantity) before thinning.
    pub const CAP: usize = 1 << 16;

    pub fn new(period_s: f64) -> Self {
        Self {
            period_s,
            prev: None,
            n: 0,
            stride: 1,
            period_err: Vec::new(),
            late: Vec::new(),
            max_err: 0.0,
            max_late: 0.0,
        }
    }

    /// The wake-up of step k (s since the epoch).
    pub fn push(&mut self, k: u64, wake_s: f64) {
        let late = (wake_s - k as f64 * self.period_s).max(0.0) * 1e6;
        let err = self.prev.map(|p| ((wake_s - p) - self.period_s).abs() * 1e6);
        self.max_late = self.max_late.max(late);
        if let Some(e) = err {
            self.max_err = self.max_err.max(e);
        }
        if self.n % self.stride == 0 {
            self.late.push(late);
            if let Some(e) = err {
                self.period_err.push(e);
            }
            if self.late.len() >= Self::CAP {
                for v in [&mut self.late, &mut self.period_err] {
                    let mut i = 0;
                    v.retain(|_| {
                        i += 1;
                        i % 2 == 1
                    });
                }
                self.stride *= 2;
            }
        }
        self.n += 1;
        self.prev = Some(wake_s);
    }

    pub fn stats(&self) -> LoopStats {
        let (p50, p99, _) = percentiles(&mut self.period_err.clone());
        let (l50, l99, _) = percentiles(&mut self.late.clone());
        LoopStats {
            period_error_p50_us: p50,
            period_error_p99_us: p99,
            period_error_max_us: self.max_err,
            lateness_p50_us: l50,
            lateness_p99_us: l99,
            lateness_max_us: self.max_late,
            steps: self.n,
        }
    }
}

/// (p50, p99, max) of a sample set (sorted in place); zeros if empty.
pub fn percentiles(v: &mut [f64]) -> (f64, f64, f64) {
    if v.is_empty() {
        return (0.0, 0.0, 0.0);
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    (at(0.5), at(0.99), v[v.len() - 1])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loop_timer_matches_the_exact_stats_and_stays_bounded() {
        let wake: Vec<f64> = (0..1000).map(|k| k as f64 * 1e-3 + if k % 10 == 0 { 2e-5 } else { 0.0 }).collect();
        let mut t = LoopTimer::new(1e-3);
        for (k, w) in wake.iter().enumerate() {
            t.push(k as u64, *w);
        }
        let (a, b) = (t.stats(), LoopStats::from_wakeups(&wake, 1e-3));
        assert_eq!(a.steps, b.steps);
        for (x, y) in [
            (a.period_error_p50_us, b.period_error_p50_us),
            (a.period_error_p99_us, b.period_error_p99_us),
            (a.period_error_max_us, b.period_error_max_us),
            (a.lateness_p99_us, b.lateness_p99_us),
            (a.lateness_max_us, b.lateness_max_us),
        ] {
            assert!((x - y).abs() < 1e-6, "{x} vs {y}");
        }
        let mut t = LoopTimer::new(1e-3);
        for k in 0..(LoopTimer::CAP as u64 * 5) {
            t.push(k, k as f64 * 1e-3);
        }
        assert!(t.late.len() < LoopTimer::CAP && t.period_err.len() < LoopTimer::CAP);
        assert_eq!(t.stats().steps, LoopTimer::CAP as u64 * 5);
    }

    #[test]
    fn loop_stats_of_a_perfect_loop_are_zero() {
        let wake: Vec<f64> = (0..100).map(|k| k as f64 * 1e-3).collect();
        let s = LoopStats::from_wakeups(&wake, 1e-3);
        assert!(s.period_error_max_us < 1e-6 && s.lateness_max_us < 1e-6);
    }
}
