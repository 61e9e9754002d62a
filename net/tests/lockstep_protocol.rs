//! The lock-step protocol in virtual time: four followers in a ring, each
//! with the agents' own `Inbox` (the fault table applied on arrival) and
//! `gate::Kept` (what a waiting follower repeats), over a network that loses
//! packets or drops a closed link's queue. No sockets, no sleeps: a round
//! stands for the agents' 100 ms repeat period, and every round every
//! follower delivers what arrived, steps as far as its inputs allow, or
//! repeats what its neighbours may lack. What the namespace lab found the
//! hard way, replayed in microseconds:
//!
//! - a message lost with a closed link is sent again and the run completes;
//! - the fault table lets a follower run ahead of a neighbour whose messages
//!   it removes (it does not wait for them);
//! - 30 % loss on follower 2 stalled a run when a waiting follower repeated
//!   only its last 3 messages; repeating from the slowest neighbour's step
//!   does not stall.

use formation_agent::{LeaderState, LinkLoss, LossWindow};
use formation_net::gate::{Kept, FOLLOWER_KEPT};
use formation_net::inbox::{self, Inbox, Source};
use formation_topology::wire::{self, EstimateMsg, Header, FORMAT_VERSION};

const IDS: [u32; 4] = [1, 2, 3, 4];

/// The ring's neighbours of each follower (1–2–3–4–1).
fn neighbours(id: u32) -> Vec<u32> {
    let n = IDS.len() as u32;
    vec![(id + n - 2) % n + 1, id % n + 1]
}

/// How the waiting followers repeat: as the agents do (from the slowest
/// neighbour's step), or as they did before the 30 % loss stall (the last
/// few only).
#[derive(Clone, Copy, PartialEq, Debug)]
enum Repeat {
    FromSlowest,
    LastOnly,
}

struct Node {
    id: u32,
    neighbours: Vec<u32>,
    inbox: Inbox,
    kept: Kept,
    /// The step this node waits for the inputs of.
    k: u64,
}

/// A deterministic packet-loss draw (xorshift), so a failure replays.
struct Draws(u64);

impl Draws {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// What happens to the packets of a link in a round.
struct Network {
    /// (from, to) → packets in flight.
    queues: std::collections::BTreeMap<(u32, u32), Vec<Vec<u8>>>,
    draws: Draws,
    /// Physical loss on every link of `node` while `rounds` holds the round.
    loss: Option<(u32, f64, std::ops::Range<u64>)>,
    /// Links of `node` closed (their queues dropped) while the round is in range.
    closed: Option<(u32, std::ops::Range<u64>)>,
}

impl Network {
    fn send(&mut self, round: u64, from: u32, to: u32, bytes: &[u8]) {
        if let Some((node, p, r)) = &self.loss {
            if (from == *node || to == *node) && r.contains(&round) && self.draws.next() < *p {
                return;
            }
        }
        if let Some((node, r)) = &self.closed {
            if (from == *node || to == *node) && r.contains(&round) {
                return;
            }
        }
        self.queues.entry((from, to)).or_default().push(bytes.to_vec());
    }

    fn close_links(&mut self, round: u64) {
        if let Some((node, r)) = &self.closed {
            if r.contains(&round) {
                self.queues.retain(|&(a, b), _| a != *node && b != *node);
            }
        }
    }

    fn deliver(&mut self, to: u32) -> Vec<(u32, Vec<u8>)> {
        let mut out = Vec::new();
        for (&(from, dest), q) in self.queues.iter_mut() {
            if dest == to {
                out.extend(q.drain(..).map(|b| (from, b)));
            }
        }
        out
    }
}

fn message(id: u32, step: u64) -> Vec<u8> {
    wire::encode(&EstimateMsg {
        header: Header { version: FORMAT_VERSION, sender: id, step, time_s: step as f64 * 1e-3, sent_ns: 0 },
        state: LeaderState::default(),
        fresh: true,
    })
}

/// The run's outcome: the round each follower completed `steps` in (None:
/// it stalled), and the furthest any follower got ahead of follower 2.
struct Outcome {
    finished: Vec<Option<u64>>,
    ahead_of_2: u64,
    republished: u64,
}

/// Runs `steps` lock-step steps of the ring for at most `rounds` rounds.
fn run(steps: u64, rounds: u64, net: &mut Network, table: &[LossWindow], repeat: Repeat) -> Outcome {
    let mut nodes: Vec<Node> = IDS
        .iter()
        .map(|&id| {
            let nb = neighbours(id);
            let mut inbox = Inbox::new(nb.len(), true);
            // The fault table, on follower 2's links, applied at the receiver (seed 7).
            let windows = |j: u32| if j == 2 || id == 2 { table } else { &[] };
            inbox.set_links(nb.iter().map(|&j| LinkLoss::new(7, j, id, windows(j))).collect());
            // With faults a neighbour may be further ahead (as the agents
            // allow): the longest window and a step per follower.
            let longest = table.iter().map(|w| w.to_k - w.from_k).max().unwrap_or(0);
            if longest > 0 {
                for slot in 0..nb.len() {
                    inbox.set_ahead(slot, inbox::LOCKSTEP_AHEAD + longest + IDS.len() as u64);
                }
            }
            Node { id, neighbours: nb, inbox, kept: Kept::new(FOLLOWER_KEPT), k: 0 }
        })
        .collect();
    // Step 0's message, as every follower publishes at start.
    for n in &mut nodes {
        let m = message(n.id, 0);
        n.kept.push(0, m.clone());
        for &j in &n.neighbours {
            net.send(0, n.id, j, &m);
        }
    }
    let mut finished = vec![None; nodes.len()];
    let (mut ahead_of_2, mut republished) = (0, 0);
    let mut taken = Vec::new();
    for round in 0..rounds {
        net.close_links(round);
        for n in &mut nodes {
            for (from, bytes) in net.deliver(n.id) {
                if let Ok((Source::Neighbour(slot), msg)) = inbox::check(Some(from), &bytes, false, &n.neighbours) {
                    n.inbox.accept(slot, &msg);
                }
            }
            let before = n.k;
            // Step as far as the inputs allow (a node waits for step k's
            // messages of its neighbours before it publishes k + 1).
            while n.k < steps && n.inbox.has_all(n.k) {
                n.inbox.take(n.k, &mut taken);
                n.k += 1;
                n.inbox.set_step(n.k);
                let m = message(n.id, n.k);
                n.kept.push(n.k, m.clone());
                for &j in &n.neighbours {
                    net.send(round, n.id, j, &m);
                }
            }
            if n.k == steps && finished[(n.id - 1) as usize].is_none() {
                finished[(n.id - 1) as usize] = Some(round);
            }
            // Waiting (or done, lingering): repeat what the neighbours may lack.
            if n.k == before {
                let slowest = match repeat {
                    Repeat::FromSlowest => n.inbox.slowest_heard(n.neighbours.len()),
                    Repeat::LastOnly => None,
                };
                let again: Vec<Vec<u8>> = n.kept.follower_repeats(slowest).cloned().collect();
                for m in &again {
                    for &j in &n.neighbours {
                        net.send(round, n.id, j, m);
                    }
                }
                republished += again.len() as u64;
            }
        }
        let k2 = nodes[1].k;
        ahead_of_2 = ahead_of_2.max(nodes.iter().map(|n| n.k.saturating_sub(k2)).max().unwrap_or(0));
        if finished.iter().all(Option::is_some) {
            break;
        }
    }
    Outcome { finished, ahead_of_2, republished }
}

fn lossless() -> Network {
    Network { queues: Default::default(), draws: Draws(0x9e37_79b9_7f4a_7c15), loss: None, closed: None }
}

/// Every follower reaches the last step, in lock-step, with nothing lost.
#[test]
fn a_lossless_ring_completes_in_lockstep() {
    let out = run(500, 10_000, &mut lossless(), &[], Repeat::FromSlowest);
    assert!(out.finished.iter().all(Option::is_some), "stalled: {:?}", out.finished);
    assert!(out.ahead_of_2 <= inbox::LOCKSTEP_AHEAD, "no fault: at most one step apart, got {}", out.ahead_of_2);
}

/// Follower 3's links closed for 50 rounds: what was queued is lost with
/// them, and the waiting followers' repeats bring it back.
#[test]
fn a_message_lost_with_a_closed_link_is_sent_again() {
    let mut net = Network { closed: Some((3, 20..70)), ..lossless() };
    let out = run(2_000, 20_000, &mut net, &[], Repeat::FromSlowest);
    assert!(out.finished.iter().all(Option::is_some), "stalled after the link closed: {:?}", out.finished);
    assert!(out.republished > 0, "nothing was repeated, so nothing was lost: the test tests nothing");
}

/// The fault table removes 30 % of follower 2's messages (both ways) for
/// steps 100–600 while its packets are also lost on the way (so it is
/// slow): its neighbours do not wait for what the table removes, so they
/// run ahead of it, and the run still completes.
#[test]
fn a_follower_runs_ahead_through_a_fault_window_and_the_run_completes() {
    let table = [LossWindow { from_k: 100, to_k: 600, loss: 0.3 }];
    let mut net = Network { loss: Some((2, 0.3, 0..4_000)), ..lossless() };
    let out = run(1_000, 20_000, &mut net, &table, Repeat::FromSlowest);
    assert!(out.finished.iter().all(Option::is_some), "stalled: {:?}", out.finished);
    assert!(
        out.ahead_of_2 > inbox::LOCKSTEP_AHEAD,
        "with messages removed by the table a neighbour runs ahead of follower 2: {} steps",
        out.ahead_of_2
    );
}

/// The lab's 30 % loss stall: the fault table removes 30 % of follower 2's
/// messages in a window while the network also loses 30 % of the packets
/// of follower 2's links. Repeating only the last few messages leaves a
/// neighbour behind waiting for ever; repeating from the slowest
/// neighbour's step completes.
#[test]
fn thirty_percent_loss_does_not_stall_and_would_with_the_old_repeat() {
    let table = [LossWindow { from_k: 50, to_k: 1_500, loss: 0.3 }];
    let lossy = || Network { loss: Some((2, 0.3, 0..4_000)), ..lossless() };
    let now = run(2_000, 20_000, &mut lossy(), &table, Repeat::FromSlowest);
    assert!(now.finished.iter().all(Option::is_some), "stalled with the repeat from the slowest: {:?}", now.finished);
    let before = run(2_000, 20_000, &mut lossy(), &table, Repeat::LastOnly);
    assert!(
        before.finished.iter().any(Option::is_none),
        "repeating the last {} only completed too ({:?}): this loss pattern does not reproduce the stall",
        formation_net::gate::REPEATED,
        before.finished
    );
}
