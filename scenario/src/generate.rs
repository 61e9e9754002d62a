//! Generated scenarios of any size (`formation generate`, and the scale
//! benchmarks): followers on formation slots behind the leader, a graph of
//! a named kind, the leader heard by the followers nearest to it, and the
//! paper's gains, robot and noise. The result is a commented TOML file that
//! loads like any other scenario; the same spec and seed give the same file.

use std::fmt::Write as _;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::error::ScenarioError;
use crate::scenario::Scenario;

/// The kinds of communication graph `formation generate` makes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GraphKind {
    /// A cycle 1–2–…–N–1, plus `chords` random extra edges.
    Ring,
    /// Followers on a square grid of slots, each linked to its 4 grid neighbours.
    Grid,
    /// Followers at random slots; every pair closer than `radius` is linked.
    RandomGeometric,
    /// Every pair linked (N(N−1)/2 edges).
    Complete,
    /// A path 1–2–…–N: the slowest graph to converge.
    Line,
}

impl GraphKind {
    pub const ALL: [GraphKind; 5] =
        [GraphKind::Ring, GraphKind::Grid, GraphKind::RandomGeometric, GraphKind::Complete, GraphKind::Line];

    /// The kind named `s` (as on the command line).
    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == s)
    }

    pub fn name(self) -> &'static str {
        match self {
            GraphKind::Ring => "ring",
            GraphKind::Grid => "grid",
            GraphKind::RandomGeometric => "random-geometric",
            GraphKind::Complete => "complete",
            GraphKind::Line => "line",
        }
    }
}

/// What to generate.
#[derive(Clone, Debug, PartialEq)]
pub struct Spec {
    pub followers: u32,
    pub graph: GraphKind,
    /// Extra random edges (ring only).
    pub chords: u32,
    /// How many followers hear the leader (the nearest to it).
    pub leader_links: u32,
    /// Link radius of the random geometric graph, m [default: 1.2 times the
    /// smallest radius that connects the slots, the longest edge of their
    /// Euclidean minimum spanning tree].
    pub radius: Option<f64>,
    pub seed: u64,
}

impl Spec {
    pub fn new(followers: u32, graph: GraphKind) -> Self {
        Self { followers, graph, chords: 0, leader_links: 1, radius: None, seed: 1 }
    }
}

/// Slot spacing, m.
const SPACING: f64 = 2.0;

/// The scenario file's text for `spec` (checked: it loads, and the graph
/// satisfies Lemma 1, or the error names the unreachable followers).
pub fn toml(spec: &Spec) -> Result<String, ScenarioError> {
    sized(spec, crate::scenario::MAX_FOLLOWERS).map(|(t, _)| t)
}

/// Most followers of a benchmark's ring ([`ring_with_chords`]): about 1 KB
/// of memory each in the simulator, and with n/5 chords 2.2 n edges, within
/// a scenario's 1,000,000.
pub const BENCH_MAX_FOLLOWERS: usize = 450_000;

/// [`toml`] with up to `most` followers, and the scenario it loads as.
fn sized(spec: &Spec, most: usize) -> Result<(String, Scenario), ScenarioError> {
    check(spec, most)?;
    let n = spec.followers;
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    let side = f64::from(n).sqrt().ceil() as u32;
    let offsets = slots(spec, side, &mut rng);
    let body_errors: Vec<[f64; 2]> =
        (0..n).map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)]).collect();
    let (edges, radius_used) = graph_edges(spec, side, &offsets, &mut rng)?;
    // The leader is heard by the followers whose slots are nearest to it.
    let mut by_distance: Vec<u32> = (0..n).collect();
    by_distance.sort_by(|&a, &b| {
        let d = |i: u32| offsets[i as usize][0].hypot(offsets[i as usize][1]);
        d(a).total_cmp(&d(b)).then(a.cmp(&b))
    });
    let hears: std::collections::BTreeSet<u32> = by_distance.iter().take(spec.leader_links as usize).copied().collect();

    let t = text(spec, &edges, radius_used, &offsets, &body_errors, &hears);
    let scenario = Scenario::from_toml_sized(&t, "generated scenario", "generated", most)?;
    let line = match scenario.graph.lambda_min_h() {
        Some(l) => format!("# λ_min(H) = {l:.6} (Lemma 1: positive, the leader reaches every follower)."),
        None => format!(
            "# λ_min(H) not computed for {n} followers (dense eigenvalues); Lemma 1 holds: the leader reaches every follower."
        ),
    };
    Ok((t.replace("#LAMBDA#", &line), scenario))
}

/// An error in the options of `formation generate`.
fn bad(message: String) -> ScenarioError {
    ScenarioError::Syntax { file: String::new(), line: None, message }
}

/// The spec's sizes and options fit together and stay within a scenario's
/// limits.
fn check(spec: &Spec, most: usize) -> Result<(), ScenarioError> {
    let n = spec.followers;
    if n == 0 {
        return Err(bad("--followers must be at least 1".into()));
    }
    if n as usize > most {
        return Err(bad(format!("--followers {n}: a scenario may have at most {most} followers")));
    }
    let edges = match spec.graph {
        GraphKind::Complete => u64::from(n) * u64::from(n - 1) / 2,
        _ => u64::from(n) * 2 + u64::from(spec.chords),
    };
    if edges > crate::scenario::MAX_EDGES as u64 {
        return Err(bad(format!(
            "{} followers in a {} graph{} make about {edges} edges; a scenario may have at most {}",
            n,
            spec.graph.name(),
            if spec.chords > 0 { format!(" with {} chords", spec.chords) } else { String::new() },
            crate::scenario::MAX_EDGES
        )));
    }
    if spec.leader_links == 0 || spec.leader_links > n {
        return Err(bad(format!("--leader-links must be between 1 and the {n} followers, not {}", spec.leader_links)));
    }
    if let Some(r) = spec.radius {
        if !(r.is_finite() && r > 0.0) {
            return Err(bad(format!("--radius must be a positive number of metres, not {r}")));
        }
    }
    if spec.radius.is_some() && spec.graph != GraphKind::RandomGeometric {
        return Err(bad(format!("--radius is for --graph random-geometric, not {}", spec.graph.name())));
    }
    if spec.chords > 0 && spec.graph != GraphKind::Ring {
        return Err(bad(format!("--chords is for --graph ring, not {}", spec.graph.name())));
    }
    Ok(())
}

/// The formation slots (offsets from the leader, m): a square block of
/// `side` columns behind the leader (x < 0), centred on its track; random
/// ones for the random geometric graph, in an area of the same size.
fn slots(spec: &Spec, side: u32, rng: &mut ChaCha8Rng) -> Vec<[f64; 2]> {
    (0..spec.followers)
        .map(|i| match spec.graph {
            GraphKind::RandomGeometric => {
                let extent = SPACING * f64::from(side);
                [-SPACING - rng.random_range(0.0..extent), rng.random_range(-extent / 2.0..extent / 2.0)]
            }
            _ => {
                let (row, col) = (i / side, i % side);
                [-SPACING * f64::from(col + 1), SPACING * (f64::from(row) - f64::from(side - 1) / 2.0)]
            }
        })
        .collect()
}

/// The graph's edges between follower ids, and the link radius used (the
/// random geometric graph only).
fn graph_edges(
    spec: &Spec,
    side: u32,
    offsets: &[[f64; 2]],
    rng: &mut ChaCha8Rng,
) -> Result<(Vec<(u32, u32)>, Option<f64>), ScenarioError> {
    let n = spec.followers;
    let mut edges: Vec<(u32, u32)> = Vec::new();
    let mut radius_used = None;
    match spec.graph {
        GraphKind::Ring => {
            edges.extend((1..n).map(|i| (i, i + 1)));
            if n > 2 {
                edges.push((1, n));
            }
            add_chords(&mut edges, n, spec.chords, rng)?;
        }
        GraphKind::Grid => {
            for i in 0..n {
                let (row, col) = (i / side, i % side);
                if col + 1 < side && i + 1 < n {
                    edges.push((i + 1, i + 2));
                }
                if row + 1 < n.div_ceil(side) && i + side < n {
                    edges.push((i + 1, i + side + 1));
                }
            }
        }
        GraphKind::RandomGeometric => {
            let radius = spec.radius.unwrap_or_else(|| 1.2 * connecting_radius(offsets));
            radius_used = Some(radius);
            for a in 0..n as usize {
                for b in a + 1..n as usize {
                    let d = (offsets[a][0] - offsets[b][0]).hypot(offsets[a][1] - offsets[b][1]);
                    if d < radius {
                        edges.push((a as u32 + 1, b as u32 + 1));
                    }
                }
            }
        }
        GraphKind::Complete => {
            for a in 1..=n {
                edges.extend((a + 1..=n).map(|b| (a, b)));
            }
        }
        GraphKind::Line => edges.extend((1..n).map(|i| (i, i + 1))),
    }
    Ok((edges, radius_used))
}

/// `chords` random extra edges on a ring of `n`, none repeated.
fn add_chords(edges: &mut Vec<(u32, u32)>, n: u32, chords: u32, rng: &mut ChaCha8Rng) -> Result<(), ScenarioError> {
    let max_edges = u64::from(n) * u64::from(n - 1) / 2;
    if edges.len() as u64 + u64::from(chords) > max_edges {
        return Err(bad(format!(
            "--chords {}: a ring of {n} has room for {} more edges",
            chords,
            max_edges - edges.len() as u64
        )));
    }
    let mut seen: std::collections::HashSet<(u32, u32)> = edges.iter().copied().collect();
    let target = edges.len() + chords as usize;
    while edges.len() < target {
        let (a, b) = (rng.random_range(1..=n), rng.random_range(1..=n));
        if a != b && seen.insert((a.min(b), a.max(b))) {
            edges.push((a.min(b), a.max(b)));
        }
    }
    Ok(())
}

/// The commented TOML file, with `#LAMBDA#` where λ_min(H)'s line goes once
/// the scenario has loaded.
fn text(
    spec: &Spec,
    edges: &[(u32, u32)],
    radius_used: Option<f64>,
    offsets: &[[f64; 2]],
    body_errors: &[[f64; 2]],
    hears: &std::collections::BTreeSet<u32>,
) -> String {
    let n = spec.followers;
    let mut t = String::new();
    let _ = writeln!(
        t,
        "# Generated by `formation generate`: {n} followers, {} graph ({} edges), seed {}.",
        spec.graph.name(),
        edges.len(),
        spec.seed
    );
    match radius_used {
        Some(r) => {
            let _ = writeln!(t, "# Followers sit on random formation slots behind the leader; those closer than");
            let _ = writeln!(t, "# {r:.3} m to each other are linked. Each starts within 1 m of its slot, and");
        }
        None => {
            let _ = writeln!(t, "# Followers sit on formation slots behind the leader, {SPACING} m apart. Each starts");
            let _ = writeln!(t, "# within 1 m of its slot, and");
        }
    }
    let _ = writeln!(t, "# {} of them (the nearest to the leader) hear the leader.", spec.leader_links);
    let _ = writeln!(t, "# Everything not written here (gains, robot, noise, leader) is the paper's; see");
    let _ = writeln!(t, "# scenarios/paper.toml for every key.");
    let _ = writeln!(t, "#LAMBDA#");
    let _ = writeln!(t, "name = \"{}{n}\"", spec.graph.name());
    let _ = writeln!(t, "seed = {}", spec.seed);
    let _ = writeln!(t);
    let _ = writeln!(t, "# Undirected follower edges, by id.");
    let _ = write!(t, "edges = [");
    for (j, (a, b)) in edges.iter().enumerate() {
        let _ = write!(t, "{}{}[{a}, {b}]", if j == 0 { "" } else { ", " }, if j % 8 == 0 { "\n  " } else { "" });
    }
    let _ = writeln!(t, "\n]");
    let _ = writeln!(t);
    for i in 0..n {
        let o = offsets[i as usize];
        let e = body_errors[i as usize];
        let _ = writeln!(t, "[[followers]]");
        let _ = writeln!(t, "id = {}", i + 1);
        let _ = writeln!(t, "offset = [{:?}, {:?}]", round(o[0]), round(o[1]));
        let _ = writeln!(t, "body_error = [{:?}, {:?}, 0.0]", round(e[0]), round(e[1]));
        if hears.contains(&i) {
            let _ = writeln!(t, "leader_link = true");
        }
        let _ = writeln!(t);
    }
    t
}

/// The smallest link radius that connects `points`: the longest edge of
/// their Euclidean minimum spanning tree (Prim, O(n²), no allocation per step).
fn connecting_radius(points: &[[f64; 2]]) -> f64 {
    let n = points.len();
    if n < 2 {
        return SPACING;
    }
    let dist = |a: usize, b: usize| (points[a][0] - points[b][0]).hypot(points[a][1] - points[b][1]);
    let mut in_tree = vec![false; n];
    let mut best: Vec<f64> = (0..n).map(|j| dist(0, j)).collect();
    in_tree[0] = true;
    let mut longest = 0.0f64;
    for _ in 1..n {
        let (next, d) = (0..n)
            .filter(|&j| !in_tree[j])
            .map(|j| (j, best[j]))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .expect("a point outside the tree");
        in_tree[next] = true;
        longest = longest.max(d);
        for j in 0..n {
            if !in_tree[j] {
                best[j] = best[j].min(dist(next, j));
            }
        }
    }
    longest
}

/// Three decimals: readable files, and values that print back the same.
fn round(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}

/// The scenario of `spec`, loaded.
pub fn scenario(spec: &Spec) -> Result<Scenario, ScenarioError> {
    sized(spec, crate::scenario::MAX_FOLLOWERS).map(|(_, s)| s)
}

/// A ring of `n` followers with `chords` extra random edges (seeded): the
/// benchmarks' scenario.
/// Up to [`BENCH_MAX_FOLLOWERS`] followers: a file may hold
/// [`crate::scenario::MAX_FOLLOWERS`].
pub fn ring_with_chords(n: u32, chords: u32, seed: u64) -> Result<Scenario, ScenarioError> {
    sized(&Spec { chords, seed, ..Spec::new(n, GraphKind::Ring) }, BENCH_MAX_FOLLOWERS).map(|(_, s)| s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_ring_is_valid_and_has_its_chords() {
        let s = ring_with_chords(100, 20, 7).expect("valid");
        assert_eq!(s.followers.len(), 100);
        assert_eq!(s.graph.edge_count(), 120);
        assert!(s.graph.lambda_min_h().unwrap() > 0.0);
    }

    #[test]
    fn every_kind_loads_with_its_edge_count() {
        for (kind, n, edges) in [
            (GraphKind::Line, 7, 6),
            (GraphKind::Complete, 6, 15),
            (GraphKind::Grid, 9, 12),
            (GraphKind::Grid, 10, 13),
            (GraphKind::Ring, 5, 5),
            (GraphKind::Ring, 1, 0),
        ] {
            let s = scenario(&Spec::new(n, kind)).unwrap_or_else(|e| panic!("{kind:?} {n}: {e}"));
            assert_eq!(s.graph.edge_count(), edges, "{kind:?} of {n}");
            assert_eq!((0..s.graph.len()).filter(|&i| s.graph.hears_leader(i)).count(), 1);
        }
    }

    #[test]
    fn same_seed_same_file_and_another_seed_another() {
        let spec = Spec { seed: 3, ..Spec::new(30, GraphKind::RandomGeometric) };
        assert_eq!(toml(&spec).unwrap(), toml(&spec).unwrap());
        let other = Spec { seed: 4, ..spec.clone() };
        assert_ne!(toml(&spec).unwrap(), toml(&other).unwrap());
    }

    #[test]
    fn a_disconnected_graph_names_the_unreachable_followers() {
        // Radius below the spacing: no edges at all; only the nearest hears the leader.
        let spec = Spec { radius: Some(0.01), ..Spec::new(5, GraphKind::RandomGeometric) };
        let e = toml(&spec).unwrap_err().to_string();
        assert!(e.contains("followers 2, 3, 4, 5") || e.contains("are not connected"), "{e}");
        let bad = Spec { chords: 3, ..Spec::new(5, GraphKind::Line) };
        assert!(toml(&bad).unwrap_err().to_string().contains("--chords"));
    }
}
