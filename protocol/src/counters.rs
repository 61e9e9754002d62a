//! What a node counts about the estimate messages it sends and receives;
//! sent with its telemetry and written to `network.json`.

use crate::wire::Reject;
use serde::{Deserialize, Serialize};

/// Per-reason counts of received estimate messages that were not used.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RejectCounts {
    pub malformed: u64,
    pub version: u64,
    pub non_finite: u64,
    pub wrong_sender: u64,
    pub not_neighbour: u64,
    /// An older step than one already used (also: duplicates of a used step).
    pub stale: u64,
    /// A step further ahead of the receiver's than any genuine sender can be.
    #[serde(default)]
    pub future: u64,
    /// From a leader of an older term than one already heard (a leader a
    /// standby took the run over from): not bad, but not used.
    #[serde(default)]
    pub old_term: u64,
}

impl RejectCounts {
    pub fn add(&mut self, r: Reject) {
        match r {
            Reject::Malformed => self.malformed += 1,
            Reject::Version => self.version += 1,
            Reject::NonFinite => self.non_finite += 1,
            Reject::WrongSender => self.wrong_sender += 1,
            Reject::NotNeighbour => self.not_neighbour += 1,
            Reject::Stale => self.stale += 1,
            Reject::Future => self.future += 1,
            Reject::OldTerm => self.old_term += 1,
        }
    }
    /// Everything but `stale` (which is lateness, not a bad message) and
    /// `old_term` (a leader that was taken over from).
    pub fn invalid(&self) -> u64 {
        self.malformed + self.version + self.non_finite + self.wrong_sender + self.not_neighbour + self.future
    }

    /// Adds another tally's counts.
    pub fn merge(&mut self, o: &RejectCounts) {
        self.malformed += o.malformed;
        self.version += o.version;
        self.non_finite += o.non_finite;
        self.wrong_sender += o.wrong_sender;
        self.not_neighbour += o.not_neighbour;
        self.stale += o.stale;
        self.future += o.future;
        self.old_term += o.old_term;
    }
}

/// Refusals counted where messages arrive, without a lock: a flood of
/// garbage on a neighbour's key never holds the follower's machine; the
/// node hands the counts over with [`AtomicRejects::take`].
#[derive(Debug, Default)]
pub struct AtomicRejects {
    counts: [std::sync::atomic::AtomicU64; 8],
}

impl AtomicRejects {
    pub fn add(&self, r: Reject) {
        let i = match r {
            Reject::Malformed => 0,
            Reject::Version => 1,
            Reject::NonFinite => 2,
            Reject::WrongSender => 3,
            Reject::NotNeighbour => 4,
            Reject::Stale => 5,
            Reject::Future => 6,
            Reject::OldTerm => 7,
        };
        self.counts[i].fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }

    /// The counts since the last take (None: nothing refused).
    pub fn take(&self) -> Option<RejectCounts> {
        let c: Vec<u64> = self.counts.iter().map(|a| a.swap(0, std::sync::atomic::Ordering::Relaxed)).collect();
        c.iter().any(|&n| n > 0).then(|| RejectCounts {
            malformed: c[0],
            version: c[1],
            non_finite: c[2],
            wrong_sender: c[3],
            not_neighbour: c[4],
            stale: c[5],
            future: c[6],
            old_term: c[7],
        })
    }
}

/// A node's message counters, sent with every telemetry batch.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Counters {
    /// Estimate messages published (republications included).
    pub sent: u64,
    /// Republications of a step's message while waiting (lock-step).
    pub republished: u64,
    /// Estimate messages received that passed every check.
    pub received: u64,
    /// Received too late to be used (lock-step: a duplicate of a used step;
    /// real time: older than the latest already held). Also in `rejected.stale`.
    pub late: u64,
    pub rejected: RejectCounts,
    /// (Real time) neighbour-steps left out of the estimator's sums because
    /// the neighbour was silent longer than `network.silence_timeout`.
    pub silent: u64,
    /// Messages removed by the scenario's fault table at this receiver (docs/model.md §14).
    #[serde(default)]
    pub fault_lost: u64,
    /// (Real time) neighbour-steps that used a message older than step
    /// k − d (`network.delay_steps`): the one of k − d had not arrived in
    /// time. The simulator's model has none.
    #[serde(default)]
    pub older: u64,
    /// (The leader) questions on `control/time` answered, and the most in
    /// any one second: each node asks about 4 a second.
    #[serde(default)]
    pub time_queries: u64,
    #[serde(default)]
    pub time_queries_peak_per_s: u64,
}

/// The questions a leader answers on `control/time`: how many, and the
/// most in one second of its clock. Shared by the queryable's callback and
/// the leader's loop.
#[derive(Debug, Default)]
pub struct QueryCount(std::sync::Mutex<(u64, i64, u64, u64)>);

impl QueryCount {
    /// One question, at `now_ns` on the leader's clock.
    pub fn note(&self, now_ns: i64) {
        let mut g = self.0.lock().unwrap_or_else(|p| p.into_inner());
        let (total, second, in_second, peak) = &mut *g;
        *total += 1;
        let s = now_ns.div_euclid(1_000_000_000);
        if s != *second {
            (*second, *in_second) = (s, 0);
        }
        *in_second += 1;
        *peak = (*peak).max(*in_second);
    }

    /// (questions, most in one second).
    pub fn read(&self) -> (u64, u64) {
        let g = self.0.lock().unwrap_or_else(|p| p.into_inner());
        (g.0, g.3)
    }
}
