//! How long a node has waited, counted so that being slow is not taken for
//! being gone. A limit on a wait ("no answer within 5 s", "no progress for
//! 60 s") is a guess that the one waited for is gone; on a loaded or slow
//! machine the waiting node itself may not have been run for seconds, and
//! the wall time that passed meanwhile says nothing of the other. So a wait
//! counts only the time its node was awake to watch: a node that waits
//! looks again at least every `every` while it is scheduled, and a gap
//! between two looks longer than `cap` (twice `every`) is time the node was
//! not run: it counts as `cap`. And a sign of life from the one waited for
//! (any message of it, a repeat of an old step included) starts the count
//! again: a peer that speaks is slow, not gone.

use std::time::Duration;

use crate::Now;

/// Time waited, as this module counts it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Patience {
    /// The previous look.
    last: Now,
    /// Counted so far, up to `last`.
    counted: Duration,
    /// The most one gap between looks counts.
    cap: Duration,
    /// The signs of life seen at the previous look ([`Patience::alive`]).
    signs: u64,
}

impl Patience {
    /// A wait begun at `now` by a node that looks again at least every
    /// `every` while it runs.
    pub fn new(now: Now, every: Duration) -> Self {
        Self { last: now, counted: Duration::ZERO, cap: every * 2, signs: 0 }
    }

    /// The time counted at `now`, without looking.
    pub fn waited(&self, now: Now) -> Duration {
        self.counted + now.saturating_sub(self.last).min(self.cap)
    }

    /// Looks at `now`: the time counted.
    pub fn look(&mut self, now: Now) -> Duration {
        self.counted = self.waited(now);
        self.last = now;
        self.counted
    }

    /// `signs`: a count of what the ones waited for sent (any message),
    /// growing while they live. A count other than at the previous look
    /// starts the wait again at `now`; the same count changes nothing.
    pub fn alive(&mut self, now: Now, signs: u64) {
        if signs != self.signs {
            self.signs = signs;
            self.counted = Duration::ZERO;
            self.last = now;
        }
    }

    /// When the wait, not looked at again, would have counted `limit`: the
    /// latest a node must look (its next wake-up for the limit).
    pub fn reaches(&self, limit: Duration) -> Now {
        self.last + limit.saturating_sub(self.counted).min(self.cap.max(Duration::from_nanos(1)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EVERY: Duration = Duration::from_millis(100);

    fn ms(m: u64) -> Now {
        Now::from_millis(m)
    }

    #[test]
    fn a_node_that_looks_on_time_counts_the_wall_time() {
        let mut p = Patience::new(ms(0), EVERY);
        for m in (100..=5_000).step_by(100) {
            p.look(ms(m));
        }
        assert_eq!(p.look(ms(5_000)), Duration::from_secs(5));
        // A look a little late (150 ms after the last) counts whole.
        assert_eq!(p.look(ms(5_150)), Duration::from_millis(5_150));
    }

    #[test]
    fn a_node_not_run_for_seconds_counts_only_the_cap_of_that_gap() {
        let mut p = Patience::new(ms(0), EVERY);
        p.look(ms(100));
        // Starved for 30 s: the gap counts 200 ms, not 30 s.
        assert_eq!(p.look(ms(30_100)), Duration::from_millis(300));
        assert_eq!(p.waited(ms(30_150)), Duration::from_millis(350), "without looking");
    }

    #[test]
    fn a_sign_of_life_starts_the_count_again_and_the_same_count_does_not() {
        let mut p = Patience::new(ms(0), EVERY);
        for m in (100..=3_000).step_by(100) {
            p.look(ms(m));
        }
        p.alive(ms(3_000), 0);
        assert_eq!(p.waited(ms(3_000)), Duration::from_secs(3), "no new sign: the same count");
        p.alive(ms(3_000), 7);
        assert_eq!(p.waited(ms(3_100)), Duration::from_millis(100), "counted again from the sign");
        p.alive(ms(3_100), 7);
        assert_eq!(p.look(ms(3_200)), Duration::from_millis(200));
    }

    #[test]
    fn the_next_look_is_due_when_the_limit_or_the_cap_is_reached() {
        let mut p = Patience::new(ms(0), EVERY);
        assert_eq!(p.reaches(Duration::from_secs(5)), ms(200), "the cap first: look at least every cap");
        for m in (100..=4_900).step_by(100) {
            p.look(ms(m));
        }
        assert_eq!(p.reaches(Duration::from_secs(5)), ms(5_000));
    }
}
