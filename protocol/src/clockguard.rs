//! One clock, the leader's: which answers on `control/time` a node files.
//!
//! A node asks the leader's timebase and may get several answers to one
//! question: zenoh delivers the question to every queryable on the key.
//! Only one of them is the leader. Without TLS nothing on the wire proves
//! who answered, so the guard judges answers by what the leader itself
//! sends:
//!
//! - **The leader's stream.** The leader stamps every message it sends
//!   (its start announcements, its estimates) with its timebase. A message
//!   cannot arrive before it was sent, so each one received gives a floor:
//!   the leader's clock minus this node's is at least `sent − arrival`.
//!   An answer whose offset lies below the floor is impossible (a clock
//!   behind the leader's) and is never filed.
//! - **Two clocks in one answer set.** Answers to one question that
//!   disagree by more than their own uncertainty come from two clocks: a
//!   second responder. From then on an answer is filed only if it agrees
//!   with the estimate already held (the leader's line never jumps to the
//!   other clock); before any estimate, the answer nearest above the floor
//!   is the leader's (a forger ahead of it would have the leader's messages
//!   arriving that much late), and with no floor yet nothing is filed.
//!
//! What this does not do: tell a forger that imitates the leader exactly
//! (same clock, answers first, no leader on the wire) from the leader. TLS
//! with the access policy does: only the leader's certificate may answer.
//!
//! Plain data, no clock and no IO; tested in virtual time.

/// One four-timestamp exchange (ns): `t1`, `t4` on the node's clock, `t2`,
/// `t3` on the reference's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Exchange {
    pub t1: i64,
    pub t2: i64,
    pub t3: i64,
    pub t4: i64,
}

impl Exchange {
    /// The reference minus the node's clock (ns), at the midpoint.
    pub fn offset(&self) -> f64 {
        ((self.t2 as f64 - self.t1 as f64) + (self.t3 as f64 - self.t4 as f64)) / 2.0
    }

    /// The round trip (ns), without the reference's time to answer.
    pub fn round_trip(&self) -> i64 {
        (self.t4 - self.t1) - (self.t3 - self.t2)
    }

    /// The node's clock at the exchange's midpoint.
    pub(crate) fn local_mid(&self) -> f64 {
        (self.t1 as f64 + self.t4 as f64) / 2.0
    }
}

/// ns: answers of one question closer than this (plus half their round
/// trips) are one clock; a message's stamp may precede the floor by this
/// much (the leader's clock read before the stamp was written).
pub const SLACK_NS: f64 = 1_000_000.0;

/// What the guard saw, for `network.json`.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GuardReport {
    /// Questions answered by two clocks that disagree.
    pub second_clock_questions: u64,
    /// The node's monotonic clock (ns) when a second clock first answered.
    pub second_clock_since_ns: Option<i64>,
    /// The largest disagreement between two answers to one question, ms.
    pub worst_disagreement_ms: f64,
    /// Answers not filed: below the leader's floor, or (once a second clock
    /// answered) away from the estimate held.
    pub refused_answers: u64,
    /// Of those, below the floor the leader's own messages set.
    pub impossible_answers: u64,
    /// Times the estimate held was found to be the second clock's (it had
    /// answered alone before the leader did) and was started afresh from
    /// the leader's answer.
    #[serde(default)]
    pub corrections: u64,
}

/// What to do with one question's answers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Judged {
    /// File this answer.
    File(Exchange),
    /// The estimate held follows the wrong clock: drop it, then file this.
    Refile(Exchange),
    /// File nothing.
    Hold,
}

/// Judges every answer set before the timebase files it.
#[derive(Clone, Debug, Default)]
pub struct ClockGuard {
    /// max(sent − arrival) over the leader's stamped messages, ns.
    floor: Option<f64>,
    report: GuardReport,
}

impl ClockGuard {
    pub fn new() -> Self {
        Self::default()
    }

    /// A message the leader stamped `sent_ns` on its timebase arrived at
    /// `local_ns` on this node's clock (stamps ≤ 0 are unknown).
    pub fn leader_sent(&mut self, sent_ns: i64, local_ns: i64) {
        if sent_ns > 0 {
            let bound = sent_ns as f64 - local_ns as f64;
            self.floor = Some(self.floor.map_or(bound, |f| f.max(bound)));
        }
    }

    /// The floor on the leader's offset, ns (None: no stamped message yet).
    pub fn floor(&self) -> Option<f64> {
        self.floor
    }

    /// Whether a second clock has answered.
    pub fn second_clock(&self) -> bool {
        self.report.second_clock_since_ns.is_some()
    }

    pub fn report(&self) -> GuardReport {
        self.report
    }

    /// The answer of one question to file, if any. `held(local_ns)`: the
    /// offset the node holds at that time of its clock, and how far from it
    /// an answer may be and still agree (None before any estimate).
    pub fn judge(&mut self, answers: &[Exchange], held: impl Fn(i64) -> Option<(f64, f64)>) -> Judged {
        let half = |x: &Exchange| x.round_trip().max(0) as f64 / 2.0;
        let floor = self.floor;
        let possible = move |x: &Exchange| floor.is_none_or(|f| x.offset() + half(x) + SLACK_NS >= f);
        let judged = self.pick(answers, &held, &half, &possible);
        let impossible = answers.iter().filter(|x| !possible(x)).count() as u64;
        self.report.impossible_answers += impossible;
        let filed = !matches!(judged, Judged::Hold);
        self.report.refused_answers += answers.len() as u64 - u64::from(filed);
        if matches!(judged, Judged::Refile(_)) {
            self.report.corrections += 1;
        }
        judged
    }

    fn pick(
        &mut self,
        answers: &[Exchange],
        held: &impl Fn(i64) -> Option<(f64, f64)>,
        half: &impl Fn(&Exchange) -> f64,
        possible: &impl Fn(&Exchange) -> bool,
    ) -> Judged {
        // Two clocks in this answer set?
        let mut spread = 0.0f64;
        for (i, a) in answers.iter().enumerate() {
            for b in &answers[i + 1..] {
                let apart = (a.offset() - b.offset()).abs();
                if apart > SLACK_NS + half(a).max(half(b)) {
                    spread = spread.max(apart);
                }
            }
        }
        if spread > 0.0 {
            self.report.second_clock_questions += 1;
            self.report.second_clock_since_ns.get_or_insert(answers[0].t4);
            self.report.worst_disagreement_ms = self.report.worst_disagreement_ms.max(spread * 1e-6);
        }
        let candidates = answers.iter().filter(|x| possible(x));
        let mid = |x: &Exchange| (x.t1 / 2).saturating_add(x.t4 / 2);
        let or_hold = |x: Option<Exchange>| x.map_or(Judged::Hold, Judged::File);
        if !self.second_clock() {
            // One clock: the answer with the smallest round trip.
            return or_hold(candidates.min_by_key(|x| x.round_trip()).copied());
        }
        // Two clocks: the one nearest above the leader's floor; without a
        // floor, only the one the node already follows.
        let by =
            |f: &dyn Fn(&Exchange) -> f64| candidates.clone().map(|x| (f(x), *x)).min_by(|a, b| a.0.total_cmp(&b.0));
        let Some(answers0) = answers.first() else { return Judged::Hold };
        let held = held(mid(answers0));
        let agrees = |x: &Exchange| held.is_some_and(|(offset, tol)| (x.offset() - offset).abs() <= tol + half(x));
        let both_here = spread > 0.0;
        match (self.floor, held) {
            (Some(floor), _) if both_here || held.is_none() => match by(&|x| (x.offset() - floor).abs()) {
                // The estimate held came from the other clock (it answered
                // alone first): start afresh from the leader's.
                Some((_, x)) if held.is_some() && !agrees(&x) => Judged::Refile(x),
                Some((_, x)) => Judged::File(x),
                None => Judged::Hold,
            },
            (Some(_), _) => or_hold(candidates.copied().find(|x| agrees(x))),
            (None, Some((offset, _))) => {
                or_hold(by(&|x| (x.offset() - offset).abs()).map(|(_, x)| x).filter(|x| agrees(x)))
            }
            (None, None) => Judged::Hold,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An answer of a clock `offset_ms` from the node's, asked at `t_ms`, with a 200 µs round trip.
    fn answer(t_ms: i64, offset_ms: f64) -> Exchange {
        let t1 = t_ms * 1_000_000;
        let t4 = t1 + 200_000;
        let t2 = t1 + 100_000 + (offset_ms * 1e6) as i64;
        Exchange { t1, t2, t3: t2, t4 }
    }

    #[test]
    fn one_clock_files_its_best_answer() {
        let mut g = ClockGuard::new();
        let x = answer(0, 3.0);
        assert_eq!(g.judge(&[x], |_| None), Judged::File(x));
        assert!(!g.second_clock());
        assert_eq!(g.report().refused_answers, 0);
    }

    #[test]
    fn a_second_clock_half_a_second_ahead_is_named_and_never_filed() {
        let mut g = ClockGuard::new();
        // The leader's start announcement: sent at its 1000 ms, here at 997.1 ms.
        g.leader_sent(1_000_000_000, 997_100_000);
        let (leader, forger) = (answer(1000, 3.0), answer(1000, 503.0));
        // Before any estimate: the answer nearest the leader's floor.
        assert_eq!(g.judge(&[forger, leader], |_| None), Judged::File(leader));
        assert!(g.second_clock());
        // With an estimate of +3 ms held, the forger's answers are refused.
        for t in 0..20 {
            assert_eq!(g.judge(&[answer(1250 + t * 250, 503.0)], |_| Some((3e6, 1e6))), Judged::Hold, "step {t}");
        }
        let r = g.report();
        assert_eq!((r.second_clock_questions, r.refused_answers), (1, 21));
        assert!((r.worst_disagreement_ms - 500.0).abs() < 1e-6, "{r:?}");
        assert_eq!(r.second_clock_since_ns, Some(1_000_200_000));
    }

    #[test]
    fn a_clock_behind_the_leaders_stream_is_impossible() {
        let mut g = ClockGuard::new();
        g.leader_sent(1_000_000_000, 997_000_000); // offset ≥ 3 ms
        assert_eq!(g.judge(&[answer(1000, -497.0)], |_| None), Judged::Hold);
        assert_eq!(g.report().impossible_answers, 1);
        let ok = answer(1000, 3.1);
        assert_eq!(g.judge(&[ok], |_| None), Judged::File(ok));
    }

    #[test]
    fn two_clocks_and_no_floor_file_nothing() {
        let mut g = ClockGuard::new();
        assert_eq!(g.judge(&[answer(0, 3.0), answer(0, 503.0)], |_| None), Judged::Hold);
        assert!(g.second_clock());
        assert_eq!(g.report().refused_answers, 2);
    }

    #[test]
    fn an_estimate_taken_from_a_forger_that_answered_first_is_dropped() {
        let mut g = ClockGuard::new();
        // The forger alone, before the leader answers: one clock, filed.
        assert_eq!(g.judge(&[answer(0, 503.0)], |_| None), Judged::File(answer(0, 503.0)));
        // Then both answer, and the leader's start announcement sets the floor at 3 ms.
        g.leader_sent(1_000_000_000, 997_000_000);
        let leader = answer(1000, 3.1);
        assert_eq!(g.judge(&[answer(1000, 503.0), leader], |_| Some((503e6, 1e6))), Judged::Refile(leader));
        // From then on the leader's answers agree with what is held.
        assert_eq!(
            g.judge(&[answer(1250, 503.0), answer(1250, 3.0)], |_| Some((3.1e6, 1e6))),
            Judged::File(answer(1250, 3.0))
        );
        assert_eq!(g.report().corrections, 1);
    }

    #[test]
    fn answers_that_agree_are_one_clock() {
        let mut g = ClockGuard::new();
        let (a, b) = (answer(0, 3.0), answer(0, 3.2));
        assert!(matches!(g.judge(&[a, b], |_| None), Judged::File(_)));
        assert!(!g.second_clock());
    }
}
