//! Maximum spanning trees on complete graphs (the Chow–Liu step).
//!
//! Chow & Liu (1968): among all tree-structured distributions, the one closest in KL divergence to `p`
//! is built on the maximum spanning tree of the pairwise mutual informations. Blankets are small (tens
//! of poses), so Prim's algorithm on the dense weight matrix (`O(n²)`) is the right tool.

/// The maximum spanning tree of the complete graph on `n` vertices with symmetric edge weights
/// `weight(i, j)` (`i < j`), as `n − 1` edges `(parent, child)` oriented away from vertex `root`.
///
/// Ties break towards the smaller vertex index, so the result is deterministic. A NaN weight counts as
/// `−∞`. Returns no edges for `n ≤ 1`; `root` must be `< n` otherwise.
pub(crate) fn maximum_spanning_tree(
    n: usize,
    root: usize,
    weight: impl Fn(usize, usize) -> f64,
) -> Vec<(usize, usize)> {
    if n <= 1 {
        return Vec::new();
    }
    let w = |i: usize, j: usize| {
        let v = if i < j { weight(i, j) } else { weight(j, i) };
        if v.is_nan() { f64::NEG_INFINITY } else { v }
    };
    let mut in_tree = vec![false; n];
    // For each vertex outside the tree: the best weight to the tree and the tree vertex giving it.
    let mut best = vec![(f64::NEG_INFINITY, root); n];
    in_tree[root] = true;
    for (v, b) in best.iter_mut().enumerate() {
        if v != root {
            *b = (w(root, v), root);
        }
    }
    let mut edges = Vec::with_capacity(n - 1);
    for _ in 1..n {
        let mut next = None;
        for v in 0..n {
            if in_tree[v] {
                continue;
            }
            match next {
                None => next = Some(v),
                Some(u) if best[v].0 > best[u].0 => next = Some(v),
                Some(_) => {}
            }
        }
        let Some(v) = next else { break };
        in_tree[v] = true;
        edges.push((best[v].1, v));
        for u in 0..n {
            if !in_tree[u] {
                let candidate = w(v, u);
                if candidate > best[u].0 {
                    best[u] = (candidate, v);
                }
            }
        }
    }
    edges
}

#[cfg(test)]
mod tests {
    use rand::{Rng as _, SeedableRng as _};
    use rand_pcg::Pcg64;

    use super::*;

    /// All spanning trees of the complete graph on `n ≥ 2` vertices, by decoding every Prüfer sequence.
    fn all_spanning_trees(n: usize) -> Vec<Vec<(usize, usize)>> {
        if n == 2 {
            return vec![vec![(0, 1)]];
        }
        let len = n - 2;
        let count = n.pow(len as u32);
        let mut trees = Vec::with_capacity(count);
        for code in 0..count {
            let mut seq = Vec::with_capacity(len);
            let mut c = code;
            for _ in 0..len {
                seq.push(c % n);
                c /= n;
            }
            let mut degree = vec![1usize; n];
            for &s in &seq {
                degree[s] += 1;
            }
            let mut edges = Vec::with_capacity(n - 1);
            for &s in &seq {
                let leaf = (0..n).find(|&v| degree[v] == 1).unwrap();
                edges.push((leaf.min(s), leaf.max(s)));
                degree[leaf] -= 1;
                degree[s] -= 1;
            }
            let rest: Vec<usize> = (0..n).filter(|&v| degree[v] == 1).collect();
            edges.push((rest[0], rest[1]));
            trees.push(edges);
        }
        trees
    }

    fn is_spanning_tree(n: usize, edges: &[(usize, usize)]) -> bool {
        let mut uf = crate::sparsification::UnionFind::new(n);
        for &(a, b) in edges {
            if uf.find(a) == uf.find(b) {
                return false;
            }
            uf.union(a, b);
        }
        edges.len() + 1 == n
    }

    #[test]
    fn prufer_enumeration_counts_cayley_trees() {
        for n in 2..=5 {
            let trees = all_spanning_trees(n);
            assert_eq!(trees.len(), n.pow(n as u32 - 2));
            assert!(trees.iter().all(|t| is_spanning_tree(n, t)));
            let mut sorted: Vec<Vec<(usize, usize)>> = trees
                .into_iter()
                .map(|mut t| {
                    t.sort_unstable();
                    t
                })
                .collect();
            sorted.sort();
            sorted.dedup();
            assert_eq!(sorted.len(), n.pow(n as u32 - 2), "trees must be distinct");
        }
    }

    // Chow & Liu 1968, §III: the optimal dependence tree is the maximum-weight spanning tree.
    #[test]
    fn maximum_spanning_tree_equals_brute_force() {
        let mut rng = Pcg64::seed_from_u64(7);
        let mut checked = 0;
        for n in 2..=5 {
            let trees = all_spanning_trees(n);
            for trial in 0..40 {
                let mut weights = vec![vec![0.0; n]; n];
                for (i, row) in weights.iter_mut().enumerate() {
                    for w in row.iter_mut().skip(i + 1) {
                        // Some trials draw from few values, to exercise ties.
                        *w = if trial % 4 == 0 {
                            f64::from(rng.random_range(0..3u8))
                        } else {
                            rng.random_range(-1.0..5.0)
                        };
                    }
                }
                let total = |edges: &[(usize, usize)]| -> f64 {
                    edges
                        .iter()
                        .map(|&(a, b)| weights[a.min(b)][a.max(b)])
                        .sum()
                };
                let best = trees
                    .iter()
                    .map(|t| total(t))
                    .fold(f64::NEG_INFINITY, f64::max);
                let root = trial % n;
                let tree = maximum_spanning_tree(n, root, |i, j| weights[i][j]);
                assert!(is_spanning_tree(n, &tree));
                assert!((total(&tree) - best).abs() < 1e-12, "n={n} trial={trial}");
                // Oriented away from the root: every child appears once, the root never.
                let mut children: Vec<usize> = tree.iter().map(|&(_, c)| c).collect();
                children.sort_unstable();
                children.dedup();
                assert_eq!(children.len(), n - 1);
                assert!(!children.contains(&root));
                // Each parent is the root or was reached earlier.
                for (k, &(p, _)) in tree.iter().enumerate() {
                    assert!(p == root || tree[..k].iter().any(|&(_, c)| c == p));
                }
                checked += 1;
            }
        }
        assert_eq!(checked, 160);
    }

    #[test]
    fn trivial_sizes_and_nan_weights() {
        assert!(maximum_spanning_tree(0, 0, |_, _| 1.0).is_empty());
        assert!(maximum_spanning_tree(1, 0, |_, _| 1.0).is_empty());
        // NaN weights are never preferred over finite ones.
        let tree =
            maximum_spanning_tree(3, 0, |i, j| if (i, j) == (0, 1) { f64::NAN } else { 1.0 });
        assert!(is_spanning_tree(3, &tree));
        assert!(!tree.iter().any(|&(a, b)| (a.min(b), a.max(b)) == (0, 1)));
    }
}
