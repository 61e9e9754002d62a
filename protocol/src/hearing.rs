//! What a follower records of its hearing for the monitor (the hearing
//! record, `formation replay`): per step and source, which step's message
//! it used. No IO, no clock: the control loop tells it each step.
//!
//! It also keeps the last messages it used of each source: when a source
//! falls silent (real time) or keeps a lock-step follower waiting, they go
//! out with the next telemetry ([`Rescued`]), because a sender that was
//! killed lost its last telemetry, and with it the steps that produced them.

use std::collections::VecDeque;

use formation_control::Message;
use formation_record::hearing::{HeardRuns, Rescued};
use formation_record::Heard;

/// One follower's hearing record between two telemetry batches.
pub struct EarLog {
    runs: HeardRuns,
    slots: usize,
    /// Per slot, the distinct messages used last (stamp order), at most `keep`.
    recent: Vec<VecDeque<(u64, Message)>>,
    keep: usize,
    /// Per slot, whether the last step heard it.
    was_heard: Vec<bool>,
    source_ids: Vec<u32>,
    rescued: Vec<Rescued>,
    /// `network.hearing_record = false`: nothing is recorded.
    on: bool,
}

/// Runs per source a batch has room for before it grows (a real-time run
/// changes a source's hearing a few times a second).
const RUNS_PER_BATCH: usize = 8;

impl EarLog {
    /// For the sources `source_ids` (by slot; 0: the leader), keeping the
    /// last `keep` messages of each for a rescue.
    pub fn new(source_ids: Vec<u32>, keep: usize) -> Self {
        let slots = source_ids.len();
        Self {
            runs: HeardRuns::with_slots(slots, RUNS_PER_BATCH),
            slots,
            recent: (0..slots).map(|_| VecDeque::with_capacity(keep)).collect(),
            keep: keep.max(1),
            was_heard: vec![false; slots],
            source_ids,
            rescued: Vec::new(),
            on: true,
        }
    }

    /// Records nothing (`network.hearing_record = false`): every batch's
    /// record is empty.
    pub fn off() -> Self {
        Self { on: false, ..Self::new(Vec::new(), 1) }
    }

    /// What `slot` gave the step being recorded: `used` is the message of
    /// step `stamp` when it was heard. Call for every slot, in slot order,
    /// then [`EarLog::end_step`].
    pub fn note(&mut self, slot: usize, heard: Heard, used: Option<(u64, &Message)>) {
        if !self.on {
            return;
        }
        self.runs.push_one(slot, heard);
        let now = used.is_some();
        if let Some((stamp, m)) = used {
            let r = &mut self.recent[slot];
            if r.back().is_none_or(|&(s, _)| s != stamp) {
                if r.len() == self.keep {
                    r.pop_front();
                }
                r.push_back((stamp, *m));
            }
        } else if self.was_heard[slot] {
            // Heard no more: the sender may be gone, with its last telemetry.
            self.rescue(slot);
        }
        self.was_heard[slot] = now;
    }

    pub fn end_step(&mut self) {
        if !self.on {
            return;
        }
        self.runs.end_step();
    }

    /// Sends the last messages used of `slot` with the next batch (a
    /// source that keeps a lock-step follower waiting).
    pub fn rescue(&mut self, slot: usize) {
        if !self.on {
            return;
        }
        let source = self.source_ids[slot];
        self.rescued.extend(self.recent[slot].drain(..).map(|(stamp, m)| Rescued {
            source,
            stamp,
            state: m.state,
            fresh: m.fresh,
        }));
    }

    /// The batch's record and rescued messages; starts the next batch.
    pub fn take(&mut self) -> (HeardRuns, Vec<Rescued>) {
        let runs = std::mem::replace(&mut self.runs, HeardRuns::with_slots(self.slots, RUNS_PER_BATCH));
        (runs, std::mem::take(&mut self.rescued))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_leader::LeaderState;

    fn msg(v: f64) -> Message {
        Message::fresh(LeaderState { v, ..Default::default() })
    }

    #[test]
    fn a_source_that_falls_silent_has_its_last_messages_rescued_once() {
        let mut e = EarLog::new(vec![3, 0], 4);
        for k in 1..=10u64 {
            let m = msg(k as f64);
            e.note(0, Heard::used(k, k - 1), Some((k - 1, &m)));
            e.note(1, Heard::used(k, k - 1), Some((k - 1, &m)));
            e.end_step();
        }
        // Source 3 falls silent at step 11; the leader does not.
        let m = msg(11.0);
        e.note(0, Heard::Silent, None);
        e.note(1, Heard::used(11, 10), Some((10, &m)));
        e.end_step();
        e.note(0, Heard::Silent, None);
        e.note(1, Heard::used(12, 11), Some((11, &m)));
        e.end_step();
        let (runs, rescued) = e.take();
        assert_eq!(runs.steps, 12);
        assert!(runs.is_consistent());
        assert_eq!(runs.slots[0], vec![(1, 10), (Heard::Silent.code(), 2)]);
        let stamps: Vec<(u32, u64)> = rescued.iter().map(|r| (r.source, r.stamp)).collect();
        assert_eq!(stamps, vec![(3, 6), (3, 7), (3, 8), (3, 9)], "the last 4 of source 3, once");
        assert_eq!(rescued[3].state.v, 10.0);
        let (next, again) = e.take();
        assert_eq!((next.steps, again.len()), (0, 0));
    }

    #[test]
    fn switched_off_it_records_nothing() {
        let mut e = EarLog::off();
        e.note(0, Heard::Age(1), None);
        e.end_step();
        e.rescue(0);
        let (runs, rescued) = e.take();
        assert_eq!((runs.steps, runs.slots.len(), rescued.len()), (0, 0, 0));
    }

    #[test]
    fn a_message_used_twice_is_kept_once() {
        let mut e = EarLog::new(vec![2], 8);
        let m = msg(1.0);
        for k in 5..9u64 {
            e.note(0, Heard::used(k, 4), Some((4, &m)));
            e.end_step();
        }
        e.rescue(0);
        let (_, rescued) = e.take();
        assert_eq!(rescued.len(), 1);
    }
}
