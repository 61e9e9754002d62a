//! Whether a real-time run kept its period, from the run's own record and
//! nothing else: how many of the followers' source-steps used a message
//! older than the modelled delay allows (a sender or a receiver late by
//! more than `network.delay_steps`), and whether the whole path stalled.
//!
//! A run whose host fell behind is still what its code did with what it
//! heard (it replays byte for byte from its hearing record, and
//! `formation replay --explain` accounts for the difference); only its
//! comparison with the nominal, timing-free model loses its meaning. The
//! tests and `formation verify` compare a run's figures with the model
//! only when [`Period::kept`] says so, whatever the host's speed: the
//! verdict reads the run, not the machine's load counters.

use std::fmt;

/// The most a run's late source-steps may be, as a share of those it used,
/// for its figures to be compared with the model's. Measured on the
/// project's 2-core VM (docs/performance.md, "Judged or not"): the lab's
/// fault-free run alone, test build, 0.86 % and 0.94 %, within the model's
/// tolerances; beside another lab 2.06 %, torque variation 1.101 of the
/// model's; the runs that failed the model's tolerances on a loaded host
/// 4.1–34.6 %.
pub const KEPT_LATE_SHARE: f64 = 0.0125;

/// A run's timing as its record says it (`network.json`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Period {
    /// Source-steps that used a message older than the modelled delay.
    pub late: u64,
    /// Source-steps the followers used (messages received and used).
    pub used: u64,
    /// Spans at which the path every message shares stalled
    /// (`health.stalls`).
    pub stalls: usize,
    /// Lock-step runs have no period to keep: every step waits for its
    /// messages.
    pub lockstep: bool,
}

impl Period {
    /// From a run folder's `network.json`, parsed. Counters a record does
    /// not hold count as zero.
    pub fn of(network: &serde_json::Value) -> Self {
        let mut p = Period { lockstep: network["timing"].as_str() == Some("lockstep"), ..Self::default() };
        for node in network["nodes"].as_object().into_iter().flat_map(|n| n.values()) {
            p.late += node["older"].as_u64().unwrap_or(0);
            p.used += node["received"].as_u64().unwrap_or(0);
        }
        p.stalls = network["health"]["stalls"].as_array().map_or(0, Vec::len);
        p
    }

    /// Several runs judged together (a study against a reference run): the
    /// sums.
    pub fn together(runs: &[Period]) -> Self {
        runs.iter().fold(Period { lockstep: !runs.is_empty(), ..Self::default() }, |a, r| Period {
            late: a.late + r.late,
            used: a.used + r.used,
            stalls: a.stalls + r.stalls,
            lockstep: a.lockstep && r.lockstep,
        })
    }

    /// Late source-steps over those used (0 when none were used).
    pub fn late_share(&self) -> f64 {
        if self.used == 0 {
            0.0
        } else {
            self.late as f64 / self.used as f64
        }
    }

    /// Whether the run heard what the model assumes closely enough for its
    /// figures to be compared with the model's: at most [`KEPT_LATE_SHARE`]
    /// of its source-steps late. (The health's stalls are said beside it,
    /// not counted: a quiet host's fault-free lab shows 80–100 of a few
    /// milliseconds, and the late source-steps they cost are counted.)
    pub fn kept(&self) -> bool {
        self.late_share() <= KEPT_LATE_SHARE
    }

    /// Why the run's figures are not compared with the model's, or None
    /// when they are: "34.6 % of source-steps late (1 % allowed)".
    pub fn why_not_judged(&self) -> Option<String> {
        if self.kept() {
            return None;
        }
        Some(format!(
            "{:.1} % of source-steps late ({:.2} % allowed)",
            100.0 * self.late_share(),
            100.0 * KEPT_LATE_SHARE
        ))
    }
}

impl fmt::Display for Period {
    /// "120 of 80,004 source-steps late (0.15 %), no stall".
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} of {} source-steps late ({:.2} %), {}",
            self.late,
            self.used,
            100.0 * self.late_share(),
            match self.stalls {
                0 => "no stall".to_string(),
                n => format!("{n} stall(s)"),
            }
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn network(older: [u64; 2], received: [u64; 2], stalls: usize) -> serde_json::Value {
        serde_json::json!({
            "timing": "realtime",
            "nodes": {
                "1": { "older": older[0], "received": received[0] },
                "2": { "older": older[1], "received": received[1] },
                "leader": {},
            },
            "health": { "stalls": vec![serde_json::json!({}); stalls] },
        })
    }

    #[test]
    fn a_run_within_the_share_kept_its_period() {
        let p = Period::of(&network([50, 49], [5_000, 5_000], 0));
        assert_eq!((p.late, p.used, p.stalls), (99, 10_000, 0));
        assert!(p.kept(), "{p}");
        assert_eq!(p.why_not_judged(), None);
    }

    #[test]
    fn a_run_over_the_share_did_not_and_stalls_are_said_not_counted() {
        let late = Period::of(&network([1_000, 2_460], [5_000, 5_000], 0));
        assert!(!late.kept());
        assert_eq!(late.why_not_judged().as_deref(), Some("34.6 % of source-steps late (1.25 % allowed)"));
        let stalled = Period::of(&network([0, 0], [5_000, 5_000], 3));
        assert!(stalled.kept(), "{stalled}");
        assert_eq!(stalled.to_string(), "0 of 10000 source-steps late (0.00 %), 3 stall(s)");
    }

    #[test]
    fn runs_together_are_summed_and_an_empty_record_is_not_late() {
        let a = Period::of(&network([0, 0], [5_000, 5_000], 0));
        let b = Period::of(&network([300, 0], [5_000, 5_000], 0));
        let both = Period::together(&[a, b]);
        assert_eq!((both.late, both.used), (300, 20_000));
        assert!(!both.kept(), "1.5 % late: {both}");
        assert!(Period::together(&[a, a, b]).kept(), "1 % late");
        assert_eq!(Period::of(&serde_json::json!({})).late_share(), 0.0);
    }
}
