//! One node's telemetry put back in step order ([`Stream`]), and the checks
//! a batch passes before anything of it is filed ([`check_batch`]). Plain
//! types: no socket, no clock.

use std::collections::BTreeMap;

/// Steps of one node that the monitor will never have.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Gap {
    /// Steps from..to.
    pub from: u64,
    pub to: u64,
    /// "restarted" (the node's process was replaced), "dropped by the
    /// sender" (its store of unacknowledged telemetry overflowed) or
    /// "killed" (its process ended without a word, lock-step).
    pub why: &'static str,
}

/// Batches that arrive ahead of the recorded end are held, up to about
/// this many bytes per node (at most 8192 batches, at least 16).
const MAX_AHEAD_BYTES: usize = 16 << 20;

/// One node's telemetry put back in step order: batches may arrive late,
/// twice (sent again), out of order, or never (steps the sender says it
/// can no longer deliver become a [`Gap`]).
#[derive(Debug)]
pub(super) struct Stream<T> {
    /// Every step below `end` is recorded or marked lost.
    pub(super) end: u64,
    /// Batches that arrived ahead of `end`, by first step.
    ahead: BTreeMap<u64, Vec<T>>,
    pub(super) gaps: Vec<Gap>,
    /// Batches that arrived ahead of a missing one and were held.
    pub(super) reordered: u64,
    /// Batches that held nothing new (sent again after a lost acknowledgement).
    pub(super) duplicates: u64,
    /// Batches given up because too many were held ahead.
    overflow: u64,
    /// Steps that came late and filled a hole (a batch sent again after an
    /// outage or a loss), as merged spans [from, to).
    pub(super) recovered: Vec<(u64, u64)>,
    /// Steps at which a new process of the sender took over.
    pub(super) restarts: Vec<u64>,
    /// The sender's process (see `Delivery::incarnation`).
    incarnation: Option<u64>,
    /// Most batches held ahead.
    max_ahead: usize,
}

impl<T> Default for Stream<T> {
    fn default() -> Self {
        Self::for_batches_of(1)
    }
}

impl<T> Stream<T> {
    /// A stream whose batches hold at most `batch` items: it holds at most
    /// [`MAX_AHEAD_BYTES`] of them ahead.
    pub(super) fn for_batches_of(batch: usize) -> Self {
        let per_batch = batch.max(1) * std::mem::size_of::<T>().max(1);
        Self {
            max_ahead: (MAX_AHEAD_BYTES / per_batch).clamp(16, 8192),
            end: 0,
            ahead: BTreeMap::new(),
            gaps: Vec::new(),
            reordered: 0,
            duplicates: 0,
            overflow: 0,
            recovered: Vec::new(),
            restarts: Vec::new(),
            incarnation: None,
        }
    }

    /// Files a checked batch (items for steps first_k, first_k + 1, …) from
    /// a sender that can deliver nothing below `available_from`; appends to
    /// `out` every item now in order, with its step.
    pub(super) fn file(
        &mut self,
        first_k: u64,
        items: Vec<T>,
        available_from: u64,
        incarnation: u64,
        out: &mut Vec<(u64, T)>,
    ) {
        let restarted = self.incarnation.is_some_and(|i| i != incarnation);
        if restarted {
            self.restarts.push(first_k);
        }
        self.incarnation = Some(incarnation);
        let end = first_k + items.len() as u64;
        if end <= self.end || items.is_empty() {
            self.duplicates += 1;
        } else if first_k > self.end {
            self.reordered += 1;
            if self.ahead.len() >= self.max_ahead {
                self.overflow += 1;
                if let Some(last) = self.ahead.keys().next_back().copied().filter(|&l| l > first_k) {
                    self.ahead.remove(&last);
                } else {
                    return;
                }
            }
            // Of two batches with one first step, keep the longer.
            match self.ahead.get(&first_k) {
                Some(held) if held.len() >= items.len() => {}
                _ => {
                    self.ahead.insert(first_k, items);
                }
            }
        } else {
            if !self.ahead.is_empty() {
                // A late batch fills the hole before held ones.
                match self.recovered.last_mut() {
                    Some(r) if r.1 >= first_k => r.1 = r.1.max(end),
                    _ => self.recovered.push((first_k, end)),
                }
            }
            self.take(first_k, items, out);
        }
        loop {
            // Held batches that now continue the stream.
            while let Some((&k, _)) = self.ahead.first_key_value().filter(|(&k, _)| k <= self.end) {
                if let Some(items) = self.ahead.remove(&k) {
                    self.take(k, items, out);
                }
            }
            // Steps the sender can no longer deliver: a gap up to what it can.
            if available_from <= self.end {
                break;
            }
            let to = self.ahead.keys().next().map_or(available_from, |&k| k.min(available_from));
            let why = if restarted { "restarted" } else { "dropped by the sender" };
            match self.gaps.last_mut() {
                Some(g) if g.to == self.end && g.why == why => g.to = to,
                _ => self.gaps.push(Gap { from: self.end, to, why }),
            }
            self.end = to;
        }
    }

    /// Appends the items of a batch beyond `end` (first_k ≤ end).
    fn take(&mut self, first_k: u64, items: Vec<T>, out: &mut Vec<(u64, T)>) {
        let skip = (self.end - first_k) as usize;
        let end = first_k + items.len() as u64;
        out.extend(items.into_iter().enumerate().skip(skip).map(|(i, x)| (first_k + i as u64, x)));
        self.end = self.end.max(end);
    }

    /// A sender that joined at step k (absent before): nothing below k is
    /// expected, so none of it is a gap.
    pub(super) fn skip_to(&mut self, k: u64) {
        if self.end < k && self.ahead.is_empty() && self.gaps.is_empty() {
            self.end = k;
        }
    }

    /// A sender whose process was killed (lock-step, docs/model.md §14):
    /// every step below `k` not recorded by now never will be, a gap of
    /// `why`. Batches held ahead stay held (they continue the stream when
    /// what is before them is in).
    pub(super) fn lose_to(&mut self, k: u64, why: &'static str) {
        let to = self.ahead.keys().next().map_or(k, |&a| a.min(k));
        if self.end < to {
            self.gaps.push(Gap { from: self.end, to, why });
            self.end = to;
        }
    }

    pub(super) fn lost_steps(&self) -> u64 {
        self.gaps.iter().map(|g| g.to - g.from).sum()
    }
}

/// Checks a batch against a run of `steps` + 1 steps before anything is
/// filed: None if it reaches beyond the run's end; otherwise the items up
/// to the first that fails `ok(k, item)`, and whether it was cut there.
pub(super) fn check_batch<T>(
    mut items: Vec<T>,
    first_k: u64,
    steps: u64,
    max_len: usize,
    ok: impl Fn(u64, &T) -> bool,
) -> Option<(Vec<T>, bool)> {
    if items.len() > max_len {
        return None;
    }
    match first_k.checked_add(items.len() as u64) {
        Some(last) if last <= steps + 1 => {}
        _ => return None,
    }
    let bad = items.iter().enumerate().position(|(i, x)| !ok(first_k + i as u64, x));
    if let Some(b) = bad {
        items.truncate(b);
    }
    Some((items, bad.is_some()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batches_are_checked_before_anything_is_recorded() {
        let ok = |_: u64, x: &f64| x.is_finite();
        // Beyond the run's end: refused whole.
        assert_eq!(check_batch(vec![1.0; 3], 9, 10, 50, ok), None);
        assert_eq!(check_batch(vec![1.0; 1], u64::MAX, 10, 50, ok), None);
        // Cut at the first non-finite item.
        assert_eq!(check_batch(vec![1.0, f64::NAN, 3.0], 4, 10, 50, ok), Some((vec![1.0], true)));
        assert_eq!(check_batch(vec![1.0, 2.0], 9, 10, 50, ok), Some((vec![1.0, 2.0], false)));
        // Longer than the run's batches: forged.
        assert_eq!(check_batch(vec![1.0; 51], 0, 1000, 50, ok), None);
    }

    /// Files batches into a stream; the steps that came out, in order.
    fn file(s: &mut Stream<u64>, first_k: u64, n: u64, available_from: u64, incarnation: u64) -> Vec<u64> {
        let mut out = Vec::new();
        s.file(first_k, (first_k..first_k + n).collect(), available_from, incarnation, &mut out);
        assert!(out.iter().all(|(k, x)| k == x), "{out:?}");
        out.into_iter().map(|(k, _)| k).collect()
    }

    #[test]
    fn a_stream_puts_late_repeated_and_overlapping_batches_back_in_order() {
        let mut s = Stream::default();
        assert_eq!(file(&mut s, 0, 5, 0, 1), (0..5).collect::<Vec<_>>());
        // 10..15 and 15..20 arrive before 5..10: held, then released in order.
        assert!(file(&mut s, 10, 5, 0, 1).is_empty());
        assert!(file(&mut s, 15, 5, 5, 1).is_empty());
        assert_eq!(s.reordered, 2);
        assert_eq!(file(&mut s, 5, 5, 5, 1), (5..20).collect::<Vec<_>>());
        // Sent again: nothing new. Overlapping: only what is new.
        assert!(file(&mut s, 10, 5, 5, 1).is_empty());
        assert_eq!(s.duplicates, 1);
        assert_eq!(file(&mut s, 18, 4, 18, 1), vec![20, 21]);
        assert!(s.gaps.is_empty());
        assert_eq!(s.end, 22);
    }

    #[test]
    fn steps_the_sender_can_no_longer_deliver_become_a_marked_gap() {
        let mut s = Stream::default();
        file(&mut s, 0, 10, 0, 1);
        // The sender dropped 10..30 from a full store; 40..45 came before 30..40.
        assert!(file(&mut s, 40, 5, 30, 1).is_empty());
        assert_eq!(s.gaps, vec![Gap { from: 10, to: 30, why: "dropped by the sender" }]);
        assert_eq!(file(&mut s, 30, 10, 30, 1), (30..45).collect::<Vec<_>>());
        // A restarted process (new incarnation) resumes at step 60.
        assert_eq!(file(&mut s, 60, 5, 60, 2), (60..65).collect::<Vec<_>>());
        assert_eq!(s.gaps[1], Gap { from: 45, to: 60, why: "restarted" });
        assert_eq!(s.lost_steps(), 35);
    }
}
