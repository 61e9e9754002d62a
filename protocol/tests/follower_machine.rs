//! The agents' own follower machine ([`FollowerMachine`]) on virtual time: four of
//! them in the paper's ring with the real leader machine, over a network of
//! queues that can lose packets, close a node's links, delay them or forge
//! one (`formation_protocol::testing`). No sockets, no threads, no clock:
//! each machine is handed what arrived and the time, and its answers go
//! back on the network. What the namespace lab found the hard way,
//! replayed in milliseconds:
//!
//! - lock-step with nothing lost equals the simulator bit for bit;
//! - a message lost with a closed link is sent again and the run completes;
//! - the fault table lets a follower run ahead of a neighbour whose
//!   messages it removes, and 30 % physical loss on top does not stall;
//! - the look-ahead window is the documented one, to the step;
//! - a follower killed mid-way through its last fan-out is the died row
//!   for every other, its last estimate carried by the step named;
//! - real time: a delay, a silent source, a message from the future, a
//!   restart's rejoin step, and a step of the leader's clock.

use std::path::Path;
use std::time::Duration;

use formation_leader::LeaderState;
use formation_protocol::follower::{self, FollowerMachine, Options};
use formation_protocol::telemetry::{EventKind, Telemetry};
use formation_protocol::testing::{start_at_epoch, Faults, World, EPOCH};
use formation_protocol::wire::{self, EstimateMsg, Header, FORMAT_VERSION};
use formation_protocol::Now;
use formation_record::FollowerSample;
use formation_scenario::Scenario;
use formation_sim::{Observer, SimFollower, Simulation};

fn paper(sets: &[&str]) -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenarios/paper.toml");
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    Scenario::load(&path, &sets).expect("the paper scenario")
}

/// The simulator's samples of every follower.
fn simulate(s: &Scenario) -> Vec<Vec<(u64, [f64; 5])>> {
    struct Rows(Vec<Vec<(u64, [f64; 5])>>);
    impl Observer for Rows {
        fn follower(&mut self, i: usize, k: u64, r: &formation_record::Row, _: bool) -> std::io::Result<()> {
            self.0[i].push((k, [r.x, r.y, r.theta, r.tau_l, r.tau_r]));
            Ok(())
        }
    }
    let mut rows = Rows(vec![Vec::new(); s.followers.len()]);
    Simulation::new(s).run(&mut rows, |_| {}).expect("the simulation runs");
    rows.0
}

fn bits(samples: &[FollowerSample]) -> Vec<(u64, [f64; 5])> {
    samples.iter().map(|s| (s.k, [s.pose.x, s.pose.y, s.pose.theta, s.torque_l, s.torque_r])).collect()
}

/// The first (step, follower) where the machines and the simulator differ.
fn first_difference(w: &World, sim: &[Vec<(u64, [f64; 5])>]) -> Option<String> {
    for (i, rows) in sim.iter().enumerate() {
        let got = bits(&w.samples(i));
        if got.len() != rows.len() {
            return Some(format!("follower {}: {} samples, the simulator {}", w.id(i), got.len(), rows.len()));
        }
        for (a, b) in got.iter().zip(rows) {
            let same = a.0 == b.0 && a.1.iter().zip(&b.1).all(|(x, y)| x.to_bits() == y.to_bits());
            if !same {
                return Some(format!("follower {} at step {}: {:?} against the simulator's {:?}", w.id(i), a.0, a, b));
            }
        }
    }
    None
}

const LOCKSTEP: &[&str] = &["duration=2", "timing=lockstep"];

/// Lock-step with nothing lost: the machines' samples are the simulator's, bit for bit.
#[test]
fn lockstep_machines_equal_the_simulator_bit_for_bit() {
    let s = paper(LOCKSTEP);
    let sim = simulate(&s);
    let mut w = World::new(s, Faults::default());
    w.start_all();
    w.drive(Duration::from_secs(600));
    assert!(w.all_ok(), "not every follower completed: {:?}", w.outcomes());
    assert_eq!(first_difference(&w, &sim), None);
}

/// Follower 2 killed mid-way through the fan-out of its estimate of step
/// 41, sent as it turned to step 41 (peers: one link's queue was written,
/// the others' not): one listener gets it, the others never will. The
/// step named is 42 (the greatest anyone holds, + 1), that last estimate
/// goes to every node with it, and every other follower completes as the
/// simulator's died row `{ node = 2, from = 42 Δt, died = true }`, bit for
/// bit. Without the estimate carried, the others waited for it until the
/// stall timeout.
#[test]
fn a_follower_killed_mid_way_through_its_last_fan_out_is_the_died_row_for_every_other() {
    let s = paper(LOCKSTEP);
    // (A packet takes 1 ms: the kill lands between the send and the arrival.)
    let mut w = World::new(s.clone(), Faults { latency: Duration::from_millis(1), ..Faults::default() });
    w.start_all();
    let i2 = (0..4).find(|&i| w.id(i) == 2).expect("follower 2");
    while w.followers[i2].step().is_none_or(|k| k < 41) {
        assert!(w.step(), "the run ended before follower 2's step 41");
    }
    let listeners: Vec<u32> = w.listeners(2).into_iter().filter(|&l| l != wire::LEADER_ID).collect();
    assert!(listeners.len() >= 2, "follower 2's estimates reach {listeners:?}: no fan-out to cut");
    w.kill(2, &listeners[..1]);
    // What was on the way to the one listener arrives before it says what it holds.
    let first = (0..4).find(|&i| w.id(i) == listeners[0]).expect("the listener");
    while w.followers[first].holding_of(2, 0).estimate < Some(41) {
        assert!(w.step(), "follower {}'s last estimate from 2 never arrived", listeners[0]);
    }
    let died = w.name_death(2);
    assert_eq!(died.at_k, 42, "{died:?}");
    assert_eq!(died.estimate.map(|m| m.header.step), Some(41), "its last estimate goes with the step");
    w.drive(Duration::from_secs(600));
    assert!(w.all_ok(), "a follower that missed the last estimate stalled: {:?}", w.outcomes());
    let dt = s.dt_s;
    let model = simulate(&paper(
        &[LOCKSTEP, &[format!("faults+={{node=2, from={}, died=true}}", 42.0 * dt).as_str()]].concat(),
    ));
    for i in (0..4).filter(|&i| i != i2) {
        let (got, want) = (bits(&w.samples(i)), &model[i]);
        let first = got
            .iter()
            .zip(want)
            .position(|(a, b)| a.0 != b.0 || a.1.iter().zip(&b.1).any(|(x, y)| x.to_bits() != y.to_bits()));
        assert!(
            got.len() == want.len() && first.is_none(),
            "follower {}: {} samples, the model {}; first difference at {first:?}",
            w.id(i),
            got.len(),
            want.len()
        );
    }
}

/// Follower 3's links closed for 5 s of virtual time: what was queued is
/// lost with them, the waiting followers' repeats bring it back, and the
/// run still equals the simulator.
#[test]
fn a_message_lost_with_a_closed_link_is_sent_again() {
    let s = paper(LOCKSTEP);
    let sim = simulate(&s);
    let closed = EPOCH + Duration::from_millis(200)..EPOCH + Duration::from_millis(5_200);
    // (A packet takes 1 ms: the run lasts long enough in virtual time to
    // meet the closed link.)
    let faults = Faults { closed: Some((3, closed)), latency: Duration::from_millis(1), ..Faults::default() };
    let mut w = World::new(s, faults);
    w.start_all();
    w.drive(Duration::from_secs(600));
    assert!(w.all_ok(), "stalled after the link closed: {:?}", w.outcomes());
    let republished: u64 = (0..4).map(|i| w.counters(i).republished).sum();
    assert!(republished > 0, "nothing was repeated, so nothing was lost: the test tests nothing");
    assert_eq!(first_difference(&w, &sim), None, "a repeat is the message it repeats");
}

/// The fault table removes 30 % of follower 2's messages (both ways) for
/// 0.1–0.6 s while 30 % of its packets are also lost on the way: its
/// neighbours do not wait for what the table removes, so they run ahead of
/// it; the run completes and is still the simulator's (which applies the
/// same table).
#[test]
fn thirty_percent_loss_through_a_fault_window_completes_and_equals_the_simulator() {
    let mut sets = LOCKSTEP.to_vec();
    sets.push("faults+={node=2, from=0.1, to=0.6, loss=0.3}");
    let s = paper(&sets);
    let sim = simulate(&s);
    let lossy = EPOCH..EPOCH + Duration::from_secs(3_600);
    let faults = Faults { loss: Some((2, 0.3, lossy)), latency: Duration::from_millis(1), ..Faults::default() };
    let mut w = World::new(s, faults);
    w.start_all();
    let mut ahead_of_2 = 0;
    let end = w.now + Duration::from_secs(600);
    while w.now < end && !w.followers.iter().all(|f| f.outcome().is_some()) && w.step() {
        let at = |i: usize| w.followers[i].step().unwrap_or(w.scenario.steps() + 1);
        let k2 = at(1);
        ahead_of_2 = ahead_of_2.max((0..4).map(|i| at(i).saturating_sub(k2)).max().unwrap_or(0));
    }
    assert!(w.all_ok(), "stalled: {:?}", w.outcomes());
    assert!(
        ahead_of_2 > 2,
        "with messages removed by the table a neighbour runs ahead of follower 2: {ahead_of_2} steps"
    );
    assert!(w.counters(0).fault_lost > 0, "the table removed nothing at follower 1");
    assert_eq!(first_difference(&w, &sim), None);
}

/// Hands follower 1 a genuine message of neighbour 2 for `step`, and says
/// whether it was refused as from the future.
fn from_the_future(w: &mut World, step: u64) -> bool {
    from_the_future_of(w, 2, step)
}

/// The same for a message of `sender` (0: the leader).
fn from_the_future_of(w: &mut World, sender: u32, step: u64) -> bool {
    let before = w.followers[0].counters().rejected.future;
    let bytes = wire::encode(&EstimateMsg {
        header: Header { version: FORMAT_VERSION, sender, step, time_s: 0.0, sent_ns: 0 },
        state: LeaderState::default(),
        fresh: true,
        term: u32::from(sender == 0),
    });
    let now = w.now;
    w.followers[0].handle_estimate(Some(sender), &bytes, Some(now));
    w.followers[0].counters().rejected.future > before
}

/// The look-ahead window, to the step, as docs/model.md §14 states it: in
/// lock-step a neighbour's message may be 2 steps ahead of the receiver's
/// step (no fault), and with a fault table the longest window plus one
/// step per follower more; the leader's, its window of 200 steps more.
/// Changing the agents' rule by one step fails here.
#[test]
fn the_lockstep_look_ahead_is_the_documented_window_to_the_step() {
    // No fault: follower 1 at step 0 takes step 2 of follower 2, refuses 3.
    let mut w = World::new(paper(LOCKSTEP), Faults::default());
    assert!(!from_the_future(&mut w, 2), "step 2 of a neighbour is within the window");
    assert!(from_the_future(&mut w, 3), "step 3 of a neighbour is beyond the window");
    // The leader may run its window of 200 steps further.
    assert!(!from_the_future_of(&mut w, 0, 202), "step 202 of the leader is within its window");
    assert!(from_the_future_of(&mut w, 0, 203), "step 203 of the leader is beyond its window");
    // A fault window of 0.5 s (500 steps) and four followers: 2 + 500 + 4.
    let mut sets = LOCKSTEP.to_vec();
    sets.push("faults+={node=3, from=0.2, to=0.7}");
    let mut w = World::new(paper(&sets), Faults::default());
    assert!(!from_the_future(&mut w, 506), "506 steps ahead is within the fault window's allowance");
    assert!(from_the_future(&mut w, 507), "507 steps ahead is beyond it");
}

const REALTIME: &[&str] = &["duration=3", "timing=realtime"];

/// Real time with a 5 ms link latency: a follower publishes its message
/// for step k + 1 while at step k, so every message is used at least 4
/// steps after the step it is for (5 ms on the way less the step it was
/// early), its latency is the link's, and nothing is refused.
#[test]
fn realtime_with_a_delay_uses_messages_as_old_as_the_delay() {
    let s = paper(REALTIME);
    let mut w = World::new(s, Faults { latency: Duration::from_millis(5), ..Faults::default() });
    w.start_all();
    w.run(Duration::from_millis(1), Duration::from_secs(10));
    assert!(w.all_ok(), "{:?}", w.outcomes());
    for i in 0..4 {
        let c = w.counters(i);
        assert_eq!(c.rejected.future + c.rejected.malformed, 0, "follower {}: {:?}", w.id(i), c.rejected);
        let links = match w.telemetry[i].last() {
            Some(Telemetry::Follower { links, .. }) => links.clone(),
            _ => Vec::new(),
        };
        assert_eq!(links.len(), w.followers[i].source_ids().len(), "follower {}: {links:?}", w.id(i));
        for l in &links {
            assert!(
                l.age_steps[0] >= 4,
                "follower {} used {}'s messages younger than the delay: {l:?}",
                w.id(i),
                l.source
            );
            assert!(
                l.latency_us[0] >= 4_500,
                "follower {}: {}'s latency below the link's 5 ms: {l:?}",
                w.id(i),
                l.source
            );
        }
    }
}

/// Real time: follower 3 cut off from 1.0 to 1.5 s. Its neighbours name it
/// silent after the silence timeout and heard again after; it is isolated,
/// publishes nothing while isolated (the publish rule), and rejoins.
#[test]
fn realtime_a_silent_source_is_named_and_an_isolated_follower_keeps_quiet() {
    let s = paper(REALTIME);
    let cut = EPOCH + Duration::from_millis(1_000)..EPOCH + Duration::from_millis(1_500);
    let mut w = World::new(s, Faults { closed: Some((3, cut)), ..Faults::default() });
    w.start_all();
    w.run(Duration::from_millis(1), Duration::from_secs(10));
    assert!(w.all_ok(), "{:?}", w.outcomes());
    let (i1, i3) = (w.scenario.index_of(1).unwrap(), w.scenario.index_of(3).unwrap());
    let events1: Vec<EventKind> = w.events(i1).iter().map(|e| e.what).collect();
    assert!(events1.contains(&EventKind::Silent(3)), "follower 1 never named 3 silent: {events1:?}");
    let silent_at = w.events(i1).iter().find(|e| e.what == EventKind::Silent(3)).unwrap().k;
    assert!((1_000..1_500).contains(&silent_at), "3 named silent at step {silent_at}, not during the cut");
    assert!(
        w.events(i1).iter().any(|e| e.what == EventKind::Heard(3) && e.k > silent_at),
        "follower 1 never heard 3 again: {events1:?}"
    );
    let events3: Vec<EventKind> = w.events(i3).iter().map(|e| e.what).collect();
    assert!(events3.contains(&EventKind::Isolated) && events3.contains(&EventKind::Rejoined), "{events3:?}");
    let sent3 = w.counters(i3).sent;
    let steps = w.scenario.steps();
    assert!(sent3 < steps - 100, "follower 3 published {sent3} of {steps} steps: it did not keep quiet while isolated");
}

/// Real time: a neighbour's message stamped far ahead of the shared
/// clock's step is refused as from the future; one within 0.1 s is taken.
#[test]
fn realtime_a_message_from_the_future_is_refused() {
    let mut w = World::new(paper(REALTIME), Faults::default());
    w.start_all();
    w.run(Duration::from_millis(1), Duration::from_millis(500));
    let k = w.followers[0].step().expect("running");
    assert!(!from_the_future(&mut w, k + 50), "50 steps (50 ms) ahead is within the 0.1 s allowance");
    assert!(from_the_future(&mut w, k + 5_000), "5 s ahead of the shared clock is from the future");
}

/// A restart: a process that hears a start 1.5 s old resumes 0.2 s ahead
/// of the run's step; it publishes nothing until it adopts an estimate,
/// then reports its resume in telemetry and completes the run.
#[test]
fn realtime_a_restart_rejoins_ahead_of_the_run_and_adopts_before_publishing() {
    let s = paper(REALTIME);
    let start = start_at_epoch();
    assert_eq!(follower::rejoin_step(&start, 0.1, &s), Ok(0), "a start 0.1 s old is not a restart");
    let k = follower::rejoin_step(&start, 1.5, &s).expect("the run is on");
    assert_eq!(k, 1_700, "1.5 s into the run plus 0.2 s to set up, at 1 ms a step");
    assert!(follower::rejoin_step(&start, 5.0, &s).is_err(), "a 3 s run is over after 5 s");

    let mut w = World::new(s, Faults::default());
    w.start_all();
    w.run(Duration::from_millis(1), Duration::from_millis(1_500));
    // Follower 4 restarts: a fresh machine resumes at step k.
    let i4 = w.scenario.index_of(4).unwrap();
    let opts = Options { stall_timeout: Duration::from_secs(60), physical_node_faults: false };
    let body = Box::new(SimFollower::new(&w.scenario, i4));
    w.followers[i4] = FollowerMachine::new(&w.scenario, i4, body, &opts);
    w.telemetry[i4].clear();
    let pose = w.scenario.followers[i4].pose;
    let now = w.now;
    w.followers[i4].start(&w.start, Some((k, pose)), now);
    assert_eq!(w.followers[i4].poll_transmit(), None, "a restart publishes nothing before it adopts an estimate");
    w.run(Duration::from_millis(1), Duration::from_secs(10));
    assert!(w.all_ok(), "{:?}", w.outcomes());
    let first = w.samples(i4).first().map(|s| s.k);
    assert_eq!(first, Some(k), "the restart's first sample is its rejoin step");
    let resumed = match w.telemetry[i4].first() {
        Some(Telemetry::Follower { resumed, .. }) => *resumed,
        _ => None,
    };
    assert_eq!(resumed.map(|r| r.k), Some(k), "the restart reports where it resumed");
    assert!(w.counters(i4).sent > 0, "the restart never published");
}

/// How a process that hears the start joins, one rule for both timings: a
/// start less than 0.2 s old is a fresh start; a real-time restart resumes
/// 0.2 s ahead of the run; a lock-step restart listens 0.3 s to its
/// neighbours' repeats first (a follower with none starts afresh).
#[test]
fn a_late_process_joins_by_one_rule_in_both_timings() {
    let start = start_at_epoch();
    let rt = paper(REALTIME);
    assert_eq!(follower::joining(&start, 0.1, &rt, 0), Ok(follower::Joining::Fresh));
    assert_eq!(follower::joining(&start, 1.5, &rt, 0), Ok(follower::Joining::At(1_700)));
    let ls = paper(LOCKSTEP);
    assert_eq!(follower::joining(&start, 0.1, &ls, 0), Ok(follower::Joining::Fresh));
    let listen = follower::joining(&start, 1.5, &ls, 0);
    assert_eq!(listen, Ok(follower::Joining::ListenFirst(Duration::from_millis(300))));
    let mut alone = paper(LOCKSTEP);
    alone.graph = formation_scenario::Graph::new(vec![1, 2, 3, 4], &[], vec![true; 4]);
    assert_eq!(follower::joining(&start, 1.5, &alone, 0), Ok(follower::Joining::Fresh), "no neighbour to listen to");
    assert!(follower::joining(&start, 5.0, &rt, 0).is_err(), "a 3 s run is over after 5 s");
}

/// Real time: the leader's clock steps 1 s ahead at t = 1 s (its stamps
/// jump). No decision of the follower compares clocks: every sample is the
/// one of the same run without the step, bit for bit.
#[test]
fn realtime_a_step_of_the_leaders_clock_changes_nothing() {
    let run = |step: Option<(Now, Duration)>| {
        let mut w = World::new(paper(REALTIME), Faults { leader_clock_step: step, ..Faults::default() });
        w.start_all();
        w.run(Duration::from_millis(1), Duration::from_secs(10));
        assert!(w.all_ok(), "{:?}", w.outcomes());
        (0..4).map(|i| bits(&w.samples(i))).collect::<Vec<_>>()
    };
    let plain = run(None);
    let stepped = run(Some((EPOCH + Duration::from_secs(1), Duration::from_secs(1))));
    assert_eq!(plain.len(), stepped.len());
    for (i, (a, b)) in plain.iter().zip(&stepped).enumerate() {
        let same = a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|(x, y)| x.0 == y.0 && x.1.iter().zip(&y.1).all(|(p, q)| p.to_bits() == q.to_bits()));
        assert!(same, "follower {}: the leader's clock step changed its run", i + 1);
    }
}

/// Real time: follower 3 told to leave at 1 s (its process got SIGTERM)
/// sends its last batch marked done and left before the step it would
/// take next, with every step it took; it publishes nothing after; its
/// machine ends well, and the others run on to the end, naming it silent
/// (as docs/model.md §14's node fault from then on).
#[test]
fn realtime_a_follower_that_leaves_says_so_in_its_last_batch_and_the_others_run_on() {
    let mut w = World::new(paper(REALTIME), Faults::default());
    w.start_all();
    w.run(Duration::from_millis(1), Duration::from_secs(1));
    let i3 = w.scenario.index_of(3).unwrap();
    w.followers[i3].handle_leave("SIGTERM");
    assert!(w.followers[i3].poll_transmit().is_none(), "nothing is published after the leave");
    w.run(Duration::from_millis(1), Duration::from_secs(10));
    assert!(matches!(w.followers[i3].outcome(), Some(Ok(()))), "{:?}", w.followers[i3].outcome());
    let last = w.telemetry[i3].last().expect("a last batch").clone();
    let Telemetry::Follower { done, left, .. } = last else { panic!("not a follower batch") };
    let samples = w.samples(i3);
    let at_k = left.as_ref().map(|l| l.at_k).expect("the last batch says the follower left");
    assert!(done, "the last batch is done");
    assert_eq!(left.map(|l| l.why), Some("SIGTERM".to_string()));
    assert!((990..=1_010).contains(&at_k), "left before step {at_k}, not at 1 s");
    assert_eq!(samples.len() as u64, at_k, "every step taken before the leave is in its telemetry");
    // The leave is news for the operator, which a quiet agent keeps to itself.
    let news: Vec<String> = std::iter::from_fn(|| w.followers[i3].poll_news()).collect();
    assert_eq!(news, [format!("follower 3: leaves the run before step {at_k}: SIGTERM")]);
    assert!(samples.iter().enumerate().all(|(n, s)| s.k == n as u64), "its samples are steps 0..{at_k}");
    let steps = w.scenario.steps();
    for (i, f) in w.followers.iter().enumerate().filter(|&(i, _)| i != i3) {
        assert!(matches!(f.outcome(), Some(Ok(()))), "follower {}: {:?}", w.id(i), f.outcome());
        assert_eq!(w.samples(i).len() as u64, steps + 1, "follower {} ran to the end", w.id(i));
    }
    let i1 = w.scenario.index_of(1).unwrap();
    let silent = w.events(i1).iter().find(|e| e.what == EventKind::Silent(3)).map(|e| e.k);
    assert!(silent.is_some_and(|k| k > at_k), "follower 1 names 3 silent after it left: {silent:?}");
}
