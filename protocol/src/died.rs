//! A follower killed in a lock-step run (docs/model.md §14, the died row):
//! the rule by which the others agree on the step its messages stop.
//!
//! Every agent holds a zenoh liveliness token for as long as its process
//! lives (`formation_net::died`); when one is lost, each other agent says
//! what it holds of the one that died — the newest estimate and the newest
//! pose it received ([`Holding`], on `control/holds/<its id>`) — and the
//! monitor, once every follower still running has said so, names the step
//! from which the killed follower's links are cut ([`Died`] on
//! `control/died`, computed by [`died_step`]); every node applies that one
//! step ([`crate::follower::FollowerMachine::handle_died`]), so the run stays the
//! model of the row `{ node = ID, from = L Δt, died = true }` whatever the
//! timing.
//!
//! Why the monitor and not each neighbour on its own: zenoh forwards the
//! loss of a token at its control priority, ahead of an estimate still
//! queued at the real-time priority in a router (zenoh-protocol 1.10.2,
//! `QoSType::DECLARE`), so a neighbour that decided on its own could miss
//! the last message another received.
//!
//! The greatest step anyone holds decides, and the monitor's [`Died`]
//! carries the killed follower's last messages, those of the steps before
//! it, to every node: with a router, what one node received the router
//! forwards to every other; between peers, each link has its own queue in
//! the sender, and a process killed while its last messages were on the
//! way reached some peers and not others (a test beside a busy core: two
//! followers waited the 60 s stall timeout for a pose a third had used).
//! A follower that lacks one takes it from the [`Died`] it applies.

use serde::{Deserialize, Serialize};

use crate::wire::EstimateMsg;

/// What one follower holds of a follower that died: the newest step of its
/// estimate and of its pose received (None: none, or not a source of it).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Holding {
    /// The scenario's fingerprint (a holding of another run is ignored).
    pub fingerprint: u64,
    /// Who says it.
    pub sender: u32,
    /// The follower that died.
    pub died: u32,
    pub estimate: Option<u64>,
    pub pose: Option<u64>,
    /// Where that newest pose put its robot (x, y, θ): the monitor's
    /// record of where a killed robot stands (its telemetry may end
    /// earlier, lost with its process).
    pub pose_at: Option<[f64; 3]>,
    /// Its two newest estimate messages heard, newest first.
    pub estimates: [Option<EstimateMsg>; 2],
}

/// The step before which follower `follower` is cut off, as the monitor
/// named it: its links are cut from `at_k`, and its robot stands at its
/// pose of step `at_k` − 2 from step `at_k` − 1 on (the died row's model).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Died {
    pub fingerprint: u64,
    pub follower: u32,
    pub at_k: u64,
    /// Its estimate of step `at_k` − 1, its last, as a holding has it
    /// (None: none does, or it sent none).
    pub estimate: Option<EstimateMsg>,
    /// Its robot's pose of step `at_k` − 2, where it stands ([`stands_at`]).
    pub pose: Option<[f64; 3]>,
}

impl Died {
    /// The step named from what the running followers hold of `follower`
    /// ([`died_step`]), with its last messages for those that lack them.
    pub fn named(fingerprint: u64, follower: u32, holdings: &[Holding]) -> Self {
        let at_k = died_step(holdings);
        let last = at_k.checked_sub(1);
        let estimate = holdings.iter().flat_map(|h| h.estimates).flatten().find(|m| Some(m.header.step) == last);
        Died { fingerprint, follower, at_k, estimate, pose: stands_at(holdings, at_k) }
    }
}

/// The step L of a follower that died, from what the others hold of it.
/// After its step m an agent sends its estimate of step m + 1, then its
/// pose of step m: the first estimate that never comes is L, and its last
/// pose is that of L − 2 (docs/model.md §14). A process killed between its
/// estimate of step m + 1 and its pose of step m finished round m − 1: so
/// L is the smaller of the newest estimate + 1 and the newest pose + 2,
/// over every holding (0: nothing was heard of it). With poses it is
/// always the newest pose + 2 (an agent sends its pose of m after its
/// estimate of m + 1): [`stands_at`] is then that pose.
pub fn died_step(holdings: &[Holding]) -> u64 {
    let newest_estimate = holdings.iter().filter_map(|h| h.estimate).max();
    let newest_pose = holdings.iter().filter_map(|h| h.pose).max();
    match (newest_estimate, newest_pose) {
        (Some(e), Some(p)) => (e + 1).min(p + 2),
        (Some(e), None) => e + 1,
        (None, Some(p)) => p + 2,
        (None, None) => 0,
    }
}

/// Where the robot of a follower that died stands (its pose of step
/// `at_k` − 2), if a holding has it.
pub fn stands_at(holdings: &[Holding], at_k: u64) -> Option<[f64; 3]> {
    let last = at_k.checked_sub(2)?;
    holdings.iter().find(|h| h.pose == Some(last)).and_then(|h| h.pose_at)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn h(sender: u32, estimate: Option<u64>, pose: Option<u64>) -> Holding {
        Holding { fingerprint: 1, sender, died: 2, estimate, pose, pose_at: None, estimates: [None; 2] }
    }

    fn estimate(step: u64) -> EstimateMsg {
        let header =
            crate::wire::Header { version: crate::wire::FORMAT_VERSION, sender: 2, step, time_s: 0.0, sent_ns: 0 };
        EstimateMsg { header, state: Default::default(), fresh: true, term: 1 }
    }

    /// Killed while its last fan-out was on the way: follower 1 got the
    /// estimate of 498 and the pose of 497, followers 3 and 4 neither. The
    /// step named is 1's (499), and the Died carries both messages to them.
    #[test]
    fn the_last_messages_one_follower_got_reach_the_others_with_the_step() {
        let mut first = h(1, Some(498), Some(497));
        (first.estimates, first.pose_at) = ([Some(estimate(498)), Some(estimate(497))], Some([1.0, 2.0, 0.5]));
        let mut third = h(3, Some(497), Some(496));
        third.estimates = [Some(estimate(497)), Some(estimate(496))];
        let fourth = h(4, None, Some(496));
        let d = Died::named(9, 2, &[third, fourth, first]);
        assert_eq!((d.fingerprint, d.follower, d.at_k), (9, 2, 499));
        assert_eq!(d.estimate.map(|m| m.header.step), Some(498), "the estimate of step L − 1");
        assert_eq!(d.pose, Some([1.0, 2.0, 0.5]), "the pose of step L − 2");
        // Killed between its estimate of 498 and its pose of 497: L = 498,
        // its last estimate (497) is the older of the newest two.
        let mut held = h(1, Some(498), Some(496));
        held.estimates = [Some(estimate(498)), Some(estimate(497))];
        let d = Died::named(9, 2, &[held, fourth]);
        assert_eq!((d.at_k, d.estimate.map(|m| m.header.step)), (498, Some(497)));
        assert_eq!(d.pose, None, "no holding has a pose_at for step 496");
    }

    #[test]
    fn a_process_killed_after_a_round_stops_at_its_next_estimate() {
        // Round 497 done: the estimate of 498 and the pose of 497 are out.
        assert_eq!(died_step(&[h(1, Some(498), Some(497)), h(3, Some(498), Some(497))]), 499);
        // A robot that is no neighbour hears only poses: the same step.
        assert_eq!(died_step(&[h(4, None, Some(497))]), 499);
        assert_eq!(died_step(&[h(1, Some(498), None)]), 499, "without the filter: estimates only");
    }

    #[test]
    fn a_process_killed_between_its_estimate_and_its_pose_stops_a_step_earlier() {
        // The estimate of 498 is out, its pose of 497 never left.
        assert_eq!(died_step(&[h(1, Some(498), Some(496)), h(4, None, Some(496))]), 498);
    }

    #[test]
    fn the_greatest_step_anyone_holds_decides_not_the_first_holding() {
        // Follower 3 has not yet received the last estimate, follower 1 has:
        // the router forwards it to 3 too.
        assert_eq!(died_step(&[h(3, Some(497), Some(496)), h(1, Some(498), Some(497))]), 499);
        assert_eq!(died_step(&[h(3, Some(497), Some(497)), h(1, Some(498), Some(496))]), 499);
        assert_eq!(died_step(&[]), 0, "nothing heard of it: cut off from step 0");
    }

    #[test]
    fn the_robot_stands_at_the_newest_pose_anyone_holds() {
        let mut a = h(1, Some(498), Some(497));
        a.pose_at = Some([1.0, 2.0, 0.5]);
        let mut b = h(3, Some(498), Some(496));
        b.pose_at = Some([0.9, 2.0, 0.5]);
        let l = died_step(&[b, a]);
        assert_eq!(stands_at(&[b, a], l), Some([1.0, 2.0, 0.5]), "the pose of step {}", l - 2);
        assert_eq!(stands_at(&[b], died_step(&[b])), Some([0.9, 2.0, 0.5]));
        assert_eq!(stands_at(&[h(4, Some(3), None)], 4), None, "no pose held");
    }
}
