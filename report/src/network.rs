//! What the network did, drawn under the error plots: for every follower of
//! a networked run, which of its sources it heard over time, and which of
//! its telemetry came late or was lost (from `network.json`'s timeline).

use std::path::Path;

use plotters::style::RGBColor;
use serde_json::Value;

use crate::case::Case;
use crate::plots::{self, Figure, FigureSpec, Line, Panel};
use formation_exit::Error;
use formation_record::at_path;

/// A follower's hearing: all sources, some, none (y offsets around its id).
const ALL: f64 = 0.3;
const SOME: f64 = 0.0;
const NONE: f64 = -0.3;
/// Telemetry marks, below the hearing line.
const TELEMETRY: f64 = -0.42;
const RECOVERED: RGBColor = RGBColor(230, 140, 0);
const LOST: RGBColor = RGBColor(200, 0, 0);

/// One follower's timeline: (t, event) in time order.
type Events = Vec<(f64, String)>;

/// One follower's record of the network: its timeline, and the spans (s)
/// of its telemetry that came late (`recovered`) or never (`gaps`).
struct NodeRecord {
    id: u32,
    events: Events,
    recovered: Vec<(f64, f64)>,
    lost: Vec<(f64, f64)>,
}

fn read_records(case: &Case) -> Result<Vec<NodeRecord>, Error> {
    let path = case.dir.join("network.json");
    let text = std::fs::read_to_string(&path).map_err(at_path(&path, "cannot read"))?;
    let json: Value = serde_json::from_str(&text).map_err(|e| crate::case::json_error(&path, &text, &e))?;
    let dt = case.summary().dt;
    let mut out = Vec::new();
    for id in case.follower_ids() {
        let node = &json["nodes"][id.to_string()];
        let mut events: Events = node["timeline"]
            .as_array()
            .map(|a| a.iter().filter_map(|e| Some((e["t"].as_f64()?, e["event"].as_str()?.to_string()))).collect())
            .unwrap_or_default();
        events.sort_by(|a, b| a.0.total_cmp(&b.0));
        out.push(NodeRecord { id, events, recovered: spans(&node["recovered"], dt), lost: spans(&node["gaps"], dt) });
    }
    Ok(out)
}

/// `[{from, to}, …]` in steps, as spans in s.
fn spans(v: &Value, dt: f64) -> Vec<(f64, f64)> {
    v.as_array()
        .map(|a| a.iter().filter_map(|g| Some((g["from"].as_f64()? * dt, g["to"].as_f64()? * dt))).collect())
        .unwrap_or_default()
}

/// The hearing line of one follower: a step function of how many of its
/// sources it hears (all, some, none), from its "hears …" / "… silent" /
/// router events.
fn hearing_line(events: &Events, end: f64) -> Vec<(f64, f64)> {
    let mut sources: Vec<String> = Vec::new();
    let mut heard: Vec<String> = Vec::new();
    let mut router = true;
    let mut points = vec![(0.0, NONE)];
    let level = |heard: &[String], sources: &[String], router: bool| {
        if !router || heard.is_empty() {
            NONE
        } else if heard.len() >= sources.len() {
            ALL
        } else {
            SOME
        }
    };
    for (t, e) in events {
        if let Some(s) = e.strip_prefix("hears ") {
            if !sources.iter().any(|x| x == s) {
                sources.push(s.to_string());
            }
            if !heard.iter().any(|x| x == s) {
                heard.push(s.to_string());
            }
        } else if let Some(s) = e.strip_suffix(" silent") {
            heard.retain(|x| x != s);
        } else if e == "router lost" {
            router = false;
        } else if e == "router back" {
            router = true;
        } else {
            continue;
        }
        let y = level(&heard, &sources, router);
        let last = points.last().map_or(NONE, |p| p.1);
        if y != last {
            points.push((*t, last));
            points.push((*t, y));
        }
    }
    let last = points.last().map_or(NONE, |p| p.1);
    points.push((end, last));
    points
}

fn timeline_figure(cases: &[&Case]) -> Result<Option<FigureSpec>, Error> {
    let mut panels = Vec::new();
    for (n, c) in cases.iter().enumerate() {
        let end = c.summary().duration;
        let shade: Vec<(f64, f64)> = c.summary().faults.iter().map(|f| (f.from, f.to)).collect();
        let mut lines = Vec::new();
        let mut first = [true, true];
        for (k, node) in read_records(c)?.into_iter().enumerate() {
            let y0 = f64::from(node.id);
            lines.push(Line {
                label: format!("Follower {}", node.id),
                colour: plots::follower_colour(k),
                width: 2,
                points: hearing_line(&node.events, end).into_iter().map(|(t, y)| (t, y0 + y)).collect(),
                legend: true,
                intervals: vec![],
            });
            for (m, (spans, colour, label)) in
                [(&node.recovered, RECOVERED, "telemetry recovered late"), (&node.lost, LOST, "telemetry lost")]
                    .into_iter()
                    .enumerate()
            {
                for &(a, b) in spans {
                    lines.push(Line {
                        label: label.into(),
                        colour,
                        width: 4,
                        points: vec![(a, y0 + TELEMETRY), (b.max(a + end / 500.0), y0 + TELEMETRY)],
                        legend: std::mem::take(&mut first[m]),
                        intervals: vec![],
                    });
                }
            }
        }
        panels.push(Panel {
            caption: format!("{}: network timeline", c.label),
            x_label: "t (s)".into(),
            y_label: "follower: hears all / some / none of its sources".into(),
            lines,
            outlines: vec![],
            equal_aspect: false,
            legend: n == 0,
            headroom: 0.15,
            shade,
            log_y: false,
        });
    }
    if panels.is_empty() {
        return Ok(None);
    }
    let rows = panels.len() as u32;
    Ok(Some(FigureSpec {
        figure: Figure {
            file: "fig_network_timeline".into(),
            title: "What the network did: sources heard and telemetry recovered".into(),
            caption: "For every follower of a networked run (from network.json's timeline): its line sits high while \
                      it hears all of its sources, in the middle while some are silent (nothing newer than \
                      network.silence_timeout), low while it hears none or has lost its router. Orange under a line: \
                      telemetry that came late (sent again after an outage or a loss) and was put back in order; \
                      red: telemetry lost for good. Grey: the fault table's windows."
                .into(),
        },
        panels,
        cols: 1,
        size: (1600, 380 * rows),
        csv_xy: ("t_s", "level"),
    }))
}

/// The network section of a report: the timeline of every networked case.
pub fn write(out: &Path, cases: &[&Case]) -> Result<String, Error> {
    let Some(spec) = timeline_figure(cases)? else { return Ok(String::new()) };
    plots::write_figure(out, &spec)?;
    let f = &spec.figure;
    let mut md = String::from("## Network (networked runs)\n\n");
    md += &plots::figure_markdown(f);
    Ok(md)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ev(list: &[(f64, &str)]) -> Events {
        list.iter().map(|(t, e)| (*t, e.to_string())).collect()
    }

    #[test]
    fn the_hearing_line_steps_with_silence_and_the_router() {
        let e = ev(&[
            (0.0, "hears the leader"),
            (0.0, "hears follower 2"),
            (8.0, "follower 2 silent"),
            (9.0, "router lost"),
            (11.0, "router back"),
            (11.1, "hears follower 2"),
        ]);
        let line = hearing_line(&e, 20.0);
        let at = |t: f64| line.iter().rev().find(|p| p.0 <= t).map(|p| p.1);
        assert_eq!(at(5.0), Some(ALL), "{line:?}");
        assert_eq!(at(8.5), Some(SOME), "{line:?}");
        assert_eq!(at(10.0), Some(NONE), "{line:?}");
        assert_eq!(at(11.05), Some(SOME), "router back, follower 2 still silent: {line:?}");
        assert_eq!(at(15.0), Some(ALL), "{line:?}");
        assert_eq!(line.last(), Some(&(20.0, ALL)));
    }

    #[test]
    fn spans_are_read_in_seconds() {
        let v = serde_json::json!([{"from": 8000, "to": 11250, "why": "restarted"}, {"from": 12000}]);
        assert_eq!(spans(&v, 1e-3), vec![(8.0, 11.25)], "a span without its end is left out");
        assert_eq!(spans(&Value::Null, 1e-3), vec![]);
    }
}
