//! `formation replay RUN_DIR --explain`: the run beside its model, as a
//! table in the terminal.

use formation_replay::explain::{self, Explanation};
use formation_replay::replay::Loaded;

use crate::error::Error as CliError;

/// Explains `loaded`'s `metric` over windows of `window` seconds and prints
/// the `top` links and windows.
pub fn run(loaded: &Loaded, metric: &str, window: f64, top: usize) -> Result<(), CliError> {
    if !(window.is_finite() && window > 0.0) {
        return Err(CliError::Input(format!("--window must be a positive number of seconds, not {window}")));
    }
    let window_steps = ((window / loaded.scenario.dt_s).round() as u64).max(1);
    let bar: std::sync::Mutex<Option<crate::progress::Progress>> = Default::default();
    let e = explain::explain(loaded, metric, window_steps, &|done, total| {
        let mut b = bar.lock().unwrap_or_else(|p| p.into_inner());
        b.get_or_insert_with(|| crate::progress::Progress::new(total as u64, "replays", false)).set(done as u64);
    })?;
    if let Some(b) = bar.lock().unwrap_or_else(|p| p.into_inner()).as_ref() {
        b.finish();
    }
    print!("{}", table(loaded, &e, top));
    Ok(())
}

fn pct(x: f64) -> String {
    format!("{:.1} %", 100.0 * x)
}

fn num(x: Option<f64>) -> String {
    x.map_or("—".into(), |v| format!("{v:.4}"))
}

/// The explanation as text.
pub fn table(loaded: &Loaded, e: &Explanation, top: usize) -> String {
    let s = &loaded.scenario;
    let dt = s.dt_s;
    let mut t = format!(
        "{}: {} followers, {} timing, Δt = {} s, network.delay_steps = {}; metric {}\n",
        loaded.dir.display(),
        s.followers.len(),
        match s.timing {
            formation_topology::Timing::Lockstep => "lock-step",
            formation_topology::Timing::Realtime => "real-time",
        },
        dt,
        s.network.delay_steps,
        e.metric
    );
    t += "the model: every message used network.delay_steps after it was sent, the fault table applied (formation sim)\n\n";
    match &e.first {
        Some(d) => {
            t += &format!(
                "first departure: step {} (t = {:.3} s), link {}: the run used {}, the model {}\n",
                d.k,
                d.k as f64 * dt,
                d.link,
                d.run.describe(),
                d.model.describe()
            )
        }
        None => t += "the run heard exactly what the model assumes: no departure\n",
    }
    let steps: u64 = e.hearing.iter().map(|h| h.steps).sum();
    let (diff, older, newer, silent, extra) = e
        .hearing
        .iter()
        .fold((0, 0, 0, 0, 0), |a, h| (a.0 + h.differing, a.1 + h.older, a.2 + h.newer, a.3 + h.silent, a.4 + h.extra));
    if steps > 0 {
        t += &format!(
            "hearing: {diff} of {steps} link-steps differ from the model ({}): {older} used an older message, {newer} a \
             newer one, {silent} heard nothing where the model heard, {extra} heard where the model did not\n",
            pct(diff as f64 / steps as f64)
        );
    }
    for (st, sh) in &e.stalls {
        t += &format!("stall: {}", st.describe(dt));
        if e.departure != 0.0 {
            t += &format!("; it explains {} of the departure", pct(sh.share));
        }
        t += "\n";
    }
    t += &followers_table(e);
    if e.departure == 0.0 {
        return t;
    }
    t += &format!(
        "\nlinks, by what replaying the run with that link as modelled takes away of the departure ({:.4}):\n",
        e.departure
    );
    t += &format!("{:>5}  {:<14} {:>16} {:>12} {:>9}\n", "rank", "link", "steps differing", "explained", "share");
    for (rank, (l, sh)) in e.links.iter().take(top).enumerate() {
        let h = e.hearing.iter().find(|h| h.link == *l);
        let d = h.map_or(String::new(), |h| {
            format!("{} ({})", h.differing, pct(h.differing as f64 / h.steps.max(1) as f64))
        });
        t += &format!("{:>5}  {:<14} {:>16} {:>12.4} {:>9}\n", rank + 1, l.to_string(), d, sh.explained, pct(sh.share));
    }
    let listed = top.min(e.links.len());
    let shown: f64 = e.links.iter().take(listed).map(|(_, s)| s.share).sum();
    let all: f64 = e.links.iter().map(|(_, s)| s.share).sum();
    let heard = crate::words::count(e.links.len(), "link");
    t += &match listed {
        n if n == e.links.len() => {
            let they = if n == 1 { "it explains" } else { "one at a time they explain" };
            format!("{heard} heard differently; {they} {}\n", pct(all))
        }
        n => {
            let first = if n == 1 { "the first explains".to_string() } else { format!("the first {n} explain") };
            format!("{heard} heard differently; {first} {}, all of them one at a time {}\n", pct(shown), pct(all))
        }
    };
    t += &format!(
        "\nwindows of {:.3} s, by what replaying the run with that window as modelled takes away:\n",
        e.window_steps as f64 * dt
    );
    t += &format!("{:>5}  {:<20} {:>12} {:>9}\n", "rank", "t (s)", "explained", "share");
    for (rank, ((a, b), sh)) in e.windows.iter().take(top).enumerate() {
        let span = format!("{:.3}–{:.3}", *a as f64 * dt, *b as f64 * dt);
        t += &format!("{:>5}  {:<20} {:>12.4} {:>9}\n", rank + 1, span, sh.explained, pct(sh.share));
    }
    t
}

/// Each follower's metric in the run and in the model, their difference, and the sum over all.
fn followers_table(e: &Explanation) -> String {
    let mut t = String::new();
    t += &format!("\n{:>9} {:>12} {:>12} {:>12} {:>9}\n", "follower", "run", "model", "run−model", "");
    let (mut sr, mut sm) = (0.0, 0.0);
    for &(id, r, m) in &e.followers {
        let d = r.zip(m).map(|(r, m)| r - m);
        sr += r.unwrap_or(0.0);
        sm += m.unwrap_or(0.0);
        let rel = r
            .zip(m)
            .filter(|(_, m)| *m != 0.0)
            .map_or(String::new(), |(r, m)| format!("{:+.1} %", 100.0 * (r / m - 1.0)));
        t += &format!("{id:>9} {:>12} {:>12} {:>12} {rel:>9}\n", num(r), num(m), num(d));
    }
    let rel = if sm != 0.0 { format!("{:+.1} %", 100.0 * (sr / sm - 1.0)) } else { String::new() };
    t += &format!("{:>9} {:>12.4} {:>12.4} {:>12.4} {rel:>9}\n", "all", sr, sm, e.departure);
    t
}
