//! The paper's figures from run folders' CSVs, as SVG and PNG (plotters),
//! each with the CSV of what it plots:
//!
//! - Fig. 3: leader and follower paths, the formation drawn at a few instants;
//! - Fig. 4: formation error of each follower over time;
//! - Fig. 5: linear velocity command v_c, conventional against bioinspired backstepping;
//! - Fig. 6: wheel torques of conventional, second-order and bioinspired SMC.
//!
//! One colour per method (paper mode) or per run folder (otherwise), the
//! same in every figure. Text uses the DejaVu Sans font shipped in `assets/`.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs;
use std::path::Path;
use std::sync::Once;

use formation_record::read_columns;
use plotters::coord::ranged1d::ValueFormatter;
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};

use crate::case::{Case, Context, Role};
use formation_exit::Error;

/// DejaVu Sans (Bitstream Vera licence, `assets/DejaVuSans-LICENSE.txt`).
static FONT: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
const FAMILY: &str = "sans-serif";

fn register_fonts() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The bytes are a valid TrueType font shipped with the source.
        let _ = register_font(FAMILY, FontStyle::Normal, FONT);
        let _ = register_font(FAMILY, FontStyle::Bold, FONT);
    });
}

/// A colour per case: by method in paper mode, by position otherwise.
pub fn colours(cases: &[Case], paper: bool) -> Vec<RGBColor> {
    cases
        .iter()
        .enumerate()
        .map(|(i, c)| match (paper, c.role) {
            (true, Role::Proposed | Role::AsifFault) => PURPLE,
            (true, Role::ConventionalBackstepping) => BLUE_M,
            (true, Role::ConventionalSmc) => RED_M,
            (true, Role::SuperTwisting) => AMBER,
            (true, Role::KfNormal | Role::KfFault) => GREEN_M,
            (true, Role::ZeroInit) => CYAN_M,
            _ => PALETTE[i % PALETTE.len()],
        })
        .collect()
}

const PURPLE: RGBColor = RGBColor(128, 0, 128);
const BLUE_M: RGBColor = RGBColor(31, 100, 200);
const RED_M: RGBColor = RGBColor(214, 39, 40);
const AMBER: RGBColor = RGBColor(225, 150, 0);
const GREEN_M: RGBColor = RGBColor(44, 160, 44);
const CYAN_M: RGBColor = RGBColor(23, 170, 190);
const PALETTE: [RGBColor; 10] = [
    BLUE_M,
    RED_M,
    PURPLE,
    AMBER,
    GREEN_M,
    CYAN_M,
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(110, 110, 110),
    RGBColor(150, 150, 20),
];
/// Followers' colours in Fig. 3 and 4 (not methods: one per follower).
const FOLLOWER_COLOURS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];
const GREY: RGBColor = RGBColor(120, 120, 120);

/// Per-follower panels show at most this many followers.
const MAX_FOLLOWER_PANELS: usize = 8;
/// Series longer than this are reduced to a min/max envelope of half as many buckets.
const MAX_POINTS: usize = 4000;

/// A figure written to the report folder.
#[derive(Clone, Debug)]
pub struct Figure {
    /// File stem of its .svg, .png and .csv.
    pub file: String,
    pub title: String,
    pub caption: String,
}

/// The time series a figure needs from one run folder.
struct RunData {
    leader: [Vec<f64>; 3],
    /// By follower id: t, x, y, v_c, tau_l, tau_r, formation_error.
    followers: BTreeMap<u32, [Vec<f64>; 7]>,
}

impl RunData {
    fn load(case: &Case) -> Result<Self, Error> {
        let l = read_columns(&case.dir.join("leader.csv"), &["t", "x", "y"])?;
        let leader: [Vec<f64>; 3] = l.try_into().map_err(|_| Error::Run("leader.csv columns".into()))?;
        let mut followers = BTreeMap::new();
        for id in case.follower_ids() {
            let cols = read_columns(
                &case.dir.join(format!("follower_{id}.csv")),
                &["t", "x", "y", "v_c", "tau_l", "tau_r", "formation_error"],
            )?;
            let cols: [Vec<f64>; 7] = cols.try_into().map_err(|_| Error::Run("follower columns".into()))?;
            followers.insert(id, cols);
        }
        Ok(Self { leader, followers })
    }
}

/// One line of a panel.
pub(super) struct Line {
    pub(super) label: String,
    pub(super) colour: RGBColor,
    pub(super) width: u32,
    pub(super) points: Vec<(f64, f64)>,
    /// Show in the legend.
    pub(super) legend: bool,
    /// Per point, an interval (low, high) drawn as a bar with caps, and a
    /// marker on the point; empty: a plain line.
    pub(super) intervals: Vec<(f64, f64)>,
}

/// A closed outline with markers at its corners (Fig. 3's formation).
pub(super) struct Outline {
    pub(super) label: String,
    pub(super) points: Vec<(f64, f64)>,
    /// Marker colour of each corner.
    pub(super) colours: Vec<RGBColor>,
}

pub(super) struct Panel {
    pub(super) caption: String,
    pub(super) x_label: String,
    pub(super) y_label: String,
    pub(super) lines: Vec<Line>,
    pub(super) outlines: Vec<Outline>,
    pub(super) equal_aspect: bool,
    pub(super) legend: bool,
    /// Extra room above the data, as a fraction of its span (for the legend).
    pub(super) headroom: f64,
    /// Spans of x shaded grey behind the lines (fault windows).
    pub(super) shade: Vec<(f64, f64)>,
    /// Logarithmic y axis (values ≤ 0 drawn at its bottom).
    pub(super) log_y: bool,
}

pub(super) struct FigureSpec {
    pub(super) figure: Figure,
    pub(super) panels: Vec<Panel>,
    pub(super) cols: usize,
    pub(super) size: (u32, u32),
    /// CSV column names of x and y.
    pub(super) csv_xy: (&'static str, &'static str),
}

/// The cases a figure compares: paper mode picks the paper's cases by role,
/// otherwise every case with CSVs.
fn pick(cases: &[Case], ctx: &Context, roles: &[Role]) -> Vec<usize> {
    if ctx.paper {
        roles.iter().filter_map(|r| cases.iter().position(|c| c.role == *r && c.has_csv)).collect()
    } else {
        (0..cases.len()).filter(|&i| cases[i].has_csv).collect()
    }
}

/// Legend text of a case in a figure: the paper's wording in paper mode,
/// the folder's name otherwise.
fn legend(case: &Case, ctx: &Context, wording: fn(Role) -> Option<&'static str>) -> String {
    match (ctx.paper, wording(case.role)) {
        (true, Some(w)) => w.to_string(),
        _ => case.label.clone(),
    }
}

/// Draws every figure into `out`.
pub fn draw_all(out: &Path, cases: &[Case], ctx: &Context, colours: &[RGBColor]) -> Result<Vec<Figure>, Error> {
    register_fonts();
    let mut data: BTreeMap<usize, RunData> = BTreeMap::new();
    let mut load = |i: usize| -> Result<(), Error> {
        if let std::collections::btree_map::Entry::Vacant(e) = data.entry(i) {
            e.insert(RunData::load(&cases[i])?);
        }
        Ok(())
    };
    let paths_cases = pick(cases, ctx, &[Role::Proposed]);
    let fig5_cases = pick(cases, ctx, &[Role::ConventionalBackstepping, Role::Proposed]);
    let fig6_cases = pick(cases, ctx, &[Role::ConventionalSmc, Role::SuperTwisting, Role::Proposed]);
    for &i in paths_cases.iter().chain(&fig5_cases).chain(&fig6_cases) {
        load(i)?;
    }
    let mut specs = Vec::new();
    if !paths_cases.is_empty() {
        specs.push(fig3(cases, &paths_cases, &data, ctx));
        specs.push(fig4(cases, &paths_cases, &data, ctx));
    }
    if !fig5_cases.is_empty() {
        specs.push(fig5(cases, &fig5_cases, &data, ctx, colours));
    }
    if !fig6_cases.is_empty() {
        specs.push(fig6(cases, &fig6_cases, &data, ctx, colours));
    }
    let mut figures = Vec::new();
    for spec in specs {
        write_figure(out, &spec)?;
        figures.push(spec.figure);
    }
    Ok(figures)
}

/// Writes a figure's SVG, PNG and CSV.
pub(super) fn write_figure(out: &Path, spec: &FigureSpec) -> Result<(), Error> {
    let svg = out.join(format!("{}.svg", spec.figure.file));
    let png = out.join(format!("{}.png", spec.figure.file));
    {
        let root = SVGBackend::new(&svg, spec.size).into_drawing_area();
        render(&root, spec).map_err(|e| Error::Run(format!("{}: {e}", svg.display())))?;
    }
    {
        let root = BitMapBackend::new(&png, spec.size).into_drawing_area();
        render(&root, spec).map_err(|e| Error::Run(format!("{}: {e}", png.display())))?;
    }
    let csv = out.join(format!("{}.csv", spec.figure.file));
    fs::write(&csv, figure_csv(spec)).map_err(formation_record::at_path(&csv, "cannot write"))?;
    Ok(())
}

/// The CSV of what a figure plots: one row per point (with its interval
/// when the figure draws intervals).
fn figure_csv(spec: &FigureSpec) -> String {
    let (x, y) = spec.csv_xy;
    let bars = spec.panels.iter().any(|p| p.lines.iter().any(|l| !l.intervals.is_empty()));
    let mut s = format!("panel,series,{x},{y}{}\n", if bars { ",ci_low,ci_high" } else { "" });
    let q = |t: &str| if t.contains([',', '"']) { format!("\"{}\"", t.replace('"', "\"\"")) } else { t.to_string() };
    for p in &spec.panels {
        for l in &p.lines {
            for (i, (a, b)) in l.points.iter().enumerate() {
                let _ = write!(s, "{},{},{a:?},{b:?}", q(&p.caption), q(&l.label));
                match l.intervals.get(i) {
                    Some((lo, hi)) => s += &format!(",{lo:?},{hi:?}\n"),
                    None if bars => s += ",,\n",
                    None => s.push('\n'),
                }
            }
        }
        for o in &p.outlines {
            for (a, b) in &o.points {
                let _ = writeln!(s, "{},{},{a:?},{b:?}{}", q(&p.caption), q(&o.label), if bars { ",," } else { "" });
            }
        }
    }
    s
}

type DrawResult<DB> = Result<(), DrawingAreaErrorKind<<DB as DrawingBackend>::ErrorType>>;

fn render<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, spec: &FigureSpec) -> DrawResult<DB> {
    root.fill(&WHITE)?;
    let area = root.titled(&spec.figure.title, (FAMILY, 26).into_font())?;
    let rows = spec.panels.len().div_ceil(spec.cols);
    let cells = area.split_evenly((rows, spec.cols));
    for (panel, cell) in spec.panels.iter().zip(cells) {
        draw_panel(&cell, panel)?;
    }
    root.present()
}

/// Axis range of the points with 4 % padding (a unit range if empty or flat).
fn range(points: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) =
        points.filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = if hi > lo { 0.04 * (hi - lo) } else { 0.5_f64.max(lo.abs() * 0.1) };
    (lo - pad, hi + pad)
}

fn draw_panel<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, p: &Panel) -> DrawResult<DB> {
    let all = || p.lines.iter().flat_map(|l| l.points.iter()).chain(p.outlines.iter().flat_map(|o| o.points.iter()));
    let bars = || p.lines.iter().flat_map(|l| l.intervals.iter().flat_map(|&(lo, hi)| [lo, hi]));
    let (mut x0, mut x1) = range(all().map(|q| q.0));
    let (mut y0, mut y1) = if p.log_y {
        log_range(all().map(|q| q.1).chain(bars()))
    } else if p.lines.iter().any(|l| !l.intervals.is_empty()) {
        range(all().map(|q| q.1).chain(bars()))
    } else {
        range(all().map(|q| q.1))
    };
    if p.legend {
        if p.log_y {
            y1 *= (y1 / y0).powf(p.headroom);
        } else {
            y1 += p.headroom * (y1 - y0);
        }
    }
    let (label_x, label_y, caption_h, margin) = (50u32, 70u32, 30u32, 12u32);
    if p.equal_aspect {
        let (w, h) = area.dim_in_pixel();
        let pw = w.saturating_sub(label_y + 2 * margin).max(1) as f64;
        let ph = h.saturating_sub(label_x + caption_h + 2 * margin).max(1) as f64;
        let (sx, sy) = ((x1 - x0) / pw, (y1 - y0) / ph);
        if sx > sy {
            let c = 0.5 * (y0 + y1);
            let half = 0.5 * sx * ph;
            (y0, y1) = (c - half, c + half);
        } else {
            let c = 0.5 * (x0 + x1);
            let half = 0.5 * sy * pw;
            (x0, x1) = (c - half, c + half);
        }
    }
    let mut builder = ChartBuilder::on(area);
    builder
        .caption(&p.caption, (FAMILY, 20).into_font())
        .margin(margin)
        .x_label_area_size(label_x)
        .y_label_area_size(label_y);
    if p.log_y {
        let mut chart = builder.build_cartesian_2d(x0..x1, (y0..y1).log_scale())?;
        draw_contents(&mut chart, p, [x0, x1, y0, y1], Some(&|v: &f64| crate::tables::sig(*v, 1)))
    } else {
        let mut chart = builder.build_cartesian_2d(x0..x1, y0..y1)?;
        draw_contents(&mut chart, p, [x0, x1, y0, y1], None)
    }
}

/// Axis range of the positive values, padded by 10 % on a log scale
/// (at most 6 decades below the largest; a unit range if none).
fn log_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        return (0.1, 1.0);
    }
    let lo = lo.max(hi * 1e-6);
    if hi > lo {
        (lo / 1.1, hi * 1.1)
    } else {
        (lo / 2.0, hi * 2.0)
    }
}

/// A tick label formatter of the y axis.
type Ticks<'a> = Option<&'a dyn Fn(&f64) -> String>;

/// Mesh, shading, outlines, lines, interval bars and legend of a panel on a
/// chart whose y axis is linear or logarithmic; `r` = [x0, x1, y0, y1].
fn draw_contents<'a, DB, Y>(
    chart: &mut ChartContext<'a, DB, Cartesian2d<RangedCoordf64, Y>>,
    p: &Panel,
    r: [f64; 4],
    ticks: Ticks,
) -> DrawResult<DB>
where
    DB: DrawingBackend + 'a,
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    let [x0, x1, y0, y1] = r;
    let mut mesh = chart.configure_mesh();
    mesh.x_desc(p.x_label.as_str())
        .y_desc(p.y_label.as_str())
        .axis_desc_style((FAMILY, 17))
        .label_style((FAMILY, 14))
        .light_line_style(RGBColor(235, 235, 235))
        .bold_line_style(RGBColor(210, 210, 210));
    if let Some(f) = ticks {
        mesh.y_label_formatter(f);
    }
    mesh.draw()?;
    let shade = GREY.mix(0.2);
    let spans = p.shade.iter().map(|&(a, b)| (a.max(x0), b.min(x1))).filter(|(a, b)| a < b);
    let s = chart.draw_series(spans.map(|(a, b)| Rectangle::new([(a, y0), (b, y1)], shade.filled())))?;
    if p.legend && !p.shade.is_empty() {
        s.label("fault window").legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 24, y + 6)], shade.filled()));
    }
    for o in &p.outlines {
        let mut closed = o.points.clone();
        if let Some(&first) = o.points.first() {
            closed.push(first);
        }
        chart.draw_series(std::iter::once(PathElement::new(closed, GREY.stroke_width(1))))?;
        chart.draw_series(o.points.iter().zip(&o.colours).map(|(&q, &c)| Circle::new(q, 5, c.filled())))?;
    }
    let mut outline_legend = p.outlines.first().map(|o| o.label.clone());
    // On a log axis, values at or below 0 sit on its bottom edge.
    let floor = |y: f64| if p.log_y { y.max(y0) } else { y };
    let cap = 0.006 * (x1 - x0);
    for l in &p.lines {
        let colour = l.colour;
        let s = chart
            .draw_series(LineSeries::new(l.points.iter().map(|&(x, y)| (x, floor(y))), colour.stroke_width(l.width)))?;
        if p.legend && l.legend {
            s.label(l.label.as_str())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 24, y)], colour.stroke_width(3)));
        }
        if !l.intervals.is_empty() {
            chart.draw_series(l.points.iter().map(|&(x, y)| Circle::new((x, floor(y)), 4, colour.filled())))?;
            chart.draw_series(l.points.iter().zip(&l.intervals).flat_map(|(&(x, _), &(lo, hi))| {
                let (lo, hi) = (floor(lo), floor(hi));
                [
                    PathElement::new(vec![(x, lo), (x, hi)], colour.stroke_width(1)),
                    PathElement::new(vec![(x - cap, lo), (x + cap, lo)], colour.stroke_width(1)),
                    PathElement::new(vec![(x - cap, hi), (x + cap, hi)], colour.stroke_width(1)),
                ]
            }))?;
        }
    }
    if p.legend {
        if let Some(label) = outline_legend.take() {
            chart.draw_series(std::iter::empty::<Circle<(f64, f64), i32>>())?.label(label).legend(|(x, y)| {
                EmptyElement::at((x, y))
                    + PathElement::new(vec![(0, 0), (24, 0)], GREY.stroke_width(1))
                    + Circle::new((12, 0), 4, GREY.filled())
            });
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.5))
            .label_font((FAMILY, 15))
            .draw()?;
    }
    Ok(())
}

/// At most [`MAX_POINTS`] points: a min/max envelope per bucket of time,
/// which keeps chattering visible as a band.
pub(super) fn envelope(t: &[f64], y: &[f64]) -> Vec<(f64, f64)> {
    let n = t.len().min(y.len());
    if n <= MAX_POINTS {
        return t.iter().copied().zip(y.iter().copied()).take(n).collect();
    }
    let buckets = MAX_POINTS / 2;
    let mut out = Vec::with_capacity(MAX_POINTS);
    for b in 0..buckets {
        let (s, e) = (b * n / buckets, ((b + 1) * n / buckets).min(n));
        if s >= e {
            continue;
        }
        let (mut lo, mut hi) = (s, s);
        for i in s..e {
            if y[i] < y[lo] {
                lo = i;
            }
            if y[i] > y[hi] {
                hi = i;
            }
        }
        let (a, c) = if lo <= hi { (lo, hi) } else { (hi, lo) };
        out.push((t[a], y[a]));
        if c != a {
            out.push((t[c], y[c]));
        }
    }
    out
}

/// Every k-th point, at most [`MAX_POINTS`] (paths, which do not chatter).
fn stride(x: &[f64], y: &[f64]) -> Vec<(f64, f64)> {
    let n = x.len().min(y.len());
    let k = n.div_ceil(MAX_POINTS).max(1);
    let mut v: Vec<(f64, f64)> = (0..n).step_by(k).map(|i| (x[i], y[i])).collect();
    if n > 0 && (n - 1) % k != 0 {
        v.push((x[n - 1], y[n - 1]));
    }
    v
}

/// The sample nearest to time t.
fn nearest(ts: &[f64], t: f64) -> Option<usize> {
    (0..ts.len()).min_by(|&a, &b| (ts[a] - t).abs().total_cmp(&(ts[b] - t).abs()))
}

/// A written figure's section of report.md: title, image, caption, files.
pub(super) fn figure_markdown(f: &Figure) -> String {
    format!(
        "### {0}\n\n![{0}]({1}.png)\n\n{2}\n\nFiles: [{1}.svg]({1}.svg), [{1}.png]({1}.png), data [{1}.csv]({1}.csv).\n\n",
        f.title, f.file, f.caption
    )
}

pub(super) fn follower_colour(i: usize) -> RGBColor {
    FOLLOWER_COLOURS[i % FOLLOWER_COLOURS.len()]
}

fn fig3(cases: &[Case], idx: &[usize], data: &BTreeMap<usize, RunData>, ctx: &Context) -> FigureSpec {
    let mut panels = Vec::new();
    let mut instants_text = String::new();
    for &i in idx {
        let (case, d) = (&cases[i], &data[&i]);
        let mut lines = vec![Line {
            label: "Leader".into(),
            colour: BLACK,
            width: 2,
            points: stride(&d.leader[1], &d.leader[2]),
            legend: true,
            intervals: vec![],
        }];
        for (k, (id, f)) in d.followers.iter().enumerate() {
            lines.push(Line {
                label: format!("Follower {id}"),
                colour: follower_colour(k),
                width: 2,
                points: stride(&f[1], &f[2]),
                legend: true,
                intervals: vec![],
            });
        }
        let duration = case.summary().duration;
        let instants: Vec<f64> = (0..4).map(|j| duration * j as f64 / 3.0).collect();
        instants_text = instants.iter().map(|t| format!("{t:.0}")).collect::<Vec<_>>().join(", ");
        let mut outlines = Vec::new();
        for &t in &instants {
            let Some(li) = nearest(&d.leader[0], t) else { continue };
            let leader = (d.leader[1][li], d.leader[2][li], BLACK);
            // Spokes from the leader to each follower (leader, F1, leader, F2, …):
            // the formation's offsets, drawn the same way at every instant.
            let mut pts = vec![leader];
            for (k, f) in d.followers.values().enumerate() {
                if let Some(fi) = nearest(&f[0], t) {
                    pts.push((f[1][fi], f[2][fi], follower_colour(k)));
                    pts.push(leader);
                }
            }
            outlines.push(Outline {
                label: format!("Formation at t = {instants_text} s"),
                points: pts.iter().map(|p| (p.0, p.1)).collect(),
                colours: pts.iter().map(|p| p.2).collect(),
            });
        }
        panels.push(Panel {
            caption: if ctx.paper {
                "Bioinspired backstepping & bioinspired SMC & ASIF".into()
            } else {
                case.label.clone()
            },
            x_label: "x (m)".into(),
            y_label: "y (m)".into(),
            lines,
            outlines,
            equal_aspect: true,
            legend: true,
            headroom: 0.3,
            shade: vec![],
            log_y: false,
        });
    }
    let rows = panels.len().max(1) as u32;
    FigureSpec {
        figure: Figure {
            file: "fig3_paths".into(),
            title: "Fig. 3  Position of mobile robots tracking a continuous path".into(),
            caption: format!(
                "Paths of the leader (black) and the followers; grey spokes join the leader to each follower at \
                 t = {instants_text} s, dots mark their positions then."
            ),
        },
        panels,
        cols: 1,
        size: (1400, 640 * rows),
        csv_xy: ("x_m", "y_m"),
    }
}

fn fig4(cases: &[Case], idx: &[usize], data: &BTreeMap<usize, RunData>, ctx: &Context) -> FigureSpec {
    let panels: Vec<Panel> = idx
        .iter()
        .map(|&i| {
            let (case, d) = (&cases[i], &data[&i]);
            let lines = d
                .followers
                .iter()
                .enumerate()
                .map(|(k, (id, f))| Line {
                    label: format!("Follower {id}"),
                    colour: follower_colour(k),
                    width: 2,
                    points: envelope(&f[0], &f[6]),
                    legend: true,
                    intervals: vec![],
                })
                .collect();
            Panel {
                caption: if ctx.paper {
                    "Bioinspired backstepping & bioinspired SMC & ASIF".into()
                } else {
                    case.label.clone()
                },
                x_label: "t (s)".into(),
                y_label: "formation error (m)".into(),
                lines,
                outlines: vec![],
                equal_aspect: false,
                legend: true,
                headroom: 0.1,
                shade: vec![],
                log_y: false,
            }
        })
        .collect();
    let cols = if panels.len() > 1 { 2 } else { 1 };
    let rows = panels.len().div_ceil(cols).max(1) as u32;
    FigureSpec {
        figure: Figure {
            file: "fig4_formation_error".into(),
            title: "Fig. 4  Formation tracking errors of each follower for tracking a continuous path".into(),
            caption: "Formation error ‖(x_i − x_r − Δx_i, y_i − y_r − Δy_i)‖ of each follower against the true leader \
                      (docs/model.md §11)."
                .into(),
        },
        panels,
        cols,
        size: (if cols == 1 { 1200 } else { 1600 }, 560 * rows),
        csv_xy: ("t_s", "formation_error_m"),
    }
}

fn fig5_wording(r: Role) -> Option<&'static str> {
    match r {
        Role::ConventionalBackstepping => Some("Conventional backstepping & bioinspired SMC & ASIF"),
        Role::Proposed => Some("Bioinspired backstepping & bioinspired SMC & ASIF"),
        _ => None,
    }
}

fn fig6_wording(r: Role) -> Option<&'static str> {
    match r {
        Role::ConventionalSmc => Some("Conventional sliding mode control"),
        Role::SuperTwisting => Some("Second order sliding mode control (super-twisting)"),
        Role::Proposed => Some("Bioinspired sliding mode control"),
        _ => None,
    }
}

/// Follower ids present in the cases, at most [`MAX_FOLLOWER_PANELS`].
fn panel_ids(idx: &[usize], data: &BTreeMap<usize, RunData>) -> (Vec<u32>, bool) {
    let mut ids: Vec<u32> = idx.iter().flat_map(|i| data[i].followers.keys().copied()).collect();
    ids.sort_unstable();
    ids.dedup();
    let cut = ids.len() > MAX_FOLLOWER_PANELS;
    ids.truncate(MAX_FOLLOWER_PANELS);
    (ids, cut)
}

/// The cases drawn in one time-series figure, with their colours.
struct Methods<'a> {
    cases: &'a [Case],
    idx: &'a [usize],
    data: &'a BTreeMap<usize, RunData>,
    ctx: &'a Context,
    colours: &'a [RGBColor],
}

/// One line per case for follower `id`: column `col` of its time series
/// against t, min/max-enveloped, labelled in the figure's wording.
fn method_lines(
    m: &Methods,
    id: u32,
    col: usize,
    wording: fn(Role) -> Option<&'static str>,
    width: impl Fn(usize) -> u32,
) -> Vec<Line> {
    m.idx
        .iter()
        .filter_map(|&i| {
            let f = m.data[&i].followers.get(&id)?;
            Some(Line {
                label: legend(&m.cases[i], m.ctx, wording),
                colour: m.colours[i],
                width: width(i),
                points: envelope(&f[0], &f[col]),
                legend: true,
                intervals: vec![],
            })
        })
        .collect()
}

fn fig5(
    cases: &[Case],
    idx: &[usize],
    data: &BTreeMap<usize, RunData>,
    ctx: &Context,
    colours: &[RGBColor],
) -> FigureSpec {
    let (ids, cut) = panel_ids(idx, data);
    let panels: Vec<Panel> = ids
        .iter()
        .enumerate()
        .map(|(n, id)| Panel {
            caption: format!("Follower {id}"),
            x_label: "t (s)".into(),
            y_label: "linear velocity command v_c (m/s)".into(),
            lines: method_lines(&Methods { cases, idx, data, ctx, colours }, *id, 3, fig5_wording, |_| 2),
            outlines: vec![],
            equal_aspect: false,
            legend: n == 0,
            headroom: 0.3,
            shade: vec![],
            log_y: false,
        })
        .collect();
    let rows = panels.len().div_ceil(2).max(1) as u32;
    FigureSpec {
        figure: Figure {
            file: "fig5_velocity_command".into(),
            title: "Fig. 5  Linear velocity commands of different methods".into(),
            caption: format!(
                "Linear velocity command v_c of each follower. The conventional backstepping command jumps at t = 0 to \
                 C₁·x̂(0); the bioinspired one stays bounded by the shunting model.{}",
                if cut { " Only the first 8 followers are shown." } else { "" }
            ),
        },
        panels,
        cols: 2,
        size: (1600, 480 * rows),
        csv_xy: ("t_s", "v_c_mps"),
    }
}

fn fig6(
    cases: &[Case],
    idx: &[usize],
    data: &BTreeMap<usize, RunData>,
    ctx: &Context,
    colours: &[RGBColor],
) -> FigureSpec {
    let (ids, cut) = panel_ids(idx, data);
    let mut panels = Vec::new();
    for (n, id) in ids.iter().enumerate() {
        for (wheel, col, name) in [("left", 4usize, "τ_L"), ("right", 5usize, "τ_R")] {
            panels.push(Panel {
                caption: format!("Follower {id}, {wheel} wheel"),
                x_label: "t (s)".into(),
                y_label: format!("torque {name} (N m)"),
                // The last drawn (the proposed method in paper mode) on top, thicker.
                lines: method_lines(&Methods { cases, idx, data, ctx, colours }, *id, col, fig6_wording, |i| {
                    if Some(&i) == idx.last() {
                        2
                    } else {
                        1
                    }
                }),
                outlines: vec![],
                equal_aspect: false,
                legend: n == 0 && wheel == "left",
                headroom: 0.45,
                shade: vec![],
                log_y: false,
            });
        }
    }
    let rows = ids.len().max(1) as u32;
    FigureSpec {
        figure: Figure {
            file: "fig6_torque".into(),
            title: "Fig. 6  Torque control commands with different control methods".into(),
            caption: format!(
                "Wheel torques τ_L, τ_R of each follower, drawn in the order of the legend (the last on top).{}",
                if cut { " Only the first 8 followers are shown." } else { "" }
            ),
        },
        panels,
        cols: 2,
        size: (1600, 400 * rows),
        csv_xy: ("t_s", "torque_nm"),
    }
}
