//! The outage study `formation paper` runs after the paper's cases
//! (docs/model.md §14): follower 3 cut off for 3 s at t = 10 s, rejoining with
//! `adopt` or `consensus`, under bioinspired and conventional backstepping;
//! and loss on follower 3's links over the whole run, p = 0 … 1.
//!
//! Each case is the proposed method of docs/model.md §12 (bioinspired SMC, ASIF,
//! estimate started at the leader, no filter fault) with a fault table and a
//! rejoin policy; the user's `--set` overrides apply first, as for the
//! paper's cases.

use formation_scenario::Scenario;

use crate::case::Study;
use crate::faults::STUDY_NODE;

/// The outage window, s of run time: [from, to).
pub const OUTAGE_S: (f64, f64) = (10.0, 13.0);
/// Loss probabilities of the sweep on follower 3's links.
pub const LOSSES: [f64; 6] = [0.0, 0.1, 0.3, 0.5, 0.9, 1.0];
/// The kinematic controllers compared: scenario value and name.
const KINEMATICS: [(&str, &str); 2] = [("bio", "bioinspired"), ("conventional", "conventional")];
/// The rejoin policies compared (docs/model.md §14).
const REJOINS: [&str; 2] = ["adopt", "consensus"];
/// The sweep's policy; [`plan`]'s notes say why one is enough.
const SWEEP_REJOIN: &str = "consensus";

/// One case of the study.
#[derive(Clone, Debug, PartialEq)]
pub struct StudyCase {
    /// Folder name.
    pub name: String,
    /// The keys that define the case, after the user's.
    pub overrides: Vec<String>,
    /// A loss-sweep case (otherwise an outage case).
    pub sweep: bool,
}

/// The study's cases for a scenario, and what report.md says about them.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    pub cases: Vec<StudyCase>,
    /// What the cases are.
    pub notes: Vec<String>,
    /// What was skipped, and why.
    pub skipped: Vec<String>,
}

/// The part the outage cases need: the window and the 5 s after it over
/// which docs/model.md §14 takes the peaks.
pub fn outage_needs_s() -> f64 {
    OUTAGE_S.1 + formation_record::outage::AFTER_S
}

/// The cases for `base` (the scenario with the user's overrides): the outage
/// cases only when the run covers the window and the 5 s after it, the
/// sweep always; none when the scenario has no follower 3.
pub fn plan(base: &Scenario) -> Plan {
    let node = STUDY_NODE;
    let mut cases = Vec::new();
    let mut notes = Vec::new();
    let mut skipped = Vec::new();
    if !base.followers.iter().any(|f| f.id == node) {
        skipped.push(format!(
            "The outage study cuts follower {node}'s links; this scenario has no follower {node}, so it was skipped."
        ));
        return Plan { cases, notes, skipped };
    }
    let (from, to) = OUTAGE_S;
    let proposed = ["dynamic=bio", "filter=asif", "estimate_init=leader"];
    if base.duration_s >= outage_needs_s() {
        for (kinematic, _) in KINEMATICS {
            for rejoin in REJOINS {
                let mut overrides: Vec<String> = vec![format!("kinematic={kinematic}")];
                overrides.extend(proposed.iter().map(|s| s.to_string()));
                overrides.push(format!("faults=[{{node={node}, from={from}, to={to}}}]"));
                overrides.push(format!("network.rejoin={rejoin}"));
                cases.push(StudyCase { name: format!("outage-{kinematic}-{rejoin}"), overrides, sweep: false });
            }
        }
        notes.push(format!(
            "Outage cases `outage-{{bio,conventional}}-{{adopt,consensus}}`: the proposed method (bioinspired or \
             conventional backstepping, bioinspired SMC, ASIF) with every link of follower {node} down for \
             {from} s ≤ t < {to} s, rejoining with `adopt` or `consensus`."
        ));
    } else {
        skipped.push(format!(
            "The outage cases were skipped: they need T ≥ {} s (follower {node}'s links down {from}–{to} s and the \
             {} s after, over which docs/model.md §14 takes the peaks), and this run has T = {} s.",
            outage_needs_s(),
            formation_record::outage::AFTER_S,
            base.duration_s
        ));
    }
    let duration = base.duration_s;
    for p in LOSSES {
        let mut overrides: Vec<String> = vec!["kinematic=bio".into()];
        overrides.extend(proposed.iter().map(|s| s.to_string()));
        overrides.push(format!("faults=[{{node={node}, from=0, to={duration}, loss={p}}}]"));
        overrides.push(format!("network.rejoin={SWEEP_REJOIN}"));
        cases.push(StudyCase { name: format!("loss-p{p}"), overrides, sweep: true });
    }
    // The chance that a rejoin happens at a given step under loss p < 1:
    // every step of the last `rejoin_after` lost on both of follower 3's links.
    let after = base.control.rejoin.after_steps;
    let p_max = LOSSES.iter().copied().filter(|&p| p < 1.0).fold(0.0, f64::max);
    let links = base.index_of(node).map_or(0, |i| base.sources_of(i).len()) as i32;
    notes.push(format!(
        "Loss cases `loss-p…`: the proposed method with each message on follower {node}'s links lost with \
         probability p over the whole run (0 ≤ t < T), p = {}, rejoining with `{SWEEP_REJOIN}` only. A rejoin \
         needs {} s ({after} steps) in which follower {node} hears none of its {links} sources; independent \
         losses give that at a step with probability p^({links}·{after}), {} for p = {p_max}, so `adopt` and \
         `consensus` run identically for p < 1. With p = 1 the follower hears nothing until the run's last \
         sample (t = T, outside [0, T)), where `adopt` would put a one-step torque spike into the run's metrics.",
        LOSSES.map(|p| p.to_string()).join(", "),
        base.source.network.rejoin_after,
        crate::tables::sig(p_max.powi(links * after as i32), 2),
    ));
    Plan { cases, notes, skipped }
}

/// The study's loaded cases, outage and loss cases apart.
pub fn study(cases: Vec<(bool, crate::Case)>, plan: Plan) -> Study {
    let (sweep, outage): (Vec<_>, Vec<_>) = cases.into_iter().partition(|(s, _)| *s);
    Study {
        node: STUDY_NODE,
        outage: outage.into_iter().map(|(_, c)| c).collect(),
        sweep: sweep.into_iter().map(|(_, c)| c).collect(),
        notes: plan.notes,
        skipped: plan.skipped,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper(duration: f64) -> Scenario {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        Scenario::load(&path, &[format!("duration={duration}")]).expect("scenario")
    }

    #[test]
    fn a_run_too_short_for_the_window_and_the_5_s_after_skips_the_outage_cases_only() {
        let short = plan(&paper(17.9));
        assert!(short.cases.iter().all(|c| c.sweep), "{:?}", short.cases);
        assert_eq!(short.cases.len(), LOSSES.len());
        assert!(short.skipped.iter().any(|n| n.contains("skipped") && n.contains("T = 17.9 s")), "{:?}", short.skipped);
        let long = plan(&paper(18.0));
        assert_eq!(long.cases.len(), 4 + LOSSES.len());
        let names: Vec<&str> = long.cases.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(
            &names[..4],
            ["outage-bio-adopt", "outage-bio-consensus", "outage-conventional-adopt", "outage-conventional-consensus"]
        );
        assert_eq!(names[4..], ["loss-p0", "loss-p0.1", "loss-p0.3", "loss-p0.5", "loss-p0.9", "loss-p1"]);
    }

    #[test]
    fn every_case_loads_and_covers_follower_3_as_planned() {
        let base = paper(20.0);
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
        for c in plan(&base).cases {
            let s = Scenario::load(&path, &c.overrides).unwrap_or_else(|e| panic!("{}: {e}", c.name));
            assert_eq!(s.faults.len(), 1, "{}", c.name);
            let f = &s.faults[0];
            assert!(f.covers(3, 1) && f.covers(4, 3) && !f.covers(1, 2), "{}: {f:?}", c.name);
            if c.sweep {
                assert_eq!((f.from_s, f.to_s), (0.0, 20.0), "{}", c.name);
            } else {
                assert_eq!((f.from_s, f.to_s, f.loss), (10.0, 13.0, 1.0), "{}", c.name);
            }
        }
    }
}
