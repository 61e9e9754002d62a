//! The receiving side of estimate messages: the checks every message
//! passes (docs/model.md §13), and the [`Inbox`] a control loop takes its inputs from
//! (docs/model.md §14's fault table applied on arrival).

use crate::latency::{LinkMeter, LinkStats};
use std::collections::{BTreeMap, VecDeque};
use std::time::Duration;

use crate::Now;

use crate::wire::{self, EstimateMsg, Reject};
use formation_control::{LinkLoss, Message};

use crate::counters::Counters;

/// Where an estimate message came from, as the receiver sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    Leader,
    /// Index of the neighbour in the receiver's neighbour list.
    Neighbour(usize),
}

/// The receiving side's checks (docs/model.md §13, issue 3): decodes, and checks that
/// the header's sender is the key's, and that the sender is one this node
/// listens to. Staleness is the caller's (it depends on the timing mode).
pub fn check(
    key_id: Option<u32>,
    bytes: &[u8],
    hears_leader: bool,
    neighbour_ids: &[u32],
) -> Result<(Source, EstimateMsg), Reject> {
    let msg = wire::decode(bytes)?;
    if key_id != Some(msg.header.sender) {
        return Err(Reject::WrongSender);
    }
    let sender = msg.header.sender;
    if sender == wire::LEADER_ID {
        return if hears_leader { Ok((Source::Leader, msg)) } else { Err(Reject::NotNeighbour) };
    }
    match neighbour_ids.iter().position(|&j| j == sender) {
        Some(n) => Ok((Source::Neighbour(n), msg)),
        None => Err(Reject::NotNeighbour),
    }
}

/// The estimate messages one node has received and not yet used, per source.
#[derive(Debug, Default)]
pub struct Inbox {
    /// Lock-step: every step received and not yet used, by step.
    pending: Vec<BTreeMap<u64, Message>>,
    /// The last step used (lock-step) or held (real time), per source.
    newest: Vec<Option<u64>>,
    /// Per source, the furthest step heard (see [`Inbox::heard_max`]).
    heard_max: Vec<Option<u64>>,
    /// Per source, its two newest messages heard, newest first (see
    /// [`Inbox::newest_heard`]).
    newest_two: Vec<[Option<EstimateMsg>; 2]>,
    /// Per source, the checked messages heard, accepted or not (see
    /// [`Inbox::signs_of_life`]).
    heard: Vec<u64>,
    /// Real time: the recent messages per source, in step order.
    history: Vec<VecDeque<(u64, Message)>>,
    pub counters: Counters,
    lockstep: bool,
    /// The receiver's current step (set by its control loop).
    current: u64,
    /// Per source: how many steps ahead of the receiver's a message may be.
    ahead: Vec<u64>,
    /// Real time: the shared clock (epoch, period), once the start is known.
    clock: Option<(Now, Duration)>,
    /// The time on that clock at which the messages now handed in arrived
    /// ([`Inbox::set_time`]).
    now: Option<Now>,
    /// Per source: the fault table's loss decisions for the link (docs/model.md §14).
    links: Vec<LinkLoss>,
    /// Per source: latency and age at use (see [`crate::latency`]).
    meters: Vec<LinkMeter>,
    /// Real time, per source: evidence of a second sender on its key.
    twins: Vec<Twin>,
    /// The highest term heard from the leader (0: none yet).
    term: u32,
}

/// What a receiver has seen of a second sender on one source's key (real
/// time). A sender's messages arrive in step order (one zenoh publisher, one
/// reliable link): a message older than the newest held, for a step not held
/// or held with other contents, came from another process with the same
/// identity. After [`TWIN_EVIDENCE`] of them the source is flagged, and
/// from then on its messages that run more than [`TWIN_PACE`] steps ahead
/// of the shared clock are dropped: the receiver keeps the stream that keeps
/// the run's pace, not the one that runs ahead of it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Twin {
    /// Messages that showed a second sender, or were dropped as its.
    pub messages: u64,
    /// The receiver's step when the source was flagged.
    pub since: Option<u64>,
}

/// Messages that show a second sender before a source is flagged as twinned.
pub const TWIN_EVIDENCE: u64 = 3;
/// How far ahead of the shared clock's step a genuine sender's message can
/// be: it publishes step k + 1's message during step k, and the clocks agree
/// to well under a step.
pub const TWIN_PACE: u64 = 2;

/// Lock-step: how far ahead of the receiver's step a neighbour's message can
/// be (it needs the receiver's step-k message before it publishes k + 1).
pub const LOCKSTEP_AHEAD: u64 = 2;
/// Real time: the default slack (steps) beyond the shared clock's step.
pub const REALTIME_AHEAD: u64 = 10;

impl Inbox {
    /// `sources` = neighbours (+1 for the leader, at the last slot, if heard).
    /// Every source may be `ahead` steps ahead of the receiver (see [`Inbox::set_ahead`]).
    pub fn new(sources: usize, lockstep: bool) -> Self {
        Self {
            pending: vec![BTreeMap::new(); sources],
            newest: vec![None; sources],
            heard_max: vec![None; sources],
            newest_two: vec![[None; 2]; sources],
            heard: vec![0; sources],
            history: vec![VecDeque::new(); sources],
            counters: Counters::default(),
            lockstep,
            current: 0,
            ahead: vec![if lockstep { LOCKSTEP_AHEAD } else { REALTIME_AHEAD }; sources],
            clock: None,
            now: None,
            links: vec![LinkLoss::none(); sources],
            meters: vec![LinkMeter::default(); sources],
            twins: vec![Twin::default(); sources],
            term: 0,
        }
    }

    /// The highest term heard from the leader (0: none yet).
    pub fn term(&self) -> u32 {
        self.term
    }

    /// The leader's message of `slot` is of `term`: whether it may be used
    /// (docs/model.md §14). Of an older term than one heard: refused. Of a
    /// newer one: taken from now on, in real time from its first message
    /// on (the new leader's steps may be behind the old one's, and a second
    /// stream on the key is not a twin).
    fn leader_term(&mut self, slot: usize, term: u32) -> bool {
        if term < self.term {
            self.counters.rejected.add(Reject::OldTerm);
            return false;
        }
        if term > self.term {
            self.term = term;
            if !self.lockstep {
                (self.newest[slot], self.twins[slot]) = (None, Twin::default());
                self.history[slot].clear();
            }
        }
        true
    }

    /// Per source, what was seen of a second sender on its key.
    pub fn twins(&self) -> &[Twin] {
        &self.twins
    }

    /// The fault table's loss decisions per source (docs/model.md §14): a message the
    /// table removes is dropped on arrival and counted (`fault_lost`), and
    /// lock-step does not wait for it.
    pub fn set_links(&mut self, links: Vec<LinkLoss>) {
        debug_assert_eq!(links.len(), self.links.len());
        if links.len() == self.links.len() {
            self.links = links;
        }
    }

    /// How many steps ahead of the receiver's step a message of `slot` may be
    /// (further ahead: rejected as [`Reject::Future`]).
    pub fn set_ahead(&mut self, slot: usize, steps: u64) {
        self.ahead[slot] = steps;
    }

    /// Real time: the shared schedule (step k due at `epoch` + k `period`),
    /// so that the receiver's step is at least the clock's.
    pub fn set_clock(&mut self, epoch: Now, period: Duration) {
        if !period.is_zero() {
            self.clock = Some((epoch, period));
        }
    }

    /// The time, on the clock of [`Inbox::set_clock`], at which the messages
    /// handed in next arrived (None: not known, and the receiver's step
    /// alone bounds how far ahead they may be). The inbox reads no clock.
    pub fn set_time(&mut self, now: Option<Now>) {
        self.now = now;
    }

    /// The furthest step heard from `slot` in a checked message, accepted or
    /// not (a restarted lock-step agent learns from it where its
    /// neighbours wait).
    pub fn heard_max(&self, slot: usize) -> Option<u64> {
        self.heard_max[slot]
    }

    /// The two newest messages heard from `slot` (by step, newest first),
    /// accepted or not: what a follower says it holds of one that died, so
    /// that a node its last fan-out missed gets them ([`crate::died`]).
    pub fn newest_heard(&self, slot: usize) -> [Option<EstimateMsg>; 2] {
        self.newest_two[slot]
    }

    /// Lock-step: whether `slot`'s message of `step` is held or was used.
    pub fn holds(&self, slot: usize, step: u64) -> bool {
        self.pending[slot].contains_key(&step) || self.newest[slot].is_some_and(|n| n >= step)
    }

    /// Lock-step: how many checked messages the sources whose step-k
    /// message is missing sent, accepted or not (a repeat of a step already
    /// held included): a neighbour that waits itself repeats its last
    /// messages, so a count that grows says it is alive, however slow
    /// ([`crate::patience`]). Counted in place: the wait polls it on every
    /// wake-up.
    pub fn signs_of_life(&mut self, k: u64) -> u64 {
        (0..self.pending.len())
            .filter(|&s| !self.pending[s].contains_key(&k) && !self.links[s].lost(k))
            .map(|s| self.heard[s])
            .sum()
    }

    /// The least advanced of the first `slots` sources, by the furthest step
    /// heard from each ([`Inbox::heard_max`]); None if none was heard.
    pub fn slowest_heard(&self, slots: usize) -> Option<u64> {
        self.heard_max[..slots].iter().flatten().copied().min()
    }

    /// The step the receiver is at (or waiting for).
    pub fn set_step(&mut self, k: u64) {
        self.current = self.current.max(k);
    }

    /// The step the run is at: the receiver's, or the shared clock's if later.
    fn pace(&self) -> u64 {
        let mut base = self.current;
        if let (Some((epoch, period)), Some(now)) = (self.clock, self.now) {
            let since = now.saturating_sub(epoch);
            base = base.max((since.as_secs_f64() / period.as_secs_f64()) as u64);
        }
        base
    }

    /// The step of the shared schedule at a sender's stamp `sent_ns` (None:
    /// no schedule, or no stamp).
    fn sent_step(&self, sent_ns: i64) -> Option<u64> {
        let (epoch, period) = self.clock?;
        let sent = Now::from_nanos(u64::try_from(sent_ns).ok().filter(|&n| n > 0)?);
        Some((sent.saturating_sub(epoch).as_secs_f64() / period.as_secs_f64()) as u64)
    }

    /// The furthest step of `slot` a genuine sender can have sent by now.
    fn limit(&self, slot: usize) -> u64 {
        self.pace().saturating_add(self.ahead[slot])
    }

    /// Whether a message of `slot` for `step` is further ahead than the
    /// receiver's step allows.
    pub fn beyond(&self, slot: usize, step: u64) -> bool {
        step > self.limit(slot)
    }

    /// Real time: whether `step` of `slot` shows (or, once flagged, comes
    /// from) a second sender on the source's key; see [`Twin`].
    fn twinned(&mut self, slot: usize, step: u64, sent_ns: i64, m: &Message) -> bool {
        let pace = self.pace();
        if self.twins[slot].since.is_some() {
            // Ahead of the run, or ahead of its own send stamp: a copy that
            // arrives late (it took two more hops, or the host is loaded) can
            // be back within the pace, but not within the time it says it
            // was sent (the genuine sender stamps step k + 1 during step k).
            let ahead_of_stamp = self.sent_step(sent_ns).is_some_and(|sent| step > sent + TWIN_PACE);
            if step > pace + TWIN_PACE || ahead_of_stamp {
                self.twins[slot].messages += 1;
                return true;
            }
            return false;
        }
        let Some(newest) = self.newest[slot] else { return false };
        if step > newest {
            return false;
        }
        let held = self.history[slot].iter().find(|(s, _)| *s == step).map(|(_, h)| h);
        if held.is_some_and(|h| same(h, m)) {
            return false; // the same message twice: not a second sender
        }
        let t = &mut self.twins[slot];
        t.messages += 1;
        if t.messages >= TWIN_EVIDENCE {
            t.since = Some(self.current);
            // Forget what ran ahead of the pace: the genuine stream carries on.
            let h = &mut self.history[slot];
            h.retain(|(s, _)| *s <= pace + TWIN_PACE);
            self.newest[slot] = h.back().map(|(s, _)| *s);
            return self.newest[slot].is_some_and(|n| step <= n);
        }
        false
    }

    /// Files a checked message, or counts it as stale or from the future;
    /// whether it was filed (and its latency worth measuring).
    pub fn accept(&mut self, slot: usize, msg: &EstimateMsg) -> bool {
        let step = msg.header.step;
        if msg.header.sender == wire::LEADER_ID && !self.leader_term(slot, msg.term) {
            return false;
        }
        self.heard[slot] += 1;
        let seen = &mut self.heard_max[slot];
        *seen = Some(seen.map_or(step, |m| m.max(step)));
        let two = &mut self.newest_two[slot];
        match two[0].map(|m| m.header.step) {
            Some(s) if s == step => {}
            Some(s) if s > step => {
                if two[1].is_none_or(|m| m.header.step < step) {
                    two[1] = Some(*msg);
                }
            }
            _ => *two = [Some(*msg), two[0]],
        }
        if step > self.limit(slot) {
            self.counters.rejected.add(Reject::Future);
            return false;
        }
        if self.links[slot].lost(step) {
            self.counters.fault_lost += 1;
            return false;
        }
        let m = Message { state: msg.state, fresh: msg.fresh };
        if !self.lockstep && self.twinned(slot, step, msg.header.sent_ns, &m) {
            self.counters.rejected.add(Reject::Stale);
            return false;
        }
        if self.newest[slot].is_some_and(|n| step <= n) {
            self.counters.late += 1;
            self.counters.rejected.add(Reject::Stale);
            return false;
        }
        self.counters.received += 1;
        if self.lockstep {
            // A republication of a pending step keeps the first copy.
            self.pending[slot].entry(step).or_insert(m);
        } else {
            self.newest[slot] = Some(step);
            let h = &mut self.history[slot];
            h.push_back((step, m));
            if h.len() > HISTORY {
                h.pop_front();
            }
        }
        true
    }

    /// A filed message of `slot`, stamped `sent_ns`, arrived at `now_ns`
    /// (both on the run's timebase).
    pub fn note_latency(&mut self, slot: usize, sent_ns: i64, now_ns: i64) {
        self.meters[slot].received(sent_ns, now_ns);
    }

    /// Per source (ids by slot), what its messages' latency and age were.
    pub fn link_stats(&self, ids: &[u32]) -> Vec<LinkStats> {
        self.meters
            .iter()
            .zip(&self.twins)
            .zip(ids)
            .map(|((m, t), &id)| LinkStats { twin_messages: t.messages, twin_since: t.since, ..m.stats(id) })
            .collect()
    }

    /// One source's loss decisions anew (a neighbour that left: its link
    /// cut from then on). Lock-step: a message already held for a step the
    /// link now loses is dropped, as if it had arrived after (a follower
    /// killed between its estimate of step L and its pose of L − 1 is cut
    /// off from L: that estimate, held by its neighbours, is never used,
    /// as in the model).
    pub fn set_link(&mut self, slot: usize, mut link: LinkLoss) {
        if let Some(p) = self.pending.get_mut(slot) {
            p.retain(|&k, _| !link.lost(k));
        }
        if let Some(l) = self.links.get_mut(slot) {
            *l = link;
        }
    }
    pub fn reject(&mut self, r: Reject) {
        self.counters.rejected.add(r);
    }

    /// Whether the fault table removes `slot`'s message of step k.
    pub fn removed(&mut self, slot: usize, k: u64) -> bool {
        self.links[slot].lost(k)
    }

    /// Lock-step: whether every source's step-k message is here (or removed
    /// by the fault table, so not to be waited for).
    pub fn has_all(&mut self, k: u64) -> bool {
        (0..self.pending.len()).all(|s| self.pending[s].contains_key(&k) || self.links[s].lost(k))
    }

    /// Lock-step: whether the step the receiver waits for now has all its
    /// inputs (false in real time, where nobody waits): a message that
    /// completes it wakes the control loop, the others need not.
    pub fn completes_wait(&mut self) -> bool {
        self.lockstep && self.has_all(self.current)
    }

    /// Lock-step: the slots whose step-k message is missing (and not removed by the table).
    pub fn missing(&mut self, k: u64) -> Vec<usize> {
        (0..self.pending.len()).filter(|&s| !self.pending[s].contains_key(&k) && !self.links[s].lost(k)).collect()
    }

    /// Lock-step: takes each source's step-k message, `None` where the fault
    /// table removed it (call after `has_all`).
    pub fn take(&mut self, k: u64, out: &mut Vec<Option<Message>>) {
        out.clear();
        for (slot, p) in self.pending.iter_mut().enumerate() {
            // Drop anything older (cannot happen with has_all, but keeps memory bounded).
            while let Some((&s, _)) = p.first_key_value() {
                if s >= k {
                    break;
                }
                p.pop_first();
            }
            out.push(p.remove(&k));
            self.newest[slot] = Some(k);
        }
    }

    /// Real time: the newest message of a source stamped at or before step
    /// k (a node running behind the shared schedule never uses values from
    /// its future), if it is at most `max_age_steps` older than k; else the
    /// source counts as silent.
    pub fn latest(&mut self, slot: usize, k: u64, max_age_steps: u64) -> Option<(u64, Message)> {
        let h = &mut self.history[slot];
        // Keep the newest entry ≤ k and everything after it.
        while h.len() > 1 && h[1].0 <= k {
            h.pop_front();
        }
        match h.front() {
            Some(&(s, state)) if s <= k && k - s <= max_age_steps => {
                self.counters.older += u64::from(s < k);
                self.meters[slot].age_steps.record(self.current.saturating_sub(s));
                Some((s, state))
            }
            _ => {
                self.counters.silent += 1;
                None
            }
        }
    }
}

/// Real time: messages kept per source (newer than the receiver's step).
const HISTORY: usize = 1024;

/// Two messages with the same contents, bit for bit.
fn same(a: &Message, b: &Message) -> bool {
    let bits = |m: &Message| {
        let s = &m.state;
        [s.pose.x, s.pose.y, s.pose.theta, s.pose_rate.x, s.pose_rate.y, s.pose_rate.theta, s.v, s.w].map(f64::to_bits)
    };
    a.fresh == b.fresh && bits(a) == bits(b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::wire::{Header, FORMAT_VERSION};

    fn msg(sender: u32, step: u64) -> EstimateMsg {
        EstimateMsg {
            header: Header { version: FORMAT_VERSION, sender, step, time_s: step as f64 * 1e-3, sent_ns: 0 },
            state: formation_leader::LeaderState { v: step as f64, ..Default::default() },
            fresh: true,
            term: u32::from(sender == wire::LEADER_ID),
        }
    }

    fn in_term(term: u32, step: u64, v: f64) -> EstimateMsg {
        let mut m = msg(wire::LEADER_ID, step);
        (m.term, m.state.v) = (term, v);
        m
    }

    /// Lock-step, a follower killed between its estimate of step L and its
    /// pose of L − 1 (formation_protocol::died): its neighbour holds that
    /// estimate when the link is cut from L; it is dropped, never used,
    /// and step L no longer waits for it (the model never delivers it).
    #[test]
    fn a_message_held_for_a_step_a_new_cut_loses_is_dropped() {
        use formation_control::LossWindow;
        let mut inbox = Inbox::new(1, true);
        inbox.set_ahead(0, 1000);
        for k in 0..=10 {
            assert!(inbox.accept(0, &msg(2, k)), "step {k}");
        }
        let cut = LinkLoss::new(1, 2, 1, &[LossWindow { from_k: 10, to_k: 100, loss: 1.0 }]);
        inbox.set_link(0, cut);
        let mut out = Vec::new();
        inbox.take(9, &mut out);
        assert_eq!(out[0].map(|m| m.state.v), Some(9.0), "step 9, before the cut, is used");
        assert!(inbox.has_all(10), "step 10 does not wait for what the cut removes");
        inbox.take(10, &mut out);
        assert_eq!(out[0], None, "the estimate of step 10 held before the cut is never used");
    }

    /// Terms (docs/model.md §14): once a message of term 2 is heard on the
    /// leader's key, term 1's are refused and counted, even for newer
    /// steps (a leader cut off whose clock runs ahead); the new term is
    /// taken from its first message on, even for steps behind the old
    /// leader's, in real time and in lock-step alike. A follower's own
    /// messages carry no term of their own (the rule is the leader's key's).
    #[test]
    fn the_leaders_messages_of_the_highest_term_heard_are_the_only_ones_used() {
        for lockstep in [false, true] {
            let mut inbox = Inbox::new(2, lockstep);
            inbox.set_ahead(1, 1000);
            assert_eq!(inbox.term(), 0);
            assert!(inbox.accept(1, &in_term(1, 5, 1.0)), "lockstep {lockstep}");
            assert!(inbox.accept(1, &in_term(1, 8, 1.0)));
            assert_eq!(inbox.term(), 1);
            assert!(inbox.accept(1, &in_term(2, 7, 2.0)), "lockstep {lockstep}: term 2 behind term 1's step 8");
            assert!(!inbox.accept(1, &in_term(1, 9, 1.0)), "lockstep {lockstep}: term 1 after term 2");
            assert_eq!((inbox.term(), inbox.counters.rejected.old_term), (2, 1), "lockstep {lockstep}");
            assert_eq!(inbox.counters.rejected.invalid(), 0, "an old term is not a bad message");
            let mut n = msg(3, 1);
            n.term = 0;
            assert!(inbox.accept(0, &n), "a neighbour's message is not the leader's");
            if !lockstep {
                assert_eq!(inbox.latest(1, 7, 10).map(|(s, m)| (s, m.state.v)), Some((7, 2.0)), "the new term's");
            }
        }
    }

    #[test]
    fn checks_name_the_reason() {
        let bytes = wire::encode(&msg(2, 5));
        assert_eq!(check(Some(2), &bytes, false, &[2, 3]).map(|r| r.0), Ok(Source::Neighbour(0)));
        assert_eq!(check(Some(3), &bytes, false, &[2, 3]).map(|r| r.0), Err(Reject::WrongSender));
        assert_eq!(check(Some(2), &bytes, false, &[3]).map(|r| r.0), Err(Reject::NotNeighbour));
        assert_eq!(check(Some(2), b"junk", false, &[2]).map(|r| r.0), Err(Reject::Malformed));
        let leader = wire::encode(&msg(0, 5));
        assert_eq!(check(Some(0), &leader, true, &[2]).map(|r| r.0), Ok(Source::Leader));
        assert_eq!(check(Some(0), &leader, false, &[2]).map(|r| r.0), Err(Reject::NotNeighbour));
    }

    #[test]
    fn lockstep_inbox_waits_for_every_source_and_counts_stale() {
        let mut inbox = Inbox::new(2, true);
        inbox.accept(0, &msg(1, 0));
        assert!(!inbox.has_all(0));
        inbox.accept(1, &msg(2, 0));
        inbox.accept(1, &msg(2, 1));
        assert!(inbox.has_all(0));
        let mut out = Vec::new();
        inbox.take(0, &mut out);
        assert_eq!(out.len(), 2);
        assert!(out.iter().all(Option::is_some));
        inbox.accept(0, &msg(1, 0));
        assert_eq!(inbox.counters.rejected.stale, 1);
        assert!(!inbox.has_all(1));
    }

    #[test]
    fn realtime_inbox_keeps_the_latest_and_leaves_out_the_silent() {
        let mut inbox = Inbox::new(1, false);
        assert_eq!(inbox.latest(0, 0, 10), None);
        inbox.accept(0, &msg(1, 3));
        inbox.accept(0, &msg(1, 2));
        assert_eq!(inbox.counters.late, 1);
        inbox.accept(0, &msg(1, 6));
        // At step 5 the message stamped 6 is in the future: use 3.
        assert_eq!(inbox.latest(0, 5, 10).map(|(_, m)| m.state.v), Some(3.0));
        assert_eq!(inbox.counters.older, 1, "step 5 used step 3's message");
        assert_eq!(inbox.latest(0, 6, 10).map(|(_, m)| m.state.v), Some(6.0));
        assert_eq!(inbox.counters.older, 1);
        assert_eq!(inbox.latest(0, 17, 10), None);
        assert_eq!(inbox.counters.silent, 2);
    }

    #[test]
    fn far_future_steps_are_rejected_and_do_not_silence_the_sender() {
        // Lock-step: neighbours at most 2 steps ahead, the leader (slot 1) 10.
        let mut inbox = Inbox::new(2, true);
        inbox.set_ahead(1, 10);
        inbox.accept(0, &msg(1, u64::MAX));
        for s in 3..1000 {
            inbox.accept(0, &msg(1, s));
        }
        inbox.accept(1, &msg(0, 11));
        assert_eq!(inbox.counters.rejected.future, 1 + 997 + 1);
        assert_eq!(inbox.counters.rejected.stale, 0);
        // Nothing pending from the flood; the genuine messages still get through.
        assert!(inbox.pending.iter().all(|p| p.is_empty()));
        for s in 0..=2 {
            inbox.accept(0, &msg(1, s));
        }
        inbox.accept(1, &msg(0, 0));
        inbox.accept(1, &msg(0, 10));
        assert!(inbox.has_all(0));
        let mut out = Vec::new();
        inbox.take(0, &mut out);
        inbox.set_step(1);
        inbox.accept(0, &msg(1, 3));
        assert_eq!(inbox.counters.rejected.future, 999);
        assert_eq!(inbox.pending[0].len(), 3);

        // Real time: a far-future message is not held, so later genuine ones are used.
        let mut inbox = Inbox::new(1, false);
        inbox.set_ahead(0, 5);
        inbox.accept(0, &msg(1, u64::MAX));
        inbox.accept(0, &msg(1, 6));
        inbox.accept(0, &msg(1, 1));
        assert_eq!(inbox.counters.rejected.future, 2);
        assert_eq!(inbox.latest(0, 1, 10).map(|(_, m)| m.state.v), Some(1.0));
        inbox.set_step(10);
        inbox.accept(0, &msg(1, 9));
        assert_eq!(inbox.latest(0, 10, 10).map(|(_, m)| m.state.v), Some(9.0));
    }

    #[test]
    fn realtime_never_uses_a_message_from_the_receivers_future() {
        let mut inbox = Inbox::new(1, false);
        inbox.set_ahead(0, 10);
        inbox.accept(0, &msg(1, 8));
        // Held message newer than k: not used (and not "0 steps old").
        assert_eq!(inbox.latest(0, 5, 10), None);
        assert_eq!(inbox.latest(0, 8, 10).map(|(_, m)| m.state.v), Some(8.0));
    }

    fn stamped(sender: u32, step: u64, sent_step: u64, v: f64) -> EstimateMsg {
        let mut m = msg(sender, step);
        m.header.sent_ns = Now::from_millis(1000 + sent_step).as_nanos() as i64;
        m.state.v = v;
        m
    }

    /// A second sender on a source's key (a copy of each genuine message,
    /// stamped 5 steps ahead, as the attack test sends): flagged after
    /// TWIN_EVIDENCE messages that show it; then dropped both while it runs
    /// ahead of the run's pace and when it arrives late enough to be back
    /// within the pace, by its own send stamp.
    #[test]
    fn a_twin_is_flagged_and_its_copies_dropped_even_when_they_arrive_late() {
        let mut inbox = Inbox::new(1, false);
        inbox.set_ahead(0, 10);
        inbox.set_clock(Now::from_millis(1000), Duration::from_millis(1));
        let at = |inbox: &mut Inbox, k: u64| {
            inbox.set_step(k);
            inbox.set_time(Some(Now::from_millis(1000 + k)));
        };
        // Steps 10..=13: the genuine k + 1 (stamped k) and the twin's k + 6.
        for k in 10..14 {
            at(&mut inbox, k);
            inbox.accept(0, &stamped(1, k + 1, k, 0.0));
            inbox.accept(0, &stamped(1, k + 6, k, 5.0));
        }
        let t = inbox.twins()[0];
        assert!(t.since.is_some(), "not flagged after {} messages of a second sender", t.messages);
        // On time: the twin runs 5 steps ahead of the pace and is dropped.
        at(&mut inbox, 20);
        inbox.accept(0, &stamped(1, 21, 20, 0.0));
        inbox.accept(0, &stamped(1, 26, 20, 5.0));
        assert_eq!(inbox.latest(0, 21, 10).map(|(s, m)| (s, m.state.v)), Some((21, 0.0)));
        // Late: at step 33 comes the twin's copy of the genuine 30 (sent at
        // step 29), stamped 35: within the pace (35 <= 33 + 2), not within
        // its send stamp (35 > 29 + 2).
        at(&mut inbox, 33);
        inbox.accept(0, &stamped(1, 34, 33, 0.0));
        let dropped = inbox.twins()[0].messages;
        inbox.accept(0, &stamped(1, 35, 29, 5.0));
        assert_eq!(inbox.twins()[0].messages, dropped + 1, "a late copy within the pace was not dropped");
        assert_eq!(inbox.latest(0, 34, 10).map(|(s, m)| (s, m.state.v)), Some((34, 0.0)));
        // The genuine stream goes on being taken.
        at(&mut inbox, 35);
        inbox.accept(0, &stamped(1, 36, 35, 0.0));
        assert_eq!(inbox.latest(0, 36, 10).map(|(s, m)| (s, m.state.v)), Some((36, 0.0)));
    }

    /// The slowest neighbour by its newest message, heard or not accepted;
    /// the leader's slot (the last) is left out by the caller.
    #[test]
    fn the_slowest_heard_neighbour_is_the_least_advanced_one() {
        let mut inbox = Inbox::new(3, true);
        assert_eq!(inbox.slowest_heard(2), None);
        inbox.accept(0, &msg(1, 7));
        assert_eq!(inbox.slowest_heard(2), Some(7), "one heard");
        inbox.accept(1, &msg(2, 1));
        inbox.accept(2, &msg(0, 0));
        assert_eq!(inbox.slowest_heard(2), Some(1), "slot 2 is not counted");
    }
}
