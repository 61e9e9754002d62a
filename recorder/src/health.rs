//! A run's verdict beyond "every step recorded": how healthy it was.
//!
//! - **degraded** (exit status 3): the formation did far worse than its
//!   model (the simulator on the same scenario, delay and fault table). The
//!   numbers it reports are not the method's.
//! - **disturbed**: the run held (its error within its model's band), but
//!   something happened that a reader must know of: followers isolated from
//!   every source, a second clock on `control/time`, a clock estimate that
//!   stepped, a process restarted, refused messages and floods counted,
//!   telemetry dropped; in real time, followers' clocks known worse than a
//!   quarter step, and link-steps that heard otherwise than the model (a
//!   host or network slower than it assumes).
//! - **healthy**: none of that.
//!
//! Also here: the monitor's count of what arrives on the run's control keys
//! ([`ControlWatch`]). Plain data: no IO, no clock.

use std::collections::BTreeMap;

use serde::Serialize;

/// A follower's formation error (RMS over the last 10 s) beyond this many
/// times its model's, plus [`ERROR_MARGIN_M`], is far beyond the model.
pub const ERROR_FACTOR: f64 = 2.0;
pub const ERROR_MARGIN_M: f64 = 0.25;

/// A node asks the leader's clock about 4 times a second (50 a second for
/// its first 10 questions): more than this many in one second at the
/// leader is a flood.
pub const TIME_QUERIES_PER_NODE_S: u64 = 60;

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    Healthy,
    Disturbed,
    Degraded,
}

/// One follower's time cut off from every source.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Isolation {
    pub follower: u32,
    /// Seconds isolated in all, and when the first isolation began (run time).
    pub seconds: f64,
    pub first_t: f64,
    pub times: u32,
}

/// A follower's formation error against its model's.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AgainstModel {
    pub follower: u32,
    pub run_m: Option<f64>,
    pub model_m: Option<f64>,
}

/// `network.json`'s `health`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Health {
    pub verdict: Verdict,
    /// What made the run degraded, one line each.
    pub degraded: Vec<String>,
    /// What disturbed it, one line each.
    pub disturbed: Vec<String>,
    pub isolated: Vec<Isolation>,
    /// Per follower, or None with `model_skipped` saying why.
    pub model: Option<Vec<AgainstModel>>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_skipped: Option<String>,
    /// Spans at which most links heard otherwise than the model at once
    /// (real time with a delay and no fault table).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stalls: Vec<formation_record::stall::Stall>,
}

impl Health {
    /// One line for the terminal: the verdict and its first reasons.
    pub fn line(&self) -> String {
        let reasons: Vec<&String> = self.degraded.iter().chain(&self.disturbed).take(4).collect();
        let more = self.degraded.len() + self.disturbed.len() - reasons.len();
        let mut s = match self.verdict {
            Verdict::Healthy => "health: healthy (the run as its model predicts, nothing refused)".to_string(),
            Verdict::Disturbed => "health: disturbed (the formation held): ".to_string(),
            Verdict::Degraded => "health: DEGRADED: ".to_string(),
        };
        s.push_str(&reasons.iter().map(|r| r.as_str()).collect::<Vec<_>>().join("; "));
        if more > 0 {
            s.push_str(&format!("; {more} more in network.json"));
        }
        s
    }
}

/// What the monitor gathered, as the verdict needs it.
#[derive(Clone, Debug, Default)]
pub struct Evidence {
    /// Two robots came closer than `safety.distance` (docs/model.md §16): who, when.
    pub too_close: Option<String>,
    /// (follower, isolated at step, rejoined at step or None: to the end).
    pub isolations: Vec<(u32, u64, Option<u64>)>,
    pub steps: u64,
    pub dt_s: f64,
    /// (node name, clock steps, second clock's worst disagreement ms if one answered).
    pub clocks: Vec<(String, u64, Option<f64>)>,
    /// Per follower: (run's formation error, model's), m.
    pub errors: Vec<(u32, Option<f64>, Option<f64>)>,
    pub model_skipped: Option<String>,
    /// Counted and refused: (what, how many).
    pub refused: Vec<(String, u64)>,
    /// (time questions at the leader, most in one second, nodes asking).
    pub time_queries: (u64, u64, u64),
    /// (node, the steps its restarted processes resumed from).
    pub restarts: Vec<(String, Vec<u64>)>,
    /// Standby leaders that took the run over: (the newest step heard from
    /// the leader before, the first step the standby published).
    pub handovers: Vec<(Option<u64>, u64)>,
    /// Per follower in real time: how far its estimate of the leader's
    /// clock may be off at its last report, µs.
    pub clock_uncertainty_us: Vec<(u32, f64)>,
    /// A quarter of the real-time period (Δt over the time scale), µs; 0 in
    /// lock-step. A clock known worse than this puts steps early or late by
    /// more than a quarter step.
    pub quarter_step_us: f64,
    /// Real time with `network.delay_steps` ≥ 1 and no fault table (where a
    /// host that keeps up hears exactly what the model assumes): the followers' link-steps
    /// that used a message older than the delay, those that heard nothing,
    /// all link-steps, and the delay.
    pub hearing: Option<HearingEvidence>,
    /// Followers whose record ends short of the run's end beyond what their
    /// restarts' gaps explain, each said as the summary says it.
    pub short: Vec<String>,
    /// Followers that left the run for good: (id, at run time s, why).
    pub left: Vec<(u32, f64, String)>,
    /// Followers absent at the start that joined later: (id, at run time s).
    pub joined: Vec<(u32, f64)>,
    /// The followers those who left cut off from the leader (Lemma 1 on
    /// the graph without them).
    pub cut_off: Vec<u32>,
    /// Where [`Evidence::hearing`] is judged: spans at which most links
    /// heard otherwise than the model at once (`formation_record::stall`).
    pub stalls: Vec<formation_record::stall::Stall>,
}

/// See [`Evidence::hearing`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HearingEvidence {
    pub older: u64,
    pub silent: u64,
    pub link_steps: u64,
    pub delay_steps: u64,
}

/// More than this share of link-steps heard otherwise than the model
/// assumes is said in the health (the 50-agent test's runs on a quiet
/// 2-core host: 0–50 of 121,121, 0.04 %; 100 agents on it: 0.2–2 %).
pub const HEARING_DEPARTURE: f64 = 1e-3;

/// What the evidence says of who ran the whole run: a follower's record
/// that ends short (degraded), and the followers that left (disturbed), with
/// those their leaving cut off from the leader.
fn who_ran(e: &Evidence, degraded: &mut Vec<String>, disturbed: &mut Vec<String>) {
    // A run that did not complete is never healthy (a follower whose
    // process was stopped at 5 s of 12 was, its metrics null).
    for s in &e.short {
        degraded.push(format!("incomplete: {s}"));
    }
    // A follower that left said so: the others ran on without it, as its
    // model does (a node fault from then on), and its record ends there.
    for (id, t, why) in &e.left {
        disturbed.push(format!("follower {id} left the run at t = {t:.3} s ({why})"));
    }
    for (id, t) in &e.joined {
        disturbed.push(format!("follower {id} joined the run at t = {t:.3} s (absent at the start)"));
    }
    if !e.cut_off.is_empty() {
        disturbed.push(format!(
            "without the followers that left, {}",
            formation_scenario::graph::no_longer_reach(&e.cut_off)
        ));
    }
}

/// The verdict from the evidence.
pub fn judge(e: &Evidence) -> Health {
    let mut degraded = Vec::new();
    let mut disturbed = Vec::new();
    if let Some(what) = &e.too_close {
        degraded.push(what.clone());
    }
    who_ran(e, &mut degraded, &mut disturbed);
    for &(id, run, model) in &e.errors {
        if let (Some(r), Some(m)) = (run, model) {
            if r > ERROR_FACTOR * m + ERROR_MARGIN_M {
                degraded.push(format!(
                    "follower {id}'s formation error over the last 10 s is {r:.3} m, its model's {m:.3} m"
                ));
            }
        }
    }
    // A stall is one event of the path every message shares: said first,
    // and once, not as a departure of each link.
    for s in &e.stalls {
        disturbed.push(s.describe(e.dt_s));
    }
    for (node, steps, second) in &e.clocks {
        if *steps > 0 {
            disturbed.push(format!("{node}'s estimate of the leader's clock stepped {steps} time(s)"));
        }
        if let Some(ms) = second {
            disturbed.push(format!(
                "{node}: a second clock answered on control/time ({ms:.1} ms from the leader's), refused"
            ));
        }
    }
    for (node, at) in &e.restarts {
        if let Some(first) = at.first() {
            disturbed.push(format!(
                "{node}'s process restarted {} time(s) (first resuming at t = {:.2} s)",
                at.len(),
                *first as f64 * e.dt_s
            ));
        }
    }
    for &(heard, at) in &e.handovers {
        disturbed.push(handover_line(heard, at, e.dt_s));
    }
    if let Some(line) = unsure_clocks(e) {
        disturbed.push(line);
    }
    if let Some(line) = heard_otherwise(e) {
        disturbed.push(line);
    }
    let mut by: BTreeMap<u32, Isolation> = BTreeMap::new();
    for &(id, from, to) in &e.isolations {
        let end = to.unwrap_or(e.steps).max(from);
        let i =
            by.entry(id).or_insert(Isolation { follower: id, seconds: 0.0, first_t: from as f64 * e.dt_s, times: 0 });
        i.seconds += (end - from) as f64 * e.dt_s;
        i.first_t = i.first_t.min(from as f64 * e.dt_s);
        i.times += 1;
    }
    let isolated: Vec<Isolation> = by.into_values().collect();
    for i in &isolated {
        disturbed.push(format!(
            "follower {} isolated from every source for {:.2} s (from t = {:.2} s{})",
            i.follower,
            i.seconds,
            i.first_t,
            if i.times > 1 { format!(", {} times", i.times) } else { String::new() }
        ));
    }
    for (what, n) in &e.refused {
        if *n > 0 {
            disturbed.push(format!("{n} {what}"));
        }
    }
    let (queries, peak, askers) = e.time_queries;
    if peak > TIME_QUERIES_PER_NODE_S * askers.max(1) {
        disturbed.push(format!(
            "a flood of questions on control/time: {peak} in one second ({queries} in all; {askers} nodes ask about 4 a second)"
        ));
    }
    let verdict = if !degraded.is_empty() {
        Verdict::Degraded
    } else if !disturbed.is_empty() {
        Verdict::Disturbed
    } else {
        Verdict::Healthy
    };
    let model = e.model_skipped.is_none().then(|| {
        e.errors.iter().map(|&(follower, run_m, model_m)| AgainstModel { follower, run_m, model_m }).collect()
    });
    Health {
        verdict,
        degraded,
        disturbed,
        isolated,
        model,
        model_skipped: e.model_skipped.clone(),
        stalls: e.stalls.clone(),
    }
}

/// Distinct keys counted one by one; the rest are counted together.
const MAX_KEYS: usize = 64;

/// Puts on the run's control keys (`control/**`) that reached the monitor
/// from other processes: per key, how many, and how many were refused (did
/// not decode as what the key carries, or carried another run's fingerprint).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ControlWatch {
    pub keys: BTreeMap<String, (u64, u64)>,
}

impl ControlWatch {
    /// A put on `rel` (the key below `formation/<run>/`), judged with the
    /// run's `fingerprint`.
    pub fn note(&mut self, rel: &str, bytes: &[u8], fingerprint: u64) {
        let ok = valid_control(rel, bytes, fingerprint);
        let key = if self.keys.contains_key(rel) || self.keys.len() < MAX_KEYS { rel } else { "(other keys)" };
        let e = self.keys.entry(key.chars().take(200).collect()).or_default();
        e.0 += 1;
        e.1 += u64::from(!ok);
    }

    /// Refused puts, in all.
    pub fn refused(&self) -> u64 {
        self.keys.values().map(|v| v.1).sum()
    }
}

/// Whether a put on control key `rel` is what that key carries.
fn valid_control(rel: &str, bytes: &[u8], fingerprint: u64) -> bool {
    use formation_protocol::codec::decode;
    let mut parts = rel.split('/');
    let (Some("control"), Some(kind)) = (parts.next(), parts.next()) else { return false };
    let rest: Vec<&str> = parts.collect();
    match (kind, rest.as_slice()) {
        ("hello", [_]) => bytes.is_empty(),
        ("ready", [_]) => {
            decode::<formation_protocol::barrier::Ready>(bytes).is_some_and(|r| r.fingerprint == fingerprint)
        }
        ("start", []) => {
            decode::<formation_protocol::barrier::Start>(bytes).is_some_and(|s| s.fingerprint == fingerprint)
        }
        ("abort", []) => formation_protocol::barrier::abort_reason(bytes).is_some(),
        ("claim", [id]) => decode::<formation_protocol::claim::Claim>(bytes).is_some_and(|c| c.id.to_string() == *id),
        // Lock-step: what a follower holds of one killed, on its own key.
        ("holds", [id]) => decode::<formation_protocol::died::Holding>(bytes)
            .is_some_and(|h| h.fingerprint == fingerprint && h.sender.to_string() == *id),
        ("died", []) => decode::<formation_protocol::died::Died>(bytes).is_some_and(|d| d.fingerprint == fingerprint),
        // `formation leave --id ID`: empty, to a follower's id.
        ("leave", [id]) => bytes.is_empty() && id.parse::<u32>().is_ok_and(|i| i > 0),
        ("denied", [node]) => {
            bytes.len() <= formation_protocol::denied::MAX_REPORT_BYTES
                && serde_json::from_slice::<formation_protocol::denied::Report>(bytes)
                    .is_ok_and(|r| r.node == *node && r.rows.len() <= formation_protocol::denied::MAX_REPORT_ROWS)
        }
        // The monitor's own acknowledgements never reach it: another is foreign.
        _ => false,
    }
}

/// One line when more than [`HEARING_DEPARTURE`] of the link-steps heard a
/// message older than the delay allows, or nothing: the run then differs
/// from its model (`formation sim` with the same delay) for that reason.
fn heard_otherwise(e: &Evidence) -> Option<String> {
    let h = e.hearing?;
    let departed = h.older + h.silent;
    if h.link_steps == 0 || (departed as f64) <= HEARING_DEPARTURE * h.link_steps as f64 {
        return None;
    }
    Some(format!(
        "{departed} of {} link-steps ({:.2} %) heard otherwise than the model: {} used a message older than \
         network.delay_steps = {} allows, {} heard nothing; the host or the network was slower than the model \
         assumes, and the run differs from it for that reason (`formation replay --explain` names the links and \
         seconds)",
        h.link_steps,
        100.0 * departed as f64 / h.link_steps as f64,
        h.older,
        h.delay_steps,
        h.silent
    ))
}

/// "the leader handed over: a standby took the run over at t = 10.505 s;
/// no leader message from t = 10.006 s (0.499 s)"; or, for a leader gone
/// before the run began, "the leader was gone before the start: a standby
/// led the run from its start".
pub fn handover_line(heard: Option<u64>, at: u64, dt_s: f64) -> String {
    if heard.is_none() && at == 0 {
        return "the leader was gone before the start: a standby led the run from its start".into();
    }
    let gap = match heard {
        Some(h) if h + 1 < at => {
            format!("; no leader message from t = {:.3} s ({:.3} s)", (h + 1) as f64 * dt_s, (at - h - 1) as f64 * dt_s)
        }
        _ => String::new(),
    };
    format!("the leader handed over: a standby took the run over at t = {:.3} s{gap}", at as f64 * dt_s)
}

/// One line for all the followers whose clock was known worse than a
/// quarter step at the end (each follower's own warning, when it runs by
/// itself; in a `launch` they are summed up here, not 100 lines on the
/// terminal).
fn unsure_clocks(e: &Evidence) -> Option<String> {
    if e.quarter_step_us <= 0.0 {
        return None;
    }
    let unsure: Vec<(u32, f64)> =
        e.clock_uncertainty_us.iter().copied().filter(|&(_, u)| u > e.quarter_step_us).collect();
    let worst = unsure.iter().copied().max_by(|a, b| a.1.total_cmp(&b.1))?;
    let least = unsure.iter().map(|u| u.1).fold(f64::INFINITY, f64::min);
    let range = if unsure.len() == 1 {
        format!("±{:.3} ms", worst.1 * 1e-3)
    } else {
        format!("±{:.3}–{:.3} ms, follower {} the worst", least * 1e-3, worst.1 * 1e-3, worst.0)
    };
    Some(format!(
        "{} of {} followers knew the leader's clock only to more than a quarter step ({:.3} ms) at the end ({range}): \
         their steps may have run early or late by that much (a host short of CPU for its processes, or a slow \
         network; network.json's nodes.*.clock and loop)",
        unsure.len(),
        e.clock_uncertainty_us.len(),
        e.quarter_step_us * 1e-3
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A follower whose record stops short (its process stopped, not
    /// restarted) makes the run degraded: it was healthy, its metrics null.
    #[test]
    fn an_incomplete_run_is_never_healthy() {
        let mut e = Evidence { steps: 12_000, dt_s: 1e-3, ..Default::default() };
        assert_eq!(judge(&e).verdict, Verdict::Healthy);
        e.short = vec!["follower 3 recorded 5150 of 12001 samples (to t = 5.149 s of T = 12 s)".into()];
        let h = judge(&e);
        assert_eq!(h.verdict, Verdict::Degraded, "{h:?}");
        assert_eq!(h.degraded, ["incomplete: follower 3 recorded 5150 of 12001 samples (to t = 5.149 s of T = 12 s)"]);
    }

    /// A handover is said with its gap; a standby that led from the start
    /// (nothing heard, step 0) is said as such, with no gap.
    #[test]
    fn a_handover_says_its_gap_or_that_the_standby_led_from_the_start() {
        assert_eq!(
            handover_line(Some(10_003), 10_503, 1e-3),
            "the leader handed over: a standby took the run over at t = 10.503 s; no leader message from t = \
             10.004 s (0.499 s)"
        );
        assert_eq!(
            handover_line(None, 0, 1e-3),
            "the leader was gone before the start: a standby led the run from its start"
        );
        assert_eq!(handover_line(None, 70, 1e-3), "the leader handed over: a standby took the run over at t = 0.070 s");
    }

    #[test]
    fn a_wrecked_formation_is_degraded_and_a_held_attack_disturbed() {
        let mut e = Evidence { steps: 30_000, dt_s: 1e-3, ..Default::default() };
        e.errors = vec![(1, Some(0.11), Some(0.10)), (2, Some(11.5), Some(0.12))];
        let h = judge(&e);
        assert_eq!(h.verdict, Verdict::Degraded, "{h:?}");
        assert!(h.degraded[0].contains("follower 2") && h.degraded[0].contains("11.500 m"), "{:?}", h.degraded);
        e.errors[1].1 = Some(0.125);
        e.clocks = vec![("follower 3".into(), 0, Some(500.0))];
        e.isolations = vec![(4, 10_000, Some(12_500)), (4, 20_000, None)];
        e.refused = vec![("malformed telemetry messages".into(), 1), ("invalid estimates".into(), 0)];
        let h = judge(&e);
        assert_eq!(h.verdict, Verdict::Disturbed, "{h:?}");
        assert_eq!(h.isolated[0].times, 2);
        assert!((h.isolated[0].seconds - 12.5).abs() < 1e-9, "{:?}", h.isolated);
        assert_eq!(h.disturbed.len(), 3, "{:?}", h.disturbed);
        e.clocks[0].1 = 1;
        let h = judge(&e);
        assert_eq!(h.verdict, Verdict::Disturbed, "a clock step the formation survived: {h:?}");
        assert!(h.disturbed.iter().any(|d| d.contains("stepped 1 time")), "{:?}", h.disturbed);
        assert_eq!(judge(&Evidence::default()).verdict, Verdict::Healthy);
    }

    #[test]
    fn followers_unsure_of_the_leaders_clock_are_summed_up_in_one_line() {
        // 100 Hz: a quarter step is 2.5 ms.
        let mut e = Evidence { quarter_step_us: 2_500.0, ..Default::default() };
        e.clock_uncertainty_us =
            (1..=100).map(|id| (id, if id % 4 == 0 { 2_500.0 + 100.0 * id as f64 } else { 800.0 })).collect();
        let h = judge(&e);
        assert_eq!(h.verdict, Verdict::Disturbed, "{h:?}");
        assert_eq!(h.disturbed.len(), 1, "one line for every follower: {:?}", h.disturbed);
        let line = &h.disturbed[0];
        for words in ["25 of 100 followers", "(2.500 ms)", "±2.900–12.500 ms, follower 100 the worst"] {
            assert!(line.contains(words), "'{words}' not in: {line}");
        }
        // At the quarter step exactly, and in lock-step (no period), nothing.
        e.clock_uncertainty_us = vec![(1, 2_500.0), (2, 100.0)];
        assert_eq!(judge(&e).verdict, Verdict::Healthy);
        e.clock_uncertainty_us = vec![(1, 9_000.0)];
        assert!(judge(&e).disturbed[0].contains("1 of 1 followers") && judge(&e).disturbed[0].contains("(±9.000 ms)"));
        e.quarter_step_us = 0.0;
        assert_eq!(judge(&e).verdict, Verdict::Healthy);
    }

    /// The issue 47 run: 419 of 121,121 link-steps (0.35 %) departed, all
    /// of them in six steps at which every link of every follower heard
    /// late or nothing. The run is disturbed, and the stall is said first,
    /// as one event with its time, before the per-link count.
    #[test]
    fn a_stall_of_every_link_at_once_is_named_first_as_one_event() {
        let stall = formation_record::stall::Stall {
            from_k: 647,
            to_k: 653,
            most_links: 121,
            links: 121,
            followers_hit: 50,
            followers: 50,
            silent: 114,
            older: 305,
        };
        let h = HearingEvidence { older: 305, silent: 114, link_steps: 121_121, delay_steps: 1 };
        let e = Evidence { hearing: Some(h), stalls: vec![stall], dt_s: 0.01, ..Default::default() };
        let got = judge(&e);
        assert_eq!(got.verdict, Verdict::Disturbed, "{got:?}");
        let line = &got.disturbed[0];
        for words in [
            "a stall of the path every message shares",
            "from t = 6.470 s to 6.530 s (6 steps)",
            "121 of 121 links",
            "50 of 50 followers",
        ] {
            assert!(line.contains(words), "'{words}' not in: {line}");
        }
        assert!(got.line().contains("a stall of the path"), "{}", got.line());
        assert_eq!(got.stalls.len(), 1, "network.json's health.stalls: {:?}", got.stalls);
    }

    #[test]
    fn a_run_that_heard_older_messages_than_its_model_says_so() {
        let h = HearingEvidence { older: 5_150, silent: 8, link_steps: 241_241, delay_steps: 1 };
        let e = Evidence { hearing: Some(h), ..Default::default() };
        let got = judge(&e);
        assert_eq!(got.verdict, Verdict::Disturbed, "{got:?}");
        let line = &got.disturbed[0];
        for words in
            ["5158 of 241241 link-steps (2.14 %)", "5150 used a message older", "delay_steps = 1", "8 heard nothing"]
        {
            assert!(line.contains(words), "'{words}' not in: {line}");
        }
        // 0.1 % or less: as the model, within what a quiet host does.
        let quiet = HearingEvidence { older: 241, silent: 0, ..h };
        assert_eq!(judge(&Evidence { hearing: Some(quiet), ..Default::default() }).verdict, Verdict::Healthy);
        let just_over = HearingEvidence { older: 241, silent: 1, ..h };
        assert_eq!(judge(&Evidence { hearing: Some(just_over), ..Default::default() }).verdict, Verdict::Disturbed);
        // No hearing evidence (lock-step, or no delay): nothing said.
        assert_eq!(judge(&Evidence::default()).verdict, Verdict::Healthy);
    }

    #[test]
    fn a_flood_of_time_questions_is_named() {
        let e = Evidence { time_queries: (30_000, 5_600, 5), ..Default::default() };
        let h = judge(&e);
        assert_eq!(h.verdict, Verdict::Disturbed);
        assert!(h.disturbed[0].contains("5600 in one second"), "{:?}", h.disturbed);
        let calm = Evidence { time_queries: (600, 60, 5), ..Default::default() };
        assert_eq!(judge(&calm).verdict, Verdict::Healthy);
    }

    #[test]
    fn control_puts_are_counted_per_key_and_foreign_ones_refused() {
        let mut w = ControlWatch::default();
        let start = formation_protocol::codec::encode(&formation_protocol::barrier::Start {
            fingerprint: 7,
            epoch_unix_ns: 1,
            time_scale: 1.0,
            sent_ns: 1,
            absent: Vec::new(),
        });
        w.note("control/start", &start, 7);
        w.note("control/start", &start, 8);
        w.note("control/hello/3", b"", 7);
        w.note("control/ready/3", &[0xff; 13], 7);
        w.note("control/ack", b"anything", 7);
        // A refusal is a line of text; a denial report the reporter's JSON.
        w.note("control/abort", b"node 1 runs another scenario", 7);
        w.note("control/abort", b"", 7);
        w.note("control/abort", &[0x49, 0x25, 0x00, 0xff], 7);
        w.note("control/denied/leader", br#"{"node":"leader","rows":[]}"#, 7);
        w.note("control/denied/leader", br#"{"node":"agent-2","rows":[]}"#, 7);
        w.note("control/denied/leader", &[0x37; 40], 7);
        // `formation leave`: empty, to a follower.
        w.note("control/leave/3", b"", 7);
        w.note("control/leave/3", b"x", 7);
        w.note("control/leave/0", b"", 7);
        for i in 0..200 {
            w.note(&format!("control/hello/x{i}"), b"", 7);
        }
        assert_eq!(w.keys["control/leave/3"], (2, 1));
        assert_eq!(w.keys["control/leave/0"], (1, 1));
        assert_eq!(w.keys["control/start"], (2, 1));
        assert_eq!(w.keys["control/ready/3"], (1, 1));
        assert_eq!(w.keys["control/abort"], (3, 2));
        assert_eq!(w.keys["control/denied/leader"], (3, 2));
        assert_eq!(w.refused(), 9);
        assert!(w.keys.len() <= MAX_KEYS + 1, "{} keys", w.keys.len());
    }
}
