//! The shapes of `[[formation.shapes]]` (docs/model.md §17) and each shape
//! change's assignment of robots to slots at the least total squared
//! distance (eq. 17.4, Kuhn–Munkres); `validate.rs` reads the schedule.
//!
//! The assignment is made from the slots the robots hold before the change
//! (where a converged formation has them), not from their measured poses:
//! every node computes it from the scenario alone, the same on every host,
//! so no message is needed and lock-step equals the simulator.
//!
//! # Examples
//!
//! A wedge of four becoming a column: each robot is given the column slot
//! that makes the total squared distance least.
//!
//! ```
//! use formation_scenario::shape::{assign, named, total_cost};
//!
//! let wedge = named("wedge", 4, 0.5).unwrap();
//! let column = named("column", 4, 0.5).unwrap();
//! let to = assign(&wedge, &column);
//! let cost = total_cost(&wedge, &column, &to);
//! assert!(cost < total_cost(&wedge, &column, &[3, 2, 1, 0]), "{to:?} costs {cost} m²");
//! ```

use pathfinding::kuhn_munkres::kuhn_munkres_min;
use pathfinding::matrix::Matrix;

/// The shapes `[[formation.shapes]] shape` may name.
pub const SHAPES: [&str; 5] = ["line", "column", "wedge", "diamond", "circle"];

/// The most followers a shape change assigns (the assignment is O(n³)).
pub const MAX_ASSIGNED: usize = 1000;

/// A named shape's n slots, `spacing` apart at least, behind the leader in
/// its frame (x ahead, y to the left; docs/model.md §17): `column` a file
/// behind it, `line` abreast one spacing behind, `wedge` a V opening
/// backwards at ±30°, `diamond` and `circle` n points around a centre behind
/// it. None for an unknown name.
pub fn named(shape: &str, n: usize, spacing: f64) -> Option<Vec<[f64; 2]>> {
    use std::f64::consts::{FRAC_PI_6, PI};
    let s = spacing;
    let slots = match shape {
        "column" => (0..n).map(|j| [-s * (j + 1) as f64, 0.0]).collect(),
        "line" => (0..n).map(|j| [-s, s * ((n as f64 - 1.0) / 2.0 - j as f64)]).collect(),
        "wedge" => (0..n)
            .map(|j| {
                let (rank, side) = ((j / 2 + 1) as f64, if j % 2 == 0 { 1.0 } else { -1.0 });
                [-s * rank * FRAC_PI_6.cos(), side * s * rank * FRAC_PI_6.sin()]
            })
            .collect(),
        // Points √2 s apart along the edges of |x − c| + |y| = R: neighbours
        // on one edge are √2 s apart, across a corner at least s.
        "diamond" => {
            let r = n as f64 * s / 4.0;
            let c = -(r + s);
            (0..n)
                .map(|j| {
                    let along = 4.0 * (j as f64) / n as f64; // in edges, from the front vertex
                    let (edge, f) = (along.floor(), along.fract());
                    let corners = [[c + r, 0.0], [c, r], [c - r, 0.0], [c, -r], [c + r, 0.0]];
                    let (a, b) = (corners[edge as usize], corners[edge as usize + 1]);
                    [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])]
                })
                .collect()
        }
        "circle" => {
            let r = if n > 1 { s / (2.0 * (PI / n as f64).sin()) } else { 0.0 };
            let c = -(r + s);
            (0..n)
                .map(|j| {
                    let phi = 2.0 * PI * j as f64 / n as f64;
                    [c + r * phi.cos(), r * phi.sin()]
                })
                .collect()
        }
        _ => return None,
    };
    Some(slots)
}

fn squared(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

/// eq. 17.4: the slot `to[result[i]]` for the robot now at `from[i]` that makes
/// Σ_i |from_i − to_σ(i)|² least (Kuhn–Munkres on the squared distances,
/// scaled to integers at a resolution of 1e−12 of the largest).
pub fn assign(from: &[[f64; 2]], to: &[[f64; 2]]) -> Vec<usize> {
    let n = from.len().min(to.len());
    if n == 0 {
        return Vec::new();
    }
    let largest = from.iter().flat_map(|&a| to.iter().map(move |&b| squared(a, b))).fold(0.0f64, f64::max);
    let scale = if largest > 0.0 { 1e12 / largest } else { 1.0 };
    let weights = Matrix::from_fn(n, n, |(i, j)| (squared(from[i], to[j]) * scale).round() as i64);
    kuhn_munkres_min(&weights).1
}

/// The first point of `points` outside `arena` ([x0, x1, y0, y1],
/// `safety.arena`) or not finite: a route that the leader may not drive.
pub fn first_outside(points: &[[f64; 2]], [x0, x1, y0, y1]: [f64; 4]) -> Option<usize> {
    let inside =
        |p: &[f64; 2]| p.iter().all(|v| v.is_finite()) && (x0..=x1).contains(&p[0]) && (y0..=y1).contains(&p[1]);
    points.iter().position(|p| !inside(p))
}

/// The two slots closest to each other (their indices from 1) and their distance.
pub fn closest(slots: &[[f64; 2]]) -> Option<(usize, usize, f64)> {
    let pairs = (0..slots.len()).flat_map(|a| (a + 1..slots.len()).map(move |b| (a, b)));
    pairs.map(|(a, b)| (a + 1, b + 1, squared(slots[a], slots[b]).sqrt())).min_by(|x, y| x.2.total_cmp(&y.2))
}

/// Σ_i |from_i − to_σ(i)|², m².
pub fn total_cost(from: &[[f64; 2]], to: &[[f64; 2]], assignment: &[usize]) -> f64 {
    from.iter().zip(assignment).map(|(&a, &j)| squared(a, to[j])).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// The least total cost over every permutation (n ≤ 8).
    fn brute_force(from: &[[f64; 2]], to: &[[f64; 2]]) -> f64 {
        fn permute(p: &mut Vec<usize>, k: usize, best: &mut f64, cost: &dyn Fn(&[usize]) -> f64) {
            if k == p.len() {
                *best = best.min(cost(p));
                return;
            }
            for i in k..p.len() {
                p.swap(k, i);
                permute(p, k + 1, best, cost);
                p.swap(k, i);
            }
        }
        let mut best = f64::INFINITY;
        permute(&mut (0..from.len()).collect(), 0, &mut best, &|p| total_cost(from, to, p));
        best
    }

    #[test]
    fn the_assignment_costs_what_the_best_permutation_costs() {
        let mut rng = StdRng::seed_from_u64(17);
        for trial in 0..300 {
            let n = 1 + trial % 7;
            let mut points =
                || (0..n).map(|_| [rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0)]).collect::<Vec<_>>();
            let (from, to) = (points(), points());
            let a = assign(&from, &to);
            let mut seen = a.clone();
            seen.sort_unstable();
            assert_eq!(seen, (0..n).collect::<Vec<_>>(), "trial {trial}: {a:?} is not a permutation");
            let (got, best) = (total_cost(&from, &to, &a), brute_force(&from, &to));
            assert!(got <= best * (1.0 + 1e-9) + 1e-12, "trial {trial}, n = {n}: {got} m² against the best {best} m²");
        }
    }

    #[test]
    fn robots_that_must_cross_are_given_the_slots_that_cost_least() {
        // A line abreast becoming a column: the left and right robots both
        // move to the centre line, one ahead of the other.
        let line = named("line", 3, 1.0).unwrap();
        let column = named("column", 3, 1.0).unwrap();
        let a = assign(&line, &column);
        assert_eq!(total_cost(&line, &column, &a), brute_force(&line, &column), "{a:?}");
    }

    #[test]
    fn every_named_shape_keeps_its_slots_a_spacing_apart() {
        for shape in SHAPES {
            for n in 1..=16 {
                let slots = named(shape, n, 0.7).unwrap();
                assert_eq!(slots.len(), n, "{shape} of {n}");
                assert!(slots.iter().all(|s| s[0] < 0.0), "{shape} of {n}: a slot ahead of the leader: {slots:?}");
                if let Some((a, b, gap)) = closest(&slots) {
                    assert!(gap >= 0.7 - 1e-9, "{shape} of {n}: slots {a} and {b} are {gap} m apart, spacing 0.7 m");
                }
            }
        }
        assert_eq!(named("star", 3, 1.0), None);
    }

    #[test]
    fn the_assignment_of_nothing_is_empty() {
        assert!(assign(&[], &[]).is_empty());
        assert_eq!(assign(&[[1.0, 1.0]], &[[1.0, 1.0]]), vec![0]);
    }

    #[test]
    fn a_point_outside_the_arena_or_not_finite_is_found() {
        let arena = [-1.0, 1.0, -2.0, 2.0];
        assert_eq!(first_outside(&[[0.0, 0.0], [1.0, -2.0]], arena), None, "the edges are inside");
        assert_eq!(first_outside(&[[0.0, 0.0], [1.5, 0.0]], arena), Some(1));
        let everywhere = [f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY];
        assert_eq!(first_outside(&[[f64::INFINITY, 0.0]], everywhere), Some(0), "not finite, even without an arena");
        assert_eq!(first_outside(&[[0.0, f64::NAN]], everywhere), Some(0));
    }
}
