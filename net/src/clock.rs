//! The one place a node reads the wall clock: the run's epoch is a Unix
//! time (the leader's [`Start`]), which each node turns into an instant of
//! its own monotonic clock once, at the start.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use crate::barrier::Start;

/// Nanoseconds since the Unix epoch on this host's wall clock (0 for a
/// clock set before 1970).
pub fn unix_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_nanos() as u64).unwrap_or(0)
}

/// The run's epoch as an instant of this process's monotonic clock.
pub fn epoch_instant(start: &Start) -> Instant {
    let now_i = Instant::now();
    let now_ns = unix_ns();
    if start.epoch_unix_ns >= now_ns {
        now_i + Duration::from_nanos(start.epoch_unix_ns - now_ns)
    } else {
        now_i.checked_sub(Duration::from_nanos(now_ns - start.epoch_unix_ns)).unwrap_or(now_i)
    }
}
