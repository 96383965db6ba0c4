//! The products of non-rigid CPD's M-step with a low-rank kernel
//! G ≈ Q Λ Qᵀ (Q orthonormal, M×k), and the conjugate-gradient solve of
//! its k×k system (Qᵀ dP Q + sΛ⁻¹) z = Qᵀ F.
//!
//! Written here rather than with faer's products because every one has three
//! right-hand sides (x, y, z): a general GEMM packs all of Q for them, and
//! its matrix-vector products read Q once per column and split their sums
//! over however many threads the machine has. Here each product reads Q once,
//! row by row, and the normal operator Qᵀ(p1 ⊙ Q v) does both of its halves on
//! a row while it is in L1 (one pass over Q where a column-major pair of
//! products takes two), stored in single precision and summed in double.
//! The sums are split into fixed blocks of rows and added in block order,
//! with lanes of 8 summed in one fixed order, so the bits are the same on
//! any thread count. The AVX-512 and AVX2 kernels fuse each multiply-add (the
//! same fused operations in the same order: the same bits on both); plain
//! x86-64 multiplies then adds, within rounding of them. Fused, the AVX-512
//! normal product takes 30 % less time (`examples/bench_mstep`: 145-169 →
//! 102-112 µs at 1,024 × 369): it is bound by how many instructions issue,
//! not by the multipliers. The CPD's E-step kernels already round
//! differently per level, so whole fits never agreed across levels anyway.

use crate::simd::Simd;
use rayon::prelude::*;

/// Rows in one parallel task, fixed so that sums split alike on every machine.
const BLOCK_ROWS: usize = 128;
/// Lanes of the dot products' accumulators (one AVX-512 register, two AVX2).
const LANES: usize = 8;

/// Conjugate-gradient iterations of one M-step before the caller's direct solve takes over.
pub const PCG_MAX_ITERATIONS: usize = 60;
/// Residual of the M-step's conjugate gradients, relative to the right-hand
/// side. Each M-step is one step of an EM that moves on: at 1e-7 the peer
/// benchmark's moved points are 1 µm from a 1e-9 solve's with 27 % fewer
/// iterations (865 against 1,185 over 100 EM iterations; 1e-6: 6.5 µm, 711).
pub const PCG_TOLERANCE: f64 = 1e-7;

/// The kernel factor Q by rows, each zero-padded to `kp` (k rounded up to 8),
/// in single precision: the products are memory-bound, and every sum is
/// taken in double precision, so rounding Q once is all that changes (the
/// moved points of the peer benchmark's 1,024-point mug pair by 0.4 µm; 15 %
/// less EM time).
pub struct LowRankFactor {
    m: usize,
    k: usize,
    kp: usize,
    rows: Vec<f32>,
    level: Simd,
}

impl LowRankFactor {
    /// Q (M×k, column-major as faer keeps it), for this CPU's widest level.
    pub fn new(q: faer::MatRef<'_, f64>) -> Self {
        Self::with_level(q, Simd::detect(Simd::Avx512))
    }

    /// As [`Self::new`] on a chosen level (tests hold the levels to each other).
    pub fn with_level(q: faer::MatRef<'_, f64>, level: Simd) -> Self {
        let (m, k) = (q.nrows(), q.ncols());
        let kp = k.div_ceil(LANES) * LANES;
        let mut rows = vec![0.0f32; m * kp];
        for (i, row) in rows.chunks_exact_mut(kp).enumerate() {
            for (j, r) in row[..k].iter_mut().enumerate() {
                *r = q[(i, j)] as f32;
            }
        }
        Self { m, k, kp, rows, level }
    }

    pub fn rank(&self) -> usize {
        self.k
    }

    /// v's three columns, each padded to kp.
    fn columns(&self, v: &[[f64; 3]]) -> Vec<f64> {
        let mut vs = vec![0.0; 3 * self.kp];
        for (j, vj) in v.iter().enumerate() {
            for c in 0..3 {
                vs[c * self.kp + j] = vj[c];
            }
        }
        vs
    }

    fn block(&self, b: usize) -> (usize, &[f32]) {
        let i0 = b * BLOCK_ROWS;
        let i1 = (i0 + BLOCK_ROWS).min(self.m);
        (i0, &self.rows[i0 * self.kp..i1 * self.kp])
    }

    /// Σ over fixed row blocks of `f(first row, block rows, acc)`, each block
    /// into its own zeroed `width`·kp accumulator, added in block order.
    fn reduce_blocks(&self, width: usize, f: impl Fn(usize, &[f32], &mut [f64]) + Sync) -> Vec<f64> {
        let blocks = self.m.div_ceil(BLOCK_ROWS);
        let partials: Vec<Vec<f64>> = (0..blocks)
            .into_par_iter()
            .map(|b| {
                let (i0, rows) = self.block(b);
                let mut acc = vec![0.0; width * self.kp];
                f(i0, rows, &mut acc);
                acc
            })
            .collect();
        let mut total = vec![0.0; width * self.kp];
        for p in &partials {
            for (t, v) in total.iter_mut().zip(p) {
                *t += v;
            }
        }
        total
    }

    /// Q z (M rows) for z with k rows.
    pub fn times(&self, z: &[[f64; 3]]) -> Vec<[f64; 3]> {
        assert_eq!(z.len(), self.k);
        let zs = self.columns(z);
        let mut out = vec![[0.0; 3]; self.m];
        out.par_chunks_mut(BLOCK_ROWS).enumerate().for_each(|(b, o)| {
            let (_, rows) = self.block(b);
            dispatch!(self.level, rows_dot3(rows, &zs, self.kp, o));
        });
        out
    }

    /// Qᵀ f (k rows) for f with M rows.
    pub fn transpose_times(&self, f: &[[f64; 3]]) -> Vec<[f64; 3]> {
        assert_eq!(f.len(), self.m);
        let acc = self.reduce_blocks(3, |i0, rows, acc| {
            dispatch!(self.level, rows_axpy3(rows, &f[i0..], self.kp, acc));
        });
        self.unpack(&acc)
    }

    fn unpack(&self, acc: &[f64]) -> Vec<[f64; 3]> {
        (0..self.k).map(|j| [acc[j], acc[self.kp + j], acc[2 * self.kp + j]]).collect()
    }

    /// diag(Qᵀ diag(p1) Q).
    pub fn normal_diagonal(&self, p1: &[f64]) -> Vec<f64> {
        assert_eq!(p1.len(), self.m);
        let acc = self.reduce_blocks(1, |i0, rows, acc| {
            for (row, p) in rows.chunks_exact(self.kp).zip(&p1[i0..]) {
                for (a, &q) in acc.iter_mut().zip(row) {
                    let q = q as f64;
                    *a += p * q * q;
                }
            }
        });
        acc[..self.k].to_vec()
    }

    /// Qᵀ (p1 ⊙ (Q v)) + reg ⊙ v, in one pass over Q.
    pub fn normal_times(&self, p1: &[f64], reg: &[f64], v: &[[f64; 3]]) -> Vec<[f64; 3]> {
        assert!(p1.len() == self.m && reg.len() == self.k && v.len() == self.k);
        let vs = self.columns(v);
        let acc = self.reduce_blocks(3, |i0, rows, acc| {
            dispatch!(self.level, rows_normal(rows, &p1[i0..], &vs, self.kp, acc));
        });
        let mut out = self.unpack(&acc);
        for ((o, r), vj) in out.iter_mut().zip(reg).zip(v) {
            for c in 0..3 {
                o[c] += r * vj[c];
            }
        }
        out
    }
}

/// Runs kernel body `$f` compiled for `$level`.
macro_rules! dispatch {
    ($level:expr, $f:ident($($arg:expr),*)) => {{
        #[cfg(target_arch = "x86_64")]
        {
            match $level {
                // SAFETY: a level above Portable is chosen only where the CPU
                // runs it (Simd::detect) or by a test that checked it.
                Simd::Avx512 => unsafe { kernels::avx512::$f($($arg),*) },
                Simd::Avx2 => unsafe { kernels::avx2::$f($($arg),*) },
                Simd::Portable => kernels::$f($($arg),*),
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = $level;
            kernels::$f($($arg),*)
        }
    }};
}
use dispatch;

/// The kernel bodies, plain Rust that LLVM vectorises; `avx2` and `avx512`
/// compile the same bodies with those features on.
mod kernels {
    use super::LANES;

    /// The dot products of `a` with the three `n`-value columns of `b`
    /// (n a multiple of LANES): lanes of 8, summed (0+4, 1+5, 2+6, 3+7),
    /// then (0+2) + (1+3).
    #[inline(always)]
    pub fn dot3(a: &[f32], b: &[f64], n: usize) -> [f64; 3] {
        let (b0, rest) = b.split_at(n);
        let (b1, b2) = rest.split_at(n);
        let mut acc = [[0.0f64; LANES]; 3];
        for (((x, y0), y1), y2) in a[..n]
            .chunks_exact(LANES)
            .zip(b0.chunks_exact(LANES))
            .zip(b1.chunks_exact(LANES))
            .zip(b2[..n].chunks_exact(LANES))
        {
            for l in 0..LANES {
                let x = x[l] as f64;
                acc[0][l] += x * y0[l];
                acc[1][l] += x * y1[l];
                acc[2][l] += x * y2[l];
            }
        }
        acc.map(|a| {
            let h = [a[0] + a[4], a[1] + a[5], a[2] + a[6], a[3] + a[7]];
            (h[0] + h[2]) + (h[1] + h[3])
        })
    }

    /// acc (three n-value columns) += a ⊗ t.
    #[inline(always)]
    pub fn axpy3(a: &[f32], t: [f64; 3], acc: &mut [f64], n: usize) {
        let (c0, rest) = acc.split_at_mut(n);
        let (c1, c2) = rest.split_at_mut(n);
        for (((x, a0), a1), a2) in a[..n].iter().zip(c0.iter_mut()).zip(c1.iter_mut()).zip(c2[..n].iter_mut()) {
            let x = *x as f64;
            *a0 += x * t[0];
            *a1 += x * t[1];
            *a2 += x * t[2];
        }
    }

    /// The row loops. The SIMD levels bring their own `rows_dot3` and
    /// `rows_normal` (LLVM does not vectorise the eight-lane sums of `dot3`
    /// well) and share `rows_axpy3`, which it does.
    pub fn rows_dot3(rows: &[f32], v: &[f64], n: usize, out: &mut [[f64; 3]]) {
        for (row, o) in rows.chunks_exact(n).zip(out) {
            *o = dot3(row, v, n);
        }
    }

    #[inline(always)]
    pub fn rows_axpy3(rows: &[f32], f: &[[f64; 3]], n: usize, acc: &mut [f64]) {
        for (row, t) in rows.chunks_exact(n).zip(f) {
            axpy3(row, *t, acc, n);
        }
    }

    pub fn rows_normal(rows: &[f32], p1: &[f64], v: &[f64], n: usize, acc: &mut [f64]) {
        for (row, p) in rows.chunks_exact(n).zip(p1) {
            let d = dot3(row, v, n);
            axpy3(row, [d[0] * p, d[1] * p, d[2] * p], acc, n);
        }
    }

    /// `dot3` in eight-lane registers (`$w` lanes each, so 8 / $w registers
    /// a column), and the normal operator on groups of `$g` rows: their dot
    /// products together, then their updates of `acc` in row order, which
    /// adds in the order one row at a time does (the same bits), with fewer
    /// loads and stores of `acc` and more independent sums in flight.
    macro_rules! compiled_for {
        ($name:ident, $feature:literal, $w:literal, $g:literal, $zero:ident, $set1:ident, $load:ident, $loadps:ident, $cvt:ident, $fma:ident, $store:ident) => {
            #[cfg(target_arch = "x86_64")]
            pub mod $name {
                use super::LANES;
                use std::arch::x86_64::*;

                /// The dot products of G rows (stride n, from `a`) with b's three
                /// columns.
                #[target_feature(enable = $feature)]
                unsafe fn dots<const G: usize>(a: *const f32, b: *const f64, n: usize) -> [[f64; 3]; G] {
                    const R: usize = LANES / $w;
                    let mut acc = [[[$zero(); R]; 3]; G];
                    for i in (0..n).step_by(LANES) {
                        for r in 0..R {
                            let off = i + r * $w;
                            // SAFETY: the callers hold off + $w <= n within G rows of a and 3 columns of b.
                            unsafe {
                                let v = [$load(b.add(off)), $load(b.add(n + off)), $load(b.add(2 * n + off))];
                                for g in 0..G {
                                    let x = $cvt($loadps(a.add(g * n + off)));
                                    for c in 0..3 {
                                        acc[g][c][r] = $fma(x, v[c], acc[g][c][r]);
                                    }
                                }
                            }
                        }
                    }
                    let mut out = [[0.0f64; 3]; G];
                    for g in 0..G {
                        for c in 0..3 {
                            let mut l = [0.0f64; LANES];
                            for r in 0..R {
                                // SAFETY: $w values at r·$w of an array of 8.
                                unsafe { $store(l.as_mut_ptr().add(r * $w), acc[g][c][r]) };
                            }
                            let h = [l[0] + l[4], l[1] + l[5], l[2] + l[6], l[3] + l[7]];
                            out[g][c] = (h[0] + h[2]) + (h[1] + h[3]);
                        }
                    }
                    out
                }

                /// acc += Σ_g row_g ⊗ t_g, rows in order.
                #[target_feature(enable = $feature)]
                unsafe fn updates<const G: usize>(a: *const f32, t: [[f64; 3]; G], n: usize, acc: *mut f64) {
                    // Loops rather than array `map`/`from_fn`, which LLVM left as
                    // calls (with a memmove) on arrays of G·3 registers.
                    let mut ts = [[$zero(); 3]; G];
                    for g in 0..G {
                        for c in 0..3 {
                            ts[g][c] = $set1(t[g][c]);
                        }
                    }
                    for i in (0..n).step_by($w) {
                        // Each row's values converted once for the three columns (the
                        // stores to acc between would otherwise make LLVM load them again).
                        let mut x = [$zero(); G];
                        for g in 0..G {
                            // SAFETY: the callers hold i + $w <= n within G rows of a and 3 columns of acc.
                            x[g] = unsafe { $cvt($loadps(a.add(g * n + i))) };
                        }
                        for c in 0..3 {
                            // SAFETY: as above.
                            unsafe {
                                let mut s = $load(acc.add(c * n + i));
                                for g in 0..G {
                                    s = $fma(x[g], ts[g][c], s);
                                }
                                $store(acc.add(c * n + i), s);
                            }
                        }
                    }
                }

                #[target_feature(enable = $feature)]
                pub unsafe fn rows_dot3(rows: &[f32], v: &[f64], n: usize, out: &mut [[f64; 3]]) {
                    assert!(n % LANES == 0 && v.len() >= 3 * n && rows.len() <= out.len() * n);
                    for (row, o) in rows.chunks_exact(n).zip(out) {
                        // SAFETY: one row of n values; v's three columns of n, asserted.
                        *o = unsafe { dots::<1>(row.as_ptr(), v.as_ptr(), n) }[0];
                    }
                }

                #[target_feature(enable = $feature)]
                pub unsafe fn rows_axpy3(rows: &[f32], f: &[[f64; 3]], n: usize, acc: &mut [f64]) {
                    super::rows_axpy3(rows, f, n, acc)
                }

                #[target_feature(enable = $feature)]
                pub unsafe fn rows_normal(rows: &[f32], p1: &[f64], v: &[f64], n: usize, acc: &mut [f64]) {
                    assert!(n % LANES == 0 && v.len() >= 3 * n && acc.len() >= 3 * n);
                    let count = (rows.len() / n).min(p1.len());
                    let mut i = 0;
                    while i + $g <= count {
                        // SAFETY: rows i..i+$g exist (count), v and acc hold 3 columns of n (asserted).
                        unsafe {
                            let a = rows.as_ptr().add(i * n);
                            let d = dots::<$g>(a, v.as_ptr(), n);
                            let mut t = [[0.0f64; 3]; $g];
                            for g in 0..$g {
                                for c in 0..3 {
                                    t[g][c] = d[g][c] * p1[i + g];
                                }
                            }
                            updates::<$g>(a, t, n, acc.as_mut_ptr());
                        }
                        i += $g;
                    }
                    while i < count {
                        // SAFETY: row i exists; as above.
                        unsafe {
                            let a = rows.as_ptr().add(i * n);
                            let d = dots::<1>(a, v.as_ptr(), n);
                            updates::<1>(a, [d[0].map(|x| x * p1[i])], n, acc.as_mut_ptr());
                        }
                        i += 1;
                    }
                }
            }
        };
    }
    #[rustfmt::skip]
    compiled_for!(avx2, "avx2,fma", 4, 4, _mm256_setzero_pd, _mm256_set1_pd, _mm256_loadu_pd, _mm_loadu_ps, _mm256_cvtps_pd, _mm256_fmadd_pd, _mm256_storeu_pd);
    #[rustfmt::skip]
    compiled_for!(avx512, "avx512f", 8, 8, _mm512_setzero_pd, _mm512_set1_pd, _mm512_loadu_pd, _mm256_loadu_ps, _mm512_cvtps_pd, _mm512_fmadd_pd, _mm512_storeu_pd);
}

/// Solves (Qᵀ diag(p1) Q + s Λ⁻¹) z = b for the three columns of `b` by
/// Jacobi-preconditioned conjugate gradients from `z0`, to a residual of
/// `tolerance` (the M-step's: [`PCG_TOLERANCE`]) of ‖b‖ per column. `None` when that takes more than
/// [`PCG_MAX_ITERATIONS`] (the caller solves directly). Returns z and the
/// iterations taken.
pub fn pcg(
    q: &LowRankFactor,
    lambda: &[f64],
    p1: &[f64],
    s: f64,
    b: &[[f64; 3]],
    z0: &[[f64; 3]],
    tolerance: f64,
) -> Option<(Vec<[f64; 3]>, usize)> {
    let k = q.rank();
    let reg: Vec<f64> = lambda.iter().map(|l| s / l.max(1e-300)).collect();
    let diag: Vec<f64> = q.normal_diagonal(p1).iter().zip(&reg).map(|(d, r)| d + r).collect();
    let apply = |v: &[[f64; 3]]| q.normal_times(p1, &reg, v);
    let dot = |a: &[[f64; 3]], b: &[[f64; 3]], c: usize| a.iter().zip(b).map(|(x, y)| x[c] * y[c]).sum::<f64>();
    let mut z = z0.to_vec();
    let ap = apply(&z);
    let mut r: Vec<[f64; 3]> = b.iter().zip(&ap).map(|(b, a)| [b[0] - a[0], b[1] - a[1], b[2] - a[2]]).collect();
    let bnorm: Vec<f64> = (0..3).map(|c| dot(b, b, c).sqrt().max(1e-300)).collect();
    let precondition = |r: &[[f64; 3]]| -> Vec<[f64; 3]> {
        r.iter().zip(&diag).map(|(r, d)| [r[0] / d, r[1] / d, r[2] / d]).collect()
    };
    let mut y = precondition(&r);
    let mut p = y.clone();
    let mut ry: Vec<f64> = (0..3).map(|c| dot(&r, &y, c)).collect();
    for it in 0..=PCG_MAX_ITERATIONS {
        if (0..3).all(|c| dot(&r, &r, c).sqrt() <= tolerance * bnorm[c]) {
            return Some((z, it));
        }
        if it == PCG_MAX_ITERATIONS {
            break;
        }
        let ap = apply(&p);
        for c in 0..3 {
            let pap = dot(&p, &ap, c);
            if !(pap > 0.0) {
                continue; // this column has converged exactly
            }
            let alpha = ry[c] / pap;
            for j in 0..k {
                z[j][c] += alpha * p[j][c];
                r[j][c] -= alpha * ap[j][c];
            }
        }
        y = precondition(&r);
        for c in 0..3 {
            let next = dot(&r, &y, c);
            let beta = if ry[c] > 0.0 { next / ry[c] } else { 0.0 };
            ry[c] = next;
            for j in 0..k {
                p[j][c] = y[j][c] + beta * p[j][c];
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::prelude::*;
    use faer::{Mat, Side};
    use rand::{Rng, SeedableRng};

    fn rows(m: &Mat<f64>) -> Vec<[f64; 3]> {
        (0..m.nrows()).map(|j| [m[(j, 0)], m[(j, 1)], m[(j, 2)]]).collect()
    }

    /// The M-step's conjugate gradients solve the same system as a direct
    /// solve (to 1e-9), on a random orthonormal Q with a decaying spectrum,
    /// uneven posteriors and a size that leaves partial blocks; every product
    /// equals its dense form (to 1e-12), and the AVX2 and AVX-512 levels give
    /// the same bits (plain x86-64, unfused, is held to the dense forms).
    #[test]
    fn the_products_and_the_conjugate_gradients_match_dense_algebra() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let (m, k) = (301, 37);
        let q = Mat::<f64>::from_fn(m, k, |_, _| rng.random::<f64>() - 0.5).qr().compute_thin_Q();
        // The factor keeps Q in single precision: the dense algebra below uses the same values.
        let q = Mat::<f64>::from_fn(m, k, |i, j| q[(i, j)] as f32 as f64);
        let lambda: Vec<f64> = (0..k).map(|j| 0.5f64.powi(j as i32 / 3)).collect();
        let p1: Vec<f64> = (0..m).map(|i| if i % 7 == 0 { 0.0 } else { rng.random::<f64>() }).collect();
        let s = 1e-3;
        let b = Mat::<f64>::from_fn(k, 3, |_, _| rng.random::<f64>() - 0.5);
        let f = Mat::<f64>::from_fn(m, 3, |_, _| rng.random::<f64>() - 0.5);
        let dpq = Mat::from_fn(m, k, |i, j| p1[i] * q[(i, j)]);
        let mut a = q.transpose() * &dpq;
        for (j, l) in lambda.iter().enumerate() {
            a[(j, j)] += s / l;
        }
        let direct = a.llt(Side::Lower).unwrap().solve(&b);
        let reg: Vec<f64> = lambda.iter().map(|l| s / l).collect();
        let close = |x: &[[f64; 3]], y: &Mat<f64>, what: &str| {
            let scale = y.norm_max();
            for (j, xj) in x.iter().enumerate() {
                for c in 0..3 {
                    assert!((xj[c] - y[(j, c)]).abs() <= 1e-12 * scale, "{what} row {j} col {c}");
                }
            }
        };
        let mut first: Option<Vec<Vec<[f64; 3]>>> = None;
        for level in Simd::available() {
            let op = LowRankFactor::with_level(q.as_ref(), level);
            let (z, its) = pcg(&op, &lambda, &p1, s, &rows(&b), &vec![[0.0; 3]; k], 1e-10).expect("converges");
            assert!(its > 0 && its <= PCG_MAX_ITERATIONS);
            let err = z
                .iter()
                .zip(rows(&direct))
                .flat_map(|(x, y)| (0..3).map(move |c| (x[c] - y[c]).abs()))
                .fold(0.0, f64::max)
                / direct.norm_max();
            assert!(err < 1e-8, "{level:?}: relative difference {err:e} after {its} iterations");
            // Warm started at the answer: no iteration needed.
            let (_, again) = pcg(&op, &lambda, &p1, s, &rows(&b), &rows(&direct), PCG_TOLERANCE).unwrap();
            assert!(again <= 1, "{again}");
            let normal = op.normal_times(&p1, &reg, &rows(&b));
            close(&normal, &(&a * &b), "normal");
            let qz = op.times(&rows(&b));
            close(&qz, &(&q * &b), "Q z");
            let qtf = op.transpose_times(&rows(&f));
            close(&qtf, &(q.transpose() * &f), "Qᵀ f");
            let d = op.normal_diagonal(&p1);
            for j in 0..k {
                assert!((d[j] + reg[j] - a[(j, j)]).abs() < 1e-12, "diagonal {j}");
            }
            if level == Simd::Portable {
                continue;
            }
            let all = vec![z, normal, qz, qtf, d.iter().map(|&x| [x, 0.0, 0.0]).collect()];
            match &first {
                None => first = Some(all),
                Some(f0) => {
                    let same = f0
                        .iter()
                        .flatten()
                        .flatten()
                        .zip(all.iter().flatten().flatten())
                        .all(|(x, y)| x.to_bits() == y.to_bits());
                    assert!(same, "{level:?} differs from the AVX2 bits");
                }
            }
        }
    }

    /// The bits do not depend on the thread count.
    #[test]
    fn the_products_are_the_same_on_one_thread_and_many() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(4);
        let (m, k) = (700, 45);
        let q = Mat::<f64>::from_fn(m, k, |_, _| rng.random::<f64>() - 0.5);
        let p1: Vec<f64> = (0..m).map(|_| rng.random::<f64>()).collect();
        let v: Vec<[f64; 3]> = (0..k).map(|_| [rng.random(), rng.random(), rng.random()]).collect();
        let reg = vec![0.1; k];
        let op = LowRankFactor::new(q.as_ref());
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| (op.normal_times(&p1, &reg, &v), op.transpose_times(&op.times(&v))))
        };
        let (a1, b1) = run(1);
        let (a3, b3) = run(3);
        let bits = |x: &[[f64; 3]]| x.iter().flatten().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a1), bits(&a3));
        assert_eq!(bits(&b1), bits(&b3));
    }
}
