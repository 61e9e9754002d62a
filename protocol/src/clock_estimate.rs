//! One timebase across hosts whose clocks disagree: a node's estimate of
//! the offset between its own monotonic clock and the leader's timebase,
//! from four-timestamp exchanges as NTP makes them.
//!
//! An exchange: the node notes `t1` on its monotonic clock and asks; the
//! leader notes `t2` when the question arrives and `t3` when it answers, on
//! its timebase; the node notes `t4` when the answer arrives. Then
//!
//! - offset θ = ((t2 − t1) + (t3 − t4)) / 2 (the leader's timebase minus
//!   the node's clock, at the exchange's midpoint),
//! - round trip δ = (t4 − t1) − (t3 − t2),
//!
//! and θ is off by at most δ / 2, the exchange's uncertainty (half of any
//! asymmetry between the two directions). Queueing only ever lengthens a
//! round trip, so the exchange with the smallest round trip of each short
//! period is the best one ([`BUCKET`]); a straight line through the best
//! exchanges of the last minute or so ([`KEPT`] periods) gives the offset
//! and its drift (two crystals differ by tens of ppm: 100 ppm is 0.36 s an
//! hour, so the line is kept up to date rather than measured once).
//!
//! The node's side is its monotonic clock, never its wall clock: a node
//! whose wall clock is set wrong, or stepped by NTP mid-run, schedules the
//! same. Should the leader's timebase itself step, best exchanges that
//! disagree with the line by far more than their uncertainty, [`STEP_AFTER`]
//! periods in a row, start the line afresh (counted in [`Estimate::steps`]).
//!
//! Plain data, no clock and no IO: fed exchanges, asked for the estimate at
//! a time of the node's clock; its tests run in virtual time.

use std::collections::VecDeque;

/// Exchanges are grouped by the node's clock into periods this long
/// (ns); the one with the smallest round trip stands for its period.
pub const BUCKET: i64 = 1_000_000_000;

/// The best exchanges of this many periods make the line.
pub const KEPT: usize = 64;

/// This many periods in a row whose best exchange disagrees with the line
/// by more than [`STEP_MARGIN`] times its uncertainty (and at least
/// [`STEP_FLOOR`]) mean the reference stepped.
pub const STEP_AFTER: usize = 3;
pub const STEP_MARGIN: f64 = 8.0;
/// ns: disagreement below this is never a step.
pub const STEP_FLOOR: f64 = 1_000_000.0;

/// Below this many periods the line has no slope: the drift is taken as
/// unknown, up to [`DRIFT_MAX`], in the uncertainty.
pub const MIN_SLOPE_PERIODS: usize = 4;

/// The largest drift between two hosts' clocks assumed before it is
/// measured (crystals are specified to ±50–100 ppm each).
pub const DRIFT_MAX: f64 = 200e-6;

pub use crate::clockguard::Exchange;

/// Why an exchange was not used.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refused {
    /// Its timestamps cannot be: the answer before the question, or the
    /// reference answering before it was asked.
    Impossible,
    /// Older than every period kept.
    TooOld,
}

/// The offset of the reference's timebase from the node's clock.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Estimate {
    /// ns to add to the node's clock to get the reference's time, at the
    /// time asked for.
    pub offset_ns: f64,
    /// ns: half the round trip of the best exchange behind the estimate,
    /// plus what the drift's own error may add since.
    pub uncertainty_ns: f64,
    /// The reference's rate against the node's clock, in parts per million
    /// (positive: the reference runs fast).
    pub drift_ppm: f64,
    /// Periods with a best exchange behind the line.
    pub periods: usize,
    /// Steps of the reference detected so far.
    pub steps: u64,
}

/// A node's estimate of the leader's clock (`network.json`'s `clock`).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ClockReport {
    /// The leader's clock minus this node's wall clock, ms (a node whose
    /// wall clock is 50 ms fast reads −50). Reported only: no decision
    /// uses a wall clock.
    pub offset_ms: f64,
    /// How far the estimate may be off (half the best round trips, and the
    /// drift's share), µs.
    pub uncertainty_us: f64,
    /// The leader's clock's rate against this node's, ppm.
    pub drift_ppm: f64,
    /// Exchanges with the leader so far.
    pub exchanges: u64,
    /// Steps of the leader's clock detected.
    pub steps: u64,
    /// Answers from a second clock, and answers refused ([`crate::clockguard`]).
    #[serde(default)]
    pub guard: crate::clockguard::GuardReport,
}

/// The best exchange of one period.
#[derive(Clone, Copy, Debug)]
struct Best {
    bucket: i64,
    exchange: Exchange,
    /// Judged to disagree with the line of the periods before it: left
    /// out of the line (a step not yet confirmed, or an odd answer).
    outlier: bool,
}

/// A node's estimate of the reference's timebase.
#[derive(Clone, Debug, Default)]
pub struct Offset {
    /// Best exchange per period, by period, at most [`KEPT`].
    best: VecDeque<Best>,
    /// Periods in a row whose best exchange disagreed with the line.
    disagreeing: usize,
    steps: u64,
    used: u64,
    /// The line as of the last exchange filed (asked for far more often
    /// than exchanges come: every published message is stamped).
    cached: Option<(Line, usize)>,
    /// Which answers are the leader's.
    guard: crate::clockguard::ClockGuard,
}

impl Offset {
    pub fn new() -> Self {
        Self::default()
    }

    /// Files an exchange (in any order: a late or reordered answer is as
    /// good as any, its four timestamps being its own).
    pub fn add(&mut self, x: Exchange) -> Result<(), Refused> {
        if x.t4 < x.t1 || x.t3 < x.t2 || x.round_trip() < 0 {
            return Err(Refused::Impossible);
        }
        let bucket = x.t1.div_euclid(BUCKET);
        if self.best.len() == KEPT && self.best.front().is_some_and(|b| bucket < b.bucket) {
            return Err(Refused::TooOld);
        }
        self.used += 1;
        match self.best.binary_search_by_key(&bucket, |b| b.bucket) {
            Ok(i) => {
                if x.round_trip() < self.best[i].exchange.round_trip() {
                    self.best[i].exchange = x;
                }
            }
            Err(i) => {
                let newest = i == self.best.len();
                self.best.insert(i, Best { bucket, exchange: x, outlier: false });
                if self.best.len() > KEPT {
                    self.best.pop_front();
                }
                // A period is judged once the next one begins: its best is then final.
                if newest && self.best.len() >= 2 {
                    self.judge_period(self.best.len() - 2);
                }
            }
        }
        self.cached = self.fit_line();
        Ok(())
    }

    /// Whether the best exchange of period `i` agrees with the line of the
    /// periods before it; [`STEP_AFTER`] disagreeing in a row restart the line.
    fn judge_period(&mut self, i: usize) {
        let Some(line) = Line::fit(self.best.iter().take(i).filter(|b| !b.outlier)) else { return };
        let outlier = !line.agrees(&self.best[i].exchange);
        self.best[i].outlier = outlier;
        self.disagreeing = if outlier { self.disagreeing + 1 } else { 0 };
        if self.disagreeing >= STEP_AFTER {
            // The last STEP_AFTER periods disagree with the line, not (we
            // take it) with each other: the reference stepped. Keep only them.
            self.best.drain(..i + 1 - STEP_AFTER);
            self.best.iter_mut().for_each(|b| b.outlier = false);
            self.disagreeing = 0;
            self.steps += 1;
        }
    }

    /// The line through the judged periods that agree, and through the
    /// newest period (not judged yet) if it agrees with them.
    fn line(&self) -> Option<(Line, usize)> {
        self.cached
    }

    fn fit_line(&self) -> Option<(Line, usize)> {
        let judged = self.best.len().saturating_sub(1);
        let agreeing = || self.best.iter().take(judged).filter(|b| !b.outlier);
        let n = agreeing().count();
        match (Line::fit(agreeing()), self.best.back()) {
            (Some(line), Some(newest)) if !line.agrees(&newest.exchange) => Some((line, n)),
            _ => Line::fit(agreeing().chain(self.best.back())).map(|l| (l, n + 1)),
        }
    }

    /// Files the answer of one question that [`crate::clockguard`] takes
    /// for the leader's (several answers: several clocks answered); whether
    /// one was filed.
    pub fn add_answers(&mut self, answers: &[Exchange]) -> bool {
        let mut guard = std::mem::take(&mut self.guard);
        // An answer agrees with the estimate held within its step rule's margin.
        let held = |t| self.at(t).map(|e| (e.offset_ns, STEP_FLOOR.max(STEP_MARGIN * e.uncertainty_ns)));
        let judged = guard.judge(answers, held);
        match judged {
            crate::clockguard::Judged::File(x) => {
                self.guard = guard;
                self.add(x).is_ok()
            }
            crate::clockguard::Judged::Refile(x) => {
                // The line followed the other clock: start it afresh.
                *self = Offset { guard, ..Offset::new() };
                self.add(x).is_ok()
            }
            crate::clockguard::Judged::Hold => {
                self.guard = guard;
                false
            }
        }
    }

    /// A message the leader stamped `sent_ns` arrived at `local_ns`.
    pub fn leader_sent(&mut self, sent_ns: i64, local_ns: i64) {
        self.guard.leader_sent(sent_ns, local_ns);
    }

    /// What the guard saw.
    pub fn guard(&self) -> &crate::clockguard::ClockGuard {
        &self.guard
    }

    /// Exchanges used so far.
    pub fn exchanges(&self) -> u64 {
        self.used
    }

    /// The estimate at `local_ns` on the node's clock (None before any exchange).
    pub fn at(&self, local_ns: i64) -> Option<Estimate> {
        let (line, periods) = self.line()?;
        let t = local_ns as f64;
        // The drift's error grows with the distance from the exchanges'
        // middle: three standard errors of the slope, or any drift up to
        // DRIFT_MAX while there are too few periods for a slope.
        let per_ns = if periods >= MIN_SLOPE_PERIODS { 3.0 * line.slope_error } else { DRIFT_MAX };
        let drift_error = per_ns * (t - line.mean_t).abs();
        Some(Estimate {
            offset_ns: line.at(t),
            uncertainty_ns: line.half_rtt + drift_error,
            drift_ppm: line.slope * 1e6,
            periods,
            steps: self.steps,
        })
    }

    /// The reference's time at `local_ns` on the node's clock.
    pub fn to_reference(&self, local_ns: i64) -> Option<i64> {
        self.at(local_ns).map(|e| local_ns + e.offset_ns.round() as i64)
    }

    /// The node's clock when the reference reads `reference_ns`.
    pub fn to_local(&self, reference_ns: i64) -> Option<i64> {
        // reference = t + a + b (t − m), so t = (reference − a + b m) / (1 + b).
        let (l, _) = self.line()?;
        let t = (reference_ns as f64 - l.a + l.slope * l.mean_t) / (1.0 + l.slope);
        Some(t.round() as i64)
    }
}

/// A straight line offset(t) = a + b (t − mean_t) through best exchanges,
/// each weighted by the inverse square of its uncertainty.
#[derive(Clone, Copy, Debug)]
struct Line {
    mean_t: f64,
    a: f64,
    slope: f64,
    /// The slope's standard error (per ns).
    slope_error: f64,
    /// The exchanges' uncertainties (half their round trips), averaged
    /// with the fit's weights: a bound on the line's error at its middle.
    half_rtt: f64,
    /// How far the exchanges scatter about the line (ns, weighted RMS).
    spread: f64,
}

impl Line {
    fn fit<'a>(best: impl Iterator<Item = &'a Best> + Clone) -> Option<Line> {
        let weight = |x: &Exchange| {
            let u = (x.round_trip() as f64 / 2.0).max(1_000.0);
            1.0 / (u * u)
        };
        let (mut w, mut wt, mut wu, mut n) = (0.0, 0.0, 0.0, 0usize);
        for b in best.clone() {
            let x = &b.exchange;
            w += weight(x);
            wt += weight(x) * x.local_mid();
            wu += weight(x) * x.round_trip() as f64 / 2.0;
            n += 1;
        }
        if n == 0 {
            return None;
        }
        let mean_t = wt / w;
        let (mut wy, mut wtt, mut wty) = (0.0, 0.0, 0.0);
        for b in best.clone() {
            let x = &b.exchange;
            let dt = x.local_mid() - mean_t;
            wy += weight(x) * x.offset();
            wtt += weight(x) * dt * dt;
            wty += weight(x) * dt * x.offset();
        }
        let a = wy / w;
        let half_rtt = wu / w;
        // Too few periods for a slope (see MIN_SLOPE_PERIODS).
        let slope = if n >= MIN_SLOPE_PERIODS && wtt > 0.0 { wty / wtt } else { 0.0 };
        let mut sse = 0.0;
        for b in best {
            let x = &b.exchange;
            let r = x.offset() - (a + slope * (x.local_mid() - mean_t));
            sse += weight(x) * r * r;
        }
        let spread = if n >= 3 { (sse / w * n as f64 / (n - 2) as f64).sqrt() } else { 0.0 };
        let slope_error = if n >= 3 && wtt > 0.0 { spread / (wtt / w).sqrt() / (n as f64).sqrt() } else { 0.0 };
        Some(Line { mean_t, a, slope, slope_error, half_rtt, spread })
    }

    fn at(&self, t: f64) -> f64 {
        self.a + self.slope * (t - self.mean_t)
    }

    /// Whether an exchange agrees with the line: within [`STEP_MARGIN`]
    /// times its own uncertainty and the line's scatter, or [`STEP_FLOOR`].
    fn agrees(&self, x: &Exchange) -> bool {
        let residual = (x.offset() - self.at(x.local_mid())).abs();
        residual <= (STEP_MARGIN * (x.round_trip() as f64 / 2.0 + self.spread)).max(STEP_FLOOR)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: i64 = 1_000_000;
    const US: i64 = 1_000;
    const S: i64 = 1_000_000_000;

    /// A reference whose time is `offset` + (1 + `ppm`·1e-6)·t at the
    /// node's clock t (ns), stepping by `step` at `step_at`.
    #[derive(Clone, Copy)]
    struct Reference {
        offset: i64,
        ppm: f64,
        step: Option<(i64, i64)>,
    }

    impl Reference {
        fn time(&self, t: i64) -> i64 {
            let stepped = self.step.map_or(0, |(at, by)| if t >= at { by } else { 0 });
            self.offset + t + (t as f64 * self.ppm * 1e-6).round() as i64 + stepped
        }

        /// An exchange asked at t1 with these one-way delays (ns) and 20 µs to answer.
        fn exchange(&self, t1: i64, there: i64, back: i64) -> Exchange {
            let t2 = self.time(t1 + there);
            let t3 = t2 + 20 * US;
            // The node's clock when the answer arrives.
            let t4 = t1 + there + 20 * US + back;
            Exchange { t1, t2, t3, t4 }
        }
    }

    /// A small deterministic generator (xorshift), for delays.
    struct Jitter(u64);

    impl Jitter {
        fn next(&mut self, max: i64) -> i64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 % max as u64) as i64
        }
    }

    /// The error of the estimate at `t` against the reference, in ns.
    fn error(o: &Offset, r: &Reference, t: i64) -> f64 {
        let e = o.at(t).expect("an estimate");
        e.offset_ns - (r.time(t) - t) as f64
    }

    #[test]
    fn one_exchange_gives_the_offset_within_half_its_round_trip() {
        let r = Reference { offset: -300 * MS, ppm: 0.0, step: None };
        let mut o = Offset::new();
        assert_eq!(o.at(0), None, "nothing before the first exchange");
        o.add(r.exchange(5 * S, 100 * US, 100 * US)).expect("accepted");
        let e = o.at(5 * S).expect("an estimate");
        assert!(error(&o, &r, 5 * S).abs() < 1.0, "symmetric delays: exact, got {e:?}");
        assert!(
            (100_000.0..100_100.0).contains(&e.uncertainty_ns),
            "half the round trip, and any drift over 0.1 ms: {e:?}"
        );
        assert_eq!(o.to_reference(5 * S), Some(r.time(5 * S)));
        assert_eq!(o.to_local(r.time(7 * S)), Some(7 * S));
        // With a drift: the two conversions are each other's inverse.
        let r = Reference { offset: 3 * S, ppm: 80.0, step: None };
        let mut o = Offset::new();
        for i in 0..100 {
            o.add(r.exchange(i * S, 100 * US, 100 * US)).expect("accepted");
        }
        for t in [50 * S, 100 * S, 150 * S] {
            let back = o.to_local(o.to_reference(t).expect("an estimate")).expect("an estimate");
            assert!((back - t).abs() <= 1, "{t} -> {back}");
            assert!((o.to_reference(t).expect("an estimate") - r.time(t)).abs() < 1_000, "at {t}");
        }
    }

    /// Asymmetric delays shift the offset by half the asymmetry, which the
    /// uncertainty covers; the smallest round trip of each period wins over
    /// queueing.
    #[test]
    fn asymmetric_delays_stay_within_the_uncertainty_and_queueing_is_filtered() {
        let r = Reference { offset: 50 * MS, ppm: 0.0, step: None };
        let mut o = Offset::new();
        let mut j = Jitter(7);
        let mut single = Vec::new();
        for i in 0..600 {
            // 100 µs there, 300 µs back, and up to 5 ms of queueing either way.
            let x = r.exchange(i * 100 * MS, 100 * US + j.next(5 * MS), 300 * US + j.next(5 * MS));
            single.push((x.offset() - r.offset as f64).abs());
            o.add(x).expect("accepted");
        }
        single.sort_by(f64::total_cmp);
        let t = 60 * S;
        let e = o.at(t).expect("an estimate");
        let err = error(&o, &r, t);
        let median = single[single.len() / 2];
        eprintln!(
            "asymmetric delays: error {err:.0} ns, uncertainty {:.0} ns; one exchange's median error {median:.0} ns",
            e.uncertainty_ns
        );
        assert!(err.abs() <= e.uncertainty_ns, "error {err} ns beyond the uncertainty {} ns", e.uncertainty_ns);
        assert!(e.uncertainty_ns < 1.0 * MS as f64, "the best exchanges were kept: {e:?}");
        // The 200 µs asymmetry shows as −100 µs, which no two-way exchange
        // can see; what remains is the filter's, a fraction of one exchange's.
        let filtered = err + 100.0 * US as f64;
        assert!(
            filtered.abs() < median / 4.0,
            "error {err} ns (−100 µs of asymmetry) against one exchange's median {median} ns"
        );
    }

    /// Two crystals 100 ppm apart: 0.36 s an hour. The line follows: the
    /// error stays within the reported uncertainty and below a quarter of a
    /// 1 kHz step all hour, and is no larger in the last quarter hour than
    /// in the first (it does not accumulate). Delays jitter by up to 2 ms
    /// each way, so the error is the jitter's, not the drift's.
    #[test]
    fn a_drift_of_100_ppm_does_not_accumulate_over_an_hour() {
        let r = Reference { offset: 1 * S, ppm: 100.0, step: None };
        let mut o = Offset::new();
        let mut j = Jitter(11);
        let (mut first, mut last) = (0.0f64, 0.0f64);
        for i in 0..3_600 * 4 {
            let t1 = i * 250 * MS;
            o.add(r.exchange(t1, 80 * US + j.next(2 * MS), 80 * US + j.next(2 * MS))).expect("accepted");
            // Between exchanges, and a quarter second ahead (where a step is due).
            let t = t1 + 250 * MS;
            let (err, e) = (error(&o, &r, t).abs(), o.at(t).expect("an estimate"));
            assert!(err <= e.uncertainty_ns, "at {} s: error {err:.0} ns beyond the uncertainty {e:?}", t / S);
            if (60 * S..900 * S).contains(&t) {
                first = first.max(err);
            } else if t >= 2_700 * S {
                last = last.max(err);
            }
        }
        let e = o.at(3_600 * S).expect("an estimate");
        eprintln!("100 ppm over an hour: worst error {first:.0} ns in the first quarter hour, {last:.0} ns in the last; drift {:.2} ppm", e.drift_ppm);
        assert!((e.drift_ppm - 100.0).abs() < 5.0, "drift {} ppm", e.drift_ppm);
        assert!(first.max(last) < 250.0 * US as f64, "worst error {first:.0} / {last:.0} ns");
        assert!(
            last <= 1.5 * first,
            "the error grew: {first:.0} ns in the first quarter hour, {last:.0} ns in the last"
        );
        let drifted = (r.time(3_600 * S) - 3_600 * S - 1 * S) as f64;
        assert!(drifted > 0.35e9, "the reference drifted {drifted} ns: the test means something");
    }

    #[test]
    fn lost_and_reordered_exchanges_change_nothing() {
        let r = Reference { offset: -1 * S, ppm: -40.0, step: None };
        let mut j = Jitter(3);
        let all: Vec<Exchange> =
            (0..300).map(|i| r.exchange(i * 200 * MS, 60 * US + j.next(MS), 60 * US + j.next(MS))).collect();
        let mut in_order = Offset::new();
        all.iter().for_each(|x| in_order.add(*x).expect("accepted"));
        // Every third lost, and the rest in a shuffled order.
        let mut kept: Vec<Exchange> = all.iter().enumerate().filter(|(i, _)| i % 3 != 1).map(|(_, x)| *x).collect();
        for i in (1..kept.len()).rev() {
            let k = j.next(i as i64 + 1) as usize;
            kept.swap(i, k);
        }
        let mut shuffled = Offset::new();
        kept.iter().for_each(|x| shuffled.add(*x).expect("accepted"));
        let t = 61 * S;
        let (a, b) = (error(&in_order, &r, t), error(&shuffled, &r, t));
        assert!(
            a.abs() < 100.0 * US as f64 && b.abs() < 100.0 * US as f64,
            "in order {a} ns, lost and shuffled {b} ns"
        );
        assert_eq!(shuffled.exchanges(), 200);
    }

    #[test]
    fn impossible_and_too_old_exchanges_are_refused() {
        let mut o = Offset::new();
        assert_eq!(o.add(Exchange { t1: 10, t2: 5, t3: 6, t4: 9 }), Err(Refused::Impossible), "answer before question");
        assert_eq!(o.add(Exchange { t1: 10, t2: 6, t3: 5, t4: 20 }), Err(Refused::Impossible), "answered before asked");
        assert_eq!(o.add(Exchange { t1: 10, t2: 0, t3: 100, t4: 20 }), Err(Refused::Impossible), "round trip < 0");
        let r = Reference { offset: 0, ppm: 0.0, step: None };
        for i in 0..KEPT as i64 + 5 {
            o.add(r.exchange(i * S, 50 * US, 50 * US)).expect("accepted");
        }
        assert_eq!(o.add(r.exchange(S, 50 * US, 50 * US)), Err(Refused::TooOld));
        assert_eq!(o.exchanges(), KEPT as u64 + 5);
    }

    /// The reference's clock steps by half a second mid-run (as NTP may
    /// step a wall clock): a few periods later the estimate follows it,
    /// and one odd exchange does not move it.
    #[test]
    fn a_step_of_the_reference_is_followed_within_a_few_periods() {
        let r = Reference { offset: 2 * S, ppm: 30.0, step: Some((600 * S, 500 * MS)) };
        let mut o = Offset::new();
        let mut j = Jitter(5);
        for i in 0..(1_200 * 4) {
            let t1 = i * 250 * MS;
            o.add(r.exchange(t1, 70 * US + j.next(MS), 70 * US + j.next(MS))).expect("accepted");
            let t = t1 + 250 * MS;
            if (590 * S..600 * S).contains(&t) || t > 600 * S + (STEP_AFTER as i64 + 2) * BUCKET {
                let err = error(&o, &r, t);
                assert!(err.abs() < 200.0 * US as f64, "at {} s: error {err} ns", t / S);
            }
        }
        assert_eq!(o.at(1_200 * S).expect("an estimate").steps, 1);
        // A single exchange 0.5 s off (a forged or confused answer) is not a step.
        let mut o = Offset::new();
        let r = Reference { offset: 0, ppm: 0.0, step: None };
        for i in 0..100 {
            let mut x = r.exchange(i * S, 50 * US, 50 * US);
            if i == 50 {
                x.t2 += 500 * MS;
                x.t3 += 500 * MS;
            }
            o.add(x).expect("accepted");
        }
        let e = o.at(100 * S).expect("an estimate");
        assert_eq!(e.steps, 0);
        assert!(e.offset_ns.abs() < 1.0 * MS as f64, "{e:?}");
    }
}
