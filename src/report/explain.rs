//! The run beside its model, in a report: for every networked case with a
//! hearing record, `formation replay --explain`'s table and a figure of
//! what each link and each second explains of the departure.

use std::fmt::Write as _;
use std::path::Path;

use formation_replay::explain::{self, Explanation};

use super::case::Case;
use super::plots::{self, Figure, FigureSpec, Line, Panel};
use crate::error::CliError;

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
pub fn write(out: &Path, cases: &[&Case]) -> Result<String, CliError> {
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
