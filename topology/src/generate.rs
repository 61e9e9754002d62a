//! Generated scenarios for scale studies: a ring of n followers plus random
//! chords, follower 1 hearing the leader, offsets on a grid behind the leader.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::error::ScenarioError;
use crate::file::{FollowerFile, ScenarioFile};
use crate::scenario::Scenario;

/// A ring of `n` followers with `chords` extra random edges (seeded), and the
/// paper's gains, robot and noise. Every follower starts on its formation
/// slot with a small body-frame error.
pub fn ring_with_chords(n: u32, chords: u32, seed: u64) -> Result<Scenario, ScenarioError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let side = (f64::from(n)).sqrt().ceil() as u32;
    let followers = (1..=n)
        .map(|id| {
            let (row, col) = ((id - 1) / side, (id - 1) % side);
            FollowerFile {
                id,
                offset: [-2.0 * f64::from(col + 1), 2.0 * f64::from(row) - f64::from(side)],
                pose: None,
                body_error: Some([rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), 0.0]),
                velocity: [0.0, 0.0],
                leader_link: id == 1,
            }
        })
        .collect();
    let mut edges: Vec<[u32; 2]> = if n > 1 { (1..=n).map(|i| [i, i % n + 1]).collect() } else { Vec::new() };
    if n == 2 {
        edges.truncate(1);
    }
    let mut seen: std::collections::HashSet<(u32, u32)> = edges.iter().map(|&[a, b]| (a.min(b), a.max(b))).collect();
    let target = edges.len() + chords as usize;
    let mut tries = 0;
    while n > 3 && edges.len() < target && tries < 20 * chords {
        tries += 1;
        let (a, b) = (rng.random_range(1..=n), rng.random_range(1..=n));
        if a != b && seen.insert((a.min(b), a.max(b))) {
            edges.push([a, b]);
        }
    }
    let file: ScenarioFile = toml::from_str("followers = []\nedges = []").map_err(|e| ScenarioError::Syntax {
        file: String::new(),
        line: None,
        message: e.to_string(),
    })?;
    Scenario::from_file(ScenarioFile { followers, edges, ..file }, &format!("ring{n}"))
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
}
