//! The lock-step gate's rules, shared by the leader and the agents: how far
//! the leader may run ahead, when a wait is reported, and which of the
//! messages a node has published it repeats for neighbours that are
//! behind, and when a waiting node repeats, warns or gives up ([`Wait`]).
//! Plain data, no IO and no clock: the nodes tell it the time and ask it
//! what to send.

use std::collections::VecDeque;
use std::time::Duration;

use crate::patience::Patience;
use crate::Now;

use crate::inbox::LOCKSTEP_AHEAD;

/// How many steps the leader may run ahead of the slowest follower that
/// hears it.
pub const WINDOW: u64 = 200;

/// A wait this long for one step's inputs is reported once on stderr (the
/// stall timeout ends it).
pub const STALL_WARNING: Duration = Duration::from_secs(5);

/// How many of its last messages a waiting follower repeats at least.
/// Without faults neighbours are at most one step apart, so a restarted
/// neighbour, which resumes one step before the least advanced of them, may
/// need a message two steps behind the most advanced one's newest.
pub const REPEATED: usize = LOCKSTEP_AHEAD as usize + 1;

/// How many published messages a follower keeps for neighbours that are
/// behind. The fault table lets a node run ahead of a neighbour whose
/// messages to it the table removes (it does not wait for them), by as many
/// steps as the table removes in a row: 30 % loss removes 5 in a row once
/// in 400 steps. A neighbour further behind than this is not helped and
/// ends at its stall timeout, naming us.
pub const FOLLOWER_KEPT: usize = 256;

/// At most this many messages a follower repeats from its slowest
/// neighbour's step in one round (100 ms).
pub const REPEAT_BURST: usize = 64;

/// How many messages the leader keeps: the window and the steps a follower
/// may be ahead.
pub const LEADER_KEPT: usize = WINDOW as usize + 1 + LOCKSTEP_AHEAD as usize;

/// The first step the leader repeats while the slowest hearing follower has
/// published `slowest`. A killed follower may have delivered its last
/// messages to the leader and not yet to its neighbours; restarted, it
/// resumes one step before the least advanced of them, which can be
/// [`LOCKSTEP_AHEAD`] steps before what the leader heard from it.
pub fn leader_from_step(slowest: u64) -> u64 {
    slowest.saturating_sub(LOCKSTEP_AHEAD)
}

/// Lock-step, the leader's window rule (the one place it is written): the
/// step every follower that hears the leader must have published before
/// the leader publishes step `k` (None: no wait, k is within the window).
pub fn leader_needs(k: u64) -> Option<u64> {
    k.checked_sub(WINDOW)
}

/// Lock-step: whether every hearing follower, by the newest step heard from
/// each (None: not heard yet), has reached `need`. True with no hearing
/// follower (nobody to wait for).
pub fn window_open(reached: &[Option<u64>], need: u64) -> bool {
    reached.iter().all(|r| r.is_some_and(|s| s >= need))
}

/// The newest step the slowest hearing follower has published (0 for one
/// not heard yet), for what the leader says and repeats.
pub fn slowest_step(reached: &[Option<u64>]) -> u64 {
    reached.iter().map(|r| r.unwrap_or(0)).min().unwrap_or(0)
}

/// Lock-step: where a restarted follower resumes, from the furthest step
/// heard from each neighbour (None: not heard) a moment after it joined.
/// Waiting neighbours repeat their last messages every 100 ms, so one heard
/// well past step 0 (beyond [`LOCKSTEP_AHEAD`] + 2) means the run is under
/// way: resume one step before the least advanced of them (adopt from their
/// messages of that step, and publish the message they wait for). 0 for a
/// run that is only starting. (A follower that hears the leader also needs
/// the leader's messages from there on: the leader keeps [`WINDOW`] steps
/// and repeats what the slowest follower lacks.)
pub fn resume_step(heard: &[Option<u64>]) -> u64 {
    let ahead = LOCKSTEP_AHEAD + 2;
    if !heard.iter().flatten().any(|&k| k > ahead) {
        return 0;
    }
    heard.iter().flatten().min().copied().unwrap_or(1).saturating_sub(1)
}

/// The last messages a node has published, by step, oldest first, at most
/// a fixed number of them.
pub struct Kept {
    capacity: usize,
    messages: VecDeque<(u64, Vec<u8>)>,
}

impl Kept {
    pub fn new(capacity: usize) -> Self {
        Self { capacity: capacity.max(1), messages: VecDeque::with_capacity(capacity.max(1)) }
    }

    /// Keeps the message of `step`, forgetting the oldest when full.
    pub fn push(&mut self, step: u64, bytes: Vec<u8>) {
        if self.messages.len() == self.capacity {
            self.messages.pop_front();
        }
        self.messages.push_back((step, bytes));
    }

    pub fn len(&self) -> usize {
        self.messages.len()
    }

    pub fn is_empty(&self) -> bool {
        self.messages.is_empty()
    }

    /// What a waiting follower repeats, oldest first: its last [`REPEATED`],
    /// and up to [`REPEAT_BURST`] from `slowest`, the step the least
    /// advanced neighbour waits for (the step of its newest message).
    pub fn follower_repeats(&self, slowest: Option<u64>) -> impl Iterator<Item = &Vec<u8>> {
        let newest = self.messages.back().map_or(0, |m| m.0);
        let last = newest.saturating_sub(REPEATED as u64 - 1);
        let from = slowest.map_or(last, |m| m.min(last));
        let burst = from.saturating_add(REPEAT_BURST as u64);
        self.messages.iter().filter(move |m| m.0 >= last || (m.0 >= from && m.0 < burst)).map(|m| &m.1)
    }

    /// What the leader repeats while the slowest hearing follower has
    /// published `slowest`: every kept message from [`leader_from_step`] on.
    pub fn leader_repeats(&self, slowest: u64) -> impl Iterator<Item = &Vec<u8>> {
        let from = leader_from_step(slowest);
        self.messages.iter().filter(move |m| m.0 >= from).map(|m| &m.1)
    }
}

/// A follower waiting for its step's inputs repeats what its neighbours
/// may lack this often.
pub const FOLLOWER_REPEAT_EVERY: Duration = Duration::from_millis(100);

/// The leader waiting for its window repeats this often.
pub const LEADER_REPEAT_EVERY: Duration = Duration::from_millis(200);

/// How long the leader waits for its window before it gives up.
pub const LEADER_STALL: Duration = Duration::from_secs(60);

/// After its last step a node repeats this often what a neighbour may still
/// wait for.
pub const LINGER_REPEAT_EVERY: Duration = Duration::from_millis(200);

/// Lock-step linger: how often a node looks whether the others have
/// reported their final step (it learns it from telemetry, which does not
/// wake its machine).
pub const LINGER_LOOK_EVERY: Duration = Duration::from_millis(10);

/// Real time: when step `k` is due on the run's timebase, `epoch + k × period`.
pub fn due(epoch: Now, period: Duration, k: u64) -> Now {
    epoch + Duration::from_nanos((period.as_nanos() as u64).saturating_mul(k))
}

/// What a waiting node does at a moment of its wait.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WaitStep {
    /// Go on waiting; `repeat`: say again what the others may lack;
    /// `warn`: report the wait once (it has lasted [`STALL_WARNING`]).
    Wait { repeat: bool, warn: bool },
    /// The wait has lasted its limit: give up (a lock-step wait), or stop
    /// lingering.
    Over,
}

/// One lock-step wait, by the clock the node passes in: a follower's for
/// its step's inputs, the leader's for its window, or either's linger
/// after its last step. Repeats come on the wait's own clock, not only
/// after a quiet period: nodes that keep waking each other with their
/// repeats would otherwise never repeat anything. Its limit counts only the
/// time the node was awake to watch, from the last sign of life of those
/// it waits for ([`Patience`]): slow is not gone.
#[derive(Clone, Debug)]
pub struct Wait {
    patience: Patience,
    said: Now,
    every: Duration,
    limit: Duration,
    warned: bool,
}

impl Wait {
    /// A wait begun at `now` that repeats `every` and is over after `limit`.
    pub fn new(now: Now, every: Duration, limit: Duration) -> Self {
        Self { patience: Patience::new(now, every), said: now, every, limit, warned: false }
    }

    /// How long it has waited at `now`, as [`Patience`] counts it.
    pub fn waited(&self, now: Now) -> Duration {
        self.patience.waited(now)
    }

    /// `signs`: what those waited for have sent so far (a count that grows
    /// while they live, [`crate::inbox::Inbox::signs_of_life`]); a new
    /// count starts the wait's limit again.
    pub fn alive(&mut self, now: Now, signs: u64) {
        self.patience.alive(now, signs);
    }

    /// When the wait next has something to do: its next repeat, or its end.
    pub fn next_wake(&self) -> Now {
        (self.said + self.every).min(self.patience.reaches(self.limit) + Duration::from_nanos(1))
    }

    /// What to do at `now`.
    pub fn poll(&mut self, now: Now) -> WaitStep {
        let waited = self.patience.look(now);
        if waited > self.limit {
            return WaitStep::Over;
        }
        let warn = !self.warned && waited > STALL_WARNING;
        self.warned |= warn;
        let repeat = now.saturating_sub(self.said) >= self.every;
        if repeat {
            self.said = now;
        }
        WaitStep::Wait { repeat, warn }
    }
}

/// Where a node's machine is (the leader's and a follower's alike).
#[derive(Clone, Debug)]
pub enum Phase {
    /// Before the start: messages are kept, nothing steps.
    Waiting,
    /// Doing step k when it is due (real time) or when what it needs is in
    /// (lock-step).
    Stepping(u64),
    /// Lock-step, after the last step: repeating the last messages until
    /// the others report their final step, for a bounded time.
    Lingering(Wait),
    /// The end: Ok, or why the run failed.
    Done(Result<(), String>),
}

impl Phase {
    /// The end of the run: None while it runs; Err says why it failed.
    pub fn outcome(&self) -> Option<&Result<(), String>> {
        match self {
            Phase::Done(r) => Some(r),
            _ => None,
        }
    }

    /// The step being done (or waited for).
    pub fn step(&self) -> Option<u64> {
        match self {
            Phase::Stepping(k) => Some(*k),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The leader's window: it publishes step k once every follower that
    /// hears it has published step k − WINDOW; a one-step change of the
    /// rule either way fails here.
    #[test]
    fn the_leader_waits_for_the_followers_exactly_one_window_behind() {
        assert_eq!(leader_needs(WINDOW - 1), None, "inside the first window: no wait");
        let k = WINDOW + 7;
        let need = leader_needs(k).expect("a wait");
        assert_eq!(need, 7);
        assert!(window_open(&[Some(k), Some(need)], need), "the slowest exactly one window behind");
        assert!(!window_open(&[Some(k), Some(need - 1)], need), "one step more behind");
        assert!(!window_open(&[Some(k), None], need), "one not heard yet");
        assert!(window_open(&[], need), "nobody hears the leader");
        assert_eq!(slowest_step(&[Some(9), None]), 0);
    }

    fn steps<'a>(it: impl Iterator<Item = &'a Vec<u8>>) -> Vec<u64> {
        it.map(|b| u64::from(b[0]) + 256 * u64::from(b[1])).collect()
    }

    fn follower_steps(s: &Kept, heard: &[Option<u64>]) -> Vec<u64> {
        let slowest = heard.iter().flatten().copied().min();
        steps(s.follower_repeats(slowest))
    }

    fn kept(capacity: usize, upto: u64) -> Kept {
        let mut s = Kept::new(capacity);
        for k in 0..=upto {
            s.push(k, vec![(k % 256) as u8, (k / 256) as u8]);
        }
        s
    }

    /// The fault table let us run ahead of a neighbour: what it waits for is
    /// repeated, not only our last messages (a lock-step run stalled on
    /// this under 30 % loss).
    #[test]
    fn a_neighbour_left_behind_gets_the_message_it_waits_for() {
        let s = kept(FOLLOWER_KEPT, 5272);
        assert_eq!(follower_steps(&s, &[Some(5269), Some(5272)]), vec![5269, 5270, 5271, 5272]);
        assert_eq!(follower_steps(&s, &[None, None]), vec![5270, 5271, 5272], "nobody heard: the last {REPEATED}");
        assert_eq!(follower_steps(&s, &[Some(5273)]), vec![5270, 5271, 5272], "a neighbour ahead");
    }

    #[test]
    fn what_is_repeated_is_bounded_and_always_holds_the_newest() {
        let s = kept(FOLLOWER_KEPT, 10_000);
        assert_eq!(s.len(), FOLLOWER_KEPT);
        let far = follower_steps(&s, &[Some(100), Some(9_999)]);
        // Older than what is kept: the last REPEATED only.
        assert_eq!(far, vec![9_998, 9_999, 10_000]);
        let behind = follower_steps(&s, &[Some(9_800)]);
        assert_eq!(behind.len(), REPEAT_BURST + REPEATED, "{behind:?}");
        assert_eq!((behind[0], behind[REPEAT_BURST - 1]), (9_800, 9_863));
        assert_eq!(&behind[REPEAT_BURST..], &[9_998, 9_999, 10_000]);
    }

    /// A restarted follower resumes up to LOCKSTEP_AHEAD steps before what
    /// the leader heard from it: the leader repeats from there, and keeps
    /// the whole window.
    #[test]
    fn the_leader_repeats_from_before_the_slowest_and_keeps_its_window() {
        let s = kept(LEADER_KEPT, 1_000);
        assert_eq!(s.len(), LEADER_KEPT, "the window and the steps ahead");
        let from = steps(s.leader_repeats(990));
        assert_eq!(from.first(), Some(&(990 - LOCKSTEP_AHEAD)), "{from:?}");
        assert_eq!(from.last(), Some(&1_000));
        assert_eq!(steps(s.leader_repeats(0)).len(), LEADER_KEPT, "not heard yet: everything kept");
        assert_eq!(slowest_step(&[Some(7), None, Some(3)]), 0, "one not heard yet");
        assert_eq!(slowest_step(&[Some(7), Some(3)]), 3);
    }

    /// A restarted follower resumes one step before the least advanced
    /// neighbour; one that hears only the first steps is at the start.
    #[test]
    fn a_restart_resumes_one_step_before_the_least_advanced_neighbour() {
        assert_eq!(resume_step(&[Some(5_731), Some(5_730)]), 5_729, "one before the slowest");
        assert_eq!(resume_step(&[None, Some(900)]), 899, "a neighbour not heard yet does not count");
        assert_eq!(resume_step(&[Some(LOCKSTEP_AHEAD + 2), Some(1)]), 0, "only starting: step 0");
        assert_eq!(resume_step(&[None, None]), 0, "nobody heard");
        assert_eq!(resume_step(&[]), 0, "no neighbours");
    }

    /// A wait repeats on its own clock, warns once after STALL_WARNING and
    /// is over after its limit (virtual time).
    #[test]
    fn a_wait_repeats_on_its_clock_warns_once_and_ends_at_its_limit() {
        let t0 = Now::ZERO;
        let ms = |m: u64| t0 + Duration::from_millis(m);
        let mut w = Wait::new(t0, FOLLOWER_REPEAT_EVERY, Duration::from_secs(8));
        assert_eq!(w.poll(ms(0)), WaitStep::Wait { repeat: false, warn: false });
        assert_eq!(w.poll(ms(99)), WaitStep::Wait { repeat: false, warn: false });
        assert_eq!(w.poll(ms(100)), WaitStep::Wait { repeat: true, warn: false });
        // Woken often (by others' repeats): still one repeat per 100 ms.
        let repeats = (101..=1_000).filter(|&m| w.poll(ms(m)) == WaitStep::Wait { repeat: true, warn: false }).count();
        assert_eq!(repeats, 9);
        let warns: Vec<u64> =
            (1_001..=8_000).filter(|&m| matches!(w.poll(ms(m)), WaitStep::Wait { warn: true, .. })).collect();
        assert_eq!(warns, [5_001], "once, just past {STALL_WARNING:?}");
        assert_eq!(w.poll(ms(8_001)), WaitStep::Over);
        assert_eq!(w.waited(ms(8_001)), Duration::from_millis(8_001));
    }

    /// A node not run for a minute (a loaded host) has not waited a minute
    /// for its neighbours; a neighbour that repeats is alive however long
    /// it takes; one that says nothing while this node watches is gone.
    #[test]
    fn a_wait_gives_up_only_on_time_watched_without_a_sign_of_life() {
        let ms = |m: u64| Now::ZERO + Duration::from_millis(m);
        let limit = Duration::from_secs(8);
        let mut w = Wait::new(ms(0), FOLLOWER_REPEAT_EVERY, limit);
        w.poll(ms(100));
        assert_eq!(w.poll(ms(60_100)), WaitStep::Wait { repeat: true, warn: false }, "starved 60 s: 0.3 s counted");
        // A neighbour repeating every 100 ms for a minute: never over.
        for i in 1..=600 {
            let now = ms(60_100 + 100 * i);
            w.alive(now, i);
            assert_ne!(w.poll(now), WaitStep::Over, "a neighbour that speaks is slow, not gone ({i} repeats)");
        }
        // Then silence, watched: over after the limit, not before.
        let t = 120_100;
        let polls: Vec<u64> = (1..=90).map(|i| t + 100 * i).filter(|&m| w.poll(ms(m)) == WaitStep::Over).collect();
        assert_eq!(polls.first(), Some(&(t + 8_100)), "over just past the limit of silence watched");
    }
}
