//! The run beside its model: `formation replay RUN_DIR --explain`'s table
//! in the terminal ([`run`], [`table`]), and in a report, for every
//! networked case with a hearing record, that table and a figure of what
//! each link and each second explains of the departure ([`write`]).

use std::fmt::Write as _;
use std::path::Path;

use formation_replay::explain::{self, Explanation};
use formation_replay::replay::Loaded;

use crate::case::Case;
use crate::plots::{self, Figure, FigureSpec, Line, Panel};
use formation_exit::Error;

/// Explains `loaded`'s `metric` over windows of `window` seconds and prints
/// the `top` links and windows.
pub fn run(loaded: &Loaded, metric: &str, window: f64, top: usize) -> Result<(), Error> {
    if !(window.is_finite() && window > 0.0) {
        return Err(Error::Input(format!("--window must be a positive number of seconds, not {window}")));
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
            formation_scenario::Timing::Lockstep => "lock-step",
            formation_scenario::Timing::Realtime => "real-time",
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

/// Links drawn and listed per case.
const TOP: usize = 10;

fn figure(cases: &[(&Case, Explanation)]) -> Option<FigureSpec> {
    let mut panels = Vec::new();
    for (n, (c, e)) in cases.iter().enumerate() {
        if e.departure == 0.0 {
            continue;
        }
        let dt = c.summary().dt;
        let mut windows: Vec<(f64, f64, f64)> =
            e.windows.iter().map(|((a, b), s)| (*a as f64 * dt, *b as f64 * dt, 100.0 * s.share)).collect();
        windows.sort_by(|a, b| a.0.total_cmp(&b.0));
        // A step line: each window's share over its span.
        let w = e.window_steps as f64 * dt;
        let steps: Vec<(f64, f64)> = windows.iter().flat_map(|&(a, b, s)| [(a, s), (b, s)]).collect();
        panels.push(Panel {
            caption: format!("{}: what each {w:.1} s window explains", c.label),
            x_label: "t (s)".into(),
            y_label: format!("share of the {} departure (%)", e.metric),
            lines: vec![Line {
                label: "window replayed as modelled".into(),
                colour: plots::follower_colour(0),
                width: 2,
                points: steps,
                legend: n == 0,
                intervals: vec![],
            }],
            outlines: vec![],
            equal_aspect: false,
            legend: n == 0,
            headroom: 0.15,
            shade: c.summary().faults.iter().map(|f| (f.from, f.to)).collect(),
            log_y: false,
        });
        let top: Vec<(f64, f64)> =
            e.links.iter().take(TOP).enumerate().map(|(i, (_, s))| ((i + 1) as f64, 100.0 * s.share)).collect();
        panels.push(Panel {
            caption: format!(
                "{}: links by rank ({})",
                c.label,
                e.links.iter().take(5).map(|(l, _)| l.to_string()).collect::<Vec<_>>().join(", ")
            ),
            x_label: "rank of the link".into(),
            y_label: format!("share of the {} departure (%)", e.metric),
            lines: vec![Line {
                label: "link replayed as modelled".into(),
                colour: plots::follower_colour(1),
                width: 2,
                intervals: top.iter().map(|&(_, s)| (0.0, s)).collect(),
                points: top,
                legend: n == 0,
            }],
            outlines: vec![],
            equal_aspect: false,
            legend: n == 0,
            headroom: 0.15,
            shade: vec![],
            log_y: false,
        });
    }
    if panels.is_empty() {
        return None;
    }
    let rows = panels.len().div_ceil(2) as u32;
    Some(FigureSpec {
        figure: Figure {
            file: "fig_explain".into(),
            title: "Why the run differed from its model".into(),
            caption: "For every networked case whose hearing departed from the model's (formation replay --explain): \
                      left, the share of the departure (summed over followers) that replaying each window with the \
                      model's hearing takes away; right, the same for each link, most explaining first (the links are \
                      named in the panel's title). Shares need not add up to 100 %: links and windows interact."
                .into(),
        },
        panels,
        cols: 2,
        size: (1600, 420 * rows),
        csv_xy: ("x", "share_percent"),
    })
}

/// The section: per case, the explanation as text; the figure.
pub fn write(out: &Path, cases: &[&Case]) -> Result<String, Error> {
    let mut explained = Vec::new();
    let mut skipped = Vec::new();
    for c in cases {
        let loaded = match formation_replay::replay::load(&c.dir) {
            Ok(l) => l,
            Err(e) => {
                skipped.push(format!("- {}: not set beside its model: {e}", c.label));
                continue;
            }
        };
        let window = ((1.0 / loaded.scenario.dt_s).round() as u64).max(1);
        let e = explain::explain(&loaded, "torque_tv", window, &|_, _| {})?;
        explained.push((*c, loaded, e));
    }
    if explained.is_empty() && skipped.is_empty() {
        return Ok(String::new());
    }
    let mut md = String::from("## The run beside its model (networked runs)\n\n");
    for s in &skipped {
        let _ = writeln!(md, "{s}");
    }
    if !skipped.is_empty() {
        md.push('\n');
    }
    md += "`formation replay --explain` for every networked case with a hearing record: the model is the same \
           scenario with every message used `network.delay_steps` after it was sent and the fault table applied (what \
           `formation sim` computes); each link and each second is replayed with the model's hearing in turn, and \
           ranked by how much of the torque variation's departure that takes away. See docs/why-did-my-run-differ.md.\n\n";
    for (c, loaded, e) in &explained {
        let _ = writeln!(md, "### {}\n\n```text\n{}```\n", c.label, crate::explain::table(loaded, e, TOP));
    }
    let pairs: Vec<(&Case, Explanation)> = explained.into_iter().map(|(c, _, e)| (c, e)).collect();
    if let Some(spec) = figure(&pairs) {
        plots::write_figure(out, &spec)?;
        let f = &spec.figure;
        md += &plots::figure_markdown(f);
    }
    Ok(md)
}
