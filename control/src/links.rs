//! Missing messages, link faults and rejoining (docs/model.md §14), on the receiving
//! side: which messages a fault removes, what a follower hears at step k,
//! and how it takes up an estimate again after isolation.
//!
//! Everything here is pure and allocation-free once built: the simulator,
//! the lock-step networked agent and the real-time agent drive the same
//! types with the same step indices, so the same scenario loses the same
//! messages in all three.

use rand_chacha::rand_core::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use formation_leader::LeaderState;
use formation_plant::wrap;
use formation_plant::Pose;

/// Steps k with `from_k ≤ k < to_k` on which a message of the link is lost
/// with probability `loss` (docs/model.md §14's fault window, in steps).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LossWindow {
    pub from_k: u64,
    pub to_k: u64,
    pub loss: f64,
}

/// A maximal run of covered steps with one loss probability, and how many
/// covered steps of the link come before it (the index of its first draw).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Segment {
    from_k: u64,
    to_k: u64,
    loss: f64,
    draws_before: u64,
}

/// The faults of one directed link (sender → receiver) and the receiver's
/// generator for it.
///
/// docs/model.md §14: a message of step k on a covered link is lost with probability
/// p (the largest p of the faults covering the link at k); the receiver
/// decides with a generator of its own for the link, seeded from (scenario
/// seed, sender, receiver), one uniform draw per covered step in step order.
/// The n-th covered step uses the n-th draw of the stream, found by position
/// in the ChaCha8 stream, so the answer for step k does not depend on which
/// steps were asked about before, or in which order.
#[derive(Clone, Debug)]
pub struct LinkLoss {
    segments: Vec<Segment>,
    rng: ChaCha8Rng,
    /// The draw index the generator's cursor is at: asking in step order
    /// reads on without seeking (a seek regenerates the block buffer).
    cursor: u64,
}

impl LinkLoss {
    /// The link's faults; `windows` may overlap and come in any order.
    pub fn new(seed: u64, sender: u32, receiver: u32, windows: &[LossWindow]) -> Self {
        let mut cuts: Vec<u64> =
            windows.iter().filter(|w| w.from_k < w.to_k).flat_map(|w| [w.from_k, w.to_k]).collect();
        cuts.sort_unstable();
        cuts.dedup();
        let mut segments: Vec<Segment> = Vec::new();
        let mut draws = 0u64;
        for pair in cuts.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            let loss = windows
                .iter()
                .filter(|w| w.from_k <= a && b <= w.to_k)
                .map(|w| w.loss)
                .fold(None, |m: Option<f64>, p| Some(m.map_or(p, |m| m.max(p))));
            let Some(loss) = loss else { continue };
            match segments.last_mut() {
                Some(s) if s.to_k == a && s.loss == loss => s.to_k = b,
                _ => segments.push(Segment { from_k: a, to_k: b, loss, draws_before: draws }),
            }
            draws += b - a;
        }
        Self { segments, rng: ChaCha8Rng::seed_from_u64(link_seed(seed, sender, receiver)), cursor: 0 }
    }

    /// A link without faults.
    pub fn none() -> Self {
        Self { segments: Vec::new(), rng: ChaCha8Rng::seed_from_u64(0), cursor: 0 }
    }

    /// Bytes this link's loss table holds on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.segments.capacity() * std::mem::size_of::<Segment>()
    }

    /// No fault ever covers this link.
    pub fn is_empty(&self) -> bool {
        self.segments.is_empty()
    }

    /// Whether the link's message of step k is lost.
    pub fn lost(&mut self, k: u64) -> bool {
        let Some(s) = self.segments.iter().find(|s| s.from_k <= k && k < s.to_k) else { return false };
        let n = s.draws_before + (k - s.from_k);
        let loss = s.loss;
        if n != self.cursor {
            self.rng.set_word_pos(u128::from(n) * 2);
        }
        self.cursor = n + 1;
        // The n-th uniform draw in [0, 1) of the stream (53 random bits).
        let u = (self.rng.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64);
        u < loss
    }
}

/// The link generator's seed: (scenario seed, sender, receiver) mixed by
/// SplitMix64 steps, so that the two directions of a link and neighbouring
/// ids get unrelated streams (and none equals a follower's noise stream).
pub fn link_seed(seed: u64, sender: u32, receiver: u32) -> u64 {
    let mix = |mut z: u64| {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    mix(mix(mix(seed ^ 0x6c69_6e6b) ^ u64::from(sender)) ^ (u64::from(receiver) << 32))
}

/// docs/model.md §13's message from a follower: its estimate of the leader's state
/// and whether that estimate is *fresh*, i.e. not held through an isolation
/// since it last came from the leader (docs/model.md §14: `adopt` takes only fresh
/// estimates). The leader's own state is always fresh.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Message {
    pub state: LeaderState,
    pub fresh: bool,
}

impl Message {
    pub fn fresh(state: LeaderState) -> Self {
        Self { state, fresh: true }
    }
}

/// What a receiver holds from each of its sources: the newest delivered
/// message and its step. docs/model.md §14: at step k a source is heard through its
/// newest delivered message stamped at or before k if that is at most the
/// silence timeout old; otherwise it is silent.
#[derive(Clone, Debug)]
pub struct Hearing {
    last: Vec<Option<(u64, Message)>>,
    timeout_steps: u64,
}

impl Hearing {
    /// `sources` slots; `timeout_steps` = `network.silence_timeout` / Δt, rounded.
    pub fn new(sources: usize, timeout_steps: u64) -> Self {
        Self { last: vec![None; sources], timeout_steps }
    }

    /// A message of `slot` stamped `k` was delivered (older ones than held are ignored).
    pub fn deliver(&mut self, slot: usize, k: u64, msg: Message) {
        let held = &mut self.last[slot];
        if held.is_none_or(|(s, _)| s <= k) {
            *held = Some((k, msg));
        }
    }

    /// What `slot` says at step k, if it is heard.
    pub fn heard(&self, slot: usize, k: u64) -> Option<&Message> {
        self.heard_at(slot, k).map(|(_, m)| m)
    }

    /// [`Hearing::heard`] with the heard message's step.
    pub fn heard_at(&self, slot: usize, k: u64) -> Option<(u64, &Message)> {
        match &self.last[slot] {
            Some((s, msg)) if *s <= k && k - s <= self.timeout_steps => Some((*s, msg)),
            _ => None,
        }
    }

    /// Bytes this holds on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.last.capacity() * std::mem::size_of::<Option<(u64, Message)>>()
    }

    pub fn sources(&self) -> usize {
        self.last.len()
    }
}

/// What a follower does when it hears a source again after isolation
/// (`network.rejoin`, docs/model.md §14).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RejoinPolicy {
    /// The paper's law unchanged: reconverge at rate k_i.
    #[default]
    Consensus,
    /// Take the leader's state if heard, else the mean of the heard
    /// neighbours' fresh estimates.
    Adopt,
}

/// The rejoin rule of a scenario.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RejoinRule {
    pub policy: RejoinPolicy,
    /// `network.rejoin_after` in steps (at least 1): how many steps without
    /// any source make the next heard step a rejoin.
    pub after_steps: u64,
}

impl Default for RejoinRule {
    fn default() -> Self {
        Self { policy: RejoinPolicy::Consensus, after_steps: 100 }
    }
}

/// The estimate `adopt` takes (docs/model.md §14): the leader's state if heard,
/// otherwise the mean of the heard neighbours' *fresh* messages, θ as the
/// first (lowest-id) of them's θ plus the mean of the wrapped differences to
/// it. `None` when neither the leader nor a fresh neighbour is heard: an
/// estimate held through an isolation of its own is no better than ours
/// (after a router restart every follower's is), so it is not taken.
pub fn adopted<'a>(
    leader: Option<&LeaderState>,
    neighbours: impl IntoIterator<Item = &'a Message>,
) -> Option<LeaderState> {
    if let Some(l) = leader {
        return Some(*l);
    }
    let mut iter = neighbours.into_iter().filter(|m| m.fresh).map(|m| &m.state);
    let first = *iter.next()?;
    let mut sum = LeaderState { pose: Pose::new(first.pose.x, first.pose.y, 0.0), ..first };
    let mut n = 1.0;
    for m in iter {
        sum.pose.x += m.pose.x;
        sum.pose.y += m.pose.y;
        sum.pose.theta += wrap(m.pose.theta - first.pose.theta);
        sum.pose_rate.x += m.pose_rate.x;
        sum.pose_rate.y += m.pose_rate.y;
        sum.pose_rate.theta += m.pose_rate.theta;
        sum.v += m.v;
        sum.w += m.w;
        n += 1.0;
    }
    Some(LeaderState {
        pose: Pose::new(sum.pose.x / n, sum.pose.y / n, wrap(first.pose.theta + sum.pose.theta / n)),
        pose_rate: Pose::new(sum.pose_rate.x / n, sum.pose_rate.y / n, sum.pose_rate.theta / n),
        v: sum.v / n,
        w: sum.w / n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn w(from_k: u64, to_k: u64, loss: f64) -> LossWindow {
        LossWindow { from_k, to_k, loss }
    }

    #[test]
    fn a_down_link_loses_exactly_its_window() {
        let mut l = LinkLoss::new(1, 0, 3, &[w(10, 20, 1.0)]);
        let lost: Vec<u64> = (0..40).filter(|&k| l.lost(k)).collect();
        assert_eq!(lost, (10..20).collect::<Vec<_>>());
        let mut none = LinkLoss::new(1, 0, 3, &[]);
        assert!(none.is_empty() && (0..100).all(|k| !none.lost(k)));
    }

    #[test]
    fn the_loss_draw_does_not_depend_on_the_order_of_evaluation() {
        let windows = [w(100, 5000, 0.3), w(3000, 8000, 0.5)];
        let mut forward = LinkLoss::new(7, 2, 4, &windows);
        let a: Vec<bool> = (0..9000).map(|k| forward.lost(k)).collect();
        // Backwards, every other step first, a fresh instance: the same answers.
        let mut other = LinkLoss::new(7, 2, 4, &windows);
        let mut b = vec![false; 9000];
        for k in (0..9000).rev().step_by(2).chain((0..9000).rev().skip(1).step_by(2)) {
            b[k as usize] = other.lost(k);
        }
        assert_eq!(a, b);
        // Another link, or the reverse direction, draws differently.
        let mut reverse = LinkLoss::new(7, 4, 2, &windows);
        let c: Vec<bool> = (0..9000).map(|k| reverse.lost(k)).collect();
        assert_ne!(a, c);
        // The rates are p where covered (largest p of the overlap), 0 elsewhere.
        let rate = |r: std::ops::Range<usize>| a[r.clone()].iter().filter(|&&x| x).count() as f64 / r.len() as f64;
        assert!((rate(100..3000) - 0.3).abs() < 0.03, "p = 0.3 window lost {}", rate(100..3000));
        assert!((rate(3000..8000) - 0.5).abs() < 0.03, "overlap (max 0.5) lost {}", rate(3000..8000));
        assert_eq!(rate(0..100) + rate(8000..9000), 0.0);
    }

    #[test]
    fn the_nth_covered_step_uses_the_nth_draw() {
        // Two windows of the same p: the second continues the first's draws.
        let mut split = LinkLoss::new(3, 1, 2, &[w(0, 50, 0.5), w(1000, 1050, 0.5)]);
        let mut joined = LinkLoss::new(3, 1, 2, &[w(0, 100, 0.5)]);
        let a: Vec<bool> = (0..50).chain(1000..1050).map(|k| split.lost(k)).collect();
        let b: Vec<bool> = (0..100).map(|k| joined.lost(k)).collect();
        assert_eq!(a, b);
    }

    #[test]
    fn hearing_keeps_the_newest_message_within_the_timeout() {
        let mut h = Hearing::new(2, 3);
        let s = |v: f64| Message::fresh(LeaderState { v, ..Default::default() });
        assert!(h.heard(0, 0).is_none());
        h.deliver(0, 5, s(5.0));
        h.deliver(0, 4, s(4.0)); // older: ignored
        assert_eq!(h.heard(0, 5).map(|m| m.state.v), Some(5.0));
        assert_eq!(h.heard(0, 8).map(|m| m.state.v), Some(5.0));
        assert!(h.heard(0, 9).is_none(), "4 steps old with a 3-step timeout");
        assert!(h.heard(0, 4).is_none(), "never a message from the receiver's future");
        assert!(h.heard(1, 5).is_none());
    }

    #[test]
    fn adopt_takes_the_leader_or_the_neighbours_mean_across_the_seam() {
        let m = |x: f64, th: f64, v: f64| LeaderState {
            pose: Pose::new(x, 2.0 * x, th),
            pose_rate: Pose::new(v, 0.0, 0.1 * v),
            v,
            w: -v,
        };
        let leader = m(9.0, 1.0, 9.0);
        let (a, b) = (Message::fresh(m(1.0, 3.1, 1.0)), Message::fresh(m(3.0, -3.1, 2.0)));
        assert_eq!(adopted(Some(&leader), [&a, &b]), Some(leader));
        let mean = adopted(None, [&a, &b]).expect("two neighbours heard");
        assert_eq!((mean.pose.x, mean.pose.y, mean.v, mean.w), (2.0, 4.0, 1.5, -1.5));
        assert_eq!(mean.pose_rate.x, 1.5);
        // 3.1 and −3.1 are 0.083 rad apart across ±π: the mean is π, not 0.
        assert!((wrap(mean.pose.theta - std::f64::consts::PI)).abs() < 1e-12, "θ = {}", mean.pose.theta);
        assert_eq!(adopted(None, []), None);
    }

    #[test]
    fn adopt_takes_no_estimate_held_through_an_isolation() {
        let m = |x: f64| LeaderState { pose: Pose::new(x, 0.0, 0.0), ..Default::default() };
        let stale = Message { state: m(1.0), fresh: false };
        let fresh = Message::fresh(m(5.0));
        assert_eq!(adopted(None, [&stale]), None, "only a stale neighbour: nothing to adopt");
        assert_eq!(
            adopted(None, [&stale, &fresh]).map(|s| s.pose.x),
            Some(5.0),
            "the stale one is left out of the mean"
        );
        assert_eq!(adopted(Some(&m(9.0)), [&stale]).map(|s| s.pose.x), Some(9.0), "the leader is always fresh");
    }
}
