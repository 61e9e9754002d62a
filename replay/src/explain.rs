//! `formation replay --explain`: a run beside its model, and which links and
//! which periods explain the difference.
//!
//! The model is the run's scenario with the hearing `formation sim` assumes
//! (every message used `network.delay_steps` after it was sent, the fault
//! table applied). The departure of a metric is, summed over followers,
//! run − model. A link (or a window of steps) explains what replaying the
//! run with that link's hearing replaced by the model's takes away:
//! Σ (run − run with the link as modelled). The shares need not add up to
//! one (the links interact), but a link that explains most of it is where
//! the network differed from the model.

use formation_record::{FollowerMetrics, Heard};

use crate::replay::{self, HearingSource, Loaded, Metrics, ModelEar};
use formation_exit::Error;

/// One link of the graph: `sender` → follower `receiver` (its slot `slot`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Link {
    pub receiver: u32,
    pub index: usize,
    pub slot: usize,
    /// 0: the leader.
    pub sender: u32,
}

impl std::fmt::Display for Link {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.sender {
            0 => write!(f, "leader → {}", self.receiver),
            s => write!(f, "{s} → {}", self.receiver),
        }
    }
}

/// How a link's recorded hearing compares with the model's.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkHearing {
    pub link: Link,
    /// Recorded steps of the receiver.
    pub steps: u64,
    /// Steps at which the run used another message than the model.
    pub differing: u64,
    /// Of those: the run's message older than the model's, newer, silent
    /// (or removed) where the model heard, heard where the model did not,
    /// or silent where the model counts the message removed (or the reverse).
    pub older: u64,
    pub newer: u64,
    pub silent: u64,
    pub extra: u64,
    pub other: u64,
}

/// What a link or a window explains of the departure.
#[derive(Clone, Debug, PartialEq)]
pub struct Share {
    /// Σ over followers of run − run with this part as modelled.
    pub explained: f64,
    /// explained / departure.
    pub share: f64,
}

/// The first step at which the run heard differently from the model.
#[derive(Clone, Debug, PartialEq)]
pub struct Departure {
    pub link: Link,
    pub k: u64,
    pub run: Heard,
    pub model: Heard,
}

/// A run beside its model.
#[derive(Clone, Debug)]
pub struct Explanation {
    pub metric: String,
    /// Per follower (id): the metric in the run, in the model, and with the
    /// run's hearing (equals the run when the record is faithful).
    pub followers: Vec<(u32, Option<f64>, Option<f64>)>,
    pub first: Option<Departure>,
    pub hearing: Vec<LinkHearing>,
    /// Σ (run − model) over followers.
    pub departure: f64,
    /// Links that heard differently from the model, most explaining first.
    pub links: Vec<(Link, Share)>,
    /// Windows of steps [from, to), most explaining first.
    pub windows: Vec<((u64, u64), Share)>,
    pub window_steps: u64,
    /// Spans at which most links heard otherwise than the model at once
    /// (real time with a delay and no fault table), in step order, with
    /// what replaying the span as modelled takes away.
    pub stalls: Vec<(formation_record::stall::Stall, Share)>,
}

/// The metric `name` of a follower's metrics (a summary.json key).
pub fn metric(m: &FollowerMetrics, name: &str) -> Option<f64> {
    serde_json::to_value(m).ok()?.get(name)?.as_f64()
}

/// The metric names --explain takes.
pub const METRICS: &[&str] = &[
    "torque_tv",
    "formation_rms_last10",
    "formation_final",
    "heading_final",
    "estimator_error_final",
    "vc_peak",
    "torque_peak",
    "rmse_v",
    "rmse_w",
];

/// Every link of the scenario, by receiver and slot.
pub fn links(loaded: &Loaded) -> Vec<Link> {
    let s = &loaded.scenario;
    (0..s.followers.len())
        .flat_map(|index| {
            let receiver = s.followers[index].id;
            s.sources_of(index).into_iter().enumerate().map(move |(slot, sender)| Link {
                receiver,
                index,
                slot,
                sender,
            })
        })
        .collect()
}

/// How each link's recorded hearing compares with the model's, and the first departure.
pub fn compare_hearing(loaded: &Loaded) -> (Vec<LinkHearing>, Option<Departure>) {
    let s = &loaded.model_scenario();
    let all = links(loaded);
    let mut out: Vec<LinkHearing> = all
        .iter()
        .map(|&link| LinkHearing { link, steps: 0, differing: 0, older: 0, newer: 0, silent: 0, extra: 0, other: 0 })
        .collect();
    let mut first: Option<Departure> = None;
    let mut base = 0;
    for (index, f) in loaded.record.followers.iter().enumerate() {
        let slots = f.sources.len();
        let mut ear = ModelEar::new(s, index);
        let mut model = vec![Heard::Silent; slots];
        let mut next_k = 0;
        let mut cursor = formation_record::hearing::Cursor::new(f);
        for k in f.segments.iter().flat_map(|s| s.first_k..s.end()) {
            let Some(heard) = cursor.at(k) else { continue };
            // The model hears every step, recorded or not.
            while next_k <= k {
                ear.hear(next_k, &mut model);
                next_k += 1;
            }
            for slot in 0..slots {
                let l = &mut out[base + slot];
                l.steps += 1;
                let (run, m) = (heard[slot], model[slot]);
                if run == m {
                    continue;
                }
                l.differing += 1;
                match (run.stamp(k), m.stamp(k)) {
                    (Some(a), Some(b)) if a < b => l.older += 1,
                    (Some(_), Some(_)) => l.newer += 1,
                    (None, Some(_)) => l.silent += 1,
                    (Some(_), None) => l.extra += 1,
                    (None, None) => l.other += 1,
                }
                if first.as_ref().is_none_or(|d| k < d.k) {
                    first = Some(Departure { link: all[base + slot], k, run, model: m });
                }
            }
        }
        base += slots;
    }
    (out, first)
}

/// The metric per follower of a replay with `hearing`.
fn metrics_with(loaded: &Loaded, hearing: HearingSource, name: &str) -> Result<Vec<Option<f64>>, Error> {
    let mut sink = Metrics::new(&loaded.scenario);
    replay::replay(loaded, hearing, &mut sink)?;
    Ok(sink.acc.iter().map(|a| metric(&a.finish(), name)).collect())
}

fn explained(run: &[Option<f64>], with: &[Option<f64>]) -> f64 {
    run.iter().zip(with).filter_map(|(a, b)| Some(a.as_ref()? - b.as_ref()?)).sum()
}

/// The run beside its model: the metric `name`, links ranked, and windows
/// of `window_steps` ranked. `progress(done, total)` after each replay.
pub fn explain(
    loaded: &Loaded,
    name: &str,
    window_steps: u64,
    progress: &(dyn Fn(usize, usize) + Sync),
) -> Result<Explanation, Error> {
    if !METRICS.contains(&name) {
        return Err(Error::Input(format!("--metric {name}: not a follower metric (one of: {})", METRICS.join(", "))));
    }
    let window_steps = window_steps.max(1);
    let (hearing, first) = compare_hearing(loaded);
    let steps = loaded.scenario.steps() + 1;
    let windows: Vec<(u64, u64)> =
        (0..steps.div_ceil(window_steps)).map(|w| (w * window_steps, ((w + 1) * window_steps).min(steps))).collect();
    // Only links that heard differently can explain anything.
    let differing: Vec<Link> = hearing.iter().filter(|h| h.differing > 0).map(|h| h.link).collect();
    let s = &loaded.scenario;
    let stalls = if s.timing == formation_scenario::Timing::Realtime && s.network.delay_steps > 0 && s.faults.is_empty()
    {
        let heard: Vec<&formation_record::hearing::FollowerHearing> = loaded.record.followers.iter().collect();
        formation_record::stall::stalls(&heard, s.network.delay_steps)
    } else {
        Vec::new()
    };
    let mut jobs: Vec<HearingSource> = vec![HearingSource::Recorded, HearingSource::Model];
    jobs.extend(differing.iter().map(|l| HearingSource::Link { index: l.index, slot: l.slot }));
    jobs.extend(windows.iter().map(|&(from_k, to_k)| HearingSource::Window { from_k, to_k }));
    jobs.extend(stalls.iter().map(|st| HearingSource::Window { from_k: st.from_k, to_k: st.to_k }));
    let total = jobs.len();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let results: Vec<Result<Vec<Option<f64>>, Error>> = {
        use rayon::prelude::*;
        jobs.par_iter()
            .map(|&h| {
                let r = metrics_with(loaded, h, name);
                progress(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1, total);
                r
            })
            .collect()
    };
    let mut results = results.into_iter().collect::<Result<Vec<_>, _>>()?.into_iter();
    let run = results.next().unwrap_or_default();
    let model = results.next().unwrap_or_default();
    let departure = explained(&run, &model);
    let share = |with: &[Option<f64>]| {
        let e = explained(&run, with);
        Share { explained: e, share: if departure != 0.0 { e / departure } else { 0.0 } }
    };
    let mut links: Vec<(Link, Share)> =
        differing.iter().map(|&l| (l, share(&results.next().unwrap_or_default()))).collect();
    let mut wins: Vec<((u64, u64), Share)> =
        windows.iter().map(|&w| (w, share(&results.next().unwrap_or_default()))).collect();
    let stalls = stalls.into_iter().map(|st| (st, share(&results.next().unwrap_or_default()))).collect();
    let by = |a: &Share, b: &Share| {
        let sign = departure.signum();
        (b.explained * sign).total_cmp(&(a.explained * sign))
    };
    links.sort_by(|a, b| by(&a.1, &b.1));
    wins.sort_by(|a, b| by(&a.1, &b.1));
    let followers = loaded
        .scenario
        .followers
        .iter()
        .enumerate()
        .map(|(i, f)| (f.id, run.get(i).copied().flatten(), model.get(i).copied().flatten()))
        .collect();
    Ok(Explanation {
        metric: name.to_string(),
        followers,
        first,
        hearing,
        departure,
        links,
        windows: wins,
        window_steps,
        stalls,
    })
}
