//! The communication graph (section II-A, docs/model.md §2).
//!
//! Followers are stored by index 0..n in ascending id. Adjacency is kept as
//! sorted neighbour lists (CSR), so the cost of everything per step is
//! O(followers + edges); the dense L and H exist only on demand, for small
//! graphs, to report λ_min(H).

use nalgebra::DMatrix;

/// Largest graph for which λ_min(H) is computed densely at load time.
pub const DENSE_EIGEN_LIMIT: usize = 1500;

/// Steps of the recursion [`Graph::estimator_growth`] iterates.
pub const GROWTH_STEPS: usize = 4000;

/// Follower ids as people read them in a line: "2, 3, 4".
pub fn id_list(ids: &[u32]) -> String {
    ids.iter().map(u32::to_string).collect::<Vec<_>>().join(", ")
}

/// Followers named in a line: "follower 3", "followers 2, 3, 4".
pub fn followers_named(ids: &[u32]) -> String {
    format!("{} {}", if ids.len() == 1 { "follower" } else { "followers" }, id_list(ids))
}

/// "follower 3 no longer reaches the leader (Lemma 1)", "followers 2, 3, 4
/// no longer reach the leader (Lemma 1)": the one wording of every line
/// that says a graph without some followers breaks Lemma 1.
pub fn no_longer_reach(cut: &[u32]) -> String {
    let verb = if cut.len() == 1 { "reaches" } else { "reach" };
    format!("{} no longer {verb} the leader (Lemma 1)", followers_named(cut))
}

/// An undirected follower graph with leader links.
#[derive(Clone, Debug, PartialEq)]
pub struct Graph {
    ids: Vec<u32>,
    /// CSR offsets into `adjacency`, length n + 1.
    offsets: Vec<usize>,
    /// Neighbour indices, ascending within each follower.
    adjacency: Vec<usize>,
    /// a_i0.
    leader_links: Vec<bool>,
}

impl Graph {
    /// Builds the graph from follower ids (ascending, unique), index pairs of
    /// undirected edges (validated: no self-loop, no duplicate) and leader links.
    pub fn new(ids: Vec<u32>, edges: &[(usize, usize)], leader_links: Vec<bool>) -> Self {
        let n = ids.len();
        let mut degree = vec![0usize; n];
        for &(a, b) in edges {
            degree[a] += 1;
            degree[b] += 1;
        }
        let mut offsets = Vec::with_capacity(n + 1);
        offsets.push(0);
        for d in &degree {
            offsets.push(offsets.last().copied().unwrap_or(0) + d);
        }
        let mut fill = offsets.clone();
        let mut adjacency = vec![0usize; offsets[n]];
        for &(a, b) in edges {
            adjacency[fill[a]] = b;
            fill[a] += 1;
            adjacency[fill[b]] = a;
            fill[b] += 1;
        }
        for i in 0..n {
            adjacency[offsets[i]..offsets[i + 1]].sort_unstable();
        }
        Self { ids, offsets, adjacency, leader_links }
    }

    pub fn len(&self) -> usize {
        self.ids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    pub fn id(&self, index: usize) -> u32 {
        self.ids[index]
    }

    pub fn ids(&self) -> &[u32] {
        &self.ids
    }

    pub fn index_of(&self, id: u32) -> Option<usize> {
        self.ids.binary_search(&id).ok()
    }

    /// Neighbour indices of follower `index`, ascending (hence ascending id).
    pub fn neighbours(&self, index: usize) -> &[usize] {
        &self.adjacency[self.offsets[index]..self.offsets[index + 1]]
    }

    /// a_i0.
    pub fn hears_leader(&self, index: usize) -> bool {
        self.leader_links[index]
    }

    pub fn edge_count(&self) -> usize {
        self.adjacency.len() / 2
    }

    /// ξ_i = Σ_j a_ij + a_i0 (docs/model.md §2).
    pub fn xi(&self, index: usize) -> usize {
        self.neighbours(index).len() + usize::from(self.leader_links[index])
    }

    /// Followers that no path connects to a follower hearing the leader, by
    /// id. Empty exactly when H is positive definite (Lemma 1).
    pub fn unreachable(&self) -> Vec<u32> {
        let n = self.len();
        let mut seen = self.leader_links.clone();
        let mut stack: Vec<usize> = (0..n).filter(|&i| seen[i]).collect();
        while let Some(i) = stack.pop() {
            for &j in self.neighbours(i) {
                if !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            }
        }
        (0..n).filter(|&i| !seen[i]).map(|i| self.ids[i]).collect()
    }

    /// Lemma 1 without the followers `gone` said in one line (None when it
    /// holds): "without follower 1, followers 2, 3, 4 no longer reach the
    /// leader (Lemma 1)". Every refusal of an absence or a leave that cuts
    /// followers off starts with it.
    pub fn cut_off_without(&self, gone: &[u32]) -> Option<String> {
        let cut = self.unreachable_without(gone);
        (!cut.is_empty()).then(|| format!("without {}, {}", followers_named(gone), no_longer_reach(&cut)))
    }

    /// Lemma 1 through a run's membership changes: followers `absent` at
    /// the start (each with the time it joins, if it does), followers that
    /// leave (id, time, s) and followers already gone. Checked at the start
    /// and at every leave, on the followers out at that moment; the first
    /// moment some present follower no longer reaches the leader, said in
    /// one line ("at t = 5 s, without followers 2 and 3, follower 4 no
    /// longer reaches the leader (Lemma 1)"), or None.
    pub fn cut_off_through(
        &self,
        absent: &[(u32, Option<f64>)],
        leaves: &[(u32, f64)],
        gone: &[u32],
    ) -> Option<String> {
        let mut moments: Vec<f64> = std::iter::once(0.0).chain(leaves.iter().map(|l| l.1)).collect();
        moments.sort_by(f64::total_cmp);
        moments.dedup();
        moments.into_iter().find_map(|t| {
            let mut out: Vec<u32> = gone.to_vec();
            out.extend(absent.iter().filter(|a| a.1.is_none_or(|j| j > t)).map(|a| a.0));
            out.extend(leaves.iter().filter(|l| l.1 <= t).map(|l| l.0));
            out.sort_unstable();
            out.dedup();
            let line = self.cut_off_without(&out)?;
            Some(if t > 0.0 { format!("at t = {t} s, {line}") } else { line })
        })
    }

    /// Lemma 1 on the graph without the followers `gone` (by id: absent,
    /// or left for good): the others that no path through the rest connects
    /// to a follower hearing the leader, by id. Empty when every remaining
    /// follower still reaches the leader.
    pub fn unreachable_without(&self, gone: &[u32]) -> Vec<u32> {
        let n = self.len();
        let out = |i: usize| gone.contains(&self.ids[i]);
        let mut seen: Vec<bool> = (0..n).map(|i| self.leader_links[i] && !out(i)).collect();
        let mut stack: Vec<usize> = (0..n).filter(|&i| seen[i]).collect();
        while let Some(i) = stack.pop() {
            for &j in self.neighbours(i) {
                if !seen[j] && !out(j) {
                    seen[j] = true;
                    stack.push(j);
                }
            }
        }
        (0..n).filter(|&i| !seen[i] && !out(i)).map(|i| self.ids[i]).collect()
    }

    /// The Laplacian L (eq. 1), dense.
    pub fn laplacian(&self) -> DMatrix<f64> {
        let n = self.len();
        let mut l = DMatrix::zeros(n, n);
        for i in 0..n {
            for &j in self.neighbours(i) {
                l[(i, j)] = -1.0;
            }
            l[(i, i)] = self.neighbours(i).len() as f64;
        }
        l
    }

    /// H = L + diag(a_10, …, a_n0) (eq. 2), dense.
    pub fn h_matrix(&self) -> DMatrix<f64> {
        let mut h = self.laplacian();
        for i in 0..self.len() {
            h[(i, i)] += f64::from(u8::from(self.leader_links[i]));
        }
        h
    }

    /// λ_min(H), which sets the estimator's convergence rate; `None` for
    /// graphs larger than [`DENSE_EIGEN_LIMIT`] (not computed).
    pub fn lambda_min_h(&self) -> Option<f64> {
        if self.is_empty() || self.len() > DENSE_EIGEN_LIMIT {
            return None;
        }
        let eig = self.h_matrix().symmetric_eigen();
        eig.eigenvalues.iter().copied().reduce(f64::min)
    }

    /// How much the position estimator's disagreement grows per step, at
    /// most, when every neighbour's message is `delay` steps older than the
    /// one step eq. 12 already takes (`network.delay_steps`): the spectral
    /// radius of eq. 11–12 as the follower steps them, linearised about
    /// consensus with the leader's terms fixed (per coordinate, gain `k`):
    ///
    ///   Ṗ_i(k) = ( −k (ξ_i P_i(k) − Σ_j a_ij P_j(k − d)) + Σ_j a_ij Ṗ_j(k − 1 − d) ) / ξ_i
    ///   P_i(k + 1) = P_i(k) + Δt Ṗ_i(k)
    ///
    /// Above 1 the estimates oscillate, the sign alternating from step to
    /// step, with an amplitude that grows by this factor each step (on a
    /// ring of 50 with 10 chords at Δt = 10 ms, k = 1 and one step of
    /// delay: 1.0026, while without the delay, or at Δt = 1 ms, it is below
    /// 1). Found by iterating the recursion ([`GROWTH_STEPS`] steps, the
    /// second half measured): O(steps × (followers + edges) × (d + 1)).
    pub fn estimator_growth(&self, k: f64, dt_s: f64, delay: usize) -> f64 {
        let n = self.len();
        if n == 0 {
            return 0.0;
        }
        // p[t] = P(k − t), t = 0..=d; r[t] = Ṗ(k − 1 − t), t = 0..=d.
        let mut p = vec![vec![0.0; n]; delay + 1];
        let mut r = vec![vec![0.0; n]; delay + 1];
        // A fixed pseudo-random start (it must not be orthogonal to the mode).
        let mut seed: u64 = 0x9E37_79B9_7F4A_7C15;
        for v in p.iter_mut().chain(r.iter_mut()).flatten() {
            seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            *v = (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5;
        }
        let mut log_growth = 0.0;
        for step in 0..GROWTH_STEPS {
            let mut rate = vec![0.0; n];
            for (i, out) in rate.iter_mut().enumerate() {
                let nb = self.neighbours(i);
                let xi = nb.len() as f64 + f64::from(u8::from(self.leader_links[i]));
                if xi == 0.0 {
                    // No source: it dead-reckons on its own last rate.
                    *out = r[0][i];
                    continue;
                }
                let (mut e, mut rates) = (xi * p[0][i], 0.0);
                for &j in nb {
                    e -= p[delay][j];
                    rates += r[delay][j];
                }
                *out = (-k * e + rates) / xi;
            }
            let next: Vec<f64> = p[0].iter().zip(&rate).map(|(pi, ri)| pi + dt_s * ri).collect();
            p.rotate_right(1);
            p[0] = next;
            r.rotate_right(1);
            r[0] = rate;
            let norm = p.iter().chain(r.iter()).flatten().map(|v| v * v).sum::<f64>().sqrt();
            if !(norm.is_finite() && norm > 0.0) {
                return norm;
            }
            if step >= GROWTH_STEPS / 2 {
                log_growth += norm.ln();
            }
            for v in p.iter_mut().chain(r.iter_mut()).flatten() {
                *v /= norm;
            }
        }
        (log_growth / (GROWTH_STEPS - GROWTH_STEPS / 2) as f64).exp()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper() -> Graph {
        Graph::new(vec![1, 2, 3, 4], &[(0, 1), (0, 2), (1, 3), (2, 3)], vec![true, false, false, false])
    }

    /// Lemma 1 through membership changes: each alone is fine, together
    /// they cut follower 4 off from the moment the second goes; a join
    /// before the leave brings the first back in time, one after does not.
    #[test]
    fn lemma_1_is_checked_at_the_start_and_at_every_leave_on_everyone_out_then() {
        let g = paper();
        assert_eq!(g.cut_off_through(&[(2, None)], &[], &[]), None);
        assert_eq!(g.cut_off_through(&[], &[(3, 5.0)], &[]), None);
        let both = g.cut_off_through(&[(2, None)], &[(3, 5.0)], &[]).expect("4 is cut off");
        assert!(both.starts_with("at t = 5 s, without followers 2") && both.contains("follower 4"), "{both}");
        assert_eq!(g.cut_off_through(&[(2, Some(4.0))], &[(3, 5.0)], &[]), None, "2 joins at 4 s, before 3 leaves");
        assert!(g.cut_off_through(&[(2, Some(6.0))], &[(3, 5.0)], &[]).is_some(), "2 joins at 6 s, after");
        assert!(g.cut_off_through(&[], &[(3, 5.0)], &[2]).is_some(), "2 already gone");
        let start = g.cut_off_through(&[(2, None), (3, None)], &[], &[]).expect("cut off at the start");
        assert!(!start.starts_with("at t"), "{start}");
    }

    #[test]
    fn paper_graph_lambda_min_matches_spec() {
        // docs/model.md §10: λ_min(H) ≈ 0.186.
        let l = paper().lambda_min_h().expect("small graph");
        assert!((l - 0.186).abs() < 5e-4, "λ_min(H) = {l}");
    }

    #[test]
    fn neighbours_are_ascending_and_xi_counts_the_leader() {
        let g = paper();
        assert_eq!(g.neighbours(0), &[1, 2]);
        assert_eq!(g.neighbours(3), &[1, 2]);
        assert_eq!(g.xi(0), 3);
        assert_eq!(g.xi(3), 2);
        assert_eq!(g.edge_count(), 4);
    }

    /// Lemma 1 on every graph of 4 followers: H is positive definite exactly
    /// when every follower is reachable from one that hears the leader.
    #[test]
    fn lemma_1_holds_on_every_small_graph() {
        let pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];
        for edge_mask in 0u32..64 {
            let edges: Vec<_> =
                pairs.iter().enumerate().filter(|(b, _)| edge_mask >> b & 1 == 1).map(|(_, &e)| e).collect();
            for leader_mask in 0u32..16 {
                let links = (0..4).map(|i| leader_mask >> i & 1 == 1).collect();
                let g = Graph::new(vec![1, 2, 3, 4], &edges, links);
                let positive_definite = g.lambda_min_h().unwrap() > 1e-9;
                assert_eq!(
                    positive_definite,
                    g.unreachable().is_empty(),
                    "edges {edges:?}, leader links {leader_mask:04b}"
                );
            }
        }
    }

    #[test]
    fn unreachable_names_the_cut_off_followers() {
        let g = Graph::new(vec![1, 2, 5, 9], &[(0, 1), (2, 3)], vec![true, false, false, false]);
        assert_eq!(g.unreachable(), vec![5, 9]);
    }

    /// The delayed estimator's growth against an independent computation
    /// (numpy's eigenvalues of the same recursion written as a matrix,
    /// 2026-11-26): a ring of 50 with 10 chords, seed 1, one follower
    /// hearing the leader, as `formation generate --followers 50 --graph
    /// ring --chords 10 --seed 1` writes it.
    #[test]
    fn the_delayed_estimator_grows_as_its_eigenvalues_say() {
        let spec = crate::generate::Spec {
            chords: 10,
            seed: 1,
            ..crate::generate::Spec::new(50, crate::generate::GraphKind::Ring)
        };
        let text = crate::generate::toml(&spec).expect("generate");
        let g = crate::Scenario::from_toml(&text, "ring50", "ring50", &[]).expect("load").graph;
        for (k, dt, d, want) in [
            (1.0, 0.01, 0, 0.99765),
            (1.0, 0.01, 1, 1.00265),
            (1.0, 0.01, 2, 1.00176),
            (0.5, 0.01, 1, 1.00014),
            (1.0, 0.001, 1, 0.99900),
        ] {
            let got = g.estimator_growth(k, dt, d);
            assert!(
                (got - want).abs() < 2e-4,
                "k = {k}, Δt = {dt}, d = {d}: growth {got:.5} per step, numpy {want:.5}"
            );
        }
        // The paper's graph: below 1 at every delay.
        for d in 0..3 {
            let got = paper().estimator_growth(1.0, 0.01, d);
            assert!(got < 1.0, "paper graph, Δt = 10 ms, d = {d}: {got:.5}");
        }
    }

    /// Lemma 1 without some followers: a path of four (leader → 1 – 2 – 3
    /// – 4) loses 3 and 4 when 2 goes, nothing when 4 goes, everyone when 1
    /// goes; the whole graph's answer is the empty removal's.
    #[test]
    fn followers_cut_off_by_others_leaving_are_named() {
        let g = Graph::new(vec![1, 2, 3, 4], &[(0, 1), (1, 2), (2, 3)], vec![true, false, false, false]);
        assert_eq!(g.unreachable_without(&[]), g.unreachable());
        assert_eq!(g.unreachable_without(&[4]), Vec::<u32>::new());
        assert_eq!(g.unreachable_without(&[2]), vec![3, 4]);
        assert_eq!(g.unreachable_without(&[1]), vec![2, 3, 4]);
        // Said in one wording, singular and plural.
        assert_eq!(g.cut_off_without(&[4]), None);
        assert_eq!(
            g.cut_off_without(&[3]).as_deref(),
            Some("without follower 3, follower 4 no longer reaches the leader (Lemma 1)")
        );
        assert_eq!(
            g.cut_off_without(&[1, 2]).as_deref(),
            Some("without followers 1, 2, followers 3, 4 no longer reach the leader (Lemma 1)")
        );
    }
}
