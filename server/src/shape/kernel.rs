//! The Gaussian kernel G(a, b)_ij = exp(−‖a_i − b_j‖² / 2β²) of the CPD
//! deformation field, and its low-rank eigen-approximation G ≈ Q Λ Qᵀ.
//!
//! Solving with the full M×M kernel costs O(M³) per EM iteration, which at
//! M = 1000 is most of a second over a registration. The kernel of a smooth
//! field has fast-decaying eigenvalues, so a rank-k factor captures it to
//! working precision and the M-step drops to O(M k²) (Woodbury). The factor
//! comes from a randomized range finder (Halko, Martinsson & Tropp 2011)
//! with power iterations: cheaper than a full eigendecomposition by the ratio
//! M/k, and exact up to the discarded tail, which we report.

use super::estep::{dist2, P3};
use super::fastexp::exp_neg;
use faer::prelude::*;
use faer::Side;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};

/// The dense kernel matrix between two point sets.
pub fn gaussian(a: &[P3], b: &[P3], beta: f64) -> Mat<f64> {
    let k = -0.5 / (beta * beta);
    Mat::from_fn(a.len(), b.len(), |i, j| exp_neg(k * dist2(&a[i], &b[j])))
}

/// G ≈ Q diag(λ) Qᵀ with orthonormal Q (M×k).
#[derive(Clone, Debug)]
pub struct LowRankKernel {
    pub q: Mat<f64>,
    pub lambda: Vec<f64>,
    /// Largest discarded eigenvalue relative to the largest kept one (0 for full rank).
    pub tail_ratio: f64,
}

impl LowRankKernel {
    pub fn rank(&self) -> usize {
        self.lambda.len()
    }

    /// Eigen-approximation of the kernel on `points`. Keeps eigenvalues above
    /// `rel_tol`·λ_max, at most `max_rank`. Small sets get the exact
    /// eigendecomposition.
    pub fn new(points: &[P3], beta: f64, max_rank: usize, rel_tol: f64, seed: u64) -> Self {
        let m = points.len();
        let g = gaussian(points, points, beta);
        let max_rank = max_rank.clamp(1, m.max(1));
        let (u, s) = if m <= 2 * max_rank + 64 { exact_eigen(&g) } else { randomized_eigen(&g, max_rank, seed) };
        // Eigenvalues descending.
        let lmax = s.first().copied().unwrap_or(0.0).max(f64::MIN_POSITIVE);
        let mut k = s.iter().take(max_rank).take_while(|&&l| l > rel_tol * lmax).count().max(1);
        k = k.min(u.ncols());
        let tail_ratio = s.get(k).map(|&l| (l / lmax).max(0.0)).unwrap_or(0.0);
        let q = u.subcols(0, k).to_owned();
        Self { q, lambda: s[..k].to_vec(), tail_ratio }
    }

    /// G·W for W with M rows (low-rank product Q Λ Qᵀ W).
    pub fn apply(&self, w: MatRef<'_, f64>) -> Mat<f64> {
        let mut t = self.q.transpose() * w;
        for (i, l) in self.lambda.iter().enumerate() {
            for j in 0..t.ncols() {
                t[(i, j)] *= l;
            }
        }
        &self.q * &t
    }
}

/// Full symmetric eigendecomposition, eigenvalues descending.
fn exact_eigen(g: &Mat<f64>) -> (Mat<f64>, Vec<f64>) {
    match g.self_adjoint_eigen(Side::Lower) {
        Ok(e) => {
            let n = g.nrows();
            let s: Vec<f64> = (0..n).rev().map(|i| e.S().column_vector()[i]).collect();
            let u = Mat::from_fn(n, n, |i, j| e.U()[(i, n - 1 - j)]);
            (u, s)
        }
        // A kernel matrix is symmetric with finite entries; should the
        // decomposition still fail, the identity (no coupling) is a safe field.
        Err(_) => (Mat::identity(g.nrows(), g.nrows()), vec![1.0; g.nrows()]),
    }
}

/// Randomized eigendecomposition of a symmetric PSD matrix (rank + oversampling,
/// two power iterations), eigenvalues descending.
fn randomized_eigen(g: &Mat<f64>, rank: usize, seed: u64) -> (Mat<f64>, Vec<f64>) {
    let m = g.nrows();
    let l = (rank + 16).min(m);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let omega = Mat::<f64>::from_fn(m, l, |_, _| StandardNormal.sample(&mut rng));
    let mut y = g * &omega;
    for _ in 0..2 {
        let q = y.qr().compute_thin_Q();
        y = g * &q;
    }
    let q = y.qr().compute_thin_Q();
    let b = q.transpose() * (g * &q);
    let (v, s) = exact_eigen(&b);
    (&q * &v, s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;

    #[test]
    fn low_rank_reproduces_the_kernel_product() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let pts: Vec<P3> = (0..900).map(|_| [r.random(), r.random(), r.random()]).collect();
        let g = gaussian(&pts, &pts, 0.5);
        let lr = LowRankKernel::new(&pts, 0.5, 300, 1e-6, 1);
        eprintln!("rank {} tail {:e}", lr.rank(), lr.tail_ratio);
        assert!(lr.rank() < 300, "rank {}", lr.rank());
        let w = Mat::from_fn(900, 3, |_, _| r.random::<f64>() - 0.5);
        let exact = &g * &w;
        let approx = lr.apply(w.as_ref());
        let err = (&exact - &approx).norm_max();
        assert!(err < 1e-4 * exact.norm_max(), "error {err} of {}", exact.norm_max());
    }
}
