//! docs/model.md §14 in the simulator: the paper scenario with follower 3 cut off
//! for 3 s at t = 10 s, under both rejoin policies, and loss on a link.
//! Each assertion carries the number it measured.

use formation_record::outage::OutageMetrics;
use formation_record::Row;
use formation_scenario::Scenario;
use formation_sim::{Observer, Simulation};

const SCENARIO: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/scenarios/paper.toml");
const OUTAGE: &str = "faults+={node=3, from=10, to=13}";

/// Per follower (by index): the largest estimator error and |v_ir| over the run.
#[derive(Default)]
struct Peaks {
    estimator: [f64; 4],
    v_ir: [f64; 4],
    vc: [f64; 4],
    /// Follower 3's estimator error at the last step of the outage (t = 12.999 s).
    f3_at_rejoin: f64,
}

impl Observer for Peaks {
    fn follower(&mut self, i: usize, k: u64, r: &Row, _last: bool) -> std::io::Result<()> {
        self.estimator[i] = self.estimator[i].max(r.estimator_error);
        self.v_ir[i] = self.v_ir[i].max(r.v_ir.abs());
        self.vc[i] = self.vc[i].max(r.v_c.abs());
        if i == 2 && k == 12_999 {
            self.f3_at_rejoin = r.estimator_error;
        }
        Ok(())
    }
}

fn run(sets: &[&str]) -> (Scenario, Peaks, std::collections::BTreeMap<u32, Vec<OutageMetrics>>) {
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    let s = Scenario::load(std::path::Path::new(SCENARIO), &sets).expect("scenario");
    let mut peaks = Peaks::default();
    let mut sim = Simulation::new(&s);
    sim.run(&mut peaks, |_| {}).expect("run");
    let outages = sim.outages();
    (s, peaks, outages)
}

#[test]
fn outage_of_follower_3_under_both_rejoin_policies() {
    let mut recovery = Vec::new();
    for policy in ["adopt", "consensus"] {
        let (s, p, outages) = run(&[OUTAGE, &format!("network.rejoin={policy}")]);
        // The others keep a path to the leader: their estimates never drift.
        for (i, id) in [(0, 1), (1, 2), (3, 4)] {
            assert!(
                p.estimator[i] < 0.02,
                "{policy}: follower {id}'s estimator error reached {:.4} m with follower 3 cut off (limit 0.02)",
                p.estimator[i]
            );
        }
        // Follower 3 dead-reckons for 3 s: its estimate is off when the links return.
        assert!(p.f3_at_rejoin > 0.1, "{policy}: follower 3 only {:.4} m off after 3 s alone", p.f3_at_rejoin);
        let m = outages[&3][0];
        let r = m.recovery_s.unwrap_or_else(|| panic!("{policy}: follower 3 never recovered: {m:?}"));
        recovery.push(r);
        // Bioinspired backstepping: |v_c| ≤ C_1 B + max |v_ir| through the outage and the rejoin.
        let k = &s.control.kinematic_gains;
        for i in 0..4 {
            let bound = k.c1 * k.shunting.b + p.v_ir[i];
            assert!(
                p.vc[i] <= bound,
                "{policy}: follower {} peak |v_c| {:.3} > C1 B + max|v_ir| = {bound:.3}",
                i + 1,
                p.vc[i]
            );
        }
    }
    let (adopt, consensus) = (recovery[0], recovery[1]);
    assert!(adopt <= 1.0, "adopt: follower 3 recovered {adopt:.3} s after the window (limit 1 s)");
    assert!(consensus > adopt, "consensus ({consensus:.3} s) should recover later than adopt ({adopt:.3} s)");
    eprintln!("recovery after the 3 s outage: adopt {adopt:.3} s, consensus {consensus:.3} s");
}

/// What a router restart is to the model: every follower cut off at once
/// (8–11.12 s, as the lab's 3 s router outage plus its reconnection). Every
/// estimate is held through the isolation, so under `adopt` none may be
/// taken from a neighbour until it has come back from the leader (docs/model.md §14's
/// freshness); then every follower recovers within a few steps, where
/// `consensus` needs over 5 s.
#[test]
fn every_follower_cut_off_at_once_recovers_at_once_under_adopt() {
    let all: Vec<String> = (1..=4).map(|id| format!("faults+={{node={id}, from=8, to=11.12}}")).collect();
    let mut recovery = std::collections::BTreeMap::new();
    for policy in ["adopt", "consensus"] {
        let mut sets: Vec<&str> = vec!["duration=20"];
        sets.extend(all.iter().map(String::as_str));
        let policy_set = format!("network.rejoin={policy}");
        sets.push(&policy_set);
        let (_, _, outages) = run(&sets);
        for id in 1..=4u32 {
            let m = outages[&id][0];
            let drift = m.peak_estimator_error.expect("samples in the span");
            assert!(drift > 3.0, "{policy}: follower {id} drifted only {drift:.3} m in 3.12 s alone");
            let r = m.recovery_s.unwrap_or_else(|| panic!("{policy}: follower {id} never recovered: {m:?}"));
            recovery.insert((policy, id), r);
        }
    }
    for id in 1..=4u32 {
        let (a, c) = (recovery[&("adopt", id)], recovery[&("consensus", id)]);
        assert!(a <= 0.01, "adopt: follower {id} recovered {a:.3} s after the window (limit 0.01 s): {recovery:?}");
        assert!(
            c > 5.0,
            "consensus: follower {id} recovered in {c:.3} s; the paper's law needs over 5 s: {recovery:?}"
        );
    }
}

#[test]
fn a_fault_free_table_changes_nothing_and_a_zero_loss_fault_neither() {
    let (_, a, _) = run(&["duration=3"]);
    let (_, b, outages) = run(&["duration=3", "faults+={link=[1,3], from=0, to=3, loss=0.0}"]);
    assert_eq!(a.estimator, b.estimator, "p = 0 on a link changed the run");
    assert_eq!(a.vc, b.vc);
    assert_eq!(outages[&1].len(), 1, "one fault window, one metrics entry");
}

#[test]
fn loss_on_a_link_changes_the_run_and_is_reproducible() {
    let sets = ["duration=3", "faults+={link=[1,3], from=0, to=3, loss=0.3}"];
    let (_, a, _) = run(&sets);
    let (_, b, _) = run(&sets);
    let (_, clean, _) = run(&["duration=3"]);
    assert_eq!(a.estimator, b.estimator, "the same table must lose the same messages");
    assert_ne!(a.estimator, clean.estimator, "30 % loss on 1–3 changed nothing");
}

#[test]
fn cutting_the_only_leader_link_isolates_the_formation_from_the_leader() {
    // Follower 1 is the only one that hears the leader: cut 0–1 for 2 s and
    // every follower dead-reckons on consensus with the others.
    let (_, p, outages) = run(&["duration=8", "faults+={link=[0,1], from=2, to=4}"]);
    let peak = outages[&4][0].peak_estimator_error.expect("samples in the span");
    assert!(peak > 0.01, "follower 4's estimate stayed within {peak:.4} m with the leader gone for 2 s");
    assert!(p.estimator.iter().all(|e| e.is_finite()));
}

/// FNV-1a, 64 bit: enough to hold a file against a golden value.
fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3))
}

/// A fault-free paper run is byte for byte what main gave before the fault
/// table existed: the golden values are the FNV-1a hashes of
/// `formation sim scenarios/paper.toml` (30 s, every sample) built from
/// commit 5d6dd50, the last commit before docs/model.md §14.
#[test]
fn a_fault_free_paper_run_is_byte_identical_to_before_the_fault_table() {
    const GOLDEN: [(&str, u64); 6] = [
        ("summary.json", 0x9fd5a8dda69719b5),
        ("follower_1.csv", 0xc79f08674a910ff4),
        ("follower_2.csv", 0xb6b3ae9e4f111be7),
        ("follower_3.csv", 0xcfcb164c63b31af6),
        ("follower_4.csv", 0x13c5718e845e6f11),
        ("leader.csv", 0x4211b968584b5044),
    ];
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("paper");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_formation"))
        .args(["sim", SCENARIO, "-q", "--out"])
        .arg(&out)
        .status()
        .expect("formation sim");
    assert!(status.success());
    for (file, golden) in GOLDEN {
        let bytes = std::fs::read(out.join(file)).expect(file);
        assert_eq!(fnv(&bytes), golden, "{file} ({} bytes) differs from the fault-free run of 5d6dd50", bytes.len());
    }
}
