//! Metrics under faults (docs/model.md §14's last bullet): for each fault window and
//! each follower, the peaks from the window's start until 5 s after its end,
//! and the recovery time of the leader estimate after the window.

use std::collections::BTreeMap;

use formation_scenario::{LinkFault, Scenario};
use serde::{Deserialize, Serialize};

use crate::row::Row;

/// How long after a window's end its peaks are still taken, s.
pub const AFTER_S: f64 = 5.0;
/// The estimator position error a follower has recovered below, m.
pub const RECOVERED_M: f64 = 0.02;
/// How long the error must stay below [`RECOVERED_M`], s.
pub const STAY_S: f64 = 1.0;

/// One fault window in steps: peaks over [from_k, until_k), recovery from to_k.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Window {
    pub from_k: u64,
    pub to_k: u64,
    pub until_k: u64,
}

impl Window {
    pub fn of(f: &LinkFault, dt_s: f64) -> Self {
        let (from_k, to_k) = f.steps(dt_s);
        Self { from_k, to_k, until_k: to_k + (AFTER_S / dt_s).round() as u64 }
    }

    /// Every fault window of a scenario, in table order.
    pub fn all(s: &Scenario) -> Vec<Window> {
        s.faults.iter().map(|f| Window::of(f, s.dt_s)).collect()
    }
}

/// One follower's metrics around one fault window. Peaks are null when no
/// sample of the span was recorded.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct OutageMetrics {
    /// Peak ‖(x_ir, y_ir) − (x_r, y_r)‖ over the span, m.
    pub peak_estimator_error: Option<f64>,
    /// Peak formation error over the span, m.
    pub peak_formation_error: Option<f64>,
    /// Peak |v_c| over the span, m/s.
    pub peak_vc: Option<f64>,
    /// Peak |v̇_c| over the span (backward differences of recorded steps), m/s².
    pub peak_vc_rate: Option<f64>,
    /// Peak |ω̇_c| over the span, rad/s².
    pub peak_wc_rate: Option<f64>,
    /// Peak |τ| over both wheels over the span, N m.
    pub peak_torque: Option<f64>,
    /// From the window's end until the estimator error is below 0.02 m and
    /// stays there for 1 s, s; null: not recovered by the end of the run.
    pub recovery_s: Option<f64>,
    /// Samples recorded in the span [from, to + 5 s) (clipped to the run).
    pub samples: u64,
}

/// Streaming accumulator of one follower's [`OutageMetrics`] for one window.
#[derive(Clone, Debug, Default)]
pub struct OutageAccumulator {
    w: Window,
    dt_s: f64,
    stay_steps: u64,
    m: OutageMetrics,
    prev: Option<(u64, f64, f64)>,
    below_since: Option<u64>,
    recovered_at: Option<u64>,
}

fn peak(p: &mut Option<f64>, x: f64) {
    *p = Some(p.map_or(x, |p| p.max(x)));
}

impl OutageAccumulator {
    pub fn new(w: Window, dt_s: f64) -> Self {
        Self { w, dt_s, stay_steps: (STAY_S / dt_s).round() as u64, ..Default::default() }
    }

    /// Adds the sample of step k (in step order; gaps allowed).
    pub fn push(&mut self, k: u64, r: &Row) {
        let rates = match self.prev {
            Some((pk, vc, wc)) if pk + 1 == k => Some(((r.v_c - vc) / self.dt_s, (r.w_c - wc) / self.dt_s)),
            // The first step: v̇_c = ω̇_c = 0 (docs/model.md §7).
            None if k == 0 => Some((0.0, 0.0)),
            _ => None,
        };
        self.prev = Some((k, r.v_c, r.w_c));
        if (self.w.from_k..self.w.until_k).contains(&k) {
            let m = &mut self.m;
            peak(&mut m.peak_estimator_error, r.estimator_error);
            peak(&mut m.peak_formation_error, r.formation_error);
            peak(&mut m.peak_vc, r.v_c.abs());
            peak(&mut m.peak_torque, r.tau_l.abs().max(r.tau_r.abs()));
            if let Some((dv, dw)) = rates {
                peak(&mut m.peak_vc_rate, dv.abs());
                peak(&mut m.peak_wc_rate, dw.abs());
            }
            m.samples += 1;
        }
        if k >= self.w.to_k && self.recovered_at.is_none() {
            if r.estimator_error < RECOVERED_M {
                let since = *self.below_since.get_or_insert(k);
                if k - since >= self.stay_steps {
                    self.recovered_at = Some(since);
                }
            } else {
                self.below_since = None;
            }
        }
    }

    pub fn finish(&self) -> OutageMetrics {
        OutageMetrics { recovery_s: self.recovered_at.map(|k| (k - self.w.to_k) as f64 * self.dt_s), ..self.m }
    }
}

/// One fault of the table with every follower's metrics around it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FaultSummary {
    /// "follower 3 down 10–13 s".
    pub fault: String,
    pub from: f64,
    pub to: f64,
    pub loss: f64,
    pub followers: BTreeMap<u32, OutageMetrics>,
}

impl FaultSummary {
    /// The scenario's faults with each follower's metrics: `per_follower`
    /// holds, by follower id, one entry per fault in table order.
    pub fn all(s: &Scenario, per_follower: &BTreeMap<u32, Vec<OutageMetrics>>) -> Vec<FaultSummary> {
        s.faults
            .iter()
            .enumerate()
            .map(|(i, f)| FaultSummary {
                fault: f.label(),
                from: f.from_s,
                to: f.to_s,
                loss: f.loss,
                followers: per_follower.iter().filter_map(|(&id, v)| v.get(i).map(|m| (id, *m))).collect(),
            })
            .collect()
    }
}

fn cell(v: Option<f64>, prec: usize) -> String {
    v.map_or_else(|| "—".to_string(), |x| format!("{x:.prec$}"))
}

/// The printed table of metrics under faults of a run recorded until
/// `duration_s` (its end, or where an incomplete run's record ends): the
/// peaks' window and the recovery say where the record ended first.
pub fn table(faults: &[FaultSummary], duration_s: f64) -> String {
    let mut out = String::new();
    for f in faults {
        let until = f.to + AFTER_S;
        let peaks = if until > duration_s {
            format!("peaks from {} s to the record's end at {duration_s} s", f.from)
        } else {
            format!("peaks from {} s to {until} s", f.from)
        };
        // Recovery needs the error low for STAY_S after the window.
        let judged = f.to + STAY_S <= duration_s;
        let recovery = if judged {
            format!("recovery: estimator error < {RECOVERED_M} m for {STAY_S} s")
        } else {
            format!("recovery: not judged, the run ends less than {STAY_S} s after the fault")
        };
        out += &format!("\n{} ({peaks}; {recovery})\n", f.fault);
        out += &format!(
            "{:>8} {:>9} {:>9} {:>9} {:>10} {:>9} {:>10}\n",
            "follower", "est_peak", "form_peak", "vc_peak", "vc_rate", "tau_peak", "recovery"
        );
        for (id, m) in &f.followers {
            out += &format!(
                "{:>8} {:>9} {:>9} {:>9} {:>10} {:>9} {:>10}\n",
                id,
                cell(m.peak_estimator_error, 4),
                cell(m.peak_formation_error, 4),
                cell(m.peak_vc, 3),
                cell(m.peak_vc_rate, 2),
                cell(m.peak_torque, 3),
                match (m.recovery_s, judged) {
                    (Some(r), _) => format!("{r:.3} s"),
                    (None, true) => "not rec.".to_string(),
                    (None, false) => "—".to_string(),
                },
            );
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(est: f64, vc: f64) -> Row {
        Row { estimator_error: est, v_c: vc, ..Default::default() }
    }

    #[test]
    fn a_run_shorter_than_the_peaks_window_says_where_it_ended() {
        let f = FaultSummary {
            fault: "follower 3 down 1–1.5 s".into(),
            from: 1.0,
            to: 1.5,
            loss: 1.0,
            followers: [(3, OutageMetrics::default())].into_iter().collect(),
        };
        let short = table(std::slice::from_ref(&f), 2.0);
        assert!(short.contains("peaks from 1 s to the record's end at 2 s"), "{short}");
        assert!(short.contains("recovery: not judged") && !short.contains("not rec."), "{short}");
        let long = table(&[f], 30.0);
        assert!(long.contains("peaks from 1 s to 6.5 s; recovery: estimator error < 0.02 m for 1 s"), "{long}");
        assert!(long.contains("not rec."), "{long}");
    }

    #[test]
    fn recovery_counts_from_the_window_end_until_the_error_stays_low_for_a_second() {
        // dt = 0.1 s, window [1, 2) s: steps 10..20, peaks until step 70.
        let w = Window { from_k: 10, to_k: 20, until_k: 70 };
        let mut a = OutageAccumulator::new(w, 0.1);
        for k in 0..100u64 {
            // Error 1 m until step 25, a blip at 30, then low.
            let e = if k < 25 || k == 30 { 1.0 } else { 0.001 };
            a.push(k, &row(e, k as f64 * 0.1));
        }
        let m = a.finish();
        // Below from 31 on and for 10 steps: recovered at 31, 1.1 s after the end.
        let r = m.recovery_s.expect("recovered");
        assert!((r - 1.1).abs() < 1e-9, "recovery {r}");
        assert_eq!(m.peak_estimator_error, Some(1.0));
        assert_eq!(m.samples, 60);
        // v_c grows 0.1 per step of 0.1 s: v̇_c = 1.
        assert!((m.peak_vc_rate.unwrap() - 1.0).abs() < 1e-9, "{:?}", m.peak_vc_rate);
    }

    #[test]
    fn a_run_that_ends_before_the_error_settles_has_not_recovered() {
        let w = Window { from_k: 10, to_k: 20, until_k: 70 };
        let mut a = OutageAccumulator::new(w, 0.1);
        for k in 0..25u64 {
            a.push(k, &row(if k < 22 { 1.0 } else { 0.0 }, 0.0));
        }
        assert_eq!(a.finish().recovery_s, None);
        let empty = OutageAccumulator::new(w, 0.1).finish();
        assert_eq!((empty.peak_estimator_error, empty.samples), (None, 0));
    }
}
