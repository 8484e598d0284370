//! Clustered principal component analysis (CPCA) of a set of vectors (supplemental §3, after
//! Sloan et al. 2003): k-means clusters, then per cluster its mean and the top left-singular
//! vectors of the mean-subtracted data matrix C (Eq. 3 of the supplemental, C = UΣVᵀ) as the
//! representatives; each vector is then its cluster's mean plus a weighted sum of them.
//!
//! The eigenproblem is solved on CCᵀ (d × d) or CᵀC (m × m), whichever is smaller: the
//! eigenvectors of CCᵀ are U; those of CᵀC are V, from which U = CVΣ⁻¹. Both give Σ². The
//! decomposition is nalgebra's symmetric eigensolver in f64; everything here is deterministic
//! (no random seeds, no threads), so a bake's bytes do not depend on the machine's load.

use nalgebra::{DMatrix, SymmetricEigen};

/// What to keep of a set of vectors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CpcaSettings {
    /// Most clusters.
    pub clusters: usize,
    /// Most representatives per cluster (1 degrades CPCA to vector quantization plus one
    /// direction; 0 to plain vector quantization).
    pub reps: usize,
    /// Fewest vectors per cluster: a set of m vectors gets at most m / this clusters, so that
    /// each cluster's bases are shared widely enough to pay for themselves.
    pub min_per_cluster: usize,
    /// A cluster keeps the fewest representatives (at most `reps`) that bring the RMS error
    /// per component of its vectors down to this (the eigenvalues left out, Σλ / (m·d),
    /// are that mean squared error); 0 keeps `reps` wherever the rank allows.
    pub tolerance: f64,
}

/// One cluster: its mean and its representatives (orthonormal, by decreasing singular value).
#[derive(Clone, Debug, PartialEq)]
pub struct Cluster {
    /// The cluster's mean vector.
    pub mean: Vec<f32>,
    /// Its representatives: orthonormal directions, by decreasing singular value.
    pub reps: Vec<Vec<f32>>,
}

/// The result: clusters, each vector's cluster and its projection weights on that cluster's
/// representatives (`weights[i].len() == clusters[assign[i]].reps.len()`).
#[derive(Clone, Debug, PartialEq)]
pub struct Cpca {
    /// Dimension of the vectors.
    pub dim: usize,
    /// The clusters.
    pub clusters: Vec<Cluster>,
    /// For each input vector, the index of its cluster.
    pub assign: Vec<u32>,
    /// For each input vector, its projection weights on its cluster's representatives.
    pub weights: Vec<Vec<f32>>,
}

impl Cpca {
    /// The reconstruction of vector `i`: mean + Σ w_j u_j.
    pub fn reconstruct(&self, i: usize) -> Vec<f32> {
        let c = &self.clusters[self.assign[i] as usize];
        let mut out = c.mean.clone();
        for (w, u) in self.weights[i].iter().zip(&c.reps) {
            for (o, x) in out.iter_mut().zip(u) {
                *o += w * x;
            }
        }
        out
    }
}

fn dist2(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(x, y)| ((x - y) as f64).powi(2)).sum()
}

/// Deterministic k-means (Lloyd) of the `m` vectors of `data` (row-major, `dim` each) into at
/// most `k` clusters. Initial centres are chosen far from each other (maximin: the vector
/// farthest from the data's mean, then repeatedly the vector farthest from every centre so
/// far), so no seed is needed; identical vectors never make two centres. Returns the centres
/// and each vector's cluster; empty clusters are dropped.
pub fn kmeans(data: &[f32], dim: usize, k: usize, iters: usize) -> (Vec<Vec<f32>>, Vec<u32>) {
    let m = if dim == 0 { 0 } else { data.len() / dim };
    let row = |i: usize| &data[i * dim..(i + 1) * dim];
    if m == 0 || k == 0 {
        return (Vec::new(), vec![0; m]);
    }
    let mut mean = vec![0f64; dim];
    for i in 0..m {
        for (a, x) in mean.iter_mut().zip(row(i)) {
            *a += *x as f64;
        }
    }
    let mean: Vec<f32> = mean.iter().map(|a| (a / m as f64) as f32).collect();
    // Maximin initialisation.
    let mut centres: Vec<Vec<f32>> = Vec::with_capacity(k);
    let mut nearest: Vec<f64> = (0..m).map(|i| dist2(row(i), &mean)).collect();
    let first = argmax(&nearest);
    centres.push(row(first).to_vec());
    nearest = (0..m).map(|i| dist2(row(i), &centres[0])).collect();
    while centres.len() < k {
        let i = argmax(&nearest);
        if nearest[i] <= 0.0 {
            break;
        }
        centres.push(row(i).to_vec());
        let c = centres.last().expect("pushed");
        for (j, n) in nearest.iter_mut().enumerate() {
            *n = n.min(dist2(row(j), c));
        }
    }
    let mut assign = vec![0u32; m];
    for it in 0..=iters {
        // Assignment step.
        let mut changed = false;
        for (i, a) in assign.iter_mut().enumerate() {
            let mut best = (f64::INFINITY, 0u32);
            for (c, centre) in centres.iter().enumerate() {
                let d = dist2(row(i), centre);
                if d < best.0 {
                    best = (d, c as u32);
                }
            }
            if *a != best.1 || it == 0 {
                changed |= *a != best.1;
                *a = best.1;
            }
        }
        if it > 0 && !changed {
            break;
        }
        // Update step.
        let mut sums = vec![vec![0f64; dim]; centres.len()];
        let mut counts = vec![0usize; centres.len()];
        for i in 0..m {
            let c = assign[i] as usize;
            counts[c] += 1;
            for (s, x) in sums[c].iter_mut().zip(row(i)) {
                *s += *x as f64;
            }
        }
        for (c, centre) in centres.iter_mut().enumerate() {
            if counts[c] > 0 {
                for (x, s) in centre.iter_mut().zip(&sums[c]) {
                    *x = (s / counts[c] as f64) as f32;
                }
            }
        }
    }
    // Drop empty clusters, renumbering the rest in order.
    let mut counts = vec![0usize; centres.len()];
    for a in &assign {
        counts[*a as usize] += 1;
    }
    let mut remap = vec![u32::MAX; centres.len()];
    let mut kept = Vec::new();
    for (c, centre) in centres.into_iter().enumerate() {
        if counts[c] > 0 {
            remap[c] = kept.len() as u32;
            kept.push(centre);
        }
    }
    for a in &mut assign {
        *a = remap[*a as usize];
    }
    (kept, assign)
}

fn argmax(v: &[f64]) -> usize {
    let mut best = 0;
    for (i, x) in v.iter().enumerate() {
        if *x > v[best] {
            best = i;
        }
    }
    best
}

/// PCA of the vectors `members` (rows of `data`, `dim` each): their mean and the fewest
/// top left-singular vectors of the mean-subtracted matrix (at most `max_reps`) whose
/// reconstruction has an RMS error per component of at most `tolerance`.
pub fn pca(
    data: &[f32],
    dim: usize,
    members: &[usize],
    max_reps: usize,
    tolerance: f64,
) -> Cluster {
    let m = members.len();
    let row = |i: usize| &data[i * dim..(i + 1) * dim];
    let mut mean = vec![0f64; dim];
    for &i in members {
        for (a, x) in mean.iter_mut().zip(row(i)) {
            *a += *x as f64;
        }
    }
    for a in &mut mean {
        *a /= m.max(1) as f64;
    }
    let mean32: Vec<f32> = mean.iter().map(|a| *a as f32).collect();
    if m < 2 || max_reps == 0 {
        return Cluster {
            mean: mean32,
            reps: Vec::new(),
        };
    }
    // C: dim × m, each column a member minus the mean.
    let c = DMatrix::<f64>::from_fn(dim, m, |r, j| row(members[j])[r] as f64 - mean[r]);
    let small_side = dim.min(m);
    let (values, vectors, use_left) = if dim <= m {
        let e = SymmetricEigen::new(&c * c.transpose());
        (e.eigenvalues, e.eigenvectors, true)
    } else {
        let e = SymmetricEigen::new(c.transpose() * &c);
        (e.eigenvalues, e.eigenvectors, false)
    };
    // Eigenpairs by decreasing eigenvalue (ties by index: deterministic).
    let mut order: Vec<usize> = (0..small_side).collect();
    order.sort_by(|&a, &b| values[b].total_cmp(&values[a]).then(a.cmp(&b)));
    let total: f64 = values.iter().map(|v| v.max(0.0)).sum();
    // The squared error left when stopping here, summed over the cluster.
    let budget = tolerance * tolerance * (m * dim) as f64;
    let mut left = total;
    let mut reps = Vec::new();
    for &k in order.iter().take(max_reps) {
        let lambda = values[k];
        if total <= 0.0 || lambda <= 1e-9 * total.max(1e-30) || left <= budget {
            break;
        }
        left -= lambda;
        let u: Vec<f64> = if use_left {
            vectors.column(k).iter().copied().collect()
        } else {
            // U = C V Σ⁻¹.
            let v = vectors.column(k);
            let u = &c * v;
            let s = lambda.sqrt();
            u.iter().map(|x| x / s).collect()
        };
        // Unit length (round-off) and a sign convention: the largest component positive.
        let norm = u.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(norm > 0.0) {
            break;
        }
        let big = u
            .iter()
            .copied()
            .fold(0.0f64, |b, x| if x.abs() > b.abs() { x } else { b });
        let sign = if big < 0.0 { -1.0 } else { 1.0 };
        reps.push(u.iter().map(|x| (sign * x / norm) as f32).collect());
    }
    Cluster { mean: mean32, reps }
}

/// Clustered PCA of the `m` vectors of `data` (row-major, `dim` each): k-means into at most
/// `min(clusters, m / min_per_cluster)` clusters, PCA per cluster, and each vector's
/// projection weights wⱼ = uⱼᵀ(x − mean).
pub fn cpca(data: &[f32], dim: usize, s: &CpcaSettings) -> Cpca {
    let m = if dim == 0 { 0 } else { data.len() / dim };
    let k = (m / s.min_per_cluster.max(1)).clamp(1, s.clusters.max(1));
    let (_, assign) = kmeans(data, dim, k, 12);
    let n_clusters = assign.iter().map(|a| *a as usize + 1).max().unwrap_or(0);
    let mut members = vec![Vec::new(); n_clusters];
    for (i, a) in assign.iter().enumerate() {
        members[*a as usize].push(i);
    }
    let clusters: Vec<Cluster> = members
        .iter()
        .map(|ms| pca(data, dim, ms, s.reps, s.tolerance))
        .collect();
    let weights = (0..m)
        .map(|i| {
            let c = &clusters[assign[i] as usize];
            let x = &data[i * dim..(i + 1) * dim];
            c.reps
                .iter()
                .map(|u| {
                    u.iter()
                        .zip(x.iter().zip(&c.mean))
                        .map(|(u, (x, mu))| (*u as f64) * (*x as f64 - *mu as f64))
                        .sum::<f64>() as f32
                })
                .collect()
        })
        .collect();
    Cpca {
        dim,
        clusters,
        assign,
        weights,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Pcg32 as Rng;

    /// Vectors of a known rank r around a mean are recovered exactly by one cluster with r
    /// representatives: the reconstruction error is round-off.
    #[test]
    fn pca_recovers_a_known_rank_exactly() {
        let (dim, m, r) = (64, 200, 5);
        let mut rng = Rng::new(7, 0);
        let basis: Vec<Vec<f32>> = (0..r)
            .map(|_| (0..dim).map(|_| rng.next_f32() - 0.5).collect())
            .collect();
        let mean: Vec<f32> = (0..dim).map(|_| rng.next_f32()).collect();
        let mut data = Vec::new();
        for _ in 0..m {
            let w: Vec<f32> = (0..r).map(|_| rng.next_f32() * 2.0 - 1.0).collect();
            for d in 0..dim {
                data.push(mean[d] + (0..r).map(|j| w[j] * basis[j][d]).sum::<f32>());
            }
        }
        let s = CpcaSettings {
            clusters: 1,
            reps: 10,
            min_per_cluster: 1,
            tolerance: 0.0,
        };
        let c = cpca(&data, dim, &s);
        assert_eq!(c.clusters.len(), 1);
        assert_eq!(c.clusters[0].reps.len(), r, "rank found");
        for i in 0..m {
            let x = &data[i * dim..(i + 1) * dim];
            let err = dist2(x, &c.reconstruct(i)).sqrt();
            assert!(err < 1e-4, "vector {i}: error {err}");
        }
        // Fewer vectors than dimensions (the CᵀC side) gives the same.
        let few = &data[..(r + 3) * dim];
        let c = cpca(few, dim, &s);
        for i in 0..r + 3 {
            let err = dist2(&few[i * dim..(i + 1) * dim], &c.reconstruct(i)).sqrt();
            assert!(err < 1e-4, "vector {i} of few: error {err}");
        }
    }

    /// Two well-separated groups are split by k-means, deterministically.
    #[test]
    fn kmeans_splits_separated_groups_deterministically() {
        let mut data = Vec::new();
        for i in 0..40 {
            let base = if i % 2 == 0 { 0.0 } else { 10.0 };
            data.extend([base + (i as f32) * 0.01, base]);
        }
        let (c1, a1) = kmeans(&data, 2, 2, 10);
        let (c2, a2) = kmeans(&data, 2, 2, 10);
        assert_eq!((c1.len(), &a1), (2, &a2));
        assert_eq!(c1, c2);
        for i in 0..40 {
            assert_eq!(a1[i], a1[i % 2], "vector {i}");
        }
        assert_ne!(a1[0], a1[1]);
    }

    /// Identical vectors, one vector, and a zero budget are normal inputs.
    #[test]
    fn degenerate_sets() {
        let s = CpcaSettings {
            clusters: 4,
            reps: 3,
            min_per_cluster: 1,
            tolerance: 0.0,
        };
        let same = vec![0.25f32; 16 * 10];
        let c = cpca(&same, 16, &s);
        assert_eq!(c.clusters.len(), 1);
        assert!(c.clusters[0].reps.is_empty());
        assert_eq!(c.reconstruct(3), vec![0.25; 16]);
        let one = vec![0.5f32; 16];
        let c = cpca(&one, 16, &s);
        assert_eq!(c.reconstruct(0), one);
        assert_eq!(cpca(&[], 16, &s).assign.len(), 0);
    }
}
