//! The latent half of the M-step: the MAP latent's normal equations from
//! one E-step's posteriors, for the isotropic fits (`em`) and the surfel
//! polish (`surfels`).
//!
//! The normal equations are A ℓ = b with A = Σᵢ P1ᵢ BᵢᵀΛBᵢ + prior and
//! b = Σᵢ BᵢᵀΛrᵢ (Bᵢ the 3×q basis rows of point i, rᵢ its
//! posterior-weighted residual in the model frame, Λ = I for isotropic
//! components, a I + b nᵢnᵢᵀ for surfels). The model is fixed during a fit,
//! so the per-point products BᵢᵀBᵢ and (Bᵢᵀnᵢ)(Bᵢᵀnᵢ)ᵀ are made once, and
//! each step is q(q+1)/2 contiguous dot products of length M with P1 for A
//! (twice that for surfels) and 3q (4q) for b.
//!
//! The products are stored and multiplied in single precision, in columns
//! padded to whole chunks of 64, summed in 64 single-precision lanes and the
//! lanes then added pairwise in double (`dot_f32`). In double, each summed
//! in one chain at the end, these sums and the residuals before them had
//! become a tenth of a mug registration (the refine's latent step 11 µs an
//! iteration). Each lane adds 7-13 products, so A and b are within 10⁻⁵ of
//! their largest entry of the double-precision sums (the test below), far
//! below what moves a fit: `eval transfer --views 12`, seeds 7 / 11 / 23,
//! kept every keypoint median and p90 of the three categories within
//! 0.005 mm of before.

use super::em::Pose;
use crate::shape::estep::{dot, Posteriors, P3};
use crate::shape::space::LinearModel;
use crate::simd::clear_upper_state;
use faer::prelude::*;
use faer::Side;

/// One model level's precomputed products, in single-precision columns over its points.
pub(super) struct LatentStep {
    pub(super) q: usize,
    /// (BᵢᵀBᵢ)_jk for j ≤ k, one column per pair (row-major pairs).
    gram: Vec<Vec<f32>>,
    /// (Bᵢᵀnᵢ)_j (Bᵢᵀnᵢ)_k for j ≤ k, as `gram`.
    normal_gram: Vec<Vec<f32>>,
    /// basis[j] as three columns.
    basis32: Vec<[Vec<f32>; 3]>,
    /// (Bᵢᵀnᵢ)_j: each mode's displacement along the point's canonical normal.
    basis_normal: Vec<Vec<f32>>,
    /// basis[j] and the mean shape as three double-precision columns (the support's row).
    pub(super) basis: Vec<[Vec<f64>; 3]>,
    pub(super) base: [Vec<f64>; 3],
}

/// Σᵢ P1ᵢ BᵢᵀBᵢ (upper triangle, row-major pairs) and Σᵢ Bᵢᵀrᵢ, and for
/// surfels the same along the normals: Σᵢ P1ᵢ (Bᵢᵀnᵢ)(Bᵢᵀnᵢ)ᵀ and
/// Σᵢ (Bᵢᵀnᵢ)(nᵢ·rᵢ).
pub(super) struct LatentSums {
    pub(super) gram: Vec<f64>,
    pub(super) b: Vec<f64>,
    pub(super) normal_gram: Vec<f64>,
    pub(super) normal_b: Vec<f64>,
}

impl LatentStep {
    /// The products of `model`'s points, with their canonical `normals` (one per point).
    pub(super) fn new(model: &LinearModel, normals: &[P3]) -> Self {
        let q = model.basis.len();
        assert_eq!(normals.len(), model.len(), "one normal per model point");
        let column = |v: &[P3], d: usize| v.iter().map(|p| p[d]).collect::<Vec<f64>>();
        let basis_normal: Vec<Vec<f64>> =
            model.basis.iter().map(|b| b.iter().zip(normals).map(|(v, n)| dot(v, n)).collect()).collect();
        let (mut gram, mut normal_gram) = (Vec::new(), Vec::new());
        for j in 0..q {
            for k in j..q {
                gram.push(padded(model.basis[j].iter().zip(&model.basis[k]).map(|(a, b)| dot(a, b) as f32)));
                normal_gram.push(padded(basis_normal[j].iter().zip(&basis_normal[k]).map(|(a, b)| (a * b) as f32)));
            }
        }
        let basis: Vec<[Vec<f64>; 3]> = model.basis.iter().map(|b| [0, 1, 2].map(|d| column(b, d))).collect();
        Self {
            q,
            gram,
            normal_gram,
            basis32: basis.iter().map(|b| b.each_ref().map(|c| single(c))).collect(),
            basis_normal: basis_normal.iter().map(|c| single(c)).collect(),
            basis,
            base: [0, 1, 2].map(|d| column(&model.base, d)),
        }
    }

    /// The sums of one step at `pose`: rᵢ = Rᵀ(PXᵢ − P1ᵢ t)/s − P1ᵢ baseᵢ;
    /// with `normals` (the level's canonical ones) the surfel sums too.
    pub(super) fn sums(&self, post: &Posteriors, pose: &Pose, normals: Option<&[P3]>) -> LatentSums {
        let m = post.p1.len();
        // rᵢ = M·PXᵢ − P1ᵢ (c + baseᵢ) with M = Rᵀ/s and c = Rᵀt/s.
        let rs = pose.r.transpose() / pose.s;
        let c = rs * pose.t;
        let p1 = padded(post.p1.iter().map(|&p| p as f32));
        let cap = m.next_multiple_of(LANES);
        let mut r: [Vec<f32>; 3] = std::array::from_fn(|_| vec![0.0; cap]);
        {
            // Slices of one length, so that the loop has no bounds checks.
            let (p1s, pxs) = (&post.p1[..m], &post.px[..m]);
            let base = self.base.each_ref().map(|b| &b[..m]);
            let [r0, r1, r2] = &mut r;
            let (o0, o1, o2) = (&mut r0[..m], &mut r1[..m], &mut r2[..m]);
            for i in 0..m {
                let (p, px) = (p1s[i], pxs[i]);
                let v =
                    |d: usize| rs[(d, 0)] * px[0] + rs[(d, 1)] * px[1] + rs[(d, 2)] * px[2] - p * (c[d] + base[d][i]);
                (o0[i], o1[i], o2[i]) = (v(0) as f32, v(1) as f32, v(2) as f32);
            }
        }
        // n·r from the single-precision residuals (what b's sums see).
        let rn = match normals {
            Some(n) => {
                let mut rn = vec![0.0f32; cap];
                for (i, (o, n)) in rn.iter_mut().zip(&n[..m]).enumerate() {
                    *o = (n[0] * r[0][i] as f64 + n[1] * r[1][i] as f64 + n[2] * r[2][i] as f64) as f32;
                }
                rn
            }
            None => Vec::new(),
        };
        let pairs = |cols: &[Vec<f32>]| cols.iter().map(|g| dot_f32(g, &p1)).collect::<Vec<f64>>();
        let b = self.basis32.iter().map(|bj| (0..3).map(|d| dot_f32(&bj[d], &r[d])).sum()).collect();
        let (normal_gram, normal_b) = match normals {
            Some(_) => (pairs(&self.normal_gram), self.basis_normal.iter().map(|bn| dot_f32(bn, &rn)).collect()),
            None => (Vec::new(), Vec::new()),
        };
        LatentSums { gram: pairs(&self.gram), b, normal_gram, normal_b }
    }
}

impl LatentSums {
    /// The normal equations' matrix and right-hand side: the matrix is
    /// scale·(a·Σ P1 BᵀB + b·Σ P1 (Bᵀn)(Bᵀn)ᵀ) with `prior_weight`/var on
    /// the diagonal, the right-hand side scale·(a·Σ Bᵀr + b·Σ (Bᵀn)(n·r)).
    /// The isotropic fits' (a, b, scale) is (1, 0, 1).
    pub(super) fn system(
        &self,
        q: usize,
        (a, b, scale): (f64, f64, f64),
        prior_weight: f64,
        var: &[f64],
    ) -> (Mat<f64>, Mat<f64>) {
        let surfel = |v: &[f64], i: usize| if b == 0.0 || v.is_empty() { 0.0 } else { b * v[i] };
        let mut am = Mat::<f64>::zeros(q, q);
        let mut bv = Mat::<f64>::zeros(q, 1);
        let mut e = 0;
        for j in 0..q {
            bv[(j, 0)] = scale * (a * self.b[j] + surfel(&self.normal_b, j));
            for k in j..q {
                let v = scale * (a * self.gram[e] + surfel(&self.normal_gram, e));
                am[(j, k)] = v;
                am[(k, j)] = v;
                e += 1;
            }
            am[(j, j)] += prior_weight / var[j];
        }
        (am, bv)
    }
}

/// Adds the support's rank-one term (`Support::latent_row`) to the latent's
/// normal equations A ℓ = b: K·g·gᵀ to A and K·g·e to b.
pub(super) fn add_support_term(a: &mut Mat<f64>, b: &mut Mat<f64>, g: &[f64], e: f64, k: f64) {
    for j in 0..g.len() {
        b[(j, 0)] += k * g[j] * e;
        for l in 0..g.len() {
            a[(j, l)] += k * g[j] * g[l];
        }
    }
}

/// A ℓ = b by Cholesky; None when A is not positive definite or ℓ not finite.
pub(super) fn solve(a: Mat<f64>, b: Mat<f64>) -> Option<Vec<f64>> {
    let sol = a.llt(Side::Lower).ok().map(|l| l.solve(&b));
    clear_upper_state();
    let sol = sol?;
    let out: Vec<f64> = (0..a.nrows()).map(|j| sol[(j, 0)]).collect();
    out.iter().all(|v| v.is_finite()).then_some(out)
}

/// A column in single precision, padded with zeros to whole chunks of `LANES`.
fn single(c: &[f64]) -> Vec<f32> {
    padded(c.iter().map(|&v| v as f32))
}

fn padded(c: impl ExactSizeIterator<Item = f32>) -> Vec<f32> {
    let n = c.len();
    let mut v = Vec::with_capacity(n.next_multiple_of(LANES));
    v.extend(c);
    v.resize(n.next_multiple_of(LANES), 0.0);
    v
}

/// The dot products' partial sums: four sixteen-lane vectors, eight of eight.
const LANES: usize = 64;

/// Σ aᵢbᵢ of single-precision columns: 64 partial sums in single precision
/// (lane l takes the products l, l + 64, …), then the lanes added pairwise:
/// l with l + 32 in single precision, then in double l with l + 16, 8, 4, 2
/// and 1. Summed in one chain at the end, the lanes had cost more than the
/// products of a 400-point column (63 ns a call, against 24 now for 448
/// points and 43 for 832). Written in intrinsics for AVX-512 (four vectors
/// of sixteen) and AVX2 (eight of eight): LLVM vectorised the portable loop
/// two lanes at a time. Every level adds in the same order with no fused
/// multiply-add, so the sum is the same bit for bit on each. The step's
/// columns are padded to whole chunks; a remainder (none here) is added
/// last, in double.
pub(super) fn dot_f32(a: &[f32], b: &[f32]) -> f64 {
    let n = a.len().min(b.len());
    let whole = n - n % LANES;
    let tail: f64 = a[whole..n].iter().zip(&b[whole..n]).map(|(x, y)| *x as f64 * *y as f64).sum();
    #[cfg(target_arch = "x86_64")]
    {
        use crate::simd::Simd;
        // SAFETY: `Simd::detect` found the features the functions are
        // compiled for; both read whole chunks below `whole` only.
        match Simd::detect(Simd::Avx512) {
            Simd::Avx512 => return unsafe { x86::dot_avx512(&a[..whole], &b[..whole]) } + tail,
            Simd::Avx2 => return unsafe { x86::dot_avx2(&a[..whole], &b[..whole]) } + tail,
            Simd::Portable => {}
        }
    }
    dot_portable(&a[..whole], &b[..whole]) + tail
}

/// The pairwise fold of the 32 lanes, in double.
#[inline(always)]
fn fold_lanes(part: &[f32; LANES]) -> f64 {
    let h32: [f32; 32] = std::array::from_fn(|l| part[l] + part[l + 32]);
    let h16: [f64; 16] = std::array::from_fn(|l| h32[l] as f64 + h32[l + 16] as f64);
    let h8: [f64; 8] = std::array::from_fn(|l| h16[l] + h16[l + 8]);
    let h4: [f64; 4] = std::array::from_fn(|l| h8[l] + h8[l + 4]);
    let h2 = [h4[0] + h4[2], h4[1] + h4[3]];
    h2[0] + h2[1]
}

fn dot_portable(a: &[f32], b: &[f32]) -> f64 {
    let mut part = [0.0f32; LANES];
    for (x, y) in a.chunks_exact(LANES).zip(b.chunks_exact(LANES)) {
        for l in 0..LANES {
            part[l] += x[l] * y[l];
        }
    }
    fold_lanes(&part)
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{fold_lanes, LANES};
    use std::arch::x86_64::*;

    /// # Safety
    /// The CPU must have AVX-512F; `a` and `b` are whole chunks of `LANES`, `b` at least as long.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn dot_avx512(a: &[f32], b: &[f32]) -> f64 {
        let mut acc = [_mm512_setzero_ps(); LANES / 16];
        for i in (0..a.len()).step_by(LANES) {
            for (v, acc) in acc.iter_mut().enumerate() {
                // SAFETY: i + LANES ≤ a.len() ≤ b.len().
                unsafe {
                    let (pa, pb) = (a.as_ptr().add(i + 16 * v), b.as_ptr().add(i + 16 * v));
                    *acc = _mm512_add_ps(*acc, _mm512_mul_ps(_mm512_loadu_ps(pa), _mm512_loadu_ps(pb)));
                }
            }
        }
        let mut part = [0.0f32; LANES];
        for (v, acc) in acc.iter().enumerate() {
            // SAFETY: `part` holds LANES lanes.
            unsafe { _mm512_storeu_ps(part.as_mut_ptr().add(16 * v), *acc) };
        }
        fold_lanes(&part)
    }

    /// # Safety
    /// The CPU must have AVX2; as `dot_avx512` otherwise.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn dot_avx2(a: &[f32], b: &[f32]) -> f64 {
        let mut acc = [_mm256_setzero_ps(); LANES / 8];
        for i in (0..a.len()).step_by(LANES) {
            for (v, acc) in acc.iter_mut().enumerate() {
                // SAFETY: i + LANES ≤ a.len() ≤ b.len().
                unsafe {
                    let (pa, pb) = (a.as_ptr().add(i + 8 * v), b.as_ptr().add(i + 8 * v));
                    *acc = _mm256_add_ps(*acc, _mm256_mul_ps(_mm256_loadu_ps(pa), _mm256_loadu_ps(pb)));
                }
            }
        }
        let mut part = [0.0f32; LANES];
        for (v, acc) in acc.iter().enumerate() {
            // SAFETY: `part` holds LANES lanes.
            unsafe { _mm256_storeu_ps(part.as_mut_ptr().add(8 * v), *acc) };
        }
        fold_lanes(&part)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The single-precision dot against f64 on every kernel level: the
    /// same bits on each, within 1e-6 of the double sum on positive terms.
    #[test]
    fn single_precision_dots_agree_on_every_level_and_with_double() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        for n in [0usize, 1, 31, 32, 33, 400, 803] {
            let a: Vec<f32> = (0..n).map(|_| r.random_range(0.0..1.0)).collect();
            let b: Vec<f32> = (0..n).map(|_| r.random_range(0.0..2.0)).collect();
            let want: f64 = a.iter().zip(&b).map(|(x, y)| *x as f64 * *y as f64).sum();
            let got = dot_f32(&a, &b);
            assert!((got - want).abs() <= 1e-6 * want.max(1e-30), "n = {n}: {got} vs {want}");
            let whole = n - n % LANES;
            let tail: f64 = a[whole..].iter().zip(&b[whole..]).map(|(x, y)| *x as f64 * *y as f64).sum();
            let portable = dot_portable(&a[..whole], &b[..whole]) + tail;
            assert_eq!(got.to_bits(), portable.to_bits(), "n = {n}");
            #[cfg(target_arch = "x86_64")]
            {
                use crate::simd::Simd;
                for level in Simd::available() {
                    // SAFETY: `available` lists only levels this CPU runs; the slices are whole chunks.
                    let v = unsafe {
                        match level {
                            Simd::Avx512 => x86::dot_avx512(&a[..whole], &b[..whole]),
                            Simd::Avx2 => x86::dot_avx2(&a[..whole], &b[..whole]),
                            Simd::Portable => dot_portable(&a[..whole], &b[..whole]),
                        }
                    } + tail;
                    assert_eq!(v.to_bits(), portable.to_bits(), "{level:?}, n = {n}");
                }
            }
        }
    }

    /// The step's single-precision sums against the same sums in double,
    /// point by point (the form the latent steps had before): a model of
    /// 403 points (a padded last chunk) and 9 modes, posteriors spanning
    /// six decades with some exact zeros, a turned and scaled pose.
    #[test]
    fn latent_sums_match_the_double_precision_sums_per_point() {
        use nalgebra::{Rotation3, Vector3};
        let r = std::cell::RefCell::new(rand_chacha::ChaCha8Rng::seed_from_u64(5));
        let (m, q) = (403, 9);
        let point = || -> P3 { [0, 1, 2].map(|_| r.borrow_mut().random_range(-1.0..1.0)) };
        let base: Vec<P3> = (0..m).map(|_| point()).collect();
        let basis: Vec<Vec<P3>> = (0..q).map(|_| (0..m).map(|_| point()).collect()).collect();
        let normals: Vec<P3> = (0..m)
            .map(|_| {
                let v = Vector3::from(point()).normalize();
                [v.x, v.y, v.z]
            })
            .collect();
        let p1: Vec<f64> = (0..m)
            .map(|i| if i % 17 == 0 { 0.0 } else { 10f64.powf(r.borrow_mut().random_range(-6.0..0.0)) })
            .collect();
        let px: Vec<P3> = p1.iter().map(|&p| point().map(|v| p * (0.3 + v))).collect();
        let post = Posteriors { p1: p1.clone(), px: px.clone(), ..Default::default() };
        let pose = Pose {
            r: Rotation3::new(Vector3::new(0.4, -0.3, 1.1)).into_inner(),
            t: Vector3::new(0.5, 0.1, -0.2),
            s: 1.3,
        };
        let model = LinearModel::new(base.clone(), basis.clone());
        let step = LatentStep::new(&model, &normals);
        let got = step.sums(&post, &pose, Some(&normals));
        // The double-precision sums, one point at a time.
        let rt = pose.r.transpose();
        let (mut gram, mut b, mut normal_gram, mut normal_b) =
            (vec![0.0; q * (q + 1) / 2], vec![0.0; q], vec![0.0; q * (q + 1) / 2], vec![0.0; q]);
        for i in 0..m {
            let res = rt * (Vector3::from(px[i]) - pose.t * p1[i]) / pose.s - Vector3::from(base[i]) * p1[i];
            let n = Vector3::from(normals[i]);
            let bn: Vec<f64> = (0..q).map(|j| Vector3::from(basis[j][i]).dot(&n)).collect();
            let mut e = 0;
            for j in 0..q {
                b[j] += Vector3::from(basis[j][i]).dot(&res);
                normal_b[j] += bn[j] * n.dot(&res);
                for k in j..q {
                    gram[e] += p1[i] * Vector3::from(basis[j][i]).dot(&Vector3::from(basis[k][i]));
                    normal_gram[e] += p1[i] * bn[j] * bn[k];
                    e += 1;
                }
            }
        }
        // Relative to the largest of each kind: the sums mix signs.
        let near = |got: &[f64], want: &[f64], what: &str| {
            let scale = want.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            for (g, w) in got.iter().zip(want) {
                assert!((g - w).abs() <= 1e-5 * scale, "{what}: {g} vs {w} (scale {scale})");
            }
        };
        near(&got.gram, &gram, "gram");
        near(&got.b, &b, "b");
        near(&got.normal_gram, &normal_gram, "normal gram");
        near(&got.normal_b, &normal_b, "normal b");
        // Without normals, the isotropic sums alone, the same.
        let iso = step.sums(&post, &pose, None);
        assert!(iso.normal_gram.is_empty() && iso.normal_b.is_empty());
        assert_eq!(iso.gram, got.gram);
        assert_eq!(iso.b, got.b);
    }
}
