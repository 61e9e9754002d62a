//! Real-time pacing of a node's loop on the run's timebase (the leader's);
//! the timing figures it gathers are [`formation_protocol::loop_timing`]'s.

pub use formation_protocol::loop_timing::*;

use std::time::{Duration, Instant};

use crate::barrier::Start;
use crate::clock::Timebase;

/// Real-time pacing: step k is due when the run's timebase reads
/// epoch + k Δt / time_scale, on this node's monotonic clock through its
/// estimate of the timebase (which follows the clocks' drift).
pub struct Pacer {
    timebase: Timebase,
    /// The epoch on the timebase (ns).
    epoch_ns: i64,
    period: Duration,
    /// The last step's due instant (used should the estimate be missing).
    due: Instant,
    /// Wake-up timing, in bounded memory whatever the run's length.
    timer: LoopTimer,
}

impl Pacer {
    pub fn new(start: &Start, dt_s: f64, timebase: Timebase) -> Self {
        let period = Duration::from_secs_f64(dt_s / start.scale());
        let epoch_ns = start.epoch_unix_ns as i64;
        let due = timebase.instant_at(epoch_ns).unwrap_or_else(Instant::now);
        Self { timebase, epoch_ns, period, due, timer: LoopTimer::new(period.as_secs_f64()) }
    }

    /// Sleeps until step k is due and records the wake-up.
    pub fn wait(&mut self, k: u64) {
        let at = self.epoch_ns.saturating_add((self.period.as_nanos() as i64).saturating_mul(k as i64));
        self.due = self.timebase.instant_at(at).unwrap_or(self.due);
        let now = Instant::now();
        if self.due > now {
            std::thread::sleep(self.due - now);
        }
        // Lateness against the step's own due instant.
        let late = Instant::now().saturating_duration_since(self.due).as_secs_f64();
        self.timer.push(k, k as f64 * self.period.as_secs_f64() + late);
    }

    pub fn stats(&self) -> LoopStats {
        self.timer.stats()
    }
}
