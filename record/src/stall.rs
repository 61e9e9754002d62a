//! Stalls of the shared path: steps of a real-time run at which most of its
//! links heard otherwise than the model at the same time.
//!
//! A slow link, a lossy cable or one busy process makes a few links hear
//! late, each at its own steps. When most links of most followers hear late
//! or nothing at the same steps, what stopped was something every message
//! depends on: the host (every node's process descheduled at once, as the
//! kernel does when real-time processes exceed their share of a second),
//! the router every client speaks through, or the leader. That is one event,
//! and a run names it as one rather than as a departure of each link.
//!
//! The model here is the one the run's health uses: real time, no fault
//! table, every message used `network.delay_steps` after it was sent. Plain
//! data: no IO, no clock.

use serde::{Deserialize, Serialize};

use crate::hearing::{FollowerHearing, Heard};

/// A step is shared when at least this share of the run's links heard
/// otherwise than the model at it...
pub const SHARED_LINKS: f64 = 0.5;
/// ...spread over at least this share of the followers...
pub const SHARED_FOLLOWERS: f64 = 0.5;
/// ...and at least this many links (a formation of two followers whose
/// one link is late is not a shared path).
pub const SHARED_MIN_LINKS: usize = 4;
/// Shared steps at most this many steps apart belong to one stall.
pub const JOIN_STEPS: u64 = 2;

/// A span of steps at which most links heard otherwise than the model.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stall {
    /// The first shared step and the step after the last.
    pub from_k: u64,
    pub to_k: u64,
    /// The most links that departed at one step of it, of `links`.
    pub most_links: usize,
    pub links: usize,
    /// Followers with at least one departed link during it, of `followers`.
    pub followers_hit: usize,
    pub followers: usize,
    /// Over the span: link-steps that heard nothing, and that used a
    /// message older than the delay.
    pub silent: u64,
    pub older: u64,
}

impl Stall {
    /// One line: "from t = 6.470 s to 6.530 s (6 steps): 121 of 121 links …".
    pub fn describe(&self, dt_s: f64) -> String {
        let steps = self.to_k - self.from_k;
        format!(
            "a stall of the path every message shares, from t = {:.3} s to {:.3} s ({steps} step{}): up to {} of {} \
             links at once, {} of {} followers, heard otherwise than the model ({} link-steps older, {} heard nothing) \
             — the host descheduling every node together (e.g. the kernel throttling real-time processes), the \
             router or the leader, not the links one by one",
            self.from_k as f64 * dt_s,
            self.to_k as f64 * dt_s,
            if steps == 1 { "" } else { "s" },
            self.most_links,
            self.links,
            self.followers_hit,
            self.followers,
            self.older,
            self.silent,
        )
    }
}

/// The runs of a follower's links that depart from a model using every
/// message `delay` steps after it was sent: (from, to, heard nothing),
/// steps [from, to). Older messages and silence depart; a newer message or
/// one the fault table removed does not, nor anything before step `delay`,
/// where the model hears nothing either.
fn departures(f: &FollowerHearing, delay: u64) -> impl Iterator<Item = (u64, u64, bool)> + '_ {
    f.segments.iter().flat_map(move |seg| {
        seg.heard.slots.iter().flat_map(move |runs| {
            let mut k = seg.first_k;
            runs.iter().filter_map(move |&(code, count)| {
                let (a, b) = (k.max(delay), k + u64::from(count));
                k = b;
                let silent = match Heard::from_code(code) {
                    Heard::Silent => true,
                    Heard::Age(age) if u64::from(age) > delay => false,
                    _ => return None,
                };
                (a < b).then_some((a, b, silent))
            })
        })
    })
}

/// The stalls of a real-time run without a fault table, from its
/// followers' hearing records and `network.delay_steps`, in step order. Linear in the record's
/// departed link-steps and the run's steps.
pub fn stalls(record: &[&FollowerHearing], delay: u64) -> Vec<Stall> {
    let steps = record.iter().flat_map(|f| f.segments.iter().map(|s| s.end())).max().unwrap_or(0);
    let links: usize = record.iter().map(|f| f.sources.len()).sum();
    let followers = record.len();
    if links < SHARED_MIN_LINKS || steps == 0 {
        return Vec::new();
    }
    let n = usize::try_from(steps).unwrap_or(usize::MAX);
    // Per step: links that heard nothing, that heard older, and followers
    // with a departed link.
    let mut silent = vec![0u32; n];
    let mut older = vec![0u32; n];
    let mut hit = vec![0u32; n];
    let mut mine = vec![false; n];
    for &f in record {
        let mut touched = Vec::new();
        for (a, b, heard_nothing) in departures(f, delay) {
            for i in a as usize..(b as usize).min(n) {
                if heard_nothing {
                    silent[i] += 1;
                } else {
                    older[i] += 1;
                }
                if !mine[i] {
                    mine[i] = true;
                    touched.push(i);
                }
            }
        }
        for i in touched {
            hit[i] += 1;
            mine[i] = false;
        }
    }
    let departed = |i: usize| (silent[i] + older[i]) as usize;
    let shared = |i: usize| {
        departed(i) >= SHARED_MIN_LINKS
            && departed(i) as f64 >= SHARED_LINKS * links as f64
            && f64::from(hit[i]) >= SHARED_FOLLOWERS * followers as f64
    };
    let mut spans: Vec<(u64, u64)> = Vec::new();
    for k in (0..n).filter(|&i| shared(i)).map(|i| i as u64) {
        match spans.last_mut() {
            Some(s) if k <= s.1 + JOIN_STEPS => s.1 = k + 1,
            _ => spans.push((k, k + 1)),
        }
    }
    spans
        .into_iter()
        .map(|(from_k, to_k)| {
            let span = from_k as usize..to_k as usize;
            Stall {
                from_k,
                to_k,
                most_links: span.clone().map(departed).max().unwrap_or(0),
                links,
                followers_hit: record
                    .iter()
                    .filter(|&&f| departures(f, delay).any(|(a, b, _)| a < to_k && from_k < b))
                    .count(),
                followers,
                silent: span.clone().map(|i| u64::from(silent[i])).sum(),
                older: span.map(|i| u64::from(older[i])).sum(),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hearing::{HeardRuns, Segment};

    /// A record of `followers` followers with `sources` sources each, every
    /// link hearing age 1 for `steps` steps, except `late` (follower index,
    /// slot, steps) heard as `how`.
    fn record(
        followers: usize,
        sources: usize,
        steps: u64,
        late: &[(usize, usize, std::ops::Range<u64>, Heard)],
    ) -> Vec<FollowerHearing> {
        let mut r = Vec::new();
        for i in 0..followers {
            let mut runs = HeardRuns::with_slots(sources, 1);
            for k in 0..steps {
                for slot in 0..sources {
                    let h = late
                        .iter()
                        .find(|(f, s, span, _)| *f == i && *s == slot && span.contains(&k))
                        .map_or(if k == 0 { Heard::Silent } else { Heard::Age(1) }, |l| l.3);
                    runs.push_one(slot, h);
                }
                runs.end_step();
            }
            let mut f = FollowerHearing::new(i as u32 + 1, (0..sources as u32).collect());
            f.segments.push(Segment { first_k: 0, heard: runs });
            r.push(f);
        }
        r
    }

    /// The run: for 6 steps every link of every follower heard
    /// nothing or an older message: one stall, every link and follower.
    #[test]
    fn every_link_late_at_once_is_one_stall() {
        let mut late = Vec::new();
        for f in 0..10 {
            for s in 0..3 {
                late.push((f, s, 647..650, Heard::Age(2 + (f as u32 % 2))));
                late.push((f, s, 650..653, Heard::Silent));
            }
        }
        let r = record(10, 3, 1001, &late);
        let got = stalls(&r.iter().collect::<Vec<_>>(), 1);
        assert_eq!(got.len(), 1, "{got:?}");
        let s = &got[0];
        assert_eq!((s.from_k, s.to_k, s.most_links, s.links), (647, 653, 30, 30), "{s:?}");
        assert_eq!((s.followers_hit, s.followers, s.older, s.silent), (10, 10, 90, 90), "{s:?}");
        assert!(s.describe(0.01).contains("from t = 6.470 s to 6.530 s (6 steps)"), "{}", s.describe(0.01));
    }

    /// One slow link, or a few followers' links late at their own steps,
    /// is no stall; nor is the first step, where the model hears nothing.
    #[test]
    fn links_late_one_by_one_are_no_stall() {
        let mut late = vec![(3, 0, 100..400, Heard::Age(2))];
        for f in 0..4 {
            late.push((f, 1, 500 + 10 * f as u64..505 + 10 * f as u64, Heard::Silent));
        }
        let r = record(10, 3, 1001, &late);
        assert_eq!(stalls(&r.iter().collect::<Vec<_>>(), 1), vec![]);
    }

    /// Shared steps two apart are one stall; further apart, two.
    #[test]
    fn shared_steps_close_together_join() {
        let all = |span: std::ops::Range<u64>| {
            let mut v = Vec::new();
            for f in 0..6 {
                for s in 0..2 {
                    v.push((f, s, span.clone(), Heard::Silent));
                }
            }
            v
        };
        let mut late = all(100..102);
        late.extend(all(104..105));
        late.extend(all(300..301));
        let r = record(6, 2, 400, &late);
        let got = stalls(&r.iter().collect::<Vec<_>>(), 1);
        let spans: Vec<(u64, u64)> = got.iter().map(|s| (s.from_k, s.to_k)).collect();
        assert_eq!(spans, vec![(100, 105), (300, 301)], "{got:?}");
    }
}
