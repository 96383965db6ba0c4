//! The Gaussian kernel G(a, b)_ij = exp(−‖a_i − b_j‖² / 2β²) of the CPD
//! deformation field, and its low-rank eigen-approximation G ≈ Q Λ Qᵀ.
//!
//! Solving with the full M×M kernel costs O(M³) per EM iteration, which at
//! M = 1000 is most of a second over a registration. The kernel of a smooth
//! field has fast-decaying eigenvalues, so a rank-k factor captures it to
//! working precision and the M-step works in k dimensions (Woodbury; see
//! `mstep`). Small sets get G's exact eigendecomposition; larger ones a
//! partial pivoted Cholesky G ≈ L Lᵀ that evaluates only the columns it
//! needs, then the eigenvectors of L Lᵀ from the small matrix Lᵀ L.

use super::estep::{dist2, P3};
use super::fastexp::exp_neg;
use crate::simd::clear_upper_state;
use crate::simd::Simd;
use faer::prelude::*;
use faer::Side;
use rayon::prelude::*;

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
    /// Largest discarded eigenvalue relative to the largest kept one (0 for
    /// full rank); for a factor from the pivoted Cholesky, at least the bound
    /// on what the Cholesky left out (its trace), relative to the largest and
    /// capped at 1.
    pub tail_ratio: f64,
}

/// Up to this many points the factor is G's own eigendecomposition (exact,
/// and cheap); above, the partial pivoted Cholesky (`pivoted_cholesky`).
/// At 1,024 points (`bench/cpd_peer.sh`) the Cholesky route builds the
/// factor in about half the time and moves the CPD's points by 1.3 µm; at
/// 4,096 it takes 0.5 s where the randomized range finder it replaced took 6.
const EXACT_MAX_POINTS: usize = 512;
/// A factor that leaves out eigenvalues above this fraction of the largest
/// (a rank cap or a β too small for the cloud) is logged as a warning.
const TAIL_WARNING: f64 = 1e-3;
/// Rows a parallel task of the Cholesky updates takes.
const BLOCK_ROWS: usize = 256;
/// Multiply-adds of a Cholesky step below which it runs on one thread. CPD
/// builds the factor on a rayon worker (`cpd::on_pool`), where a fork and
/// join costs microseconds: at 1,024 points two threads take from the 64th
/// column on (`examples/bench_kernel`, 2 threads: 66 → 53 ms; it was 2²⁰,
/// the 1,024th).
const PAR_MIN_WORK: usize = 1 << 16;
/// A pivot below this (G's diagonal is 1) is rounding error: the points left
/// are, to working precision, combinations of the pivots taken.
const MIN_PIVOT: f64 = 1e-13;

impl LowRankKernel {
    pub fn rank(&self) -> usize {
        self.lambda.len()
    }

    /// Eigen-approximation of the kernel on `points`. Keeps eigenvalues above
    /// `rel_tol`·λ_max, at most `max_rank`. Deterministic.
    pub fn new(points: &[P3], beta: f64, max_rank: usize, rel_tol: f64) -> Self {
        let m = points.len();
        let max_rank = max_rank.clamp(1, m.max(1));
        if m <= EXACT_MAX_POINTS {
            let (u, s) = exact_eigen(&gaussian(points, points, beta));
            let k = kept_rank(&s, max_rank, rel_tol).min(u.ncols());
            return Self::truncated(u.as_ref(), &s, k, 0.0);
        }
        // Columns enough for the largest `max_rank` eigenpairs should the
        // tolerance alone want more.
        let max_columns = m.min(max_rank.saturating_mul(3) / 2 + 64);
        let (l, left_out) = pivoted_cholesky(points, beta, rel_tol, max_columns, Simd::detect(Simd::Avx512));
        let r = l.len() / m.max(1);
        // Eigenvectors of L Lᵀ from Lᵀ L = V S Vᵀ: L Lᵀ = (L V S^-½) S (L V S^-½)ᵀ.
        let lmat = MatRef::from_column_major_slice(&l, m, r);
        // Its lower half only: the eigendecomposition reads no other.
        let mut gram = Mat::<f64>::zeros(r, r);
        {
            use faer::linalg::matmul::triangular::{matmul, BlockStructure};
            let full = BlockStructure::Rectangular;
            let lower = BlockStructure::TriangularLower;
            let par = faer::get_global_parallelism();
            matmul(gram.as_mut(), lower, faer::Accum::Replace, lmat.transpose(), full, lmat, full, 1.0, par);
        }
        clear_upper_state();
        let (v, s) = exact_eigen(&gram);
        let lmax = s.first().copied().unwrap_or(0.0).max(f64::MIN_POSITIVE);
        let k = kept_rank(&s, max_rank, rel_tol).min(r);
        // Only the k eigenvectors kept are carried back to M rows.
        let vk = Mat::from_fn(r, k, |i, j| v[(i, j)] / s[j].max(f64::MIN_POSITIVE).sqrt());
        let u = lmat * &vk;
        clear_upper_state();
        Self::truncated(u.as_ref(), &s, k, (left_out / lmax).min(1.0))
    }

    /// The first k eigenpairs of (u, s) (s descending); `floor`: a known
    /// bound on the tail.
    fn truncated(u: MatRef<'_, f64>, s: &[f64], k: usize, floor: f64) -> Self {
        let lmax = s.first().copied().unwrap_or(0.0).max(f64::MIN_POSITIVE);
        let tail_ratio = s.get(k).map_or(0.0, |&l| (l / lmax).max(0.0)).max(floor);
        if tail_ratio > TAIL_WARNING {
            tracing::warn!(
                rank = k,
                tail_ratio,
                "the kernel factor leaves out eigenvalues up to {tail_ratio:.1e} of the largest: the deformation \
                 field is coarser than asked (raise the maximum rank or β)"
            );
        }
        Self { q: u.subcols(0, k).to_owned(), lambda: s[..k].to_vec(), tail_ratio }
    }

    /// G·W for W with M rows (low-rank product Q Λ Qᵀ W).
    pub fn apply(&self, w: MatRef<'_, f64>) -> Mat<f64> {
        let mut t = self.q.transpose() * w;
        for (i, l) in self.lambda.iter().enumerate() {
            for j in 0..t.ncols() {
                t[(i, j)] *= l;
            }
        }
        let gw = &self.q * &t;
        clear_upper_state();
        gw
    }
}

/// How many of the eigenvalues `s` (descending) lie above `rel_tol` of the
/// largest, at most `max_rank`, at least 1.
fn kept_rank(s: &[f64], max_rank: usize, rel_tol: f64) -> usize {
    let lmax = s.first().copied().unwrap_or(0.0).max(f64::MIN_POSITIVE);
    s.iter().take(max_rank).take_while(|&&l| l > rel_tol * lmax).count().max(1)
}

/// G ≈ L Lᵀ by partial pivoted Cholesky (Harbrecht, Peters & Schneider
/// 2012): each step takes the point whose diagonal G leaves most
/// unexplained, evaluates that one kernel column and takes it out of the
/// rest. Written by hand because no library here factors a matrix it is
/// given a column at a time: it evaluates r of G's M columns and keeps M·r
/// numbers, where an eigendecomposition or a randomized range finder forms
/// all M² (at 4,096 points: seconds and 134 MB; at 100,000, out of memory).
///
/// Stops when the trace it leaves out, which bounds the error's 2-norm, is
/// at most `rel_tol` times a lower bound of λ_max (‖l₀‖², the first
/// column's squared norm, since G ⪰ l₀l₀ᵀ; after `RAYLEIGH_AT` columns a
/// Rayleigh quotient of L Lᵀ, `rayleigh_lower_bound`): the error is then no larger than
/// the eigenvalues the caller drops anyway. Also stops at a pivot that is
/// rounding error and at `max_columns`. Returns L by columns (M values
/// each) and the trace left out.
fn pivoted_cholesky(points: &[P3], beta: f64, rel_tol: f64, max_columns: usize, simd: Simd) -> (Vec<f64>, f64) {
    let m = points.len();
    let kb = -0.5 / (beta * beta);
    let mut d = vec![1.0f64; m];
    let mut l: Vec<f64> = Vec::new();
    let mut pivots: Vec<usize> = Vec::new();
    let mut lambda_lower = 0.0;
    let mut col = vec![0.0; m];
    while pivots.len() < max_columns {
        let r = pivots.len();
        if r > 0 && d.iter().sum::<f64>() <= rel_tol * lambda_lower {
            break;
        }
        // The first of the largest (deterministic on ties).
        let (p, dp) = d.iter().enumerate().fold((0, f64::NEG_INFINITY), |b, (i, &x)| if x > b.1 { (i, x) } else { b });
        if !(dp > MIN_PIVOT) {
            break;
        }
        // Row p of L so far: each earlier column's weight in this one.
        let lp: Vec<f64> = (0..r).map(|c| l[c * m + p]).collect();
        let step = ColumnStep { points, pivot: points[p], kb, inv_sqrt_pivot: 1.0 / dp.sqrt(), l: &l, m, lp: &lp };
        let update = |(b, out): (usize, &mut [f64])| step.run(simd, b * BLOCK_ROWS, out);
        // In parallel once a step is worth a fork and join (the blocks are
        // the same either way, so are the bits).
        if m * r >= PAR_MIN_WORK {
            col.par_chunks_mut(BLOCK_ROWS).enumerate().for_each(update);
        } else {
            col.chunks_mut(BLOCK_ROWS).enumerate().for_each(update);
        }
        for &i in &pivots {
            col[i] = 0.0; // exactly explained already
        }
        for (di, c) in d.iter_mut().zip(&col) {
            *di = (*di - c * c).max(0.0);
        }
        d[p] = 0.0;
        if r == 0 {
            lambda_lower = col.iter().map(|c| c * c).sum();
        }
        pivots.push(p);
        l.extend_from_slice(&col);
        if pivots.len() == RAYLEIGH_AT {
            lambda_lower = lambda_lower.max(rayleigh_lower_bound(&l, m));
        }
    }
    let left = d.iter().sum();
    (l, left)
}

/// One step of the pivoted Cholesky on a block of rows: the pivot's kernel
/// column less what the earlier columns explain, over the root of the pivot.
struct ColumnStep<'a> {
    points: &'a [P3],
    pivot: P3,
    kb: f64,
    inv_sqrt_pivot: f64,
    /// The columns so far, M values each.
    l: &'a [f64],
    m: usize,
    /// Row `pivot` of `l`.
    lp: &'a [f64],
}

impl ColumnStep<'_> {
    /// Rows i0.. (as many as `out` holds) on the widest level `simd` allows:
    /// each row's sum is the same sequence of multiplications and additions
    /// (never fused) on every level, so are the bits; the wide levels run the
    /// step about 3× faster than baseline x86-64's two lanes.
    fn run(&self, simd: Simd, i0: usize, out: &mut [f64]) {
        #[cfg(target_arch = "x86_64")]
        {
            // SAFETY: `simd` comes from `Simd::detect` (or a test that checked
            // the CPU), so the CPU runs what these are compiled for.
            match simd {
                Simd::Avx512 => return unsafe { self.run_avx512(i0, out) },
                Simd::Avx2 => return unsafe { self.run_avx2(i0, out) },
                Simd::Portable => {}
            }
        }
        let _ = simd;
        self.body(i0, out)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    unsafe fn run_avx512(&self, i0: usize, out: &mut [f64]) {
        self.body(i0, out)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn run_avx2(&self, i0: usize, out: &mut [f64]) {
        self.body(i0, out)
    }

    #[inline(always)]
    fn body(&self, i0: usize, out: &mut [f64]) {
        let (m, n, prev, lp) = (self.m, out.len(), self.l, self.lp);
        for (o, y) in out.iter_mut().zip(&self.points[i0..]) {
            *o = exp_neg(self.kb * dist2(y, &self.pivot));
        }
        // Four columns a pass over the block (fewer loads and stores of it).
        let r = lp.len();
        let mut c = 0;
        while c + 4 <= r {
            let w = [lp[c], lp[c + 1], lp[c + 2], lp[c + 3]];
            let seg = |k: usize| &prev[(c + k) * m + i0..(c + k) * m + i0 + n];
            let (a0, a1, a2, a3) = (seg(0), seg(1), seg(2), seg(3));
            for i in 0..n {
                out[i] = out[i] - w[0] * a0[i] - w[1] * a1[i] - w[2] * a2[i] - w[3] * a3[i];
            }
            c += 4;
        }
        for (cc, w) in lp.iter().enumerate().skip(c) {
            let a = &prev[cc * m + i0..cc * m + i0 + n];
            for i in 0..n {
                out[i] -= w * a[i];
            }
        }
        for o in out.iter_mut() {
            *o *= self.inv_sqrt_pivot;
        }
    }
}

/// Columns after which the Cholesky refines its lower bound of λ_max.
const RAYLEIGH_AT: usize = 48;

/// A lower bound of λ_max(G) from L's first columns (M values each): the
/// Rayleigh quotient of L Lᵀ after a few power iterations from the first
/// column (G ⪰ L Lᵀ, so any Rayleigh quotient of L Lᵀ is one). The leading
/// pivots already hold the leading modes: on the 1,024-point mug it is
/// within 1 % of λ_max where ‖l₀‖² is 2.2× below, and the Cholesky's stop,
/// relative to it, comes that much sooner.
fn rayleigh_lower_bound(l: &[f64], m: usize) -> f64 {
    let r = l.len() / m;
    let mut v: Vec<f64> = l[..m].to_vec();
    let mut quotient = 0.0;
    for _ in 0..4 {
        let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(norm > 0.0) {
            return 0.0;
        }
        v.iter_mut().for_each(|x| *x /= norm);
        // t = Lᵀ v; ‖t‖² = vᵀ L Lᵀ v; then v = L t.
        let t: Vec<f64> = l.chunks_exact(m).map(|c| c.iter().zip(&v).map(|(a, b)| a * b).sum()).collect();
        quotient = t.iter().map(|x| x * x).sum();
        v.iter_mut().for_each(|x| *x = 0.0);
        for (c, tc) in l.chunks_exact(m).zip(&t).take(r) {
            for (x, a) in v.iter_mut().zip(c) {
                *x += tc * a;
            }
        }
    }
    quotient
}

/// Full symmetric eigendecomposition, eigenvalues descending.
fn exact_eigen(g: &Mat<f64>) -> (Mat<f64>, Vec<f64>) {
    let eigen = g.self_adjoint_eigen(Side::Lower);
    clear_upper_state();
    match eigen {
        Ok(e) => {
            let n = g.nrows();
            let s: Vec<f64> = (0..n).rev().map(|i| e.S().column_vector()[i]).collect();
            let u = Mat::from_fn(n, n, |i, j| e.U()[(i, n - 1 - j)]);
            (u, s)
        }
        // A kernel or Gram matrix is symmetric with finite entries; should the
        // decomposition still fail, the identity (no coupling) is a safe field.
        Err(_) => (Mat::identity(g.nrows(), g.nrows()), vec![1.0; g.nrows()]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Above `EXACT_MAX_POINTS` the Cholesky route gives the exact
    /// eigendecomposition's spectrum and products, to the tolerance asked.
    #[test]
    fn the_cholesky_route_matches_the_exact_eigendecomposition() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(6);
        let pts: Vec<P3> = (0..700).map(|_| [r.random(), 0.5 * r.random::<f64>(), 0.3 * r.random::<f64>()]).collect();
        assert!(pts.len() > EXACT_MAX_POINTS);
        let chol = LowRankKernel::new(&pts, 0.3, 1000, 1e-8);
        let (u, s) = exact_eigen(&gaussian(&pts, &pts, 0.3));
        let exact = LowRankKernel::truncated(u.as_ref(), &s, kept_rank(&s, 1000, 1e-8), 0.0);
        assert!(chol.rank().abs_diff(exact.rank()) <= 2, "rank {} vs {}", chol.rank(), exact.rank());
        for (a, b) in chol.lambda.iter().zip(&exact.lambda).take(chol.rank().min(exact.rank()) / 2) {
            assert!((a - b).abs() <= 1e-7 * exact.lambda[0], "eigenvalue {a} vs {b}");
        }
        let qtq = chol.q.transpose() * &chol.q;
        assert!((&qtq - Mat::<f64>::identity(chol.rank(), chol.rank())).norm_max() < 1e-6, "Q not orthonormal");
        let w = Mat::from_fn(pts.len(), 3, |_, _| r.random::<f64>() - 0.5);
        let (a, b) = (chol.apply(w.as_ref()), exact.apply(w.as_ref()));
        assert!((&a - &b).norm_max() < 1e-6 * b.norm_max(), "{} of {}", (&a - &b).norm_max(), b.norm_max());
    }

    /// The Cholesky's vector levels are the same arithmetic: the same bits.
    #[test]
    fn the_cholesky_has_the_same_bits_on_every_simd_level() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(8);
        let pts: Vec<P3> = (0..900).map(|_| [r.random(), 0.7 * r.random::<f64>(), 0.4 * r.random::<f64>()]).collect();
        let reference = pivoted_cholesky(&pts, 0.3, 1e-8, 2000, Simd::Portable);
        assert!(reference.0.len() / pts.len() > 100, "too few columns to test: {}", reference.0.len() / pts.len());
        for level in [Simd::Avx2, Simd::Avx512] {
            if Simd::detect(level) == level {
                let got = pivoted_cholesky(&pts, 0.3, 1e-8, 2000, level);
                assert!(got.0 == reference.0 && got.1 == reference.1, "{level:?} differs from portable");
            }
        }
    }

    /// A factor capped far below the kernel's rank says so: β small against
    /// the points' spacing makes G nearly the identity, whose eigenvalues are
    /// all alike; on both routes the tail is then near the largest.
    #[test]
    fn a_capped_factor_reports_its_tail() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for n in [300, 900] {
            let pts: Vec<P3> = (0..n).map(|_| [r.random(), r.random(), r.random()]).collect();
            let capped = LowRankKernel::new(&pts, 0.01, 50, 1e-8);
            assert_eq!(capped.rank(), 50);
            assert!(capped.tail_ratio > 0.5 && capped.tail_ratio <= 1.0, "{n}: {}", capped.tail_ratio);
            let smooth = LowRankKernel::new(&pts, 0.5, 300, 1e-6);
            assert!(smooth.tail_ratio < 1e-5, "{n}: {}", smooth.tail_ratio);
        }
    }

    #[test]
    fn low_rank_reproduces_the_kernel_product() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let pts: Vec<P3> = (0..900).map(|_| [r.random(), r.random(), r.random()]).collect();
        let g = gaussian(&pts, &pts, 0.5);
        let lr = LowRankKernel::new(&pts, 0.5, 300, 1e-6);
        eprintln!("rank {} tail {:e}", lr.rank(), lr.tail_ratio);
        assert!(lr.rank() < 300, "rank {}", lr.rank());
        let w = Mat::from_fn(900, 3, |_, _| r.random::<f64>() - 0.5);
        let exact = &g * &w;
        let approx = lr.apply(w.as_ref());
        let err = (&exact - &approx).norm_max();
        assert!(err < 1e-4 * exact.norm_max(), "error {err} of {}", exact.norm_max());
    }
}
