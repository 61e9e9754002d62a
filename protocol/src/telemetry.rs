//! Telemetry for the monitor: every step of a node, in batches, on
//! `telemetry/<id>`. Never feeds control.

use formation_leader::LeaderState;
use serde::{Deserialize, Serialize};

use crate::counters::Counters;
use crate::courier::CourierStats;
use crate::loop_timing::LoopStats;
use formation_record::hearing::{HeardRuns, Rescued, Resume};
use formation_record::FollowerSample;

/// Telemetry for the monitor: every step of a node, in batches. Never feeds control.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Telemetry {
    Follower {
        id: u32,
        /// Step of `samples[0]`.
        first_k: u64,
        samples: Vec<FollowerSample>,
        counters: Counters,
        /// The node has sent its final step.
        done: bool,
        loop_stats: Option<LoopStats>,
        delivery: Delivery,
        /// What the network did to this node during the batch's steps.
        events: Vec<NetEvent>,
        /// The node's estimate of the leader's clock when it sent the batch.
        clock: Option<ClockReport>,
        /// Per source, its messages' latency and age so far.
        links: Vec<LinkStats>,
        /// What the follower heard at each of the batch's steps (the hearing record).
        heard: HeardRuns,
        /// The last messages used of sources that fell silent (see [`crate::hearing`]).
        rescued: Vec<Rescued>,
        /// A restarted process: the step it resumed from and its robot's pose then.
        resumed: Option<Resume>,
        /// The run diverged at the batch's last step: which quantity.
        diverged: Option<String>,
        /// The follower left the run for good with this batch (its last).
        left: Option<Left>,
    },
    Leader {
        first_k: u64,
        /// The true leader state at steps first_k, first_k + 1, …
        states: Vec<LeaderState>,
        counters: Counters,
        done: bool,
        loop_stats: Option<LoopStats>,
        delivery: Delivery,
        /// Sent by a standby that took the run over: when.
        handover: Option<Handover>,
        /// The sender's term, and whether it stood down.
        term: Term,
    },
}

/// A leader's term (docs/model.md §14): 1 for the leader the run started
/// with, one more for each standby that took the run over. A leader that
/// hears one of a higher term stands down: its last batch says at which
/// step (the first it did not take).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Term {
    pub number: u32,
    pub stood_down_at: Option<u64>,
}

/// A standby leader took the run over (docs/model.md §14): the newest step
/// it had heard from the leader, and the first it published itself. In
/// between, in real time, no leader message went out: the handover's gap.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Handover {
    pub heard: Option<u64>,
    pub at_k: u64,
}

impl Handover {
    /// The steps whose leader message never went out, [from, to): after the
    /// newest heard, before the standby's first (None: none, or unknown).
    pub fn gap(&self) -> Option<(u64, u64)> {
        self.heard.map(|h| (h + 1, self.at_k)).filter(|g| g.0 < g.1)
    }
}

/// A follower that left the run for good (its process was told to stop:
/// SIGTERM, Ctrl-C): the first step it did not take, and why, in a few words.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Left {
    pub at_k: u64,
    pub why: String,
}

/// The most characters of [`Left::why`] a monitor keeps.
pub const MAX_LEFT_WHY: usize = 40;

/// How the sender's telemetry gets through (see [`crate::courier`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Delivery {
    /// Steps below this that the monitor does not hold will never come
    /// (dropped from a full store, or produced by an earlier process).
    pub available_from: u64,
    /// This process's start (ns since the Unix epoch): a new value from the
    /// same node means it was restarted.
    pub incarnation: u64,
    pub courier: CourierStats,
}

pub use crate::clock_estimate::ClockReport;
pub use crate::latency::LinkStats;

/// One entry of a node's network timeline (`network.json`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct NetEvent {
    /// The step at which the node noticed.
    pub k: u64,
    pub what: EventKind,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub enum EventKind {
    /// A source (0: the leader) is heard again, or for the first time.
    Heard(u32),
    /// A source fell silent (nothing newer than `network.silence_timeout`).
    Silent(u32),
    /// The session lost its last router (client mode).
    RouterLost,
    /// The session has a router again.
    RouterBack,
    /// No source heard for `network.rejoin_after`: the estimate dead-reckons.
    Isolated,
    /// A source heard again after isolation (docs/model.md §14's rejoin).
    Rejoined,
    /// A second clock answered on `control/time` (its answers are refused).
    SecondClock,
}

impl EventKind {
    pub fn describe(&self) -> String {
        let name = |s: u32| if s == 0 { "the leader".to_string() } else { format!("follower {s}") };
        match *self {
            EventKind::Heard(s) => format!("hears {}", name(s)),
            EventKind::Silent(s) => format!("{} silent", name(s)),
            EventKind::RouterLost => "router lost".into(),
            EventKind::RouterBack => "router back".into(),
            EventKind::Isolated => "isolated: no source heard, dead-reckoning".into(),
            EventKind::Rejoined => "rejoined".into(),
            EventKind::SecondClock => "a second clock answers on control/time: refused".into(),
        }
    }
}

/// The monitor's acknowledgements on `control/ack`, about every 100 ms:
/// per node (0: the leader), the first step it does not hold.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Ack {
    pub fingerprint: u64,
    pub next_k: Vec<(u32, u64)>,
}

impl Telemetry {
    /// Follower `id`'s report, on its own key, that it left the run: the
    /// first step it did not take.
    pub fn left_at(&self, id: u32) -> Option<u64> {
        match self {
            Telemetry::Follower { id: sender, done: true, left: Some(l), .. } if *sender == id => Some(l.at_k),
            _ => None,
        }
    }

    /// Whether this is follower `id`'s report, on its own key, of its final
    /// step of a run of `steps` + 1 steps (a batch that ends there).
    pub fn reports_final_step(&self, id: u32, steps: u64) -> bool {
        matches!(self, Telemetry::Follower { id: sender, first_k, samples, done: true, .. }
            if *sender == id && first_k.checked_add(samples.len() as u64) == Some(steps + 1))
    }
}

impl Ack {
    /// The first step the monitor lacks of `node`, if this acknowledgement
    /// is of this scenario (`fingerprint`) and names the node.
    pub fn next_k_of(&self, fingerprint: u64, node: u32) -> Option<u64> {
        (self.fingerprint == fingerprint).then(|| self.next_k.iter().find(|(n, _)| *n == node).map(|&(_, k)| k))?
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::{decode, encode};

    fn follower(id: u32, first_k: u64, n: u64, done: bool) -> Telemetry {
        let sample = |k: u64| FollowerSample { k, ..FollowerSample::default() };
        Telemetry::Follower {
            id,
            first_k,
            samples: (0..n).map(|i| sample(first_k.wrapping_add(i))).collect(),
            heard: HeardRuns::uniform(1, n as u32, formation_record::Heard::Age(1)),
            rescued: Vec::new(),
            resumed: None,
            diverged: None,
            left: None,
            counters: Counters::default(),
            done,
            loop_stats: None,
            delivery: Delivery::default(),
            events: vec![NetEvent { k: first_k, what: EventKind::Silent(2) }],
            clock: Some(ClockReport {
                offset_ms: -50.0,
                uncertainty_us: 80.0,
                drift_ppm: 3.0,
                exchanges: 9,
                steps: 0,
                ..Default::default()
            }),
            links: vec![LinkStats {
                source: 2,
                messages: 9,
                latency_us: [40, 90, 120],
                uses: 9,
                age_steps: [0, 1, 1],
                twin_messages: 0,
                twin_since: None,
            }],
        }
    }

    #[test]
    fn a_final_step_counts_only_from_its_own_follower_and_at_the_runs_end() {
        let steps = 100;
        let last = follower(3, 91, 10, true);
        assert_eq!(decode::<Telemetry>(&encode(&last)), Some(last.clone()), "round trip");
        assert!(last.reports_final_step(3, steps));
        assert!(!last.reports_final_step(4, steps), "on another follower's key");
        assert!(!follower(3, 91, 10, false).reports_final_step(3, steps), "not done");
        assert!(!follower(3, 90, 10, true).reports_final_step(3, steps), "ends one step short");
        assert!(!follower(3, u64::MAX - 3, 10, true).reports_final_step(3, steps), "overflowing steps");
        let leader = Telemetry::Leader {
            first_k: 91,
            states: vec![],
            counters: Counters::default(),
            done: true,
            loop_stats: None,
            delivery: Delivery::default(),
            handover: None,
            term: Term { number: 1, stood_down_at: None },
        };
        assert!(!leader.reports_final_step(0, steps));
    }

    #[test]
    fn an_acknowledgement_counts_only_for_its_scenario_and_node() {
        let ack = Ack { fingerprint: 7, next_k: vec![(0, 40), (2, 35)] };
        assert_eq!(decode::<Ack>(&encode(&ack)), Some(ack.clone()), "round trip");
        assert_eq!(ack.next_k_of(7, 2), Some(35));
        assert_eq!(ack.next_k_of(7, 0), Some(40));
        assert_eq!(ack.next_k_of(7, 3), None, "a node it does not name");
        assert_eq!(ack.next_k_of(8, 2), None, "another scenario's monitor");
        assert_eq!(decode::<Ack>(b"garbage"), None);
    }

    #[test]
    fn every_event_has_words() {
        let all = [
            EventKind::Heard(0),
            EventKind::Silent(3),
            EventKind::RouterLost,
            EventKind::RouterBack,
            EventKind::Isolated,
            EventKind::Rejoined,
        ];
        let words: Vec<String> = all.iter().map(EventKind::describe).collect();
        assert_eq!(words[0], "hears the leader");
        assert_eq!(words[1], "follower 3 silent");
        assert!(words.iter().all(|w| !w.is_empty()));
    }
}
